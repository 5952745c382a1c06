"""Live daemon under load: how many 100 Hz sensors one gateway process sustains.

For each rung of a sensor-count ladder this starts three processes on this machine:

* the sensors: ``bench/pty_fleet.py``, N simulated devices on pseudo-terminals, every byte
  simulated and encoded up front, written at the real rate (one sample per write by default);
* the daemon: ``recal run`` reading the N ports, calibrating every sensor in
  process, logging everything to MCAP on disk and publishing on Zenoh (a peer on 127.0.0.1);
* this script: a Zenoh peer subscribed to ``recal/<sensor>/calibrated`` of the first
  ``--probe`` sensors, stamping each message's arrival.

and reports, for a run of ``--seconds``:

* CPU: the daemon's user+system time (all its threads, /proc/<pid>/stat) over the run after
  a warm-up, as a share of one core; the writer's too, since both share this machine's cores;
* latency: per calibrated sample, arrival at the subscriber minus the moment the writer sent
  it (its time stamp, see pty_fleet.py); p50, p99 and max over every probed sample;
* loss: samples written vs samples in the MCAP raw topic (every one, exactly once, in order)
  and in the calibrated topic;
* sustained: nothing lost, and the daemon kept up (latency p99 under --max-p99-ms, and it had
  logged everything within --max-catchup-s of the last write).

Full run (about 6 min per rung)::

    python bench/daemon_scale.py --seconds 300 --sensors 1,10,50,100,200,300,400

Quick check (20 s per rung)::

    python bench/daemon_scale.py --quick

The machine has 2 cores shared by the writer, the daemon, this script (and whatever else
runs): the daemon never has a core to itself, so its numbers are upper bounds.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from child_process import ChildProcess
from pty_fleet import FleetProcess
from recal.commands.demo import free_port
from recal.daemon.gateway import READY_PREFIX
from recal.errors import RecordingError
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_calibrated, decode_json
from recal.io.repair import repair

__all__ = ["main", "run_rung"]

RATE_HZ = 100.0


def sensor_id(i: int) -> str:
    return f"s{i:03d}"


def gateway_toml(links: Sequence[str], zenoh_port: int, workdir: Path, *,
                 run_nodes: bool = True, mode: str = "peer",
                 connect: Sequence[str] = (), extra: str = "", first: int = 0) -> str:
    """A gateway config for the fleet's ports (priors match the simulated sensors); the
    sensors are numbered from ``first``."""
    listen = f'["tcp/127.0.0.1:{zenoh_port}"]' if zenoh_port else "[]"
    lines = [f"run_nodes = {'true' if run_nodes else 'false'}", extra, "[zenoh]",
             f'mode = "{mode}"', f"listen = {listen}",
             f"connect = {json.dumps(list(connect))}",
             "[checkpoint]", f'dir = "{workdir / "ck"}"', "interval_s = 60"]
    for i, link in enumerate(links, start=first):
        lines += ["[[sensors]]", f'id = "{sensor_id(i)}"', f'port = "{link}"', "aux_names = []",
                  f"rate_hz = {RATE_HZ}", "prior = { counts_per_g = 1024.0, zero_g = 0 }"]
    return "\n".join(lines) + "\n"


class LatencyProbe:
    """A Zenoh session that stamps the arrival of calibrated messages of a few sensors and asks
    the status queryables how far the gateways (and nodes) got."""

    def __init__(self, config: Any, sensors: Sequence[int], topic: str = "calibrated") -> None:
        self.bus = Bus(config)
        self.records: list[tuple[int, int, bytes]] = []
        for i in sensors:
            self.bus.subscribe(key(sensor_id(i), topic),
                               lambda m, i=i: self.records.append((time.time_ns(), i, m.payload)))

    @classmethod
    def peer_of(cls, daemon_port: int, sensors: Sequence[int]) -> LatencyProbe:
        """A peer connected straight to a daemon listening on ``daemon_port``."""
        return cls(zenoh_config("peer", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{daemon_port}"]),
                   sensors)

    def counts(self, n_sensors: int) -> tuple[int, int, int]:
        """(ports open at gateways, raw samples logged by gateways, samples calibrated), summed
        over the status replies (gateways and nodes both answer)."""
        docs = [decode_json(p) for _, p in self.bus.get(
            "recal/*/status", timeout_s=3.0, max_replies=2 * n_sensors + 8)]
        gw = [d["gateway"] for d in docs if "gateway" in d]
        cal = sum(d["node"].get("samples", 0) for d in docs if d.get("node"))
        return (sum(1 for g in gw if g.get("open")), sum(g.get("samples_logged", 0) for g in gw),
                cal)

    def close(self) -> None:
        self.bus.close()


def until(cond: Callable[[], bool], timeout_s: float, interval_s: float = 0.25) -> float:
    """Seconds until ``cond()`` held (bounded by ``timeout_s``); inf if it never did."""
    t0 = time.monotonic()
    for _ in range(int(timeout_s / interval_s) + 1):
        if cond():
            return time.monotonic() - t0
        if time.monotonic() - t0 >= timeout_s:
            break
        time.sleep(interval_s)
    return float("inf")


def latencies_ms(records: Sequence[tuple[int, int, bytes]], written: dict, chunk: int,
                 after_ns: int) -> np.ndarray:
    """Arrival minus write time, per sample, of calibrated messages ``(arrival_ns, sensor
    index, payload)``; samples written before ``after_ns`` are left out."""
    times = np.load(written["times"])
    step_us = round(1e6 / RATE_HZ)
    out = []
    for arrival, i, payload in records:
        t_us = decode_calibrated(payload)[1].t_us
        sent = times[np.minimum(t_us // step_us // chunk, len(times) - 1), i % times.shape[1]]
        out.append((arrival - sent)[sent >= after_ns])
    return np.concatenate(out) / 1e6 if out else np.zeros(0)


def verify(mcap: Path, sent: Sequence[int], calibrated: bool = True,
           first: int = 0) -> dict[str, int]:
    """Samples missing from the raw (and calibrated) topics, compared with what was sent to
    sensors ``first``, ``first + 1``, ...

    Every sensor's raw time stamps must be exactly 0, 10 ms, ... in order (the fleet's
    stream), one per sample sent. A file its process did not close (killed after its stop
    timeout) is checked on a repaired copy: what it had written still counts, the rest is
    lost."""
    try:
        parts = rec.recording_parts(mcap)
        return _missing(parts, sent, calibrated, first)
    except RecordingError:
        fixed = mcap.with_suffix(".repaired.mcap")
        repair(mcap, fixed)
        return _missing(rec.recording_parts(fixed), sent, calibrated, first)


def _missing(parts: list[Path], sent: Sequence[int], calibrated: bool,
             first: int) -> dict[str, int]:
    want = {sensor_id(i): n for i, n in enumerate(sent, start=first)}
    raw: dict[str, list[np.ndarray]] = {s: [] for s in want}
    cal: dict[str, int] = dict.fromkeys(want, 0)
    for sid, batch, _ in rec.iter_raw(parts):
        raw.setdefault(sid, []).append(batch.t_us)
    if calibrated:
        for sid, batch, _ in rec.iter_calibrated(parts):
            cal[sid] = cal.get(sid, 0) + len(batch)
    lost = wrong = cal_missing = 0
    step_us = round(1e6 / RATE_HZ)
    for sid, n in want.items():
        t = np.concatenate(raw[sid]) if raw[sid] else np.zeros(0, np.int64)
        expected = np.arange(n, dtype=np.int64) * step_us
        good = min(len(t), n)
        lost += n - good
        wrong += int(np.count_nonzero(t[:good] != expected[:good])) + max(0, len(t) - n)
        cal_missing += max(0, n - cal[sid]) if calibrated else 0
    return {"lost": lost, "wrong": wrong, "cal_missing": cal_missing}


def run_rung(n: int, batch_ms: float, a: argparse.Namespace, root: Path) -> dict[str, Any]:
    """One rung of the ladder: N sensors for ``a.seconds``, the daemon handling arrivals
    every ``batch_ms`` (0: at once); the table row."""
    work = Path(tempfile.mkdtemp(prefix=f"n{n}-", dir=root))
    fleet = FleetProcess(work, n, a.seconds, rate_hz=RATE_HZ, chunk=a.chunk, fmt="ascii")
    zport = free_port()
    cfg = work / "gateway.toml"
    cfg.write_text(gateway_toml(fleet.links, zport, work, extra=a.extra_toml))
    mcap = work / "gw.mcap"
    daemon = ChildProcess([sys.executable, "-m", "recal", "run", "--config", str(cfg),
                           "--mcap", str(mcap), "--batch-ms", str(batch_ms)],
                          work / "gateway.log")
    probe: LatencyProbe | None = None
    try:
        daemon.wait_line(READY_PREFIX, 120)
        probe = LatencyProbe.peer_of(zport, range(min(n, a.probe)))
        if until(lambda: probe.counts(n)[0] >= n, 60) == float("inf"):
            raise RuntimeError(f"ports did not open:\n{daemon.output()[-2000:]}")
        started = fleet.go()
        warm_ns = started["start_ns"] + int(a.warmup_s * 1e9)
        sleep_until(warm_ns)
        cpu0, wall0 = daemon.cpu_seconds(), time.monotonic()
        end_ns = started["start_ns"] + int(a.seconds * 1e9)
        sleep_until(end_ns)
        cpu1, wall1 = daemon.cpu_seconds(), time.monotonic()
        rss = daemon.rss_mb()
        written = fleet.done(60 + a.seconds)
        total = sum(written["sent"])
        catchup = until(lambda: min(probe.counts(n)[1:]) >= total, a.max_catchup_s + 60)
        lat = latencies_ms(probe.records, written, a.chunk, warm_ns)
        probe.close()
        probe = None
        code = daemon.terminate(120)
        fleet.close()
        check = verify(mcap, written["sent"])
        row = {
            "sensors": n, "batch_ms": batch_ms, "samples_per_s": n * RATE_HZ,
            "seconds": a.seconds,
            "daemon_cpu_pct": 100 * (cpu1 - cpu0) / (wall1 - wall0), "rss_mb": rss,
            "writer_cpu_pct": 100 * written["cpu_s"] / a.seconds,
            "writer_late_p99_ms": written["late_ms"]["p99"],
            "writer_backlog_bytes": written["max_backlog_bytes"],
            "lat_p50_ms": pct(lat, 50), "lat_p99_ms": pct(lat, 99),
            "lat_max_ms": float(lat.max()) if len(lat) else float("nan"),
            "probed_samples": len(lat), "catchup_s": catchup, "sent": total, **check,
            "exit": code, "load1": os.getloadavg()[0],
        }
        row["cpu_us_per_sample"] = row["daemon_cpu_pct"] * 1e4 / row["samples_per_s"]
        row["sustained"] = (check["lost"] == 0 and check["wrong"] == 0
                            and check["cal_missing"] == 0 and code == 0
                            and (row["lat_p99_ms"] <= a.max_p99_ms or a.probe == 0)
                            and catchup <= a.max_catchup_s)
        return row
    finally:
        if probe is not None:
            probe.close()
        daemon.kill()
        fleet.close()
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)


def pct(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def sleep_until(t_ns: int) -> None:
    wait = (t_ns - time.time_ns()) / 1e9
    if wait > 0:
        time.sleep(wait)


COLUMNS = [("sensors", "sensors", "{:d}"), ("batch_ms", "batch ms", "{:g}"),
           ("samples_per_s", "samples/s", "{:.0f}"),
           ("daemon_cpu_pct", "daemon CPU % of a core", "{:.1f}"),
           ("cpu_us_per_sample", "daemon CPU us/sample", "{:.0f}"),
           ("writer_cpu_pct", "writer CPU %", "{:.1f}"), ("rss_mb", "daemon RSS MB", "{:.0f}"),
           ("lat_p50_ms", "latency p50 ms", "{:.2f}"), ("lat_p99_ms", "p99 ms", "{:.2f}"),
           ("lat_max_ms", "max ms", "{:.1f}"), ("writer_late_p99_ms", "writer late p99 ms",
                                                 "{:.2f}"),
           ("catchup_s", "catch-up s", "{:.1f}"), ("sent", "samples sent", "{:d}"),
           ("lost", "lost", "{:d}"), ("cal_missing", "not calibrated", "{:d}"),
           ("load1", "load avg", "{:.1f}"), ("sustained", "sustained", "{}")]


def print_table(rows: Sequence[dict[str, Any]], out: Any = sys.stdout,
                columns: Sequence[tuple[str, str, str]] = COLUMNS) -> None:
    """A markdown table of ``rows``: (key, header, format) per column."""
    print("| " + " | ".join(h for _, h, _ in columns) + " |", file=out)
    print("|" + "---|" * len(columns), file=out)
    for r in rows:
        print("| " + " | ".join(fmt.format(r[k]) for k, _, fmt in columns) + " |", file=out)
    out.flush()


def report(rows: Sequence[dict[str, Any]], header: str, json_path: str | None,
           columns: Sequence[tuple[str, str, str]] = COLUMNS) -> None:
    """The bench's output: a comment line saying what ran, the table, the rows as JSON."""
    print(header)
    print_table(rows, columns=columns)
    if json_path:
        Path(json_path).write_text(json.dumps(list(rows), indent=1))


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sensors", default="1,10,50,100,200,300,400",
                    help="comma-separated ladder of sensor counts")
    ap.add_argument("--seconds", type=float, default=300.0, help="streaming time per rung")
    ap.add_argument("--warmup-s", type=float, default=None,
                    help="left out of CPU and latency (default: 10 %% of --seconds, 2-30 s)")
    ap.add_argument("--chunk", type=int, default=1, help="samples per device write")
    ap.add_argument("--batch-ms", default="0",
                    help="comma-separated daemon --batch-ms values; each runs the whole ladder")
    ap.add_argument("--probe", type=int, default=10, help="sensors whose latency is measured")
    ap.add_argument("--max-p99-ms", type=float, default=1000.0,
                    help="a rung is sustained only with latency p99 below this")
    ap.add_argument("--max-catchup-s", type=float, default=5.0)
    ap.add_argument("--extra-toml", default="", help="top-level TOML lines for the daemon")
    ap.add_argument("--nice", type=int, default=0,
                    help="run the daemon and this probe at this nice value (negative needs "
                    "root): shows their own latency apart from other load on a shared machine")
    ap.add_argument("--quick", action="store_true", help="20 s per rung, ladder 1,10,50,100")
    ap.add_argument("--keep", action="store_true", help="keep the work directories")
    ap.add_argument("--stop-at-failure", action="store_true",
                    help="stop the ladder at the first rung not sustained")
    ap.add_argument("--json", help="also write the rows here")
    a = ap.parse_args(argv)
    if a.quick:
        a.seconds = min(a.seconds, 20.0)
        if a.sensors == ap.get_default("sensors"):
            a.sensors = "1,10,50,100"
    if a.warmup_s is None:
        a.warmup_s = min(30.0, max(2.0, 0.1 * a.seconds))
    return a


def main(argv: Sequence[str] | None = None) -> int:
    a = _parse(argv)
    if a.nice:
        os.nice(a.nice)  # before any thread exists: the probe's Zenoh threads inherit it
    root = Path(tempfile.mkdtemp(prefix="daemon-scale-"))
    rows = []
    try:
        for batch_ms in (float(x) for x in a.batch_ms.split(",")):
            for n in (int(x) for x in a.sensors.split(",")):
                row = run_rung(n, batch_ms, a, root)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
                if a.stop_at_failure and not row["sustained"]:
                    break
    finally:
        if not a.keep:
            shutil.rmtree(root, ignore_errors=True)
    report(rows, f"# daemon_scale: {a.seconds:.0f} s per rung, {RATE_HZ:.0f} Hz sensors, "
           f"{a.chunk} sample(s) per write, latency over {a.probe} sensors, daemon nice "
           f"{a.nice}; {os.cpu_count()} cores shared by writer, daemon and probe", a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
