"""Mounting alignment: how the worn sensor is tilted against the body (Zheng et al., sec. II.B/C).

On a reference posture (the wearer upright and still) the calibrated reading is gravity alone,
+1 g along the body's vertical. Its direction in the sensor frame gives the mounting tilt:

    sin θx = a_x / G,   sin θy = a_y / G                      Zheng eq. 3-4 (G = |a|)

and the body-frame acceleration follows by turning the sensor's x-z plane by θ1 (eq. 6-7) and
then its y-z plane by θy (eq. 8). Zheng uses θ1 = θx, which is exact only when θy = 0; here
θ1 = atan2(a_x, a_z) so the rotation takes the reference gravity exactly to +z for any tilt,
and θy stays Zheng's arcsin. Both agree with the paper to second order in the tilt. The
heading (rotation about the vertical) is not observable from gravity and is left at zero.

Zheng found the small-angle treatment good below 7° and alarms when θx or θy exceeds it; the
limit is a parameter here.

Also here: :class:`StillTracker`, which finds the first moment a quasi-static run has lasted
long enough to serve as the reference, and keeps the run's mean calibrated reading.

Pure numpy: arrays in, arrays and small dataclasses out; no I/O, no clocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "DEFAULT_TILT_LIMIT_DEG",
    "Alignment",
    "StillTracker",
    "estimate_alignment",
    "rotation_from_angles",
    "tilt_from_z_deg",
    "to_body",
    "zheng_angles",
]

DEFAULT_TILT_LIMIT_DEG = 7.0
"""Zheng et al.: beyond 7° the device asks the wearer to adjust the sensor."""


def zheng_angles(g: np.ndarray) -> tuple[float, float]:
    """(θx, θy) in radians of a gravity reading g (any unit): Zheng eq. 3-4, arcsin(g_xy / |g|)."""
    g = np.asarray(g, np.float64).reshape(3)
    norm = float(np.linalg.norm(g))
    if not norm > 0:
        raise ValueError("gravity vector has zero length")
    u = g / norm
    return float(np.arcsin(np.clip(u[0], -1, 1))), float(np.arcsin(np.clip(u[1], -1, 1)))


def rotation_from_angles(theta1: float, theta_y: float) -> np.ndarray:
    """R (3,3), sensor -> body: Zheng eq. 6-7 (x-z plane by theta1) then eq. 8 (y-z by θy).

    With a_body = R @ a_sensor:
        eq. 6-7:  x' = x cos θ1 - z sin θ1,   z' = x sin θ1 + z cos θ1
        eq. 8:    y'' = y cos θy - z' sin θy,  z'' = y sin θy + z' cos θy
    """
    c1, s1 = np.cos(theta1), np.sin(theta1)
    cy, sy = np.cos(theta_y), np.sin(theta_y)
    first = np.array([[c1, 0.0, -s1], [0.0, 1.0, 0.0], [s1, 0.0, c1]])
    second = np.array([[1.0, 0.0, 0.0], [0.0, cy, -sy], [0.0, sy, cy]])
    return second @ first


@dataclass(frozen=True, eq=False)
class Alignment:
    """The mounting of one sensor, from one reference posture.

    Attributes:
        gravity_g: (3,) mean calibrated reading on the reference posture, g, sensor frame.
        rotation: (3,3) R with a_body = R @ a_sensor; R @ gravity_g / |gravity_g| = +z.
        theta_x_deg, theta_y_deg: Zheng eq. 3-4 angles, degrees.
        tilt_deg: angle between the reference gravity and the sensor's +z, degrees.
        limit_deg: the alarm limit the alignment was judged against.
        n: samples averaged; t_us: device time of the last of them.
    """

    gravity_g: np.ndarray
    rotation: np.ndarray
    theta_x_deg: float
    theta_y_deg: float
    tilt_deg: float
    limit_deg: float
    n: int = 0
    t_us: int | None = None

    @property
    def alarm(self) -> bool:
        """Zheng's rule: either angle beyond the limit means the sensor should be re-seated."""
        return max(abs(self.theta_x_deg), abs(self.theta_y_deg)) > self.limit_deg

    def to_dict(self) -> dict:
        return {"gravity_g": self.gravity_g.tolist(), "rotation": self.rotation.tolist(),
                "theta_x_deg": self.theta_x_deg, "theta_y_deg": self.theta_y_deg,
                "tilt_deg": self.tilt_deg, "limit_deg": self.limit_deg, "alarm": self.alarm,
                "n": self.n, "t_us": self.t_us}

    @classmethod
    def from_dict(cls, d: dict) -> Alignment:
        t = d.get("t_us")
        return cls(np.asarray(d["gravity_g"], np.float64), np.asarray(d["rotation"], np.float64),
                   float(d["theta_x_deg"]), float(d["theta_y_deg"]), float(d["tilt_deg"]),
                   float(d.get("limit_deg", DEFAULT_TILT_LIMIT_DEG)), int(d.get("n", 0)),
                   None if t is None else int(t))


def estimate_alignment(gravity_g: np.ndarray, limit_deg: float = DEFAULT_TILT_LIMIT_DEG,
                       n: int = 0, t_us: int | None = None) -> Alignment:
    """The mounting from the mean calibrated reading on a reference posture (g, sensor frame)."""
    g = np.asarray(gravity_g, np.float64).reshape(3)
    if not (np.all(np.isfinite(g)) and np.linalg.norm(g) > 0):
        raise ValueError(f"gravity vector must be finite and non-zero, got {g.tolist()}")
    u = g / np.linalg.norm(g)
    theta_x, theta_y = zheng_angles(u)
    # θ1 zeroes x exactly (eq. 6); the y-z turn by Zheng's θy then zeroes y (eq. 8), because
    # after the first turn the vector is (0, u_y, sqrt(u_x² + u_z²)) with unit length.
    theta1 = float(np.arctan2(u[0], u[2]))
    R = rotation_from_angles(theta1, theta_y)
    tilt = float(np.degrees(np.arccos(np.clip(u[2], -1.0, 1.0))))
    return Alignment(g, R, float(np.degrees(theta_x)), float(np.degrees(theta_y)), tilt,
                     float(limit_deg), int(n), t_us)


def to_body(rotation: np.ndarray, a_g: np.ndarray) -> np.ndarray:
    """Rotate (N,3) sensor-frame accelerations into the body frame: each row R @ a."""
    return np.asarray(a_g, np.float64).reshape(-1, 3) @ np.asarray(rotation, np.float64).T


def tilt_from_z_deg(g: np.ndarray) -> float:
    """Angle in degrees between a reading and the sensor's +z axis."""
    g = np.asarray(g, np.float64).reshape(3)
    norm = float(np.linalg.norm(g))
    return float(np.degrees(np.arccos(np.clip(g[2] / norm, -1, 1)))) if norm > 0 else 180.0


class StillTracker:
    """Follows the current quasi-static run of calibrated samples, batch by batch.

    A run is a stretch of gated samples without a time gap above ``max_gap_us``. The tracker
    keeps the run's start, length and sum (bounded state), and :meth:`feed` reports the first
    sample at which a run has lasted ``min_s`` while ``armed`` (the caller decides when a
    reference may be taken, e.g. after an accepted calibration update).

    Args:
        min_s: how long a run must last to be a reference posture, seconds.
        max_gap_us: a larger step between consecutive samples breaks the run, microseconds.
    """

    def __init__(self, min_s: float, max_gap_us: int) -> None:
        if not min_s > 0 or not max_gap_us > 0:
            raise ValueError("min_s and max_gap_us must be positive")
        self.min_us = round(min_s * 1e6)
        self.max_gap_us = int(max_gap_us)
        self.start_us: int | None = None  # first sample of the open run (None: no run)
        self.last_us: int | None = None  # last sample seen (gated or not)
        self.last_gate = False
        self.n = 0
        self.sum_g = np.zeros(3)
        self.fired = False  # the open run already produced a reference

    @property
    def duration_s(self) -> float:
        """How long the open run has lasted (0 without one), seconds."""
        if self.start_us is None or self.last_us is None or not self.last_gate:
            return 0.0
        return (self.last_us - self.start_us) / 1e6

    def mean(self) -> np.ndarray | None:
        """Mean calibrated reading of the open run so far (g), or None without one."""
        if self.n == 0 or not self.last_gate:
            return None
        return self.sum_g / self.n

    def feed(self, t_us: np.ndarray, a_g: np.ndarray, gate: np.ndarray,
             armed: bool = True) -> tuple[np.ndarray, int, int] | None:
        """Add a batch; return (mean g, samples, t_us of the last) when a run first reaches
        ``min_s`` while armed, else None. At most one reference per call (the first)."""
        t_us = np.asarray(t_us, np.int64)
        a_g = np.asarray(a_g, np.float64).reshape(-1, 3)
        gate = np.asarray(gate, bool)
        if len(t_us) == 0:
            return None
        quick = self._feed_uniform(t_us, a_g, gate, armed)
        if quick is not False:
            return quick
        prev = int(t_us[0]) - 1 if self.last_us is None else self.last_us
        dt = np.empty(len(t_us), np.int64)  # np.diff(t_us, prepend=prev)
        dt[0] = int(t_us[0]) - prev
        np.subtract(t_us[1:], t_us[:-1], out=dt[1:])
        joined = gate & (dt > 0) & (dt <= self.max_gap_us)
        # a run starts where the gate opens, or continues across a break in time
        prev_gate = np.empty_like(gate)
        prev_gate[0] = self.last_gate
        prev_gate[1:] = gate[:-1]
        starts = gate & ~(prev_gate & joined)
        result = None
        # segments: each run, and each stretch of ungated samples as a whole (ending a run is
        # idempotent, so one call per stretch, not one per sample)
        first_ungated = ~gate & np.concatenate(([True], gate[:-1]))
        bounds = np.concatenate(([0], np.flatnonzero(starts | first_ungated), [len(gate)]))
        bounds = np.unique(bounds)
        for i0, i1 in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
            if not gate[i0]:
                self._end_run()
                continue
            if starts[i0]:
                self._start_run(int(t_us[i0]))
            hit = self._extend(t_us[i0:i1], a_g[i0:i1], armed and result is None)
            if hit is not None:
                result = hit
        self.last_us = int(t_us[-1])
        self.last_gate = bool(gate[-1])
        return result

    def _feed_uniform(self, t_us: np.ndarray, a_g: np.ndarray, gate: np.ndarray,
                      armed: bool) -> tuple[np.ndarray, int, int] | bool | None:
        """`feed` for the common batches, all moving or all continuing the open run, without
        the segment bookkeeping; False when the batch is neither (the general path runs)."""
        if not gate.any():
            self._end_run()
        elif (gate.all() and self.last_gate and self.start_us is not None
              and self.last_us is not None
              and 0 < int(t_us[0]) - self.last_us <= self.max_gap_us
              and (len(t_us) == 1 or bool(np.all((np.diff(t_us) > 0)
                                                 & (np.diff(t_us) <= self.max_gap_us))))):
            hit = self._extend(t_us, a_g, armed)
            self.last_us, self.last_gate = int(t_us[-1]), True
            return hit
        else:
            return False
        self.last_us, self.last_gate = int(t_us[-1]), False
        return None

    def _start_run(self, t0_us: int) -> None:
        self.start_us, self.n, self.sum_g, self.fired = t0_us, 0, np.zeros(3), False

    def _end_run(self) -> None:
        self.start_us, self.n, self.sum_g, self.fired = None, 0, np.zeros(3), False

    def _extend(self, t: np.ndarray, a: np.ndarray,
                may_fire: bool) -> tuple[np.ndarray, int, int] | None:
        """Add gated samples of the open run; fire at the first one that completes min_s."""
        assert self.start_us is not None
        if may_fire and not self.fired:
            due = np.flatnonzero(t - self.start_us >= self.min_us)
            if len(due):
                k = int(due[0]) + 1
                self.sum_g = self.sum_g + a[:k].sum(0)
                self.n += k
                self.fired = True
                hit = (self.sum_g / self.n, self.n, int(t[k - 1]))
                self.sum_g = self.sum_g + a[k:].sum(0)
                self.n += len(t) - k
                return hit
        self.sum_g = self.sum_g + a.sum(0)
        self.n += len(t)
        return None

    def rearm(self) -> None:
        """Let the open run produce a reference again (an alignment was requested)."""
        self.fired = False
