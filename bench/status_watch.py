"""The self-watch and the predicted error on simulated wearers (core/status.py).

    python bench/status_watch.py            # 8 seed pairs, 25 Hz (about a minute)
    python bench/status_watch.py --pairs 3  # fewer

Per seed pair (A, B): one wearer for 80 min, sensor A's readings for the first 40, then sensor
B's (offsets +-50 mg, gains +-3 %, other values) under the same id, through one `Pipeline`
with the datasheet prior. Printed: when the output first went suspect after the swap, when
it was calibrated again, the 1 s vector error (RMS over still seconds) 30-40 min after the
swap, the self-watch's resets; and on A alone (the 40 min before the swap, 20-40 min) the RMS
error the parameters cause (output against the true parameters' correction of the same
readings: no sensor noise in it) against the RMS predicted sigma.
"""

from __future__ import annotations

import argparse

import numpy as np

from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import Status
from recal.samples import CalibratedBatch, RawBatch
from recal.sim import wearer as sim

RATE_HZ = 25.0
S0 = 1024.0
SWAP_MIN = 40.0


def _spec(seed: int) -> sim.SensorSpec:
    return sim.SensorSpec.random(np.random.default_rng(seed), offset_mg=50, gain_pct=3)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(x**2)))


def run_pair(seed_a: int, seed_b: int) -> dict:
    spec_a = _spec(seed_a)
    res = sim.simulate(80 / 60, RATE_HZ, seed_a, spec_a)
    b = sim.with_sensor(res, _spec(seed_b))
    k = int(SWAP_MIN * 60 * RATE_HZ)
    raw = RawBatch(res.raw.t_us, np.concatenate([res.raw.v[:k], b.raw.v[k:]]), res.raw.aux,
                   res.raw.aux_names)
    model = SensorModel.diagonal(S0)
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model))
    outs = [pipe.step(raw[i:i + 250]) for i in range(0, len(raw), 250)]
    out = CalibratedBatch.concat([o.calibrated for o in outs])
    minute = (out.t_us - out.t_us[k]) / 60e6
    after = minute >= 0
    suspect = minute[after & (out.status == Status.SUSPECT)]
    first_suspect = float(suspect[0]) if len(suspect) else None
    back = minute[after & (minute > (suspect[-1] if len(suspect) else 0))
                  & (out.status == Status.CALIBRATED)]
    n = int(RATE_HZ)
    m = len(out) // n
    e = 1e3 * np.linalg.norm((out.a_g - res.truth.a_true_g)[:m * n].reshape(m, n, 3).mean(1),
                             axis=1)
    e = np.where(res.truth.still[:m * n].reshape(m, n).all(1), e, np.nan)
    sec_min = np.arange(m) / 60.0 - SWAP_MIN
    truth_p = np.concatenate([S0 * np.array(spec_a.offset_g), S0 * (1 + np.array(spec_a.gain))])
    cov = pipe.covariates(raw.t_us[:k], raw.aux[:k])
    par_err = 1e3 * np.linalg.norm(out.a_g[:k] - model.correct(truth_p, raw.v[:k], cov), axis=1)
    late_a = (minute[:k] >= -20) & (out.status[:k] == Status.CALIBRATED)
    return {"first_suspect_min": first_suspect,
            "calibrated_again_min": float(back[0]) if len(back) else None,
            "err_30_40_mg": _rms(e[(sec_min >= 30) & (sec_min < 40)]),
            "err_before_swap_mg": _rms(e[(sec_min >= -10) & (sec_min < 0)]),
            "resets": pipe.watch.triggers,
            "a_param_err_mg": _rms(par_err[late_a]), "a_sigma_mg": _rms(out.sigma_mg[:k][late_a])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=8)
    args = ap.parse_args()
    print("| A, B | first suspect (min after swap) | calibrated again | 1 s err 30-40 min mg "
          "| before swap mg | resets | A: param error / predicted sigma mg |")
    print("|---|---|---|---|---|---|---|")
    for i in range(args.pairs):
        a, b = 2 * i + 1, 2 * i + 2
        r = run_pair(a, b)
        fs = "never" if r["first_suspect_min"] is None else f"{r['first_suspect_min']:.1f}"
        ca = "-" if r["calibrated_again_min"] is None else f"{r['calibrated_again_min']:.1f}"
        print(f"| {a}, {b} | {fs} | {ca} | {r['err_30_40_mg']:.2f} | "
              f"{r['err_before_swap_mg']:.2f} | {r['resets']} | "
              f"{r['a_param_err_mg']:.2f} / {r['a_sigma_mg']:.2f} |")


if __name__ == "__main__":
    main()
