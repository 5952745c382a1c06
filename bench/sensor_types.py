"""Any accelerometer as it is plugged in, with no prior: error and gains per sensor type and tool.

    python bench/sensor_types.py            # 2 h per type, the default wearer, seeds 1-2
    python bench/sensor_types.py --quick    # 40 min, a livelier wearer, seed 1

Each type of `recal.sim.wearer.SENSOR_TYPES` (offsets +-40 mg, gains +-3 %, 4 mg noise, 50 Hz; the
analog parts on an unsigned ADC with zero-g at mid-scale; "adxl335-adc12 sag": its output
ratiometric, the supply sagging 3.3 -> 2.9 V, the ADC reference fixed) goes through the three
tools' core code with no prior: replay (`Pipeline`, batches of 1000, as `recal replay`),
hindsight (`hindsight.calibrate`) and discover (`discovery.discover`: its fit applied to every
sample; for "sag" replay and hindsight use the model it found, as `--model` does).
Error = 1 s vector RMS of |calibrated - true| after the first 30 min (the noise alone: 0.98
mg). Gain error = the largest |fitted - true| relative gain over the axes, in %, both against
their own mean (the reference every tool reports with no prior: `pipeline.gain_reference`).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from recal.core import discovery, discovery_data, hindsight
from recal.core.effects import Covariates, Scale
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.samples import RawBatch
from recal.sim import wearer as sim

RATE = 50.0
TYPES: dict[str, dict[str, Any]] = {
    "default": {},
    "adxl335-adc12": {},
    "adxl335-adc12 sag": {"ratiometric_per_v": 1 / 3.3, "v_ref_v": 3.3},
    "mma7260-adc14": {},
    "adxl345-10bit": {},
    "digital-2g": {},
    "digital-16g": {},
    "phone-ms2": {},
}
LIVELY = {"still_s": (8.0, 40.0), "move_s": (2.0, 8.0), "p_upright": 0.2, "p_lying": 0.3,
          "p_any": 0.5}


def _rel_gain_pct(s: np.ndarray) -> np.ndarray:
    return 100.0 * (s / s.mean() - 1.0)


def _scored(a: np.ndarray, r: sim.SimResult) -> float:
    k = int(1800 * RATE)
    if not np.all(np.isfinite(a)):
        return float("nan")
    return sim.error_1s_mg(a[k:], r.truth.a_true_g[k:], RATE)


def _correct(model: SensorModel, p: np.ndarray, raw: RawBatch) -> np.ndarray:
    cov = Covariates.from_samples(raw.t_us, raw.aux, raw.aux_names, int(raw.t_us[0]))
    return model.correct(p, raw.v, cov)


def _replay(raw: RawBatch, model: SensorModel, prior: Any = None) -> tuple[np.ndarray,
                                                                            Pipeline]:
    pipe = Pipeline(PipelineConfig(rate_hz=RATE), model, prior, raw.aux_names)
    a = np.concatenate([pipe.step(raw[i:i + 1000]).calibrated.a_g
                        for i in range(0, len(raw), 1000)])
    return a, pipe


def run(kind: str, seed: int, hours: float, lively: bool) -> dict:
    name = kind.split()[0]
    extra = TYPES[kind]
    wear = dict(LIVELY) if lively else {}
    if extra:
        wear |= {"vdd_start_v": 3.3, "vdd_end_v": 2.9}
    spec = sim.sensor_type(name, np.random.default_rng(seed), offset_mg=40.0, gain_pct=3.0,
                           **extra)
    r = sim.simulate(hours, RATE, seed, spec, sim.WearerSpec(**wear))
    raw = r.raw
    true_g = _rel_gain_pct(1.0 + np.asarray(spec.gain))
    t0 = time.perf_counter()
    data = discovery_data.data_from_batches(lambda: [raw])
    res = discovery.discover(data)
    a_d = _correct(res.model, res.p, raw)
    if extra:  # the model discover wrote, replayed (its s0: the mean fitted scale)
        s_ref = float(np.mean(res.p[res.model.slice(Scale())]))
        model = SensorModel(res.model.effects, s_ref, res.model.spreads)
        a_r, pipe = _replay(raw, model, res.prior)
    else:
        a_r, pipe = _replay(raw, SensorModel.diagonal())
    h_model = (SensorModel(res.model.effects, discovery_data.rate_and_scale([raw])[1],
                           res.model.spreads) if extra  # `recal hindsight --model`
               else SensorModel.diagonal(discovery_data.rate_and_scale([raw])[1]))
    fit = hindsight.calibrate(lambda: [raw], h_model, PipelineConfig(rate_hz=RATE))
    a_h = hindsight.HindsightFit.correct(fit, raw)
    sec = time.perf_counter() - t0
    gains = {}
    for tool, (m, p) in {"replay": (pipe.model, pipe.params), "hindsight": (fit.model, fit.p),
                         "discover": (res.model, res.p)}.items():
        gains[tool] = float(np.max(np.abs(_rel_gain_pct(p[m.slice(Scale())]) - true_g)))
    return {"replay": _scored(a_r, r), "hindsight": _scored(a_h, r),
            "discover": _scored(a_d, r), "gains": gains, "phase": pipe.phase,
            "selected": [e.label for e in res.model.effects if e.label not in
                         ("offset", "scale")], "seconds": sec}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="40 min, a livelier wearer, seed 1")
    a = ap.parse_args()
    hours, seeds = (40 / 60, (1,)) if a.quick else (2.0, (1, 2))
    print(f"{'sensor type':<20}{'seed':>5}{'replay':>9}{'hindsight':>10}{'discover':>9}"
          f"   gain error % (replay, hindsight, discover)   effects found")
    for kind in TYPES:
        for seed in seeds:
            out = run(kind, seed, hours, a.quick)
            g = out["gains"]
            print(f"{kind:<20}{seed:>5}{out['replay']:>8.2f} {out['hindsight']:>9.2f} "
                  f"{out['discover']:>8.2f}   {g['replay']:.3f}, {g['hindsight']:.3f}, "
                  f"{g['discover']:.3f}{'':>20}{', '.join(out['selected']) or '-'}")


if __name__ == "__main__":
    main()
