"""Live daemon per arrival: CPU per sample of ``recal run`` beside the floor, in one run.

For each sensor count (default 1 and 10 sensors at 100 Hz, one sample per device write), and
each of ``--runs`` rounds, this runs one after the other on an identically fed set of
pseudo-terminals (``bench/pty_fleet.py``, same simulated bytes, same write times):

* the floor: a bare ``select`` + ``os.read`` loop over the same ptys in a process of its own
  (it reads and discards; what any reader of these ports must pay for its wake-ups);
* the daemon: the real ``recal run`` (MCAP log and Zenoh on, default settings), measured by
  ``bench/daemon_scale.py``'s rung: CPU of all its threads over the run after the warm-up,
  latency from the device write to the calibrated sample at a Zenoh subscriber, nothing lost.

and reports medians over the rounds: CPU per sample (us) of each, their ratio, latency p50/p99,
the daemon's RSS at the end of the run (its discovery worker is spawned at the first run, 10
min of device time in: `bench/live_loop.py --live` measures it).

``--old-src DIR`` also runs the daemon from another source tree (``DIR/service`` first on
``PYTHONPATH``, e.g. ``git archive <commit> service | tar -x -C DIR``), interleaved with the
new one in every round, so old and new are measured side by side on the same load::

    python bench/arrival_cost.py --runs 3 --seconds 40 --old-src /tmp/recal-old

The daemons here start from an empty state folder (calibrating), not from a checkpoint.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import daemon_scale
from child_process import ChildProcess
from pty_fleet import FleetProcess

__all__ = ["floor_run", "main"]

# The floor: open every link, then select + read until stdin closes; nothing else but, with a
# work of W us (argv[1]), that much CPU spent per read (a stand-in for a reader whose handling
# costs W us, to show what this machine's scheduling does to its latency). The first link's
# lines are timed as read (and worked): "t_us read_ns" pairs go to argv[2] at the end.
FLOOR_CODE = """
import os, select, sys, time
work_s, times_path = float(sys.argv[1]) / 1e6, sys.argv[2]
fds = [os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY) for p in sys.argv[3:]]
import tty
for fd in fds:
    tty.setraw(fd)
poller = select.poll()
for fd in fds:
    poller.register(fd, select.POLLIN)
poller.register(0, select.POLLIN)
print("ready", flush=True)
n, tail, seen = 0, b"", []
while True:
    for fd, ev in poller.poll(1000):
        if fd == 0:
            with open(times_path, "w") as f:
                f.writelines(f"{t} {ns}\\n" for t, ns in seen)
            print("read", n, flush=True)
            sys.exit(0)
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            continue
        n += len(data)
        if work_s:
            end = time.thread_time() + work_s
            while time.thread_time() < end:
                pass
        if fd == fds[0] and len(seen) < 1_000_000:
            now = time.time_ns()
            lines = (tail + data).split(b"\\n")
            tail = lines.pop()
            seen += [(ln.split(b",", 1)[0].decode(), now) for ln in lines
                     if ln[:1].isdigit()]
"""


def floor_run(n: int, a: argparse.Namespace, root: Path, work_us: float = 0.0
              ) -> dict[str, Any]:
    """CPU of the bare read loop on ``n`` ptys fed as the daemon's are, and the latency
    from the device's write to the first pty's line read (and ``work_us`` of CPU spent on
    each read; the daemon's latency adds a Zenoh hop to a subscriber)."""
    work = Path(tempfile.mkdtemp(prefix=f"floor{n}-", dir=root))
    fleet = FleetProcess(work, n, a.seconds, rate_hz=daemon_scale.RATE_HZ, chunk=1, fmt="ascii")
    times_path = work / "floor-times.txt"
    reader = ChildProcess([sys.executable, "-c", FLOOR_CODE, str(work_us), str(times_path),
                           *fleet.links], work / "floor.log", stdin=True)
    try:
        reader.wait_line("ready", 30)
        started = fleet.go()
        daemon_scale.sleep_until(started["start_ns"] + int(a.warmup_s * 1e9))
        cpu0, wall0 = reader.cpu_seconds(), time.monotonic()
        daemon_scale.sleep_until(started["start_ns"] + int(a.seconds * 1e9))
        cpu1, wall1 = reader.cpu_seconds(), time.monotonic()
        written = fleet.done(60 + a.seconds)
        pct = 100 * (cpu1 - cpu0) / (wall1 - wall0)
        if reader.proc.stdin is not None:
            reader.proc.stdin.close()
        reader.wait_line("read ", 30)
        lat = _floor_latency_ms(times_path, written,
                                started["start_ns"] + int(a.warmup_s * 1e9))
        return {"sensors": n, "work_us": work_us, "floor_cpu_pct": pct,
                "floor_us_per_sample": pct * 1e4 / (n * daemon_scale.RATE_HZ),
                "lat_p50_ms": float(np.percentile(lat, 50)),
                "lat_p99_ms": float(np.percentile(lat, 99))}
    finally:
        reader.terminate(10)
        fleet.close()
        shutil.rmtree(work, ignore_errors=True)


def _floor_latency_ms(times_path: Path, written: dict, after_ns: int) -> np.ndarray:
    """Read minus write time (ms) of the first pty's samples written after ``after_ns``."""
    t_us, read_ns = np.loadtxt(times_path, dtype=np.int64, ndmin=2).T
    times = np.load(written["times"])
    sent = times[np.minimum(t_us // round(1e6 / daemon_scale.RATE_HZ), len(times) - 1), 0]
    keep = sent >= after_ns
    return (read_ns[keep] - sent[keep]) / 1e6


def daemon_run(n: int, a: argparse.Namespace, root: Path, src: str | None) -> dict[str, Any]:
    """``recal run`` on ``n`` sensors, from this tree or ``src`` (PYTHONPATH first)."""
    saved = os.environ.get("PYTHONPATH")
    if src:
        os.environ["PYTHONPATH"] = str(Path(src) / "service") + (
            os.pathsep + saved if saved else "")
    try:
        return daemon_scale.run_rung(n, 0.0, a, root)
    finally:
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sensors", default="1,10")
    ap.add_argument("--seconds", type=float, default=40.0, help="streaming time per run")
    ap.add_argument("--warmup-s", type=float, default=8.0)
    ap.add_argument("--runs", type=int, default=3, help="rounds; medians are reported")
    ap.add_argument("--old-src", help="also run the daemon from this source tree")
    ap.add_argument("--probe", type=int, default=10)
    ap.add_argument("--floor-work-us", type=float, default=1000.0,
                    help="also run the floor spending this much CPU per read (0: not): the "
                         "latency this machine gives a reader that costs as much as the daemon")
    a = ap.parse_args(argv)
    # what daemon_scale.run_rung reads
    a.chunk, a.extra_toml, a.keep, a.max_p99_ms, a.max_catchup_s = 1, "", False, 1000.0, 5.0
    return a


def _median(rows: list[dict[str, Any]], k: str) -> float:
    return statistics.median(r[k] for r in rows)


def main(argv: Sequence[str] | None = None) -> int:
    a = _parse(argv)
    root = Path(tempfile.mkdtemp(prefix="arrival-cost-"))
    variants = [("new", None)] + ([("old", a.old_src)] if a.old_src else [])
    results: dict[tuple[str, int], list[dict[str, Any]]] = {}
    floors: dict[int, list[dict[str, Any]]] = {}
    worked: dict[int, list[dict[str, Any]]] = {}
    try:
        for r in range(a.runs):
            for n in (int(x) for x in a.sensors.split(",")):
                floors.setdefault(n, []).append(floor_run(n, a, root))
                if a.floor_work_us > 0:
                    worked.setdefault(n, []).append(floor_run(n, a, root, a.floor_work_us))
                    print("floor", n, floors[n][-1], worked[n][-1], file=sys.stderr, flush=True)
                # alternate the order so neither variant always runs second
                for name, src in (variants if r % 2 == 0 else variants[::-1]):
                    row = daemon_run(n, a, root, src)
                    results.setdefault((name, n), []).append(row)
                    print(name, n, {k: row[k] for k in ("cpu_us_per_sample", "lat_p50_ms",
                                                        "lat_p99_ms", "lost", "load1")},
                          floors[n][-1]["floor_us_per_sample"], file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(f"# arrival_cost: {a.runs} runs of {a.seconds:g} s (warm-up {a.warmup_s:g} s), "
          f"100 Hz sensors, one sample per write; medians; {os.cpu_count()} cores; load "
          f"{os.getloadavg()[0]:.2f}")
    print("| daemon | sensors | floor us/sample | daemon us/sample | ratio | latency p50 ms "
          "| p99 ms | lost | RSS MB | load avg |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (name, n), rows in results.items():
        fl = _median(floors[n], "floor_us_per_sample")
        us = _median(rows, "cpu_us_per_sample")
        print(f"| {name} | {n} | {fl:.0f} | {us:.0f} | {us / fl:.1f} | "
              f"{_median(rows, 'lat_p50_ms'):.2f} | {_median(rows, 'lat_p99_ms'):.2f} | "
              f"{sum(r['lost'] for r in rows)} | {_median(rows, 'rss_mb'):.0f} | "
              f"{_median(rows, 'load1'):.1f} |")
    print("\n| floor | sensors | work us/read | us/sample | latency p50 ms | p99 ms |")
    print("|---|---|---|---|---|---|")
    for n, rows in sorted(floors.items()):
        for r_ in (rows, worked.get(n, [])):
            if r_:
                print(f"| bare read loop | {n} | {r_[0]['work_us']:.0f} | "
                      f"{_median(r_, 'floor_us_per_sample'):.0f} | "
                      f"{_median(r_, 'lat_p50_ms'):.2f} | {_median(r_, 'lat_p99_ms'):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
