"""Mounting alignment: how the worn sensor is tilted against the body (Zheng et al., sec. II.B/C).

On a reference posture (the wearer upright and still) the calibrated reading is gravity alone,
+1 g along the body's vertical. Its direction in the sensor frame gives the mounting tilt:

    sin θx = a_x / G,   sin θy = a_y / G                      Zheng eq. 3-4 (G = |a|)

and the body-frame acceleration follows by turning the sensor's x-z plane by θ1 (eq. 6-7) and
then its y-z plane by θy (eq. 8). Zheng uses θ1 = θx, which is exact only when θy = 0; here
θ1 = atan2(a_x, a_z) so the rotation takes the reference gravity exactly to +z for any tilt,
and θy stays Zheng's arcsin. Both agree with the paper to second order in the tilt. The
heading (rotation about the vertical) is not observable from gravity and is left at zero.

The tilt alarm: Zheng alarms when θx or θy of the worn sensor exceeds 7°, the tilt up to which
the paper's small-angle treatment matched its measurements. Here the rotation is exact at any
tilt, so a sensor worn tilted is simply aligned; and one still upright period cannot tell a
tilted mounting from a wearer leaning or sitting back (simulated wearers stand within 30° of
vertical: Zheng's rule on the reference alarmed on most of them). What does go wrong is a
mounting that moves after the reference was taken: the body frame is then off by the move.
So the alarm is for a slip (:class:`SlipWatch`): the reference is one upright still period;
the alarm is raised when ``periods`` (4) later upright still periods, each separated from the
one before by movement, all lie beyond the limit from the reference *and* agree with each
other within ``agree_deg`` (3°). A slip turns every later posture by the same rotation, so the
wearer's usual upright posture comes back turned, again and again, the same way; postures
that merely differ from the reference scatter and rarely agree, and one upright period near
the reference breaks the streak. Lying and bending (beyond ``upright_max_deg`` of the
reference) say nothing and are skipped. The alarm clears when ``periods`` upright periods in
a row are back within the limit (the sensor was re-seated). Why 4 and 3°: the fewest periods
that raise no false alarm on simulated wearers leaning anywhere within 30° while every 10° slip
of a wearer who stands alike is still caught (bench/tilt_alarm.py; docs/performance.md).
While the alarm stands the body frame keeps the reference's rotation (off by the slip, which
the alarm says); a new reference (a query on ``recal/<sensor>/align``) ends it. What the rule
cannot see: a wearer whose only upright posture after the reference is a second, steady one
beyond the limit from it (gravity alone cannot tell that from a slip), a wearer whose upright
postures scatter more than ``agree_deg`` (no slip is caught there), and a slip about the
vertical.

Also here: :class:`StillTracker`, which finds the moment each quasi-static run has lasted long
enough to serve as a reference (or as a check of it), and keeps the run's mean calibrated
reading.

Pure numpy: arrays in, arrays and small dataclasses out; no I/O, no clocks. See docs/design.md
("The tilt alarm").
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from recal.errors import ConfigError, InputError

__all__ = [
    "DEFAULT_TILT_LIMIT_DEG",
    "Alignment",
    "MountChange",
    "SlipWatch",
    "StillHit",
    "StillTracker",
    "angle_deg",
    "estimate_alignment",
    "rotation_from_angles",
    "tilt_from_z_deg",
    "to_body",
    "zheng_angles",
]

DEFAULT_TILT_LIMIT_DEG = 7.0
"""Zheng et al.: beyond 7° the device asks the wearer to adjust the sensor (here: a slip)."""

SLIP_PERIODS = 4
"""Separate upright still periods that must agree before a slip (or a re-seat) is believed."""

SLIP_AGREE_DEG = 3.0
"""... each within this angle of their mean direction (a slip turns them all alike)."""

SLIP_MIN_MOVE_S = 3.0
"""A still run counts as a separate period only after this long without quasi-static samples
(shorter: the detector paused within one posture, which would otherwise agree with itself)."""


def zheng_angles(g: np.ndarray) -> tuple[float, float]:
    """(θx, θy) in radians of a gravity reading g (any unit): Zheng eq. 3-4, arcsin(g_xy / |g|)."""
    g = np.asarray(g, np.float64).reshape(3)
    norm = float(np.linalg.norm(g))
    if not norm > 0:
        raise InputError("gravity vector has zero length")
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
        limit_deg: the tilt alarm's limit: how far the mounting may move from this reference.
        n: samples averaged; t_us: device time of the last of them.
        moved_deg: None while the mounting is where the reference found it; the angle it has
            moved since, once a slip was confirmed (:class:`SlipWatch`) and until it clears.
    """

    gravity_g: np.ndarray
    rotation: np.ndarray
    theta_x_deg: float
    theta_y_deg: float
    tilt_deg: float
    limit_deg: float
    n: int = 0
    t_us: int | None = None
    moved_deg: float | None = None

    @property
    def alarm(self) -> bool:
        """The tilt alarm stands: the mounting slipped beyond the limit since the reference
        (a tilted reference alone is no alarm: the rotation is exact at any tilt)."""
        return self.moved_deg is not None

    def to_dict(self) -> dict:
        return {"gravity_g": self.gravity_g.tolist(), "rotation": self.rotation.tolist(),
                "theta_x_deg": self.theta_x_deg, "theta_y_deg": self.theta_y_deg,
                "tilt_deg": self.tilt_deg, "limit_deg": self.limit_deg, "alarm": self.alarm,
                "moved_deg": self.moved_deg, "n": self.n, "t_us": self.t_us}

    @classmethod
    def from_dict(cls, d: dict) -> Alignment:
        t, moved = d.get("t_us"), d.get("moved_deg")
        return cls(np.asarray(d["gravity_g"], np.float64), np.asarray(d["rotation"], np.float64),
                   float(d["theta_x_deg"]), float(d["theta_y_deg"]), float(d["tilt_deg"]),
                   float(d.get("limit_deg", DEFAULT_TILT_LIMIT_DEG)), int(d.get("n", 0)),
                   None if t is None else int(t), None if moved is None else float(moved))


def estimate_alignment(gravity_g: np.ndarray, limit_deg: float = DEFAULT_TILT_LIMIT_DEG,
                       n: int = 0, t_us: int | None = None) -> Alignment:
    """The mounting from the mean calibrated reading on a reference posture (g, sensor frame)."""
    g = np.asarray(gravity_g, np.float64).reshape(3)
    if not (np.all(np.isfinite(g)) and np.linalg.norm(g) > 0):
        raise InputError(f"gravity vector must be finite and non-zero, got {g.tolist()}")
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


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two non-zero vectors (atan2 form: accurate near 0° too)."""
    a = np.asarray(a, np.float64).reshape(3)
    b = np.asarray(b, np.float64).reshape(3)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def _unit(g: np.ndarray) -> np.ndarray:
    g = np.asarray(g, np.float64).reshape(3)
    norm = float(np.linalg.norm(g))
    if not (np.all(np.isfinite(g)) and norm > 0):
        raise InputError(f"gravity vector must be finite and non-zero, got {g.tolist()}")
    return g / norm


@dataclass(frozen=True, eq=False)
class MountChange:
    """A change of mounting that :class:`SlipWatch` believes, from ``periods`` still periods.

    Attributes:
        kind: "slipped" (beyond the limit from the reference) or "reseated" (back within it).
        moved_deg: angle between the periods' mean gravity direction and the reference's.
        gravity_g: (3,) the periods' mean gravity direction (unit, sensor frame).
        theta_x_deg, theta_y_deg: Zheng eq. 3-4 angles of that direction, degrees.
        spread_deg: the largest angle of one period from their mean direction.
        periods: how many periods agreed; first_t_us, t_us: device times of the first and last.
    """

    kind: str
    moved_deg: float
    gravity_g: np.ndarray
    theta_x_deg: float
    theta_y_deg: float
    spread_deg: float
    periods: int
    first_t_us: int
    t_us: int

    def to_dict(self) -> dict:
        return {"kind": self.kind, "moved_deg": self.moved_deg,
                "gravity_g": self.gravity_g.tolist(), "theta_x_deg": self.theta_x_deg,
                "theta_y_deg": self.theta_y_deg, "spread_deg": self.spread_deg,
                "periods": self.periods, "first_t_us": self.first_t_us, "t_us": self.t_us}


class SlipWatch:
    """Checks later still periods against a reference posture: the tilt alarm's rule (see the
    module docstring for why a slip and not the tilt itself). Bounded state: the last
    ``periods`` upright directions.

    Args:
        reference_g: gravity on the reference posture (any unit, sensor frame).
        limit_deg: a mounting moved farther than this from the reference has slipped.
        upright_max_deg: periods farther than this from the reference are not upright
            (lying, bending) and are skipped.
        periods: how many upright periods in a row must agree.
        agree_deg: ... each within this angle of their mean direction (for a slip).
        min_move_s: a period counts only after at least this long without quasi-static samples.
        alarmed: the alarm already stands (restored with an alignment that has ``moved_deg``).
    """

    def __init__(self, reference_g: np.ndarray, limit_deg: float = DEFAULT_TILT_LIMIT_DEG, *,
                 upright_max_deg: float = 30.0, periods: int = SLIP_PERIODS,
                 agree_deg: float = SLIP_AGREE_DEG, min_move_s: float = SLIP_MIN_MOVE_S,
                 alarmed: bool = False) -> None:
        if periods < 1 or not limit_deg > 0 or not agree_deg > 0 or min_move_s < 0:
            raise ConfigError("periods >= 1, limit_deg > 0, agree_deg > 0, min_move_s >= 0")
        self.reference = _unit(reference_g)
        self.limit_deg = float(limit_deg)
        self.upright_max_deg = float(upright_max_deg)
        self.agree_deg = float(agree_deg)
        self.min_move_s = float(min_move_s)
        self.alarmed = bool(alarmed)
        self._recent: deque[tuple[np.ndarray, int]] = deque(maxlen=int(periods))

    def observe(self, mean_g: np.ndarray, t_us: int,
                gap_s: float | None = None) -> MountChange | None:
        """One still period's mean calibrated reading; the change it confirms, if any.

        gap_s: time since the previous still run ended (None: no run before), seconds.
        """
        if gap_s is not None and gap_s < self.min_move_s:
            return None  # the same posture after a pause of the detector: not a new period
        u = _unit(mean_g)
        if angle_deg(u, self.reference) > self.upright_max_deg:
            return None  # lying or bending: says nothing about the upright mounting
        self._recent.append((u, int(t_us)))
        if len(self._recent) < (self._recent.maxlen or 1):
            return None
        dirs = np.array([d for d, _ in self._recent])
        off_deg = np.array([angle_deg(d, self.reference) for d in dirs])
        mean = dirs.sum(axis=0)
        mean /= np.linalg.norm(mean)
        spread = max(angle_deg(d, mean) for d in dirs)
        if not self.alarmed and bool(np.all(off_deg > self.limit_deg)) \
                and spread <= self.agree_deg:
            self.alarmed = True
            return self._change("slipped", mean, spread)
        if self.alarmed and bool(np.all(off_deg <= self.limit_deg)):
            self.alarmed = False
            return self._change("reseated", mean, spread)
        return None

    def _change(self, kind: str, mean: np.ndarray, spread: float) -> MountChange:
        tx, ty = zheng_angles(mean)
        return MountChange(kind, angle_deg(mean, self.reference), mean, float(np.degrees(tx)),
                           float(np.degrees(ty)), spread, len(self._recent),
                           self._recent[0][1], self._recent[-1][1])


def tilt_from_z_deg(g: np.ndarray) -> float:
    """Angle in degrees between a reading and the sensor's +z axis."""
    g = np.asarray(g, np.float64).reshape(3)
    norm = float(np.linalg.norm(g))
    return float(np.degrees(np.arccos(np.clip(g[2] / norm, -1, 1)))) if norm > 0 else 180.0


class StillHit(NamedTuple):
    """A still run that has just lasted ``min_s``: its mean so far and where it stands."""

    mean_g: np.ndarray  # (3,) mean calibrated reading of the run up to t_us, g
    n: int  # samples averaged
    t_us: int  # device time of the sample that completed min_s
    gap_s: float | None  # time since the run before it ended (None: no run before), s


class StillTracker:
    """Follows the current quasi-static run of calibrated samples, batch by batch.

    A run is a stretch of gated samples without a time gap above ``max_gap_us``. The tracker
    keeps the run's start, length and sum (bounded state), and :meth:`feed` reports every
    run of the batch at the first sample at which it has lasted ``min_s`` while ``armed``
    (the caller decides when a reference may be taken, e.g. after an accepted calibration
    update), so what is reported does not depend on how the samples were cut into batches.

    Args:
        min_s: how long a run must last to be a reference posture, seconds.
        max_gap_us: a larger step between consecutive samples breaks the run, microseconds.
    """

    def __init__(self, min_s: float, max_gap_us: int) -> None:
        if not min_s > 0 or not max_gap_us > 0:
            raise ConfigError("min_s and max_gap_us must be positive")
        self.min_us = round(min_s * 1e6)
        self.max_gap_us = int(max_gap_us)
        self.start_us: int | None = None  # first sample of the open run (None: no run)
        self.last_us: int | None = None  # last sample seen (gated or not)
        self.last_gate = False
        self.n = 0
        self.sum_g = np.zeros(3)
        self.fired = False  # the open run already produced a reference
        self.end_us: int | None = None  # last gated sample of the latest run
        self.gap_us: int | None = None  # from the run before the open one to its start

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
             armed: bool = True) -> list[StillHit]:
        """Add a batch; return the runs that first reach ``min_s`` in it while armed (in
        time order; usually none, at most one per run)."""
        if len(t_us) == 1:
            one = self._feed_one(int(t_us[0]), a_g, bool(gate[0]), armed)
            if one is not None:
                return one
        t_us = np.asarray(t_us, np.int64)
        a_g = np.asarray(a_g, np.float64).reshape(-1, 3)
        gate = np.asarray(gate, bool)
        if len(t_us) == 0:
            return []
        quick = self._feed_uniform(t_us, a_g, gate, armed)
        if quick is not None:
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
        hits: list[StillHit] = []
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
            hit = self._extend(t_us[i0:i1], a_g[i0:i1], armed)
            if hit is not None:
                hits.append(hit)
        self.last_us = int(t_us[-1])
        self.last_gate = bool(gate[-1])
        return hits

    def _feed_uniform(self, t_us: np.ndarray, a_g: np.ndarray, gate: np.ndarray,
                      armed: bool) -> list[StillHit] | None:
        """`feed` for the common batches, all moving or all continuing the open run, without
        the segment bookkeeping; None when the batch is neither (the general path runs)."""
        if not gate.any():
            self._end_run()
        elif (gate.all() and self.last_gate and self.start_us is not None
              and self.last_us is not None
              and 0 < int(t_us[0]) - self.last_us <= self.max_gap_us
              and (len(t_us) == 1 or bool(np.all((np.diff(t_us) > 0)
                                                 & (np.diff(t_us) <= self.max_gap_us))))):
            hit = self._extend(t_us, a_g, armed)
            self.last_us, self.last_gate = int(t_us[-1]), True
            return [] if hit is None else [hit]
        else:
            return None
        self.last_us, self.last_gate = int(t_us[-1]), False
        return []

    def _feed_one(self, t0_us: int, a_g: np.ndarray, gated: bool,
                  armed: bool) -> list[StillHit] | None:
        """`feed` of one sample (a live sensor's arrival) on scalars when it ends the run or
        continues it without completing min_s while armed; None otherwise (the array path
        runs). The same state as `_feed_uniform` leaves: the run's sum adds the sample's row
        (its one-row sum is the row plus 0.0, which changes nothing added to a sum that
        starts at +0.0 and so is never -0.0)."""
        if not gated:
            self._end_run()
            self.last_us, self.last_gate = t0_us, False
            return []
        start = self.start_us
        if not (self.last_gate and start is not None and self.last_us is not None
                and 0 < t0_us - self.last_us <= self.max_gap_us):
            return None  # a run starts here
        if armed and not self.fired and t0_us - start >= self.min_us:
            return None  # the run fires at this sample
        self.end_us = t0_us
        self.sum_g = self.sum_g + np.asarray(a_g, np.float64).reshape(3)
        self.n += 1
        self.last_us, self.last_gate = t0_us, True
        return []

    def _start_run(self, t0_us: int) -> None:
        self.gap_us = None if self.end_us is None else t0_us - self.end_us
        self.start_us, self.n, self.sum_g, self.fired = t0_us, 0, np.zeros(3), False

    def _end_run(self) -> None:
        self.start_us, self.n, self.sum_g, self.fired = None, 0, np.zeros(3), False

    def _extend(self, t: np.ndarray, a: np.ndarray, may_fire: bool) -> StillHit | None:
        """Add gated samples of the open run; fire at the first one that completes min_s."""
        assert self.start_us is not None
        self.end_us = int(t[-1])
        if may_fire and not self.fired:
            due = np.flatnonzero(t - self.start_us >= self.min_us)
            if len(due):
                k = int(due[0]) + 1
                self.sum_g = self.sum_g + a[:k].sum(0)
                self.n += k
                self.fired = True
                gap_s = None if self.gap_us is None else self.gap_us / 1e6
                hit = StillHit(self.sum_g / self.n, self.n, int(t[k - 1]), gap_s)
                self.sum_g = self.sum_g + a[k:].sum(0)
                self.n += len(t) - k
                return hit
        self.sum_g = self.sum_g + a.sum(0)
        self.n += len(t)
        return None

    def rearm(self) -> None:
        """Let the open run produce a reference again (an alignment was requested)."""
        self.fired = False
