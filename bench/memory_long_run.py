"""Memory over a long run: RSS while a simulated week at 100 Hz goes through the
daemon's code path.

    python bench/memory_long_run.py            # 7 days (60.5 M samples), 3 runs
    python bench/memory_long_run.py --quick    # 12 h (4.3 M samples), 3 runs

The daemon's code path is what the gateway does with every batch it reads: log it
(`RecordingWriter.write_raw`), then `CalibrationNode.process` it (detector, windows, estimator,
alignment; calibrated, body, plot, calibration states and events into the same recording).
The writer has the gateway's default [mcap] settings (32 KiB chunks, a flush every second, one
file, no rotation: the most index the writer can accumulate) except fsync (a week of fsyncs
measures the disk, not memory), and its flush clock follows device time, so the file is
chunked as a live week would be (a chunk at least every second). The sensor is configured
with a prior (1024 counts/g) as in configs/gateway.toml.

Input: generated hour by hour in a separate process (recal.sim.wearer, the same sensor, a new wearer
schedule every hour), one MCAP of 1000-sample messages read back one message at a time: never
in memory as a whole. Each run is a fresh process; a thread samples VmRSS from
/proc/self/status every 0.5 s together with the samples processed so far.

Reported (medians over --runs runs): RSS after imports, after the warm-up (the first simulated
day, or the first tenth of a shorter recording), at the end; growth = end - warm-up and the
largest RSS after warm-up - warm-up; the kernel's peak (VmHWM). Targets: growth <= 5 MB,
peak <= 300 MB.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from child_process import status_mb

RATE_HZ = 100.0
SENSOR = "s1"
T0_NS = 1_700_000_000_000_000_000
SAMPLES_PER_MESSAGE = 1000
#: longest a generating or measuring child may take (a week runs in 2-5 min on this machine)
CHILD_TIMEOUT_S = 3600.0


def generate(path: Path, hours: int, seed: int) -> None:
    """The recording, one simulated hour at a time (never all of it in memory)."""
    from recal.io.recording_writer import RecordingWriter
    from recal.sim.wearer import SensorSpec, simulate

    sensor = SensorSpec.random(np.random.default_rng(seed), offset_mg=40.0, gain_pct=3.0)
    with RecordingWriter(path, chunk_size=4 << 20, background_flush=False, fsync=False,
                         overwrite=True) as w:
        for h in range(hours):
            raw = simulate(1.0, RATE_HZ, seed * 1000 + h, sensor,
                           start_us=h * 3_600_000_000).raw
            for i in range(0, len(raw), SAMPLES_PER_MESSAGE):
                b = raw[i:i + SAMPLES_PER_MESSAGE]
                w.write_raw(SENSOR, b, T0_NS + int(b.t_us[0]) * 1000)


class DeviceClock:
    """Monotonic seconds for the writer's flush timing, following the device time fed."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def measure(path: Path, out_dir: Path, warmup_samples: int) -> dict[str, Any]:
    """One run in this (fresh) process: the daemon's code path over the recording."""
    from recal.config.settings import PriorConfig, SensorConfig, ServiceConfig
    from recal.io import recording as rec
    from recal.io.recording_writer import RecordingWriter
    from recal.node.node import CalibrationNode, node_settings
    from recal.node.sinks import RecordingSink

    cfg = ServiceConfig()
    m = cfg.mcap
    clock = DeviceClock()
    writer = RecordingWriter(out_dir / "daemon.mcap", chunk_size=m.chunk_size,
                             flush_interval_s=m.flush_interval_s,
                             compression=m.compression,  # type: ignore[arg-type]
                             fsync=False, clock=clock, background_flush=False,
                             overwrite=True)
    sensor = SensorConfig(id=SENSOR, rate_hz=RATE_HZ, prior=PriorConfig(counts_per_g=1024.0))
    node = CalibrationNode(node_settings(sensor, cfg), RecordingSink(writer))
    done = [0]
    trace: list[tuple[float, int, float]] = []  # (s since start, samples, RSS MB)
    stop = threading.Event()
    t0 = time.perf_counter()

    def sample() -> None:
        while not stop.wait(0.5):
            trace.append((time.perf_counter() - t0, done[0], status_mb("self", "VmRSS")["VmRSS"]))

    rss_start = status_mb("self", "VmRSS")["VmRSS"]
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    for _, batch, log_ns in rec.iter_raw(path):
        clock.now_s = batch.t_us[-1] / 1e6
        writer.write_raw(SENSOR, batch, log_ns)
        node.process(batch, log_ns)
        done[0] += len(batch)
    rss_end = status_mb("self", "VmRSS")["VmRSS"]  # before close (the summary is written then)
    writer.close()
    seconds = time.perf_counter() - t0
    stop.set()
    sampler.join()
    after = [r for _, n, r in trace if n >= warmup_samples]
    rss_warm = after[0] if after else rss_end
    return {"samples": done[0], "seconds": seconds, "rss_start_mb": rss_start,
            "rss_warm_mb": rss_warm, "rss_end_mb": rss_end,
            "growth_mb": rss_end - rss_warm,
            "max_growth_mb": max([*after, rss_end]) - rss_warm,
            "peak_mb": status_mb("self", "VmHWM")["VmHWM"],
            "updates": node.pipeline.counts["updates"] if node.pipeline else 0,
            "out_bytes": sum(p.stat().st_size for p in writer.paths),
            "trace": trace}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="12 simulated hours, 3 runs")
    ap.add_argument("--hours", type=int, help="simulated hours (default 168 = 7 days)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--keep", type=Path, help="keep (and reuse) the input recording here")
    ap.add_argument("--generate", type=Path, help=argparse.SUPPRESS)  # child: write input
    ap.add_argument("--measure", type=Path, help=argparse.SUPPRESS)  # child: one run
    ap.add_argument("--out-dir", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--warmup", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    hours = a.hours or (12 if a.quick else 168)
    if a.generate is not None:
        generate(a.generate, hours, a.seed)
        return 0
    if a.measure is not None:
        print(json.dumps(measure(a.measure, a.out_dir, a.warmup)))
        return 0

    n_samples = round(hours * 3600 * RATE_HZ)
    warmup = round(min(24.0, hours / 10) * 3600 * RATE_HZ)
    me = [sys.executable, str(Path(__file__).resolve())]
    with tempfile.TemporaryDirectory(prefix="recal-memory-bench-") as tmp:
        src = (a.keep or Path(tmp)) / f"week-{hours}h-seed{a.seed}.mcap"
        src.parent.mkdir(parents=True, exist_ok=True)
        if not src.exists():
            t = time.perf_counter()
            subprocess.run([*me, "--generate", str(src), "--hours", str(hours), "--seed",
                            str(a.seed)], check=True, timeout=CHILD_TIMEOUT_S)
            print(f"generated {src.name}: {n_samples:,} samples in "
                  f"{time.perf_counter() - t:.0f} s", flush=True)
        runs = []
        for k in range(a.runs):
            res = subprocess.run([*me, "--measure", str(src), "--out-dir", tmp, "--warmup",
                                  str(warmup)], check=True, capture_output=True, text=True,
                                 timeout=CHILD_TIMEOUT_S)
            r = json.loads(res.stdout)
            runs.append(r)
            print(f"  run {k + 1}: {r['samples']:,} samples in {r['seconds']:.0f} s, RSS "
                  f"{r['rss_warm_mb']:.1f} -> {r['rss_end_mb']:.1f} MB, peak "
                  f"{r['peak_mb']:.1f} MB", flush=True)
    med = {k: statistics.median(r[k] for r in runs) for k in (
        "rss_start_mb", "rss_warm_mb", "rss_end_mb", "growth_mb", "max_growth_mb", "peak_mb",
        "seconds")}
    print(f"\nrecal memory over a long run: {hours} h at {RATE_HZ:g} Hz ({n_samples:,} samples) "
          f"through the daemon's code path, {len(runs)} runs, medians")
    head = (f"{'RSS after imports':>17} | {'after warm-up':>13} | {'at end':>7} | "
            f"{'growth':>7} | {'max growth':>10} | {'peak (VmHWM)':>12} | {'run time':>8}")
    print(head)
    print("-" * len(head))
    print(f"{med['rss_start_mb']:>14.1f} MB | {med['rss_warm_mb']:>10.1f} MB | "
          f"{med['rss_end_mb']:>4.1f} MB | {med['growth_mb']:>4.1f} MB | "
          f"{med['max_growth_mb']:>7.1f} MB | {med['peak_mb']:>9.1f} MB | "
          f"{med['seconds']:>6.0f} s")
    print(f"\nwarm-up: the first {warmup:,} samples; targets: growth <= 5 MB, peak <= 300 MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
