"""Speed against accuracy for two core settings the README discusses: the window length
(`window_s`) and the longest time between re-fits (`max_update_interval_s`).

For each setting, against the defaults (2 s, 300 s):
  speed       the 24 h, 50 Hz plain and cross-axis cases of bench/compare_tools.py: core
              samples/s (best of --runs), re-fits, 1 s error after 30 min and over the whole
              recording (mg)
  issue 2     the wearers of bench/in_use_accuracy.py (2 h each): the worst 1 s error per group
              against its target (mg)
  drift 12 h  two 12 h wearers whose offsets drift 2.5 mg/h (seeds 4 and 13, diagonal model):
              the 1 s error after 30 min (mg), where fewer re-fits must still follow the drift

    python bench/core_settings.py                          # window_s 2, 4 and 10; interval 300, 900
    python bench/core_settings.py --window-s 2,6 --interval-s 300 --runs 1
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

import compare_tools as ct
import in_use_accuracy as ia
from recal.core.model import SensorModel
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec, WearerSpec, error_1s_mg, simulate

DRIFT_SEEDS = (4, 13)
DRIFT_G_PER_H = 0.0025
DRIFT_HOURS = 12.0


def speed_rows(settings: dict, runs: int, hours: float) -> list[str]:
    rows = []
    for case in ct.CASES[:2]:
        sim = ct.simulate_case(case, hours)
        raw = RawBatch(sim.raw.t_us, sim.raw.v / ct.COUNTS_PER_G, sim.raw.aux,
                       sim.raw.aux_names)
        model = case.models[0][1]()
        results = [ct.run_recal(raw, model, 100_000, **settings) for _ in range(runs)]
        cal, _, pipe = results[0]
        updates = pipe.counts["updates"]
        best = min(sec for _, sec, _ in results)
        row = ct.Row(case.name, "recal", "streaming")
        ct.score(row, cal, sim, int(1800 * ct.RATE_HZ))
        rows.append(f"{case.name} {hours:g} h: {len(raw) / best / 1e6:.2f} M samples/s, "
                    f"{updates} re-fits, 1 s err {row.err_mg:.2f} mg (whole {row.err_all_mg:.2f})")
    return rows


def issue2_rows(settings: dict) -> list[str]:
    rows = []
    for group, (seeds, cross, full, upright, drift, target) in ia.CASES.items():
        errs = [ia.run_case(s, cross, full, upright, drift, **settings)["err"] for s in seeds]
        worst = int(np.argmax(errs))
        tgt = f" (target {target:g})" if target is not None else ""
        rows.append(f"{group}: worst {errs[worst]:.2f} mg at seed {seeds[worst]}{tgt}")
    return rows


def drift_rows(settings: dict) -> list[str]:
    rows = []
    for seed in DRIFT_SEEDS:
        rng = np.random.default_rng(seed)
        sensor = SensorSpec.random(rng, offset_mg=50, gain_pct=3)
        sensor = replace(sensor, offset_drift_g_per_h=tuple(rng.choice([-1, 1], 3)
                                                            * DRIFT_G_PER_H))
        r = simulate(DRIFT_HOURS, 50.0, seed, sensor, WearerSpec())
        cal, _, pipe = ct.run_recal(r.raw, SensorModel.diagonal(1024.0), 100_000, **settings)
        m = r.raw.t_us >= 1800e6
        err = error_1s_mg(cal[m], r.truth.a_true_g[m], 50.0, False)
        rows.append(f"drift {1e3 * DRIFT_G_PER_H:g} mg/h, {DRIFT_HOURS:g} h, seed {seed}: "
                    f"{err:.3f} mg, {pipe.counts['updates']} re-fits")
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--window-s", default="2,4,10", help="window lengths to try (s)")
    ap.add_argument("--interval-s", default="300,900", help="max_update_interval_s to try")
    ap.add_argument("--runs", type=int, default=2, help="timed runs per speed case (best)")
    ap.add_argument("--hours", type=float, default=24.0, help="length of the speed cases")
    a = ap.parse_args(argv)
    windows = [float(x) for x in a.window_s.split(",")]
    intervals = [float(x) for x in a.interval_s.split(",")]
    if a.runs < 1 or a.hours <= 0 or not windows or not intervals:
        ap.error("--runs must be at least 1, --hours positive, and each list non-empty")
    settings = [{"window_s": w} for w in windows if w != 2.0]
    settings += [{"max_update_interval_s": s} for s in intervals if s != 300.0]
    for s in [{}, *settings]:
        name = ", ".join(f"{k} = {v:g}" for k, v in s.items()) or "defaults (2 s, 300 s)"
        print(f"\n## {name}", flush=True)
        for line in [*speed_rows(s, a.runs, a.hours), *issue2_rows(s), *drift_rows(s)]:
            print(f"- {line}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
