"""The simulator's sensor: a triaxial accelerometer's forward model from true specific force
to the readings it sends, its inverse, and the sensor types people plug in.

`recal.sim.wearer` passes a simulated wearer's motion through it; tests and benches compare what the
estimator recovers with the truth it was given. Pure numpy.

Sensor forward model (the estimator inverts it; tests compare its output with `a_true_g`)
--------------------------------------------------------------------------------------
Let a = a_true_g (g, ideal orthonormal frame), T = temperature channel (°C), V = supply
channel (V), t = time in hours since the first sample. T and V are exactly the values that
appear in `raw.aux` (noisy, quantized), so the model is exactly invertible from the recording.

1. nonlinearity:  a' = a + q ⊙ a²                        (q = `q_per_g`, 1/g, per axis)
2. sensitivity:   u = diag(1 + gain + gain_tc ⊙ (T − T_ref)) · S · a'
3. offset:        u += offset_g + offset_tc_g ⊙ (T − T_ref) + offset_drift_g_per_h ⊙ t
   zero-g:        u += zero_g_counts / counts_per_g      (an analog part's mid-supply output)
4. ratiometric:   u *= 1 + ratiometric_per_v · (V − V_ref)  (zero-g and sensitivity alike: a
                  ratiometric part read by an ADC with a fixed reference)
5. noise:         u += N(0, noise_g²) per axis, white
6. ADC:           v = clip(round(u · counts_per_g), ±floor(full_scale_g · counts_per_g))
                  (with counts_per_g None: v = clip(u, ±full_scale_g) in g; no clipping if
                  full_scale_g is None; with adc_bits, unsigned: clip to 0 .. 2^adc_bits − 1;
                  with quantize False, no rounding: a phone's floats, e.g. in m/s²)

Cross-axis matrix S (rows = actual sensing-axis directions, unit norm), from the three
misalignment angles (α_xy, α_xz, α_yz) = `misalignment_rad`:

    S = rownorm([[1, tan α_xy, tan α_xz],
                 [0, 1,        tan α_yz],
                 [0, 0,        1       ]])

i.e. the sensing z axis *is* the frame's z axis, the sensing y axis lies in the frame's y-z
plane, tilted by α_yz towards +z, and the sensing x axis leans by ≈α_xy towards +y and ≈α_xz
towards +z. S is upper-triangular: this fixes the rotation gauge (a rotation of the frame is
not observable from |a| = 1 g) the same way as `recal.core.effects.CrossAxis`: with U the
un-normalized matrix above, that effect's unit upper-triangular M is inv(U) and the per-axis
scale is counts_per_g · (1 + gain_i) / ‖U_i‖ (U_i = row i of U).
The angles between sensing axes as Georgieva et al. report them, φ = ∠(x,y), ψ = ∠(x,z),
θ = ∠(y,z), come from `sensing_axis_angles_deg(S)`; θ = 90° − α_yz exactly, and to first
order φ ≈ 90° − α_xy, ψ ≈ 90° − α_xz (exactly so when the other angles are 0).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from recal.core.effects import sim_options
from recal.errors import UsageError

__all__ = [
    "SENSOR_TYPES",
    "ZERO3",
    "SensorSpec",
    "Vec3",
    "error_1s_mg",
    "forward_model",
    "inverse_model",
    "misalignment_matrix",
    "sensing_axis_angles_deg",
    "sensor_type",
]

Vec3 = tuple[float, float, float]
ZERO3: Vec3 = (0.0, 0.0, 0.0)
_NOISE_CHUNK = 1 << 20  # samples per noise draw: bounds the temporary (N,3) arrays


# --- sensor ----------------------------------------------------------------------------------

def misalignment_matrix(misalignment_rad: np.ndarray | Vec3) -> np.ndarray:
    """S (3,3) with unit-norm rows = sensing-axis directions, from (α_xy, α_xz, α_yz) in rad."""
    a_xy, a_xz, a_yz = (float(x) for x in misalignment_rad)
    u = np.array([[1.0, math.tan(a_xy), math.tan(a_xz)],
                  [0.0, 1.0, math.tan(a_yz)],
                  [0.0, 0.0, 1.0]])
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def sensing_axis_angles_deg(s: np.ndarray) -> dict[str, float]:
    """Angles between the sensing axes (rows of s), Georgieva et al.: φ=∠(x,y), ψ=∠(x,z),
    θ=∠(y,z), in degrees (90 for orthogonal axes). Rows need not be normalized."""
    rows = np.asarray(s, np.float64)
    rows = rows / np.linalg.norm(rows, axis=1, keepdims=True)

    def ang(i: int, j: int) -> float:
        return float(np.degrees(np.arccos(np.clip(rows[i] @ rows[j], -1.0, 1.0))))

    return {"phi_xy_deg": ang(0, 1), "psi_xz_deg": ang(0, 2), "theta_yz_deg": ang(1, 2)}


def _vec3(x: Any, name: str) -> Vec3:
    arr = np.asarray(x, np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise UsageError(f"{name} must be 3 finite numbers, got {x!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


_VEC3_FIELDS = ("offset_g", "gain", "misalignment_rad", "q_per_g", "gain_tc_per_c",
                "offset_tc_g_per_c", "offset_drift_g_per_h")


@dataclass(frozen=True)
class SensorSpec:
    """Parameters of the sensor forward model (see the module docstring for the equations).

    Attributes:
        counts_per_g: ADC counts per g; None turns quantization off and `v` is in g.
        full_scale_g: clipping limit in g (±); None disables clipping.
        offset_g: (3,) zero-g offset in g.
        gain: (3,) relative sensitivity error (0.03 = +3 %).
        misalignment_rad: (α_xy, α_xz, α_yz) cross-axis angles in rad, see `misalignment_matrix`.
        q_per_g: (3,) quadratic nonlinearity in 1/g, applied to the ideal-frame acceleration.
        gain_tc_per_c: (3,) relative sensitivity change per °C of T − t_ref_c.
        offset_tc_g_per_c: (3,) offset change in g per °C of T − t_ref_c.
        offset_drift_g_per_h: (3,) linear offset drift in g per hour since the first sample.
        ratiometric_per_v: relative change of the whole output per volt of V − v_ref_v.
        noise_g: white noise standard deviation per axis in g (0 = none).
        t_ref_c: reference temperature in °C.
        v_ref_v: reference supply voltage in V.
        temp_channel: aux channel name of the temperature in the recording.
        supply_channel: aux channel name of the supply voltage in the recording.
        zero_g_counts: the reading at 0 g in counts (2048: mid-scale of a 12-bit ADC reading
            an analog part); it scales with the supply like the sensitivity (ratiometric).
        adc_bits: an unsigned ADC of this many bits: readings clipped to 0 .. 2^bits − 1
            instead of ±full_scale_g. None: signed (a digital part's two's complement).
        quantize: round to whole counts; False: floats in the unit of counts_per_g (a phone's
            m/s², counts_per_g = 9.80665).
    """

    counts_per_g: float | None = 1024.0
    full_scale_g: float | None = 8.0
    offset_g: Vec3 = ZERO3
    gain: Vec3 = ZERO3
    misalignment_rad: Vec3 = ZERO3
    q_per_g: Vec3 = ZERO3
    gain_tc_per_c: Vec3 = ZERO3
    offset_tc_g_per_c: Vec3 = ZERO3
    offset_drift_g_per_h: Vec3 = ZERO3
    ratiometric_per_v: float = 0.0
    noise_g: float = 0.004
    t_ref_c: float = 25.0
    v_ref_v: float = 3.3
    temp_channel: str = "temp_c"
    supply_channel: str = "vdd_v"
    zero_g_counts: float = 0.0
    adc_bits: int | None = None
    quantize: bool = True

    def __post_init__(self) -> None:
        # accept lists / arrays but store plain float tuples: hashable and JSON-friendly
        for name in _VEC3_FIELDS:
            object.__setattr__(self, name, _vec3(getattr(self, name), name))
        if self.counts_per_g is not None and not self.counts_per_g > 0:
            raise UsageError("counts_per_g must be positive or None")
        if self.full_scale_g is not None and not self.full_scale_g > 0:
            raise UsageError("full_scale_g must be positive or None")
        if self.noise_g < 0:
            raise UsageError("noise_g must be >= 0")
        if self.temp_channel == self.supply_channel:
            raise UsageError("temperature and supply channels need different names")
        if (self.zero_g_counts or self.adc_bits is not None) and self.counts_per_g is None:
            raise UsageError("zero_g_counts and adc_bits need counts_per_g")
        if self.adc_bits is not None and not 2 <= self.adc_bits <= 32:
            raise UsageError("adc_bits must be in 2..32")

    @property
    def matrix(self) -> np.ndarray:
        """S (3,3): unit-norm rows = sensing-axis directions in the ideal frame."""
        return misalignment_matrix(self.misalignment_rad)

    @property
    def axis_angles_deg(self) -> dict[str, float]:
        """Georgieva's φ=∠(x,y), ψ=∠(x,z), θ=∠(y,z) in degrees."""
        return sensing_axis_angles_deg(self.matrix)

    @property
    def full_scale_counts(self) -> float | None:
        """Clipping limit in counts (±), a whole number so clipped readings stay integers
        (None for an unsigned ADC, which clips at 0 and 2^adc_bits − 1)."""
        if self.full_scale_g is None or self.counts_per_g is None or self.adc_bits is not None:
            return None
        return float(math.floor(self.full_scale_g * self.counts_per_g + 1e-9))

    def needs(self, channel: str) -> bool:
        """Whether an effect of the sensor reads `channel` ("temperature", "supply", "time"):
        a nonzero field that an effect's simulator option sets (`effects.SimOption`)."""
        return any(bool(np.any(np.asarray(getattr(self, o.field)) != 0.0))
                   for o in sim_options() if o.channel == channel)

    @property
    def needs_temp(self) -> bool:
        return self.needs("temperature")

    @property
    def needs_supply(self) -> bool:
        return self.needs("supply")

    @property
    def needs_time(self) -> bool:
        return self.needs("time")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable fields (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SensorSpec:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    @classmethod
    def random(cls, rng: np.random.Generator, offset_mg: float = 50.0, gain_pct: float = 3.0,
               cross_axis_deg: float = 0.0, **overrides: Any) -> SensorSpec:
        """A sensor with offsets uniform in ±offset_mg, gains in ±gain_pct %, misalignment
        angles in ±cross_axis_deg; any other field from `overrides` (else its default)."""
        offset = rng.uniform(-offset_mg, offset_mg, 3) / 1000.0
        gain = rng.uniform(-gain_pct, gain_pct, 3) / 100.0
        angles = np.radians(rng.uniform(-cross_axis_deg, cross_axis_deg, 3))
        return cls(**({"offset_g": offset, "gain": gain, "misalignment_rad": angles}
                      | overrides))


#: The accelerometers people plug in, as `SensorSpec` fields (`sensor_type`): analog parts on
#: an unsigned ADC (zero-g at mid-scale; ADXL335: 300 mV/g at 3.3 V into 12 bits, 372 counts
#: per g; MMA7260 as Zheng et al. read it: 800 mV/g, a 14-bit converter whose top bit is the
#: sign, 3.0 V reference, 2185 counts per g, zero-g 4096), digital parts in two's complement
#: at several ranges, a phone in m/s² (floats).
SENSOR_TYPES: dict[str, dict[str, Any]] = {
    "default": {},
    "adxl335-adc12": {"counts_per_g": 372.0, "zero_g_counts": 2048.0, "adc_bits": 12,
                      "full_scale_g": None},
    "mma7260-adc14": {"counts_per_g": 2185.0, "zero_g_counts": 4096.0, "adc_bits": 13,
                      "full_scale_g": None},
    "digital-2g": {"counts_per_g": 16384.0, "full_scale_g": 2.0},
    "digital-4g": {"counts_per_g": 8192.0, "full_scale_g": 4.0},
    "digital-8g": {"counts_per_g": 4096.0, "full_scale_g": 8.0},
    "digital-16g": {"counts_per_g": 2048.0, "full_scale_g": 16.0},
    "adxl345-10bit": {"counts_per_g": 256.0, "full_scale_g": 2.0},
    "phone-ms2": {"counts_per_g": 9.80665, "full_scale_g": 8.0, "quantize": False},
}


def sensor_type(name: str, rng: np.random.Generator, offset_mg: float = 50.0,
                gain_pct: float = 3.0, cross_axis_deg: float = 0.0,
                **overrides: Any) -> SensorSpec:
    """A random sensor (`SensorSpec.random`) of one of `SENSOR_TYPES`; `overrides` last."""
    try:
        fields_ = SENSOR_TYPES[name]
    except KeyError:
        raise UsageError(f"unknown sensor type {name!r}; known: {sorted(SENSOR_TYPES)}") from None
    return SensorSpec.random(rng, offset_mg, gain_pct, cross_axis_deg, **(fields_ | overrides))


def _delta(x: np.ndarray | None, ref: float, n: int, what: str) -> np.ndarray:
    if x is None:
        raise ValueError(f"the sensor has a {what} effect but no {what} values were given")
    x = np.asarray(x, np.float64).reshape(-1)
    if len(x) != n:
        raise ValueError(f"{what} has {len(x)} values for {n} samples")
    return x - ref


def forward_model(a_g: np.ndarray, sensor: SensorSpec, *, temp_c: np.ndarray | None = None,
                  vdd_v: np.ndarray | None = None, t_h: np.ndarray | None = None,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """Raw readings (N,3) from the true specific force a_g (N,3, g, ideal frame).

    temp_c / vdd_v / t_h (N,) are only needed by the effects that use them; rng only when
    sensor.noise_g > 0. Steps and conventions: module docstring. Zero effects are skipped,
    so an ideal sensor without noise and quantization returns a copy of a_g bit for bit.
    """
    a = np.asarray(a_g, np.float64).reshape(-1, 3)
    n = len(a)
    q = np.array(sensor.q_per_g)
    u = a + q * a**2 if q.any() else a
    if any(sensor.misalignment_rad):
        u = u @ sensor.matrix.T
    elif u is a:
        u = a.copy()  # everything below works in place
    gain = 1.0 + np.array(sensor.gain)
    if any(sensor.gain_tc_per_c):
        dt = _delta(temp_c, sensor.t_ref_c, n, "temperature")
        for j in range(3):  # per column: (N,) temporaries instead of (N,3) ones
            u[:, j] *= gain[j] + sensor.gain_tc_per_c[j] * dt
    elif np.any(gain != 1.0):
        u *= gain
    if any(sensor.offset_g):
        u += np.array(sensor.offset_g)
    if any(sensor.offset_tc_g_per_c):
        dt = _delta(temp_c, sensor.t_ref_c, n, "temperature")
        for j in range(3):
            u[:, j] += sensor.offset_tc_g_per_c[j] * dt
    if any(sensor.offset_drift_g_per_h):
        hours = _delta(t_h, 0.0, n, "time")
        for j in range(3):
            u[:, j] += sensor.offset_drift_g_per_h[j] * hours
    if sensor.zero_g_counts:
        u += sensor.zero_g_counts / sensor.counts_per_g  # type: ignore[operator]
    if sensor.ratiometric_per_v:
        dv = _delta(vdd_v, sensor.v_ref_v, n, "supply")
        u *= (1.0 + sensor.ratiometric_per_v * dv)[:, None]
    if sensor.noise_g > 0:
        if rng is None:
            raise ValueError("noise_g > 0 needs an rng")
        # chunked so that a day of samples never holds a second full-size noise array
        for i in range(0, n, _NOISE_CHUNK):
            u[i:i + _NOISE_CHUNK] += sensor.noise_g * rng.standard_normal(
                (min(_NOISE_CHUNK, n - i), 3))
    return _adc(u, sensor)


def _adc(u: np.ndarray, sensor: SensorSpec) -> np.ndarray:
    """Quantize (round half to even, like np.rint) and clip, in place."""
    if sensor.counts_per_g is not None:
        u *= sensor.counts_per_g
        if sensor.quantize:
            np.rint(u, out=u)
        lim = sensor.full_scale_counts
    else:
        lim = sensor.full_scale_g
    if sensor.adc_bits is not None:
        np.clip(u, 0.0, float(2**sensor.adc_bits - 1), out=u)
    elif lim is not None:
        np.clip(u, -lim, lim, out=u)
    return u


def error_1s_mg(cal_g: np.ndarray, truth_g: np.ndarray, rate_hz: float,
                align: bool = False) -> float:
    """The accuracy figure of the tests, benches and README, in mg: RMS over 1 s windows of
    |mean(calibrated - true)|. align: rotate the calibrated output onto the truth first (the
    best rotation, fitted on every 10th sample): a rotation of the sensor frame is not
    observable from gravity alone."""
    c, a = np.asarray(cal_g, np.float64), np.asarray(truth_g, np.float64)
    if align:
        rot, _ = Rotation.align_vectors(a[::10], c[::10])
        c = rot.apply(c)
    n = round(rate_hz)
    k = len(c) // n
    e = (c - a)[:k * n].reshape(k, n, 3).mean(axis=1)
    return 1e3 * float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def inverse_model(v: np.ndarray, sensor: SensorSpec, *, temp_c: np.ndarray | None = None,
                  vdd_v: np.ndarray | None = None, t_h: np.ndarray | None = None) -> np.ndarray:
    """The exact inverse of `forward_model` without noise, quantization and clipping:
    raw readings (N,3) -> a in g (N,3). What a perfect calibration would output."""
    u = np.array(v, np.float64).reshape(-1, 3)
    n = len(u)
    if sensor.counts_per_g is not None:
        u /= sensor.counts_per_g
    if sensor.ratiometric_per_v:
        u /= (1.0 + sensor.ratiometric_per_v * _delta(vdd_v, sensor.v_ref_v, n, "supply"))[:, None]
    if sensor.zero_g_counts:
        u -= sensor.zero_g_counts / sensor.counts_per_g  # type: ignore[operator]
    u -= np.array(sensor.offset_g)
    if any(sensor.offset_tc_g_per_c):
        u -= (_delta(temp_c, sensor.t_ref_c, n, "temperature")[:, None]
              * np.array(sensor.offset_tc_g_per_c))
    if any(sensor.offset_drift_g_per_h):
        u -= _delta(t_h, 0.0, n, "time")[:, None] * np.array(sensor.offset_drift_g_per_h)
    gain = 1.0 + np.array(sensor.gain)
    if any(sensor.gain_tc_per_c):
        gain = gain + (_delta(temp_c, sensor.t_ref_c, n, "temperature")[:, None]
                       * np.array(sensor.gain_tc_per_c))
    u /= gain
    a1 = np.linalg.solve(sensor.matrix, u.T).T
    q = np.array(sensor.q_per_g)
    # a + q a² = a1, the root that tends to a1 as q -> 0 (stable form, no cancellation)
    return 2.0 * a1 / (1.0 + np.sqrt(np.maximum(1.0 + 4.0 * q * a1, 0.0)))
