"""Is `recal hindsight`'s sigma honest where the model lacks an effect? (cases and metric:
bench/honesty_cases.py)

    python bench/hindsight_honesty.py                 # every case, seed 1, 2 h at 50 Hz
    python bench/hindsight_honesty.py --seeds 1 2 --hours 1

Each recording goes through what `recal hindsight` runs (no prior, the diagonal model at the
median norm: `hindsight.calibrate`, then `hindsight_file.Corrected` per batch). Three rows per
case: "params only" scores the parameters' covariance alone with every sample calibrated (the
sigma before what the model cannot explain counted), "with misfit" the published sigma and
statuses, "with misfit, any status" the published sigma on every window (suspect ones too).
Columns: 1 s windows marked calibrated (of all), fraction beyond 3 and 10 sigma_eff, RMS
sigma_eff / RMS error, RMS error and RMS sigma of those windows (mg), the fit's residual
(mg) and reduced chi-square.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from honesty_cases import CASES, honesty
from recal.commands.hindsight import Corrected
from recal.core import hindsight
from recal.core.discovery_data import rate_and_scale
from recal.core.effects import Covariates
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import Status, predicted_sigma_mg
from recal.samples import rebatch


def run(case_index: int, seed: int, hours: float) -> list[dict]:
    case = CASES[case_index]
    raw, truth, noise_g = case.recording(seed, hours)
    rate_hz, median_norm = rate_and_scale([raw])
    cfg = PipelineConfig(rate_hz=rate_hz)
    t0 = time.perf_counter()
    fit = hindsight.calibrate(lambda: [raw], case.model_for(median_norm, raw), cfg)
    corrected = Corrected(fit, cfg)
    outs = [corrected(b) for b in rebatch([raw])]
    seconds = time.perf_counter() - t0
    cal = np.concatenate([o.a_g for o in outs])
    sigma = np.concatenate([o.sigma_mg for o in outs])
    status = np.concatenate([o.status for o in outs])
    cov = Covariates.from_samples(raw.t_us, raw.aux, raw.aux_names, fit.t0_us)
    sigma_p = predicted_sigma_mg(fit.model, fit.p, fit.cov, raw.v, cov)
    before = honesty(cal, truth, sigma_p, np.full(len(raw), Status.CALIBRATED), rate_hz, noise_g)
    after = honesty(cal, truth, sigma, status, rate_hz, noise_g)
    every = honesty(cal, truth, sigma, np.full(len(raw), Status.CALIBRATED), rate_hz, noise_g)
    extra = {"case": case.name, "seed": seed, "residual_mg": fit.residual_rms_mg,
             "chi2": fit.chi2, "seconds": seconds}
    return [{**extra, "sigma": "params only", **before}, {**extra, "sigma": "with misfit", **after},
            {**extra, "sigma": "with misfit, any status", **every}]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1])
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--cases", type=int, nargs="+", default=list(range(len(CASES))),
                    help="case indices (bench/honesty_cases.py CASES)")
    args = ap.parse_args()
    print("| case | seed | sigma | calibrated / windows | > 3 sigma_eff | > 10 sigma_eff | "
          "sigma_eff / error | error mg | sigma mg | residual mg | chi2 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for i in args.cases:
        for seed in args.seeds:
            for row in run(i, seed, args.hours):
                print(f"| {row['case']} | {row['seed']} | {row['sigma']} | "
                      f"{row['calibrated']} / {row['windows']} | {100 * row['beyond_3']:.1f} % | "
                      f"{100 * row['beyond_10']:.1f} % | {row['over']:.2f} | "
                      f"{row['error_rms_mg']:.2f} | {row['sigma_rms_mg']:.2f} | "
                      f"{row['residual_mg']:.2f} | {row['chi2']:.3g} |", flush=True)


if __name__ == "__main__":
    main()
