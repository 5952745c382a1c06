"""Seeded simulator of a wearer-like triaxial accelerometer recording, with ground truth.

A wearer alternates still postures (upright, lying, any orientation) with walking-like
movements; the true specific force in the ideal sensor frame is passed through a sensor
forward model to give the raw readings the device would send. Pure numpy/scipy, no I/O
except `save_truth` / `load_truth`. Same seed -> bit-identical result.

The sensor (its forward model, cross-axis matrix and the sensor types people plug in) is
`recal.sim.sensor`, the wearer's settings `recal.sim.wearer_spec`, the temperature and supply
channels `recal.sim.aux_channels`; the names of the first two are importable from here too.

Wearer model
------------
Still posture k has an at-rest reading direction g_k (unit, sensor frame: what the sensor
reads at rest, gravity counted +1 g "up"), drawn by kind: upright (within `upright_tilt_deg`
of +z), lying (within ±`lying_band_deg` of the x-y plane), any (uniform on the sphere). Its
orientation A_k is the smallest rotation with A_k g_k = +z (sensor -> world). During the
posture the reading is g_k tilted by a slow sway plus a tiny bounded vertical part, so |a| stays
within 1 mg of 1 g for the default `sway_g`. A movement from posture k to k+1 has orientation
R(t) = W(t) · slerp(A_k, A_k+1; smoothstep(t/D)) with a step-locked wobble W, and linear
acceleration of walking at 1.6-2.2 Hz; the reading is R(t)ᵀ (ẑ + a_lin(t)) in g.

Mounting slip (optional, `MountSlip`): the sensor turns on the body by Q(t), a tilt of
deg · ramp(t) about a horizontal axis of the sensor frame (at azimuth_deg from +x), where ramp
goes 0 -> 1 linearly over over_s from at_s (a step when over_s = 0). The wearer's motion is
unchanged; the sensor reads Q(t)ᵀ a, so `a_true_g` (the ideal sensor frame, what a perfect
calibration outputs) includes the slip, while `posture_up` stays the postures' directions as
the sensor was first worn. Without a slip nothing of the above changes (same draws, same bits).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from recal.errors import UsageError
from recal.samples import RawBatch
from recal.sim import aux_channels
from recal.sim.sensor import (
    SENSOR_TYPES,
    SensorSpec,
    error_1s_mg,
    forward_model,
    inverse_model,
    misalignment_matrix,
    sensing_axis_angles_deg,
    sensor_type,
)
from recal.sim.wearer_spec import PostureSpec, StepSpec, SupplySpec, TemperatureSpec, WearerSpec

__all__ = [
    "POSTURE_KINDS",
    "SENSOR_TYPES",
    "MountSlip",
    "PostureSpec",
    "SensorSpec",
    "SimResult",
    "StepSpec",
    "SupplySpec",
    "TemperatureSpec",
    "Truth",
    "WearerSpec",
    "error_1s_mg",
    "forward_model",
    "inverse_model",
    "load_truth",
    "misalignment_matrix",
    "save_truth",
    "sensing_axis_angles_deg",
    "sensor_type",
    "simulate",
    "with_sensor",
]

POSTURE_KINDS: tuple[str, ...] = ("upright", "lying", "any")
_EZ = np.array([0.0, 0.0, 1.0])
_FORMAT_VERSION = 1


# --- wearer ----------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Truth:
    """What a perfect calibration and a perfect detector would know.

    Attributes:
        a_true_g: (N,3) true specific force in g, ideal orthonormal sensor frame.
        still: (N,) bool, inside a still posture and at least still_margin_s from its ends.
        posture_id: (N,) int64, index of the still posture a sample belongs to, -1 in movement.
        posture_kind: (P,) "upright" / "lying" / "any" per still posture.
        posture_up: (P,3) at-rest reading direction of each posture (unit, sensor frame).
        params: JSON-serializable: "sensor" (SensorSpec.to_dict), "S", "axis_angles_deg",
            "wearer", "seed", "hours", "rate_hz", "start_us", "n_samples", "aux_names", ...
    """

    a_true_g: np.ndarray
    still: np.ndarray
    posture_id: np.ndarray
    posture_kind: tuple[str, ...]
    posture_up: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def sensor(self) -> SensorSpec:
        return SensorSpec.from_dict(self.params["sensor"])


@dataclass(frozen=True, eq=False)
class SimResult:
    """A simulated recording: what the device sends, and the ground truth behind it."""

    raw: RawBatch
    truth: Truth


@dataclass(frozen=True)
class _Segment:
    """A stretch of the schedule, [start_s, stop_s) in seconds since the first sample."""

    start_s: float
    stop_s: float
    still: bool
    posture: int  # still: its posture; movement: the posture it leads to


def _draw_up(kind: str, w: PostureSpec, rng: np.random.Generator) -> np.ndarray:
    """At-rest reading direction (unit) of a posture of the given kind, uniform in its region."""
    if kind == "upright":
        z = rng.uniform(math.cos(math.radians(w.upright_tilt_deg)), 1.0)
    elif kind == "lying":
        s = math.sin(math.radians(w.lying_band_deg))
        z = rng.uniform(-s, s)
    else:
        z = rng.uniform(-1.0, 1.0)
    az = rng.uniform(0.0, 2 * math.pi)
    r = math.sqrt(max(0.0, 1.0 - z * z))  # z uniform -> uniform on the sphere's zone
    return np.array([r * math.cos(az), r * math.sin(az), z])


def _schedule(total_s: float, w: PostureSpec,
              rng: np.random.Generator) -> tuple[list[_Segment], list[str], np.ndarray]:
    """Alternate still postures and movements until total_s is covered."""
    probs = w.kind_probabilities
    segments: list[_Segment] = []
    kinds: list[str] = []
    ups: list[np.ndarray] = []
    t = 0.0

    def new_posture() -> int:
        kind = POSTURE_KINDS[int(rng.choice(3, p=probs))]
        kinds.append(kind)
        ups.append(_draw_up(kind, w, rng))
        return len(kinds) - 1

    k = new_posture()
    while True:
        d = rng.uniform(*w.still_s)
        segments.append(_Segment(t, t + d, True, k))
        t += d
        if t >= total_s:
            break
        d = rng.uniform(*w.move_s)
        k = new_posture()  # the target of the movement exists even if the recording ends
        segments.append(_Segment(t, t + d, False, k))
        t += d
        if t >= total_s:
            break
    return segments, kinds, np.array(ups).reshape(-1, 3)


def _align_to_up(g: np.ndarray) -> Rotation:
    """Smallest rotation A with A g = +z (sensor -> world for a sensor reading g at rest)."""
    axis = np.cross(g, _EZ)
    s, c = float(np.linalg.norm(axis)), float(g @ _EZ)
    if s < 1e-12:
        return Rotation.identity() if c > 0 else Rotation.from_rotvec([math.pi, 0.0, 0.0])
    return Rotation.from_rotvec(axis / s * math.atan2(s, c))


def _sines(tau_s: np.ndarray, freqs_hz: np.ndarray, phases: np.ndarray,
           amp: float) -> np.ndarray:
    """Sum of sinusoids of equal amplitude: bounded, smooth, band-limited."""
    return amp * np.sin(2 * np.pi * np.outer(tau_s, freqs_hz) + phases).sum(axis=1)


def _still_segment(up: np.ndarray, tau_s: np.ndarray, w: PostureSpec,
                   rng: np.random.Generator) -> np.ndarray:
    """Readings (n,3) of a still posture: tilt sway perpendicular to up, plus a vertical part
    at 15 % of sway_g so that | |a| - 1 | <= 0.3 sway_g (bounded, no Gaussian tails)."""
    lo_hz = min(0.02, w.sway_max_hz)
    f = rng.uniform(lo_hz, w.sway_max_hz, 8)
    ph = rng.uniform(0.0, 2 * math.pi, 8)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    # 3 sinusoids per tilt axis, amplitude sway/sqrt(3) each: RMS of the tilt vector = sway_g
    amp = w.sway_g / math.sqrt(3.0)
    s1 = _sines(tau_s, f[:3], ph[:3], amp)
    s2 = _sines(tau_s, f[3:6], ph[3:6], amp)
    vertical = _sines(tau_s, f[6:], ph[6:], 0.15 * w.sway_g)
    a = up + s1[:, None] * e1 + s2[:, None] * e2
    a *= ((1.0 + vertical) / np.linalg.norm(a, axis=1))[:, None]
    return a


def _smooth_ramp(x: np.ndarray) -> np.ndarray:
    """0 -> 1 with zero slope at both ends (sin²), x clipped to [0, 1]."""
    return np.sin(0.5 * np.pi * np.clip(x, 0.0, 1.0)) ** 2


def _move_segment(a_from: Rotation, a_to: Rotation, tau_s: np.ndarray, dur_s: float,
                  w: StepSpec, rng: np.random.Generator) -> np.ndarray:
    """Readings (n,3) of a walking-like movement from one posture orientation to the next."""
    f_hz = rng.uniform(*w.step_hz)
    amp_v = rng.uniform(*w.step_vertical_g)
    heading = rng.uniform(0.0, 2 * math.pi)
    ph = rng.uniform(0.0, 2 * math.pi, 9)
    # steps and wobble fade in and out, so the movement joins the still postures smoothly
    ramp_s = min(1.0, dur_s / 4)
    env = _smooth_ramp(tau_s / ramp_s) * _smooth_ramp((dur_s - tau_s) / ramp_s)
    phase = 2 * np.pi * f_hz * tau_s + ph[0]
    vert = amp_v * (np.sin(phase) + 0.35 * np.sin(2 * phase + ph[1])
                    + 0.12 * np.sin(3 * phase + ph[2]))
    fwd = amp_v * w.step_forward_ratio * (np.sin(phase + ph[3]) + 0.3 * np.sin(2 * phase + ph[4]))
    lat = amp_v * w.step_lateral_ratio * np.sin(0.5 * phase + ph[5])  # stride = 2 steps
    ch, sh = math.cos(heading), math.sin(heading)
    f_world = np.empty((len(tau_s), 3))
    f_world[:, 0] = env * (fwd * ch - lat * sh)
    f_world[:, 1] = env * (fwd * sh + lat * ch)
    f_world[:, 2] = 1.0 + env * vert  # gravity as the accelerometer reads it: +1 g up
    wob = math.radians(w.wobble_deg) * env
    rotvec = np.stack([wob * np.sin(0.5 * phase + ph[6]), wob * np.sin(0.5 * phase + ph[7]),
                       0.5 * wob * np.sin(phase + ph[8])], axis=1)
    x = np.clip(tau_s / dur_s, 0.0, 1.0)
    slerp = Slerp([0.0, 1.0], Rotation.concatenate([a_from, a_to]))
    r = Rotation.from_rotvec(rotvec) * slerp(x * x * (3.0 - 2.0 * x))  # smoothstep
    return r.inv().apply(f_world)


def _wearer_motion(segments: list[_Segment], ups: np.ndarray, n: int, rate_hz: float,
                   w: WearerSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray,
                                                                      np.ndarray]:
    """a_true_g (n,3), still (n,) and posture_id (n,) from the schedule."""
    a = np.empty((n, 3))
    still = np.zeros(n, bool)
    posture_id = np.full(n, -1, np.int64)
    orient = [_align_to_up(g) for g in ups]
    margin = w.postures.still_margin_s
    for k, seg in enumerate(segments):
        i0 = min(n, math.ceil(seg.start_s * rate_hz))
        i1 = min(n, math.ceil(seg.stop_s * rate_hz))
        tau = np.arange(i0, i1) / rate_hz - seg.start_s
        if seg.still:
            a[i0:i1] = _still_segment(ups[seg.posture], tau, w.postures, rng)
            posture_id[i0:i1] = seg.posture
            dur = seg.stop_s - seg.start_s
            still[i0:i1] = (tau >= margin) & (tau <= dur - margin)
        else:
            prev = segments[k - 1].posture
            a[i0:i1] = _move_segment(orient[prev], orient[seg.posture], tau,
                                     seg.stop_s - seg.start_s, w.steps, rng)
    # a recording that ends inside a still posture loses its end margin too
    last = segments[-1]
    if last.still:
        still[max(0, n - math.ceil(margin * rate_hz)):n] = False
    return a, still, posture_id


@dataclass(frozen=True)
class MountSlip:
    """The sensor turning on the body after it was put on (see the module docstring).

    Attributes:
        deg: how far it tilts in the end, degrees.
        at_s: when it starts to move, seconds after the first sample.
        over_s: how long the move takes, seconds (0: at once, a strap knocked loose; minutes
            or hours: one sliding slowly).
        azimuth_deg: direction of the tilt axis in the sensor's x-y plane, degrees from +x.
    """

    deg: float
    at_s: float
    over_s: float = 0.0
    azimuth_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.deg) and math.isfinite(self.at_s) and self.at_s >= 0
                and math.isfinite(self.over_s) and self.over_s >= 0
                and math.isfinite(self.azimuth_deg)):
            raise UsageError("slip: deg, azimuth_deg finite; at_s, over_s finite and >= 0")

    def angle_deg(self, t_s: np.ndarray) -> np.ndarray:
        """The tilt at times t_s (seconds after the first sample), degrees."""
        t = np.asarray(t_s, np.float64)
        if self.over_s == 0:
            return np.where(t >= self.at_s, self.deg, 0.0)
        return self.deg * np.clip((t - self.at_s) / self.over_s, 0.0, 1.0)

    def rotvec(self, t_s: np.ndarray) -> np.ndarray:
        """Q(t) as rotation vectors (n,3), radians: the sensor axes turned in the body frame."""
        az = math.radians(self.azimuth_deg)
        axis = np.array([math.cos(az), math.sin(az), 0.0])
        return np.radians(self.angle_deg(t_s))[:, None] * axis

    def apply(self, a_g: np.ndarray, t_s: np.ndarray) -> np.ndarray:
        """Q(t)ᵀ a for each row: the body-frame force as the turned sensor reads it, in place
        from at_s on (samples before are untouched)."""
        i0 = int(np.searchsorted(t_s, self.at_s))
        if i0 < len(a_g):
            q = Rotation.from_rotvec(self.rotvec(t_s[i0:]))
            a_g[i0:] = q.inv().apply(a_g[i0:])
        return a_g


# --- the simulation --------------------------------------------------------------------------

def _streams(seed: int) -> list[np.random.Generator]:
    """Independent generators for schedule, motion, temperature, supply and sensor noise."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)]


def simulate(hours: float, rate_hz: float, seed: int, sensor: SensorSpec | None = None,
             wearer: WearerSpec | None = None, *, start_us: int = 0,
             slip: MountSlip | None = None) -> SimResult:
    """Simulate `hours` of a wearer at `rate_hz`, sensed by `sensor`. Deterministic in seed.

    Independent random streams (numpy SeedSequence children) drive the schedule, the motion,
    the temperature, the supply and the sensor noise, so e.g. changing the sensor does not
    change a_true_g, and enabling aux channels does not change the postures. A `slip` turns
    the sensor on the body (module docstring) and draws nothing: the same seed gives the same
    wearer and noise with or without it; params["slip"] records it.
    """
    sensor = SensorSpec() if sensor is None else sensor
    wearer = WearerSpec() if wearer is None else wearer
    if hours <= 0 or rate_hz <= 0:
        raise UsageError("hours and rate_hz must be positive")
    n = round(hours * 3600 * rate_hz)
    if n < 1:
        raise UsageError("recording shorter than one sample")
    r_sched, r_motion, r_temp, r_vdd, r_noise = _streams(seed)

    t_s = np.arange(n) / rate_hz
    t_us = np.round(t_s * 1e6).astype(np.int64)
    t_us += np.int64(start_us)
    segments, kinds, ups = _schedule(n / rate_hz, wearer.postures, r_sched)
    a_true, still, posture_id = _wearer_motion(segments, ups, n, rate_hz, wearer, r_motion)
    if slip is not None:
        slip.apply(a_true, t_s)

    aux_names: list[str] = []
    if sensor.needs_temp or wearer.always_aux:
        aux_names.append(sensor.temp_channel)
    if sensor.needs_supply or wearer.always_aux:
        aux_names.append(sensor.supply_channel)
    aux = np.empty((n, len(aux_names)))  # filled column by column, no stacking copy
    temp = vdd = None
    if sensor.temp_channel in aux_names:
        temp = aux[:, aux_names.index(sensor.temp_channel)]
        temp[:] = aux_channels.temperature(t_s, wearer.temperature, r_temp)
    if sensor.supply_channel in aux_names:
        vdd = aux[:, aux_names.index(sensor.supply_channel)]
        vdd[:] = aux_channels.supply(t_s, rate_hz, wearer.supply, r_vdd)
    t_h = t_s / 3600.0 if sensor.needs_time else None
    del t_s
    v = forward_model(a_true, sensor, temp_c=temp, vdd_v=vdd, t_h=t_h, rng=r_noise)
    raw = RawBatch(t_us, v, aux, tuple(aux_names))

    params = {
        "format_version": _FORMAT_VERSION,
        "sensor": sensor.to_dict(),
        "S": sensor.matrix.tolist(),
        "axis_angles_deg": sensor.axis_angles_deg,
        "full_scale_counts": sensor.full_scale_counts,
        "wearer": wearer.to_dict(),
        "seed": int(seed),
        "hours": float(hours),
        "rate_hz": float(rate_hz),
        "start_us": int(start_us),
        "n_samples": int(n),
        "n_postures": len(kinds),
        "aux_names": aux_names,
        "v_unit": "counts" if sensor.counts_per_g is not None else "g",
    }
    if slip is not None:
        params["slip"] = asdict(slip)
    truth = Truth(a_true, still, posture_id, tuple(kinds), ups, params)
    return SimResult(raw, truth)


def with_sensor(result: SimResult, sensor: SensorSpec, seed: int | None = None) -> SimResult:
    """The same wearer and aux channels seen by another sensor.

    With seed None the noise is the one `simulate` would draw, so when both recordings carry
    the same aux channels, with_sensor(simulate(h, r, s, A, w), B) equals
    simulate(h, r, s, B, w). Aux channels the new sensor needs must already be in the
    recording (use WearerSpec.always_aux); aux_names stay those of `result`."""
    p = result.truth.params
    names = result.raw.aux_names
    temp = result.raw.channel(sensor.temp_channel) if sensor.temp_channel in names else None
    vdd = result.raw.channel(sensor.supply_channel) if sensor.supply_channel in names else None
    t_h = np.arange(len(result.raw)) / p["rate_hz"] / 3600.0  # as simulate computes it
    rng = _streams(p["seed"] if seed is None else seed)[4]
    v = forward_model(result.truth.a_true_g, sensor, temp_c=temp, vdd_v=vdd, t_h=t_h, rng=rng)
    params = p | {"sensor": sensor.to_dict(), "S": sensor.matrix.tolist(),
                  "axis_angles_deg": sensor.axis_angles_deg,
                  "full_scale_counts": sensor.full_scale_counts,
                  "v_unit": "counts" if sensor.counts_per_g is not None else "g"}
    return SimResult(replace(result.raw, v=v), replace(result.truth, params=params))


# --- files -----------------------------------------------------------------------------------

def save_truth(path: str | Path, result: SimResult) -> None:
    """Write a SimResult (raw and truth) to a compressed .npz; params and names as JSON."""
    meta = {"params": result.truth.params, "posture_kind": list(result.truth.posture_kind),
            "aux_names": list(result.raw.aux_names)}
    with open(path, "wb") as fh:  # a file object keeps numpy from appending ".npz"
        np.savez_compressed(fh, t_us=result.raw.t_us, v=result.raw.v, aux=result.raw.aux,
                            a_true_g=result.truth.a_true_g, still=result.truth.still,
                            posture_id=result.truth.posture_id,
                            posture_up=result.truth.posture_up, meta=np.array(json.dumps(meta)))


def load_truth(path: str | Path) -> SimResult:
    """Read what `save_truth` wrote."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        raw = RawBatch(z["t_us"], z["v"], z["aux"], tuple(meta["aux_names"]))
        truth = Truth(z["a_true_g"], z["still"], z["posture_id"], tuple(meta["posture_kind"]),
                      z["posture_up"], meta["params"])
    return SimResult(raw, truth)
