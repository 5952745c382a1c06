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

    python bench/hindsight_honesty.py --discover      # DISCOVERY_CASES, seed 1, 2 h at 50 Hz

``--discover``: each recording of `honesty_cases.DISCOVERY_CASES` (effects nothing declares)
through what `recal hindsight` runs without --model (`hindsight.discover_and_calibrate`, then
`Corrected`), against the floor: the same fit given the true model (the case's terms as
discovery names them). One row per case against the goals: samples calibrated (>= 90 %), RMS
1 s error of every window / the floor's (<= 1.2), of calibrated windows beyond 3 (<= 1 %) and
10 sigma_eff (none), median sigma against 3x the median error + 0.5 mg, the effects adopted
and whether they are the sensor's.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from honesty_cases import CASES, DISCOVERY_CASES, honesty
from recal.commands.hindsight import Corrected
from recal.core import discovery_data as dd
from recal.core import hindsight
from recal.core.candidates import candidates
from recal.core.discovery_data import rate_and_scale
from recal.core.effects import Covariates
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import Status, predicted_sigma_mg
from recal.samples import RawBatch, rebatch


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


def _outputs(fit: hindsight.HindsightFit, cfg: PipelineConfig, raw: RawBatch
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    corrected = Corrected(fit, cfg)
    outs = [corrected(b) for b in rebatch([raw])]
    return (np.concatenate([o.a_g for o in outs]), np.concatenate([o.sigma_mg for o in outs]),
            np.concatenate([o.status for o in outs]))


def true_model(found_data: dd.DiscoveryData, terms: tuple) -> SensorModel:
    """The diagonal model with the case's effects as discovery proposes them."""
    model = SensorModel.diagonal(found_data.s0)
    for kind, cov in terms:
        eff, spread = next((e, sp) for e, sp in candidates(model, found_data)
                           if e.kind == kind and e.covariate == cov
                           and getattr(e, "reference", None) is None)
        model = model.with_effect(eff, spread)
    return model


def run_discover(case_index: int, seed: int, hours: float) -> dict:
    case = DISCOVERY_CASES[case_index]
    raw, truth, noise_g = case.recording(seed, hours)
    rate_hz, median_norm = rate_and_scale([raw])
    cfg = PipelineConfig(rate_hz=rate_hz)
    t0 = time.perf_counter()
    fit, found = hindsight.discover_and_calibrate(lambda: [raw], median_norm, cfg)
    cal, sigma, status = _outputs(fit, cfg, raw)
    seconds = time.perf_counter() - t0
    floor_fit = hindsight.calibrate(lambda: [raw], true_model(found.data, case.terms), cfg)
    floor_cal, *_ = _outputs(floor_fit, cfg, raw)
    every = np.full(len(raw), Status.CALIBRATED)
    h = honesty(cal, truth, sigma, status, rate_hz, noise_g)
    floor = honesty(floor_cal, truth, sigma, every, rate_hz, noise_g)["error_all_rms_mg"]
    adopted = sorted(f"{e.kind}[{e.covariate}]" for e in found.selected)
    wanted = sorted(f"{k}[{c}]" for k, c in case.terms)
    return {"case": case.name, "seed": seed, "seconds": seconds,
            "calibrated_pct": 100 * float(np.mean(status == Status.CALIBRATED)),
            "error_mg": h["error_all_rms_mg"], "floor_mg": floor,
            "beyond_3": h["beyond_3"], "beyond_10": h["beyond_10"],
            "sigma_median_mg": h["sigma_median_mg"], "error_median_mg": h["error_median_mg"],
            "adopted": adopted, "right": adopted == wanted,
            "heldout": (found.heldout_base_mg, found.heldout_final_mg)}


def main_discover(args: argparse.Namespace) -> None:
    print("| case | seed | calibrated | 1 s error / floor (mg) | > 3 sigma_eff | > 10 sigma_eff "
          "| median sigma / error (mg) | adopted (held-out mg) | right | s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for i in args.cases or range(len(DISCOVERY_CASES)):
        for seed in args.seeds:
            r = run_discover(i, seed, args.hours)
            print(f"| {r['case']} | {seed} | {r['calibrated_pct']:.1f} % | "
                  f"{r['error_mg']:.2f} / {r['floor_mg']:.2f} = "
                  f"{r['error_mg'] / r['floor_mg']:.2f} | {100 * r['beyond_3']:.2f} % | "
                  f"{100 * r['beyond_10']:.2f} % | {r['sigma_median_mg']:.2f} / "
                  f"{r['error_median_mg']:.2f} | {', '.join(r['adopted']) or 'nothing'} "
                  f"({r['heldout'][0]:.2f} -> {r['heldout'][1]:.2f}) | "
                  f"{'yes' if r['right'] else 'NO'} | {r['seconds']:.0f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1])
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--cases", type=int, nargs="+",
                    help="case indices (bench/honesty_cases.py CASES, DISCOVERY_CASES)")
    ap.add_argument("--discover", action="store_true",
                    help="recal hindsight without --model on DISCOVERY_CASES")
    args = ap.parse_args()
    if args.discover:
        main_discover(args)
        return
    print("| case | seed | sigma | calibrated / windows | > 3 sigma_eff | > 10 sigma_eff | "
          "sigma_eff / error | error mg | sigma mg | residual mg | chi2 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for i in args.cases or range(len(CASES)):
        for seed in args.seeds:
            for row in run(i, seed, args.hours):
                print(f"| {row['case']} | {row['seed']} | {row['sigma']} | "
                      f"{row['calibrated']} / {row['windows']} | {100 * row['beyond_3']:.1f} % | "
                      f"{100 * row['beyond_10']:.1f} % | {row['over']:.2f} | "
                      f"{row['error_rms_mg']:.2f} | {row['sigma_rms_mg']:.2f} | "
                      f"{row['residual_mg']:.2f} | {row['chi2']:.3g} |", flush=True)


if __name__ == "__main__":
    main()
