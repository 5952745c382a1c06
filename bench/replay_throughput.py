"""Replay end to end: MCAP in -> calibrated MCAP out, beside merely reading the file.

    python bench/replay_throughput.py            # full: 2 h at 100 Hz per case, 5 runs
    python bench/replay_throughput.py --quick    # 15 min per case, 3 runs
    python bench/replay_throughput.py --old /path/to/old/tree --hours 2 --runs 3 \
        --live-minutes 30                        # an old tree's replay beside this one's

Replay is `recal.commands.replay.replay(in, out)` (what `recal replay` runs): every raw message
through the calibration node the gateway runs live (detector, windows, estimator, correction,
alignment), and everything written to a new MCAP (raw, calibrated, body, plot, calibration
states, events). Targets: at least 1 M samples/s, and at least half the speed of merely
reading and decoding the same file's messages with the mcap reader (ratio >= 0.5).

Timed back to back in every run, on the same file (the machine is shared and noisy: ratios are
taken within a run, and the table shows medians over --runs runs):

    mcap reader    mcap.reader.make_reader(f).iter_messages() + recal's decode_raw of every
                   raw message (the reference for the ratio)
    recal reader   recal.io.recording.iter_raw (the reader replay uses)
    core alone     Pipeline.step over the already decoded batches, one step per message (the
                   calibration's share; no node, no MCAP)
    replay         recal.commands.replay.replay end to end: wall clock, and its CPU seconds (the
                   output is compressed on a second thread, so CPU can exceed wall)

Rates are samples per wall-clock second; "per CPU s" divides by the process's CPU time
instead (both threads), which a busy machine inflates much less than wall time: when other
processes share the cores, "replay CPU/wall" drops below 1 and the wall rates with it.

Recordings: a simulated wearer at 100 Hz (recal.sim.wearer defaults: still 20-180 s, moving 4-30 s;
offsets +-40 mg, gains +-3 %, 1024 counts/g), written as `recal simulate` writes them (zstd,
32 KiB chunks, no prior, so replay bootstraps), in messages of 1000 samples (`recal simulate`,
`recal import`) and of 100 and 10 samples (a live gateway logs what each serial read brought:
a few samples per message at 100 Hz). Replay feeds the node several consecutive messages at a
time when it can (the pipeline is batch-size invariant); outputs stay per message.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from layout import module
from recal.core.pipeline import Pipeline
from recal.io import messages
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.samples import RawBatch

replay = module("recal.commands.replay", "recal.replay").replay
_settings = module("recal.config.settings", "recal.config")
SensorConfig, ServiceConfig = _settings.SensorConfig, _settings.ServiceConfig
model_and_prior = module("recal.config.model_prior", "recal.config.settings",
                         "recal.config").model_and_prior
_wearer = module("recal.sim.wearer", "recal.sim")
SensorSpec, simulate = _wearer.SensorSpec, _wearer.simulate

RATE_HZ = 100.0
SENSOR = "s1"


def write_recording(path: Path, raw: RawBatch, samples_per_message: int) -> None:
    """The samples in float64 messages of the given size, one per batch (the first log form,
    which every version reads: the same input for an old tree's run of this bench)."""
    with RecordingWriter(path, background_flush=False, fsync=False, overwrite=True) as w:
        for i in range(0, len(raw), samples_per_message):
            b = raw[i:i + samples_per_message]
            w.write_encoded(f"/{SENSOR}/raw", messages.encode_raw(SENSOR, b),
                            1_700_000_000_000_000_000 + int(b.t_us[0]) * 1000,
                            int(b.t_us[0]) * 1000, schema=messages.RAW_SCHEMA)


def read_mcap(path: Path) -> int:
    """Samples read and decoded with the mcap library's reader."""
    n = 0
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if channel.topic.endswith("/raw"):
                n += len(messages.decode_raw(message.data)[1])
    return n


def read_recal(path: Path) -> int:
    return sum(len(b) for _, b, _ in rec.iter_raw(path))


def core_alone(batches: list[RawBatch]) -> int:
    """Pipeline.step per message, set up as replay sets up a sensor without prior."""
    cfg = ServiceConfig()
    model, prior = model_and_prior(SensorConfig(id=SENSOR), cfg.pipeline)
    pipe = Pipeline(cfg.pipeline.pipeline_config(RATE_HZ), model, prior, ())
    for b in batches:
        pipe.step(b)
    return pipe.counts["samples"]


def timed(fn: Callable[[], int]) -> tuple[float, float, int]:
    """(wall s, CPU s, samples) of one call."""
    w, c = time.perf_counter(), time.process_time()
    n = fn()
    return time.perf_counter() - w, time.process_time() - c, n


def run_case(path: Path, out: Path, runs: int) -> dict[str, list[float]]:
    batches = [b for _, b, _ in rec.iter_raw(path)]
    res: dict[str, list[float]] = {k: [] for k in (
        "mcap", "recal", "core", "replay", "replay_cpu", "ratio_mcap", "ratio_recal",
        "replay_per_cpu", "ratio_mcap_cpu")}
    for _ in range(runs):
        t_mcap, c_mcap, n = timed(lambda: read_mcap(path))
        t_recal, _, n2 = timed(lambda: read_recal(path))
        t_core, _, n3 = timed(lambda: core_alone(batches))
        t_rep, c_rep, n4 = timed(lambda: replay(path, out, progress=False,
                                                overwrite=True)["samples"])
        if not n == n2 == n3 == n4:
            raise RuntimeError(f"sample counts differ: {n} {n2} {n3} {n4}")
        res["mcap"].append(n / t_mcap)
        res["recal"].append(n / t_recal)
        res["core"].append(n / t_core)
        res["replay"].append(n / t_rep)
        res["replay_cpu"].append(c_rep / t_rep)
        res["ratio_mcap"].append(t_mcap / t_rep)
        res["ratio_recal"].append(t_recal / t_rep)
        res["replay_per_cpu"].append(n / c_rep)
        res["ratio_mcap_cpu"].append(c_mcap / c_rep)
    return res


_CHILD = r"""
import json, sys, time
from mcap.reader import make_reader
from recal.io import messages
try:
    from recal.commands.replay import replay
except ModuleNotFoundError:  # a tree from before the package layout
    from recal.replay import replay
src, out = sys.argv[1], sys.argv[2]
t = time.perf_counter()
n = 0
with open(src, "rb") as f:
    for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
        if channel.topic.endswith("/raw"):
            n += len(messages.decode_raw(message.data)[1])
t_mcap = time.perf_counter() - t
t, c = time.perf_counter(), time.process_time()
summary = replay(src, out, progress=False, overwrite=True)
print(json.dumps({"n": n, "mcap": t_mcap, "replay": time.perf_counter() - t,
                  "cpu": time.process_time() - c, "samples": summary["samples"]}))
"""


def replay_in(tree: Path, src: Path, out: Path) -> dict[str, float]:
    """The mcap reader's and `replay`'s seconds on ``src`` in a fresh process importing recal
    from ``tree``/service (its imports warmed by nothing: as `recal replay` runs)."""
    import json
    import os
    import subprocess
    r = subprocess.run([sys.executable, "-c", _CHILD, str(src), str(out)], check=True,
                       capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(tree / "service")})
    return json.loads(r.stdout)


def write_live(path: Path, raw: RawBatch, minutes: float) -> None:
    """A log as the daemon writes it: one sample per arrival, joined per 1 s flush."""
    class Clock:
        now_s = 0.0

        def __call__(self) -> float:
            return self.now_s
    clock = Clock()
    n = min(len(raw), round(minutes * 60 * RATE_HZ))
    with RecordingWriter(path, clock=clock, background_flush=False, fsync=False,
                         overwrite=True) as w:
        for i in range(n):
            clock.now_s = i / RATE_HZ
            w.log_raw(SENSOR, raw[i:i + 1], 1_700_000_000_000_000_000 + int(raw.t_us[i]) * 1000)


def old_beside_new(old: Path, raw: RawBatch, sizes: list[int], live_min: float,
                   runs: int) -> None:
    """`replay` of the same files by an old tree and this one, alternating, each in its own
    process; medians of the per-run ratios."""
    new = Path(__file__).resolve().parents[1]
    print(f"old {old} beside new {new}: {runs} runs alternating, medians", flush=True)
    print("| input | samples | old replay s | new replay s | old replay/mcap reader | "
          "new replay/mcap reader |")
    print("|---|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory(prefix="recal-replay-ab-") as tmp:
        cases = []
        for size in sizes:
            cases.append((f"{size} samples/msg", Path(tmp) / f"in-{size}.mcap"))
            write_recording(cases[-1][1], raw, size)
        if live_min > 0:
            cases.append((f"live log, {live_min:g} min", Path(tmp) / "live.mcap"))
            write_live(cases[-1][1], raw, live_min)
        for name, src in cases:
            got: dict[str, list[dict[str, float]]] = {"old": [], "new": []}
            for _ in range(runs):
                for label, tree in (("old", old), ("new", new)):
                    got[label].append(replay_in(tree, src, Path(tmp) / "out.mcap"))
            med = {label: (statistics.median(r["replay"] for r in rs),
                           statistics.median(r["mcap"] / r["replay"] for r in rs))
                   for label, rs in got.items()}
            print(f"| {name} | {int(got['new'][0]['n'])} | {med['old'][0]:.2f} | "
                  f"{med['new'][0]:.2f} | {med['old'][1]:.3f} | {med['new'][1]:.3f} |",
                  flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="15 min per case, 3 runs")
    ap.add_argument("--hours", type=float, help="simulated hours per case (default 2)")
    ap.add_argument("--runs", type=int, help="timed runs per case (default 5)")
    ap.add_argument("--sizes", default="1000,100,10", help="samples per message, comma list")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--old", type=Path, help="an old tree (a checkout whose service/ holds "
                    "recal): its replay beside this one's, whole processes, alternating")
    ap.add_argument("--live-minutes", type=float, default=0.0,
                    help="with --old: also a log as the daemon writes it (one sample per "
                         "arrival), this many minutes of the simulation")
    a = ap.parse_args(argv)
    hours = a.hours or (0.25 if a.quick else 2.0)
    runs = a.runs or (3 if a.quick else 5)
    sizes = [int(s) for s in a.sizes.split(",")]
    sensor = SensorSpec.random(np.random.default_rng(a.seed), offset_mg=40.0, gain_pct=3.0)
    raw = simulate(hours, RATE_HZ, a.seed, sensor).raw
    if a.old is not None:
        old_beside_new(a.old, raw, sizes, a.live_minutes, runs)
        return 0
    print(f"recal replay throughput: {len(raw):,} samples ({hours:g} h at {RATE_HZ:g} Hz) per "
          f"case, {runs} runs, medians (M samples/s)", flush=True)
    head = (f"{'samples/msg':>11} | {'mcap reader':>11} | {'recal reader':>12} | "
            f"{'core alone':>10} | {'replay':>7} | {'replay CPU/wall':>15} | "
            f"{'replay/mcap reader':>18} | {'replay/recal reader':>19} | "
            f"{'replay per CPU s':>16} | {'replay/mcap per CPU s':>21}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="recal-replay-bench-") as tmp:
        for size in sizes:
            src = Path(tmp) / f"in-{size}.mcap"
            write_recording(src, raw, size)
            r = run_case(src, Path(tmp) / "out.mcap", runs)
            med = {k: statistics.median(v) for k, v in r.items()}
            rows.append(f"{size:>11} | {med['mcap'] / 1e6:>11.2f} | {med['recal'] / 1e6:>12.2f} | "
                        f"{med['core'] / 1e6:>10.2f} | {med['replay'] / 1e6:>7.2f} | "
                        f"{med['replay_cpu']:>15.2f} | {med['ratio_mcap']:>18.2f} | "
                        f"{med['ratio_recal']:>19.2f} | {med['replay_per_cpu'] / 1e6:>16.2f} | "
                        f"{med['ratio_mcap_cpu']:>21.2f}")
            print(f"  {size} samples/msg done: replay {med['replay'] / 1e6:.2f} M/s "
                  f"(runs: {', '.join(f'{x / 1e6:.2f}' for x in r['replay'])})", flush=True)
    print()
    print(head)
    print("-" * len(head))
    for row in rows:
        print(row)
    print("\ntargets: replay >= 1.00 M samples/s; replay/mcap reader >= 0.50 (ratios are per "
          "run, then the median)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
