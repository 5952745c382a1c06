"""How tight is sigma where the status says calibrated? Median error and median sigma of the
calibrated 1 s windows, beside the honesty columns, on bench/sigma_honesty.py's wearer cases
(the same streams, pipeline and scoring: its `run` pieces), each with the model lacking the
effect and with the effect's term (`honesty_cases.with_terms`).

    python bench/sigma_tightness.py --minutes 60 --seeds 1
    python bench/sigma_tightness.py --only "with its term"

Columns: cal % (seconds wholly calibrated), median error and median sigma_eff (mg) of those
seconds, the goal median sigma_eff <= 3 x median error + 0.5 mg (ok), >3 / >10 sigma_eff %,
the summary's misfit figure (`Pipeline.summary()["misfit_mg"]`) at the end, and beside it
`recal discover`'s held-out residual of the same model on the same windows (the buffer's, those
since a fitted offset jump if any: `discovery.discover_pipeline`, nothing added).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import sigma_honesty as sh
from recal.core.buffer import Windows
from recal.core.discovery import DiscoveryConfig, discover_pipeline
from recal.errors import RecalError
from recal.sim import wearer as sim

#: The wearer cases with an effect, lacking it and with its term, and the clean one.
NAMES = ("digital, diagonal model (fits)",
         "temperature 1.5 mg/degC on offsets, diagonal",
         "temperature 1.5 mg/degC on offsets, with its term (fits)",
         "cross-axis 1.5 deg, diagonal (lacks it)",
         "cross-axis 1.5 deg, full model (fits)",
         "analog 12-bit, sagging supply (ratiometric), diagonal",
         "analog 12-bit, sagging supply, with its term (fits)")


def measure(name: str, minutes: float, seed: int) -> dict:
    """One case through the pipeline as `sigma_honesty.run` streams it; the calibrated
    seconds' medians."""
    case = sh.CASES[name]
    spec = case.spec(np.random.default_rng(seed))
    wearer = sim.WearerSpec(temp_excursion_every_h=0.5)
    res = sim.simulate(minutes / 60, sh.RATE_HZ, seed, spec, wearer)
    pipe = sh._pipe(spec, case, res.raw)
    out = sh._stream(pipe, res.raw)
    truth = res.truth.a_true_g
    if case.align:  # gravity cannot see a rotation of the frame (sigma_honesty's rule)
        h = len(out) // 2
        rot, _ = Rotation.align_vectors(truth[h::10], out.a_g[h::10])
        out = replace(out, a_g=rot.apply(out.a_g))
    e, s, cal, _ = sh._seconds(out, truth)
    s_eff = np.hypot(s, 1e3 * spec.noise_g / np.sqrt(sh.RATE_HZ))
    ec, sc = e[cal], s_eff[cal]
    med_e = float(np.median(ec)) if len(ec) else float("nan")
    med_s = float(np.median(sc)) if len(sc) else float("nan")
    return {"cal_pct": 100 * cal.mean(), "med_err": med_e, "med_sigma": med_s,
            "ok": bool(med_s <= 3 * med_e + 0.5),
            "b3": 100 * float(np.mean(ec > 3 * sc)) if len(ec) else 0.0,
            "b10": 100 * float(np.mean(ec > 10 * sc)) if len(ec) else 0.0,
            "misfit": pipe.summary().get("misfit_mg", 0.0), "heldout": _heldout_mg(pipe)}


def _heldout_mg(pipe: sh.Pipeline) -> float:
    """discover's held-out RMS of |a| - 1 g of the model in force on the buffer's windows
    (since a fitted offset jump, as the misfit figure counts them); NaN: too few."""
    w = pipe.buffer.windows()
    step = pipe.estimate.step_us if pipe.estimate is not None else None
    if step is not None:
        k = w.t_us >= step
        w = Windows(w.v[k], w.aux[k], w.t_us[k], w.n[k], w.var[k])
    try:
        return discover_pipeline(w, pipe.aux_names, pipe.t0_us or 0, pipe.model, pipe.params,
                                 DiscoveryConfig(max_steps=0)).heldout_base_mg
    except RecalError:  # too few windows for held-out blocks: no figure
        return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--only", default="")
    args = ap.parse_args()
    print("case | seed | cal % | median err mg | median sigma_eff mg | <= 3x+0.5 | >3 % | "
          ">10 % | misfit mg | discover held-out mg")
    print("---|---|---|---|---|---|---|---|---|---")
    for name in NAMES:
        if args.only not in name:
            continue
        for seed in range(1, args.seeds + 1):
            r = measure(name, args.minutes, seed)
            print(f"{name} | {seed} | {r['cal_pct']:.0f} | {r['med_err']:.2f} | "
                  f"{r['med_sigma']:.2f} | {'yes' if r['ok'] else 'no'} | {r['b3']:.2f} | "
                  f"{r['b10']:.2f} | {r['misfit']:.2f} | {r['heldout']:.2f}", flush=True)


if __name__ == "__main__":
    main()
