"""Cases and metric of the sigma-honesty benches (hindsight_honesty.py; shared, so every tool is
measured on the same recordings by the same rule).

A case is a simulated recording (2 h at 50 Hz by default) and the model a user would run on it:
without `recal discover`, the diagonal model (offsets, scales) on a sensor that also has an
effect the model lacks, or on a clean sensor (digital, a phone, a wearer who never lies down),
and the full model on a sensor with cross-axis terms; after it, the diagonal model with the
effect's term (`with_terms`, as discover adds it); and a lab's six poses held twice
(`six_poses`, no prior). `honesty` scores a tool's output on it:

* windows: 1 s windows (rate samples each) whose every sample is marked calibrated;
* error: |mean over the window of (calibrated - true)| in mg, after the best rotation (a
  rotation of the sensor frame is not observable from gravity, `sim.error_1s_mg`);
* sigma_eff = sqrt(sigma^2 + n^2), sigma the window's mean predicted sigma (mg), n the sensor
  noise left in a 1 s mean: 1e3 noise_g sqrt(3 / rate), the norm of three axes' noise;
* beyond_3 / beyond_10: fraction of those windows whose error exceeds 3 / 10 sigma_eff (goal:
  at most 1 % and none);
* over: RMS sigma_eff / RMS error over them (where the model fits: within 1/3 .. 3);
* error_all_rms_mg: RMS error of every 1 s window, whatever its status.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from recal.core.discovery_data import covariate_spread
from recal.core.effects import make_effect
from recal.core.model import SensorModel
from recal.core.status import Status
from recal.samples import RawBatch
from recal.sim.sensor import sensor_type
from recal.sim.wearer import SensorSpec, SimResult, WearerSpec, forward_model, simulate, with_sensor

__all__ = ["CASES", "DISCOVERY_CASES", "Case", "honesty", "six_poses", "with_terms"]


@dataclass(frozen=True)
class Case:
    """One recording and the model run on it.

    Attributes:
        name: the case's name in the tables.
        sensor: the sensor from a random generator (the seed's).
        model: the sensor model the tool runs (s0: the sensor's counts per g).
        wearer: wearer settings other than the defaults.
        lacks: the effect the model lacks ("" for a clean case).
    """

    name: str
    sensor: Callable[[np.random.Generator], SensorSpec]
    model: Callable[[float], SensorModel] = SensorModel.diagonal
    wearer: dict = field(default_factory=dict)
    lacks: str = ""
    swap: bool = False  # another sensor of the same kind from half time on, under the same id
    #: effects the model has beyond ``model`` (kind, channel), added as `recal discover` adds
    #: them (`with_terms`)
    terms: tuple[tuple[str, str], ...] = ()
    poses: bool = False  # a lab's six positions twice over (`six_poses`), not a wearer

    def recording(self, seed: int, hours: float = 2.0, rate_hz: float = 50.0
                  ) -> tuple[RawBatch, np.ndarray, float]:
        """(raw, true specific force in g, the sensor's noise in g) of this case."""
        if self.poses:
            spec = self.sensor(np.random.default_rng(seed))
            return (*six_poses(spec, seed, rate_hz), spec.noise_g)
        r = self.simulate(seed, hours, rate_hz)
        return r.raw, r.truth.a_true_g, float(r.truth.params["sensor"]["noise_g"])

    def model_for(self, s0: float, raw: RawBatch) -> SensorModel:
        """The model the tool runs on ``raw``: ``model`` at s0 with the case's terms."""
        return with_terms(self.model(s0), self.terms, raw)

    def simulate(self, seed: int, hours: float = 2.0, rate_hz: float = 50.0) -> SimResult:
        r = simulate(hours, rate_hz, seed, self.sensor(np.random.default_rng(seed)),
                     WearerSpec(**self.wearer))
        if not self.swap:
            return r
        other = with_sensor(r, self.sensor(np.random.default_rng(seed + 100)))
        k = len(r.raw) // 2
        v = np.concatenate([r.raw.v[:k], other.raw.v[k:]])
        return SimResult(replace(r.raw, v=v), r.truth)


def _digital(rng: np.random.Generator, **over: object) -> SensorSpec:
    return SensorSpec.random(rng, offset_mg=50, gain_pct=3, **over)


def _temp_offsets(rng: np.random.Generator) -> SensorSpec:
    s = _digital(rng)
    return replace(s, offset_tc_g_per_c=tuple(rng.choice([-1.0, 1.0], 3) * 0.002))


def _analog_supply(rng: np.random.Generator, **over: object) -> SensorSpec:
    return sensor_type("adxl335-adc12", rng, ratiometric_per_v=1 / 3.3, v_ref_v=3.3, **over)


def _signs(rng: np.random.Generator, size: float) -> tuple[float, ...]:
    return tuple(rng.choice([-1.0, 1.0], 3) * size)


def with_terms(model: SensorModel, terms: tuple[tuple[str, str], ...], raw: RawBatch
               ) -> SensorModel:
    """The model with each (kind, channel) effect as `recal discover` adds it
    (`discovery.candidates`: reference the channel's median, spread its 5-95 % range), at
    nominal with the effect's own prior."""
    for kind, channel in terms:
        c = raw.aux[:, raw.aux_names.index(channel)]
        model = model.with_effect(make_effect(kind, channel, float(np.median(c))),
                                  covariate_spread(c))
    return model


#: The lab stream (`six_poses`): each pose held this long, a hand's turn between them.
POSE_HOLD_S = 5.0
POSE_TURN_S = 2.0
_SIX = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


def six_poses(spec: SensorSpec, seed: int, rate_hz: float) -> tuple[RawBatch, np.ndarray]:
    """The six positions held POSE_HOLD_S each, then again (the second round is what a lab
    measures once calibrated), a hand's turn of POSE_TURN_S between poses; (raw, truth)."""
    rng = np.random.default_rng(seed)
    dirs = np.concatenate([_SIX, _SIX])
    parts = []
    for i, d in enumerate(dirs):
        parts.append(np.tile(d, (int(POSE_HOLD_S * rate_hz), 1)))
        if i + 1 < len(dirs):
            s = np.linspace(0.0, 1.0, int(POSE_TURN_S * rate_hz))[:, None]
            mid = (1 - s) * d + s * dirs[i + 1] + np.array([0.3, 0.2, 0.25])
            mid /= np.linalg.norm(mid, axis=1, keepdims=True)
            parts.append(mid * (1 + 0.4 * np.sin(np.pi * s)))  # a hand's push and stop
    a = np.concatenate(parts)
    v = forward_model(a, spec, rng=rng)
    t = np.arange(len(v), dtype=np.int64) * round(1e6 / rate_hz)
    return RawBatch(t, v, np.zeros((len(v), 0))), a


CASES: tuple[Case, ...] = (
    Case("clean digital", _digital),
    Case("temperature on offsets (2 mg/C)", _temp_offsets, lacks="offset[temp]"),
    Case("cross-axis 1.5 deg, diagonal model",
         lambda rng: _digital(rng, cross_axis_deg=1.5), lacks="cross_axis"),
    Case("analog 12-bit, sagging supply", _analog_supply,
         wearer={"vdd_start_v": 3.3, "vdd_end_v": 2.9}, lacks="ratiometric[vdd]"),
    # where the model describes the sensor, other kinds of sensor and wearer
    Case("phone m/s2", lambda rng: sensor_type("phone-ms2", rng)),
    Case("cross-axis 1.5 deg, full model", lambda rng: _digital(rng, cross_axis_deg=1.5),
         model=SensorModel.full),
    Case("upright only", _digital, wearer={"upright_only": True}),
    # two sensors in one recording: one fit cannot describe both (a poor fit)
    Case("another sensor at half time", _digital, lacks="another sensor", swap=True),
    # each effect with its term in the model, as `recal discover` adds it (the model fits)
    Case("temperature on offsets (2 mg/C), with its term", _temp_offsets,
         terms=(("offset", "temp_c"),)),
    Case("analog 12-bit, sagging supply, with its term", _analog_supply,
         wearer={"vdd_start_v": 3.3, "vdd_end_v": 2.9}, terms=(("ratiometric", "vdd_v"),)),
    Case("six clean poses twice (lab)", _digital, poses=True),
)


_SAG = {"vdd_start_v": 3.3, "vdd_end_v": 2.9, "always_aux": True}
#: Recordings whose effect nothing declares, for tools that select effects (`recal hindsight`
#: without --model): the default wearer (temperature wandering within the hour, the supply
#: running down), both channels always written; ``terms`` are the effects the sensor has,
#: (kind, covariate) as discovery names them, covariate None for cross-axis, "time" for drift.
DISCOVERY_CASES: tuple[Case, ...] = (
    Case("clean digital", _digital, wearer={"always_aux": True}),
    Case("temperature on offsets (2 mg/C)", _temp_offsets, wearer={"always_aux": True},
         terms=(("offset", "temp_c"),)),
    Case("temperature on gains (0.1 %/C)",
         lambda rng: _digital(rng, gain_tc_per_c=_signs(rng, 0.001)),
         wearer={"always_aux": True}, terms=(("gain", "temp_c"),)),
    Case("analog 12-bit, sagging supply", _analog_supply, wearer=_SAG,
         terms=(("ratiometric", "vdd_v"),)),
    Case("cross-axis 1.5 deg", lambda rng: _digital(rng, cross_axis_deg=1.5),
         wearer={"always_aux": True}, terms=(("cross_axis", None),)),  # type: ignore[arg-type]
    Case("drift 10 mg/h", lambda rng: _digital(rng, offset_drift_g_per_h=_signs(rng, 0.01)),
         wearer={"always_aux": True}, terms=(("offset", "time"),)),
    Case("temperature on offsets + analog supply",
         lambda rng: _analog_supply(rng, offset_tc_g_per_c=_signs(rng, 0.002)), wearer=_SAG,
         terms=(("ratiometric", "vdd_v"), ("offset", "temp_c"))),
    Case("cross-axis + temperature on offsets",
         lambda rng: _digital(rng, cross_axis_deg=1.5, offset_tc_g_per_c=_signs(rng, 0.002)),
         wearer={"always_aux": True},
         terms=(("cross_axis", None), ("offset", "temp_c"))),  # type: ignore[arg-type]
    Case("drift + temperature on gains",
         lambda rng: _digital(rng, offset_drift_g_per_h=_signs(rng, 0.01),
                              gain_tc_per_c=_signs(rng, 0.001)),
         wearer={"always_aux": True}, terms=(("offset", "time"), ("gain", "temp_c"))),
)


def _align(cal: np.ndarray, truth: np.ndarray) -> np.ndarray:
    ok = np.all(np.isfinite(cal), axis=1)
    rot, _ = Rotation.align_vectors(truth[ok][::10], cal[ok][::10])
    return rot.apply(cal)


def honesty(cal_g: np.ndarray, truth_g: np.ndarray, sigma_mg: np.ndarray, status: np.ndarray,
            rate_hz: float, noise_g: float) -> dict:
    """The metric of the module doc for one tool's output on one recording."""
    n = round(rate_hz)
    k = len(cal_g) // n
    c = _align(np.asarray(cal_g, np.float64), np.asarray(truth_g, np.float64))
    e = 1e3 * np.linalg.norm((c - truth_g)[:k * n].reshape(k, n, 3).mean(axis=1), axis=1)
    sig = np.asarray(sigma_mg, np.float64)[:k * n].reshape(k, n).mean(axis=1)
    cal = np.all(np.asarray(status)[:k * n].reshape(k, n) == Status.CALIBRATED, axis=1)
    noise_mg = 1e3 * noise_g * np.sqrt(3.0 / rate_hz)
    eff = np.sqrt(sig**2 + noise_mg**2)
    m = cal & np.isfinite(e) & np.isfinite(eff)
    if not m.any():
        return {"windows": int(k), "calibrated": 0, "beyond_3": float("nan"),
                "beyond_10": float("nan"), "over": float("nan"), "error_rms_mg": float("nan"),
                "sigma_rms_mg": float("nan"), "error_median_mg": float("nan"),
                "sigma_median_mg": float("nan"),
                "error_all_rms_mg": float(np.sqrt(np.nanmean(e**2)))}
    return {"windows": int(k), "calibrated": int(m.sum()),
            "beyond_3": float(np.mean(e[m] > 3 * eff[m])),
            "beyond_10": float(np.mean(e[m] > 10 * eff[m])),
            "over": float(np.sqrt(np.mean(eff[m]**2)) / np.sqrt(np.mean(e[m]**2))),
            "error_rms_mg": float(np.sqrt(np.mean(e[m]**2))),
            "sigma_rms_mg": float(np.sqrt(np.mean(sig[m]**2))),
            "error_median_mg": float(np.median(e[m])), "sigma_median_mg": float(np.median(sig[m])),
            "error_all_rms_mg": float(np.sqrt(np.nanmean(e**2)))}
