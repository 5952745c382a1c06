"""`bench/live_loop.py --live`: each case through a real pseudo-terminal into `recal run`
(the module doc of live_loop.py says what is measured and why)."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from child_process import ChildProcess, cpu_seconds, status_mb
from recal.commands.demo import free_port
from recal.core.model import SensorModel
from recal.core.status import Status
from recal.daemon.gateway import READY_PREFIX
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_json
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice

__all__ = ["main"]

SID = "s1"
CHUNK = 50  # samples per pty write


def _config(work: Path, link: str, zport: int, raw: RawBatch, s0: float, zero: float,
            rate: float) -> Path:
    """A gateway config for the one sensor: the defaults (discovery on), the simulated
    sensor's nominal prior (as the in-process stream's)."""
    path = work / "gateway.toml"
    path.write_text(f"""[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{zport}"]
connect = []

[checkpoint]
dir = "{work / 'ck'}"
interval_s = 60

[[sensors]]
id = "{SID}"
port = "{link}"
aux_names = {json.dumps(list(raw.aux_names))}
rate_hz = {rate}
prior = {{ counts_per_g = {s0}, zero_g = {zero} }}
""")
    return path


def _samples(bus: Bus) -> int:
    """The node's sample count from the daemon's status reply (-1: no reply)."""
    for _k, payload in bus.get(key(SID, "status"), timeout_s=1.0):
        node = decode_json(payload).get("node") or {}
        return int(node.get("samples", -1))
    return -1


def _children(pid: int) -> list[int]:
    """The direct child processes of ``pid`` (Linux: /proc/<pid>/task/*/children)."""
    out: list[int] = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out += [int(x) for x in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
        except OSError:
            continue
    return out


def _worker(pid: int) -> int | None:
    """The daemon's discovery worker (a spawned multiprocessing child; not the resource
    tracker spawn also starts)."""
    for c in _children(pid):
        try:
            cmd = Path(f"/proc/{c}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd:
            return c
    return None


def _stream(dev: PtyDevice, raw: RawBatch, per_s: float) -> None:
    """Write ``raw`` CHUNK samples at a time, paced at ``per_s`` samples per wall second."""
    start = time.monotonic()
    for i in range(0, len(raw), CHUNK):  # bounded: one pass
        wait = start + i / per_s - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, 1.0))
        dev.write_batch(raw[i:i + CHUNK])


def live_case(raw: RawBatch, s0: float, zero: float, rate: float, speed: float,
              old_src: str | None) -> dict[str, Any]:
    """The recording through a pty into `recal run`; its calibrated output and discovery
    events from the MCAP log, CPU and peak RSS of the daemon and its worker."""
    work = Path(tempfile.mkdtemp(prefix="live-loop-"))
    link, zport = str(work / "tty0"), free_port()
    cfg = _config(work, link, zport, raw, s0, zero, rate)
    saved = os.environ.get("PYTHONPATH")
    if old_src:
        os.environ["PYTHONPATH"] = str(Path(old_src) / "service") + (
            os.pathsep + saved if saved else "")
    try:
        with PtyDevice(link, write_timeout_s=60.0) as dev:
            daemon = ChildProcess([sys.executable, "-m", "recal", "run", "--config", str(cfg),
                                   "--mcap", str(work / "live.mcap")], work / "gateway.log")
            bus = None
            try:
                ready = daemon.wait_line(READY_PREFIX, 120)
                mcap = Path(re.search(r"mcap=(\S+)", ready).group(1))  # type: ignore[union-attr]
                bus = Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"],
                                       [f"tcp/127.0.0.1:{zport}"]))
                for _ in range(100):  # bounded: the port opens within seconds
                    if _samples(bus) >= 0:
                        break
                    time.sleep(0.1)
                cpu0, t0 = cpu_seconds(daemon.pid), time.monotonic()
                _stream(dev, raw, speed * rate)
                deadline = time.monotonic() + 600
                while _samples(bus) < len(raw) and time.monotonic() < deadline:  # bounded
                    time.sleep(0.5)
                wall = time.monotonic() - t0
                cpu = cpu_seconds(daemon.pid) - cpu0
                mem = status_mb(daemon.pid, "VmHWM", "VmRSS")
                w = _worker(daemon.pid)
                wmem = status_mb(w, "VmHWM", "VmRSS") if w else {}
                wcpu = cpu_seconds(w) if w else float("nan")
            finally:
                if bus is not None:
                    bus.close()
                daemon.proc.send_signal(signal.SIGTERM)
                daemon.wait(60)
        cal = rec.read_all_calibrated(mcap, SID)
        # `recal replay` of the live log, with its defaults: where it adopts, its output
        replayed = work / "replayed.mcap"
        subprocess.run([sys.executable, "-m", "recal", "replay", str(mcap), "--out",
                        str(replayed), "--quiet"], check=True, stdout=subprocess.DEVNULL)
        again = rec.read_all_calibrated(replayed, SID)
        if len(again) != len(cal) or not np.array_equal(again.t_us, cal.t_us):
            agree = "differs (samples)"
        else:
            off = np.max(np.abs(again.a_g - cal.a_g), axis=1) > 1e-9
            st = again.status != cal.status
            agree = ("same" if not (off.any() or st.any()) else
                     f"{int(off.sum())} values differ ("
                     + ", ".join(f"{Status(k).label} {int(n)}" for k, n in
                                 zip(*np.unique(cal.status[off], return_counts=True),
                                     strict=True))
                     + f"), {int(st.sum())} statuses")
        return {"cal": cal, "events": _discoveries(mcap), "replayed": _discoveries(replayed),
                "replay_output_same": agree, "cpu_us": 1e6 * cpu / len(raw), "wall_s": wall,
                "rss": mem, "worker_rss": wmem, "worker_cpu_s": wcpu}
    finally:
        if old_src:
            if saved is None:
                os.environ.pop("PYTHONPATH", None)
            else:
                os.environ["PYTHONPATH"] = saved
        shutil.rmtree(work, ignore_errors=True)


def _discoveries(mcap: Path) -> list[dict]:
    return [o for _, o, _ in rec.iter_json([mcap], f"/{SID}/events")
            if o.get("kind") == "discovery"]


def _adopted(events: Sequence[dict], t0: int) -> list[tuple[str, float, int]]:
    return [("+".join(e["detail"]["added"]), (e["t_us"] - t0) / 60e6, e["t_us"] - t0)
            for e in events if e["detail"]["adopted"]]


def main(a: argparse.Namespace, cases: Sequence[Any], simulated: Callable[..., Any],
         run: Callable[..., Any], true_model: Callable[..., SensorModel],
         after: Callable[..., dict]) -> int:
    print(f"# --live: through a pty into `recal run` at {a.speed:g}x real time"
          + (f", daemon from {a.old_src}" if a.old_src else ""))
    print("| case | cal % | err/floor | >3 / >10 % | med sig / med err mg | adopted (min) | "
          "replay of the live log: adopts, output | daemon us/sample | daemon RSS peak MB | "
          "worker RSS peak MB, CPU s |\n|---|---|---|---|---|---|---|---|---|---|")
    for case in cases:
        if a.only and a.only not in case.name:
            continue
        spec, res = simulated(case, a)
        raw, truth = res.raw, res.truth.a_true_g
        s0, zero = float(spec.counts_per_g or 1.0), float(spec.zero_g_counts)
        out = live_case(raw, s0, zero, a.rate, a.speed, a.old_src)
        cal = out["cal"]
        if len(cal) != len(raw):
            print(f"| {case.name} | {len(raw) - len(cal)} samples missing from the log |")
            continue
        fl, _, _ = run(raw, true_model(case, s0, raw), spec.zero_g_counts, False, a.rate)
        start = int(np.searchsorted(raw.t_us, raw.t_us[0] + 3.6e9))
        m = after(cal, truth, spec.noise_g, a.rate, start)
        f = after(fl, truth, spec.noise_g, a.rate, start)
        t0 = int(cal.t_us[0])
        live = _adopted(out["events"], t0)
        again = _adopted(out["replayed"], t0)
        same = ("same" if [x[::2] for x in live] == [x[::2] for x in again]
                else f"differs: {[x[::2] for x in again]}")
        same += ", output " + out["replay_output_same"]
        said = "; ".join(f"{n} @{mnt:.0f}" for n, mnt, _ in live) or "-"
        w = out["worker_rss"]
        print(f"| {case.name} | {m['cal_pct']:.1f} | {m['err_rms_mg'] / f['err_rms_mg']:.2f} | "
              f"{100 * m['beyond_3']:.2f} / {100 * m['beyond_10']:.2f} | "
              f"{m['med_sig']:.2f} / {m['med_err']:.2f} | {said} | {same} | "
              f"{out['cpu_us']:.0f} | {out['rss'].get('VmHWM', float('nan')):.0f} / "
              f"{out['rss'].get('VmRSS', float('nan')):.0f} | "
              f"{w.get('VmHWM', float('nan')):.0f}, {out['worker_cpu_s']:.1f} |", flush=True)
    return 0
