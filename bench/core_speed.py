"""The streaming core's speed on one case of `compare_tools` (Pipeline.step over 100 000-sample
batches, `compare_tools.run_recal`), median of several runs; with --profile, cProfile's top
functions by own time instead.

Old beside new: run it once with the old tree's `service/` first on PYTHONPATH, once without,
alternating (the ratio of the two medians is what counts on a shared machine):

    PYTHONPATH=/path/to/old/service python bench/core_speed.py --case plain --hours 6 --runs 5
    python bench/core_speed.py --case plain --hours 6 --runs 5

With --cpu the process's CPU seconds of each run are timed instead of the wall clock (on a
machine shared with other work they vary less, though still with the load).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import compare_tools as ct


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="plain", choices=[c.name for c in ct.CASES])
    ap.add_argument("--hours", type=float, default=6.0)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--batch", type=int, default=100_000)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--cpu", action="store_true", help="time process CPU, not the wall clock")
    args = ap.parse_args(argv)
    case = next(c for c in ct.CASES if c.name == args.case)
    sim = ct.simulate_case(case, args.hours)
    raw_g = ct.RawBatch(sim.raw.t_us, sim.raw.v / ct.COUNTS_PER_G, sim.raw.aux,
                        sim.raw.aux_names)
    model = case.models[0][1]()
    if args.profile:
        prof = cProfile.Profile()
        prof.runcall(ct.run_recal, raw_g, model, args.batch)
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
        return 0
    seconds = [_timed(raw_g, model, args.batch, args.cpu) for _ in range(args.runs)]
    med = statistics.median(seconds)
    import recal
    clock = "CPU" if args.cpu else "wall"
    print(f"{recal.__file__}: {case.name} {len(raw_g)} samples, median {med:.3f} s {clock} "
          f"of {args.runs}, {len(raw_g) / med / 1e6:.2f} M samples/s")
    return 0


def _timed(raw_g: ct.RawBatch, model: ct.SensorModel, batch: int, cpu: bool) -> float:
    """One `run_recal`: its own wall time, or the process CPU seconds it took."""
    c0 = time.process_time()
    wall = ct.run_recal(raw_g, model, batch)[1]
    return time.process_time() - c0 if cpu else wall


if __name__ == "__main__":
    raise SystemExit(main())
