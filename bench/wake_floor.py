"""What one 100 Hz sensor costs a Python process per arrival, stage by stage.

The daemon's goals (issue 5) are CPU <= 2 % of a core at 1 sensor and p99 latency <= 5 ms.
Samples 10 ms apart cannot be gathered into batches within 5 ms, so each arrival is handled on
its own, and 2 % of a core at 100 Hz leaves 200 us per arrival for everything. This measures
what the gateway's stages cost on this machine without Zenoh or the daemon around them: one
simulated sensor on a pseudo-terminal (ASCII lines, written at its real rate by
`pty_fleet.py` in a child process), read by this process in a selector loop like the gateway's.
Each stage adds to the one before, in a run of its own:

    wake    selector wait + os.read of what arrived (no work at all: the floor)
    parse   SerialSource.poll: read and parse the lines (recal.io.frames)
    step    + Pipeline.step on the parsed samples (detector, windows, estimator, correction)
    log     + the raw and calibrated messages written to an MCAP file (RecordingWriter)

CPU is this process's user + system time over the run after a warm-up, per arrival and as a
share of one core; medians of --runs runs.

A second table runs the same work in this process without the pty (lines from memory, so no
read): each call back to back ("warm"), then each after `IDLE_S` of sleep, as between two
arrivals of a 100 Hz sensor ("after idling"). The ratio is what idling between arrivals does
to the cost of the same code on this machine (caches and predictors cold again).

    python bench/wake_floor.py                 # 20 s per stage, 3 runs, the warm table: ~6 min
    python bench/wake_floor.py --seconds 5 --runs 1
"""

from __future__ import annotations

import argparse
import os
import resource
import selectors
import statistics
import tempfile
import time
from pathlib import Path

from pty_fleet import FleetProcess
from recal.config import SensorConfig, ServiceConfig, model_and_prior
from recal.core.pipeline import Pipeline
from recal.io.ascii_lines import encode_ascii
from recal.io.recording_writer import RecordingWriter
from recal.io.serial_source import SerialSource
from recal.io.wire_formats import make_parser
from recal.samples import RawBatch
from recal.sim.wearer import simulate

RATE_HZ = 100.0
STAGES = ("wake", "parse", "step", "log")
IDLE_S = 1.0 / RATE_HZ


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class _Handler:
    """What the loop does with one arrival, up to `stage`."""

    def __init__(self, stage: str, src: SerialSource | None, out: Path) -> None:
        self.stage, self.src = stage, src
        cfg = ServiceConfig()
        model, prior = model_and_prior(SensorConfig(id="s1"), cfg.pipeline)
        self.pipe = Pipeline(cfg.pipeline.pipeline_config(RATE_HZ), model, prior, ())
        self.writer = (RecordingWriter(out, background_flush=False, fsync=False,
                                       overwrite=True) if stage == "log" else None)
        self.samples = 0

    def __call__(self, fd: int) -> None:
        if self.stage == "wake":
            self.samples += len(os.read(fd, 65536)) > 0
            return
        assert self.src is not None, "a handler without a source is fed by work()"
        self.work(self.src.poll(readable=True)[0])

    def work(self, batch: RawBatch) -> None:
        """Everything after the read and parse, up to `stage`."""
        self.samples += len(batch)
        if self.stage == "parse" or not len(batch):
            return
        cal = self.pipe.step(batch).calibrated
        if self.writer is not None:
            now_ns = time.time_ns()
            self.writer.write_raw("s1", batch, now_ns)
            self.writer.write_calibrated("s1", cal, now_ns)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def run_stage(stage: str, seconds: float, warmup_s: float, root: Path) -> dict[str, float]:
    work = Path(tempfile.mkdtemp(prefix=f"{stage}-", dir=root))
    fleet = FleetProcess(work, 1, seconds + warmup_s, rate_hz=RATE_HZ, fmt="ascii")
    src = SerialSource(fleet.links[0], make_parser("ascii"))
    handler: _Handler | None = None
    sel = selectors.DefaultSelector()
    try:
        src.poll()  # opens the port
        fd = src.fileno()
        if fd is None:
            raise RuntimeError(f"{fleet.links[0]} did not open")
        handler = _Handler(stage, src, work / "out.mcap")
        sel.register(fd, selectors.EVENT_READ)
        started = fleet.go()
        t_warm = started["start_ns"] / 1e9 + warmup_s
        t_end = started["start_ns"] / 1e9 + warmup_s + seconds
        wakes, cpu0, n0, wall0 = 0, None, 0, time.monotonic()
        while time.time() < t_end:
            if cpu0 is None and time.time() >= t_warm:
                cpu0, wall0, n0, wakes = _cpu_s(), time.monotonic(), handler.samples, 0
            if sel.select(0.5):
                handler(fd)
                wakes += 1
        cpu, wall = _cpu_s() - (cpu0 or 0.0), time.monotonic() - wall0
        fleet.done(30)
        return {"cpu_pct": 100.0 * cpu / wall, "us_per_wake": 1e6 * cpu / max(wakes, 1),
                "wakes_per_s": wakes / wall, "samples": handler.samples - n0}
    finally:
        sel.close()
        if handler is not None:
            handler.close()
        src.close()
        fleet.close()


def warm_and_idle(stage: str, calls: int, root: Path) -> tuple[float, float]:
    """CPU us per call of `stage`'s work on one line each: back to back, and each call after
    IDLE_S of sleep (the sleep's own wake-up counted, as an arrival's is)."""
    raw = simulate(2 * calls / RATE_HZ / 3600, RATE_HZ, 1).raw
    lines = encode_ascii(raw).splitlines(keepends=True)
    work = Path(tempfile.mkdtemp(prefix=f"warm-{stage}-", dir=root))
    handler = _Handler(stage, None, work / "out.mcap")
    parser = make_parser("ascii")
    try:
        per_call = []
        for gap_s, part in ((0.0, lines[:calls]), (IDLE_S, lines[calls:2 * calls])):
            cpu0 = _cpu_s()
            for line in part:
                if gap_s:
                    time.sleep(gap_s)
                if stage != "wake":
                    handler.work(parser.feed(line))
            per_call.append(1e6 * (_cpu_s() - cpu0) / len(part))
        return per_call[0], per_call[1]
    finally:
        handler.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="measured seconds per stage")
    ap.add_argument("--warmup", type=float, default=3.0, help="seconds before measuring")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--calls", type=int, default=500,
                    help="calls per run in the warm / after-idling table")
    a = ap.parse_args(argv)
    if a.seconds <= 0 or a.warmup < 0 or a.runs < 1 or a.calls < 1:
        ap.error("--seconds must be positive, --warmup not negative, --runs and --calls at "
                 "least 1")
    res: dict[str, list[dict[str, float]]] = {s: [] for s in STAGES}
    with tempfile.TemporaryDirectory(prefix="wake-floor-") as tmp:
        for r in range(a.runs):
            for stage in STAGES:
                res[stage].append(run_stage(stage, a.seconds, a.warmup, Path(tmp)))
                print(f"  run {r + 1}/{a.runs} {stage}: "
                      f"{res[stage][-1]['cpu_pct']:.2f} % CPU", flush=True)
    print(f"\none 100 Hz sensor on a pty, {a.seconds:g} s per stage, medians of {a.runs} runs\n")
    print(f"{'stage':>6} | {'CPU % of a core':>15} | {'us per arrival':>14} | "
          f"{'arrivals/s':>10} | {'samples':>7}")
    print("-" * 66)
    for stage in STAGES:
        med = {k: statistics.median(x[k] for x in res[stage]) for k in res[stage][0]}
        print(f"{stage:>6} | {med['cpu_pct']:>15.2f} | {med['us_per_wake']:>14.0f} | "
              f"{med['wakes_per_s']:>10.1f} | {med['samples']:>7.0f}")
    print("\ngoal: 2 % of a core at 1 sensor = 200 us per arrival at 100 arrivals/s")
    print(f"\nthe same work per line without the pty, CPU us per call, medians of {a.runs} runs "
          f"of {a.calls} calls\n")
    print(f"{'stage':>6} | {'warm (back to back)':>19} | {'after idling 10 ms':>18} | "
          f"{'ratio':>5}")
    print("-" * 60)
    with tempfile.TemporaryDirectory(prefix="wake-warm-") as tmp:
        for stage in STAGES:
            pairs = [warm_and_idle(stage, a.calls, Path(tmp)) for _ in range(a.runs)]
            warm = statistics.median(w for w, _ in pairs)
            idle = statistics.median(i for _, i in pairs)
            ratio = f"{idle / warm:5.1f}" if warm >= 1.0 else "    -"
            print(f"{stage:>6} | {warm:>19.0f} | {idle:>18.0f} | {ratio}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
