"""Quasi-static moments detector (Lötters 1998, eq. 1-2), streaming.

    v_in  = |v - z| / s0                 eq. 1, the vector norm, here in g (z: zero-g, raw)
    v_out = LPF(REC(HPF(v_in)))          eq. 2, 0.5 Hz high-pass, rectifier, 0.5 Hz low-pass

A sample is quasi-static when v_out is below the threshold T (Lötters' T_v, here in g) and it
is neither clipped (near full scale) nor part of a flat-lined stretch (a device that repeats its
last sample while idle: zero variance is not stillness, it is no data). A sensor whose counts
are coarse against its noise (1/256 g: `quantization.coarse`) repeats its reading bit for bit
when still, so for it a flat line takes flat_coarse_s, not flat_s (the step is learned from
the samples as they come: `quantization.observe`, carried in the state).

Streaming in the manner of scipy.signal.sosfilt: the filter state travels in `DetectorState`, so a
recording fed in one batch or sample by sample gives the same gates to the last bit. The
filters are `recal.core.sos_filter`'s, so a daemon does not import scipy.signal.
The threshold and why: docs/design.md ("The detector threshold").
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from recal.core import quantization as quant
from recal.core.sos_filter import butter_sos, sos_rows, sos_zi, sosfilt, sosfilt_one
from recal.core.triaxial import all3, any3, norm3

__all__ = ["Detector", "DetectorConfig", "DetectorOutput", "DetectorState", "detect", "init_state"]

#: Default threshold on the detector output, in g: the middle of the range that works on both
#: simulated wearers and the Xsens multi-position recording (lower, still postures' own noise
#: crosses it; higher, hand rotations get into the calibration). The sweep that chose it is in
#: docs/design.md, "The detector threshold".
DEFAULT_THRESHOLD_G = 0.015


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings.

    Attributes:
        rate_hz: sample rate the filters are designed for.
        threshold_g: T, the largest detector output still called quasi-static.
        hp_hz, lp_hz: the high- and low-pass corner frequencies (Lötters: 0.5 Hz each).
        order: Butterworth order of each filter.
        s0: nominal raw units per g, so that the norm and threshold are in g.
        clip_raw: |v - zero_raw| on any axis at or above this (raw units) counts as clipped;
            None = off.
        flat_s: this long of bit-identical samples is a flat line, not stillness.
        flat_coarse_s: the same for a sensor whose step is coarse (`quantization.coarse`):
            a still one repeats its reading for minutes; longer than a wearer stays still.
        zero_raw: the reading at 0 g (raw units, per axis), taken off before the norm: an
            analog part on an unsigned ADC reads ~2048 counts at 0 g, and the norm of such
            readings follows the offset, not the acceleration.
    """

    rate_hz: float
    threshold_g: float = DEFAULT_THRESHOLD_G
    hp_hz: float = 0.5
    lp_hz: float = 0.5
    order: int = 2
    s0: float = 1.0
    clip_raw: float | None = None
    flat_s: float = 1.0
    flat_coarse_s: float = 3600.0
    zero_raw: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def sos(self) -> tuple[np.ndarray, np.ndarray]:
        return _butter_pair(self.order, self.hp_hz, self.lp_hz, self.rate_hz)

    @property
    def flat_n(self) -> int:
        return max(2, round(self.flat_s * self.rate_hz))

    @property
    def flat_coarse_n(self) -> int:
        return max(self.flat_n, round(self.flat_coarse_s * self.rate_hz))

    @functools.cached_property
    def one(self) -> tuple:
        """What `_detect_one` reads of the configuration, made once per configuration (the
        configuration is immutable): the filters' sections as Python floats (hp, lp), and
        zero_raw, s0, threshold_g, clip_raw, flat_n - 1, flat_coarse_n - 1 and the least
        step that is coarse (raw units)."""
        hp, lp = _butter_pair(self.order, self.hp_hz, self.lp_hz, self.rate_hz)
        return (sos_rows(hp), sos_rows(lp), self.zero_raw, self.s0, self.threshold_g,
                self.clip_raw, self.flat_n - 1, self.flat_coarse_n - 1,
                quant.COARSE_STEP_G * self.s0)


@dataclass(frozen=True, eq=False)
class DetectorState:
    """Filter states (sosfilt zi), the flat-line run and the sensor's step (per axis, raw
    units, inf: not seen; learned on `changes` samples: `quantization.observe`) carried
    between batches."""

    zi_hp: np.ndarray
    zi_lp: np.ndarray
    last_v: np.ndarray
    same_run: int
    started: bool
    step_raw: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    changes: int = 0

    def to_dict(self) -> dict:
        """JSON-able (NaN in last_v, before a first sample, and an unknown step as None)."""
        return {"zi_hp": self.zi_hp.tolist(), "zi_lp": self.zi_lp.tolist(),
                "last_v": [None if np.isnan(x) else float(x) for x in self.last_v],
                "same_run": self.same_run, "started": self.started,
                "step_raw": [None if np.isinf(x) else float(x) for x in self.step_raw],
                "changes": self.changes}

    @classmethod
    def from_dict(cls, d: dict) -> DetectorState:
        step = d.get("step_raw", [None] * 3)  # a state saved before the step was learned
        return cls(np.asarray(d["zi_hp"], float), np.asarray(d["zi_lp"], float),
                   np.array([np.nan if x is None else x for x in d["last_v"]], float),
                   int(d["same_run"]), bool(d["started"]),
                   np.array([np.inf if x is None else x for x in step], float),
                   int(d.get("changes", 0)))


class Detector:
    """A detector at work on one sensor: its settings (`cfg`, for the sensor's scale and zero-g)
    and its filter state (`state`, replaced at every batch: `detect`)."""

    __slots__ = ("cfg", "state")

    def __init__(self, cfg: DetectorConfig, state: DetectorState | None = None) -> None:
        self.cfg = cfg
        self.state = init_state(cfg) if state is None else state

    def to_dict(self) -> dict:
        """The scale and zero-g it runs at (the other settings are the pipeline's) and the
        state (`DetectorState.to_dict`)."""
        return {"s0": self.cfg.s0, "zero_raw": list(self.cfg.zero_raw), **self.state.to_dict()}


@dataclass(frozen=True, eq=False)
class DetectorOutput:
    """Per sample: detector output (g), and the reasons a sample is not quasi-static."""

    detector_g: np.ndarray
    below_threshold: np.ndarray
    clipped: np.ndarray
    flat: np.ndarray
    #: the gate when its maker has it already (`_detect_one`); None: worked out when asked
    still: np.ndarray | None = None

    @property
    def gate(self) -> np.ndarray:
        if self.still is not None:
            return self.still
        return self.below_threshold & ~self.clipped & ~self.flat


@functools.lru_cache(maxsize=64)
def _butter_pair(order: int, hp_hz: float, lp_hz: float,
                 rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The high- and low-pass designs, made once per setting: a live sensor sending one sample
    per batch would otherwise pay for the design on every batch."""
    # Shared between callers, never changed in place.
    return (butter_sos(order, hp_hz, rate_hz, highpass=True),
            butter_sos(order, lp_hz, rate_hz, highpass=False))


def init_state(cfg: DetectorConfig) -> DetectorState:
    hp, lp = cfg.sos()
    return DetectorState(np.zeros((hp.shape[0], 2)), np.zeros((lp.shape[0], 2)),
                         np.full(3, np.nan), 0, False)


def _start(cfg: DetectorConfig, state: DetectorState, x0_g: float) -> DetectorState:
    """Start the filters in steady state for the first sample; the low-pass starts *above*
    threshold, so a recording is not called still before the detector has seen a second of it."""
    hp, lp = cfg.sos()
    return replace(state, zi_hp=sos_zi(hp) * x0_g,
                   zi_lp=sos_zi(lp) * (2.0 * cfg.threshold_g), started=True)


def _repeats(v: np.ndarray, last_v: np.ndarray, run0: int) -> tuple[np.ndarray, np.ndarray]:
    """Where a sample repeats its predecessor bit for bit (indices), and for each how many
    samples before it were the same in a row (carried from run0)."""
    same = np.empty(len(v), bool)
    same[0] = bool(np.all(v[0] == last_v))
    same[1:] = all3(v[1:] == v[:-1])
    pos = np.flatnonzero(same)
    if not len(pos):
        return pos, pos
    new = np.ones(len(pos), bool)  # first repeat of each run of repeats
    new[1:] = pos[1:] - pos[:-1] != 1
    starts = np.flatnonzero(new)
    first = np.repeat(pos[starts], np.diff(np.append(starts, len(pos))))
    return pos, pos - first + 1 + np.where(first == 0, run0, 0)


def _flat_runs(v: np.ndarray, last_v: np.ndarray, run0: int) -> np.ndarray:
    """For each sample, how many samples before it were bit-identical in a row (carried).

    Worked out only where a sample repeats its predecessor (rare in a noisy sensor, so this
    costs little beyond the comparison itself)."""
    if len(v) == 1:  # one sample per arrival: the same count without the run bookkeeping
        same0 = bool(v[0, 0] == last_v[0] and v[0, 1] == last_v[1] and v[0, 2] == last_v[2])
        return np.array([run0 + 1 if same0 else 0], np.int64)
    runs = np.zeros(len(v), np.int64)
    pos, reps = _repeats(v, last_v, run0)
    runs[pos] = reps
    return runs


def _flat(v: np.ndarray, last_v: np.ndarray, run0: int,
          flat_n: int | np.ndarray) -> tuple[np.ndarray, int]:
    """``_flat_runs(...) >= flat_n - 1`` (flat_n: one or one per sample) and the last
    sample's run, worked out at the repeats alone (no count for every sample)."""
    pos, reps = _repeats(v, last_v, run0)
    thr = np.asarray(flat_n) - 1
    if thr.ndim:
        flat = thr <= 0
        flat[pos] = reps >= thr[pos]
    else:
        flat = np.full(len(v), bool(thr <= 0))
        flat[pos] = reps >= thr
    return flat, int(reps[-1]) if len(pos) and pos[-1] == len(v) - 1 else 0


def detect(cfg: DetectorConfig, state: DetectorState,
           v: np.ndarray) -> tuple[DetectorState, DetectorOutput]:
    """Run the detector on raw samples v (N,3); returns the new state and per-sample output."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    if len(v) == 1 and state.started:
        one = _detect_one(cfg, state, v)
        if one is not None:
            return one
    if len(v) == 0:
        empty = np.zeros(0, bool)
        return state, DetectorOutput(np.zeros(0), empty, empty, empty)
    vc = v - np.asarray(cfg.zero_raw) if any(cfg.zero_raw) else v
    v_in = norm3(vc)  # eq. 1
    if cfg.s0 != 1.0:  # (a division by 1 changes no bit)
        v_in /= cfg.s0
    if not np.isfinite(v_in.max()):  # NaN/inf (the max of norms keeps either) skip the
        # filters: one would poison their state for good
        return _detect_finite(cfg, state, v, np.isfinite(v_in))
    if not state.started:
        state = _start(cfg, state, float(v_in[0]))
    hp, lp = cfg.sos()
    y_hp, zi_hp = sosfilt(hp, v_in, state.zi_hp)
    v_out, zi_lp = sosfilt(lp, np.abs(y_hp), state.zi_lp)  # eq. 2
    step, changes = state.step_raw, state.changes
    if changes < quant.LATTICE_CHANGES:  # still learning the step: sample by sample
        step, changes, steps = quant.observe(step, changes, v, state.last_v)
        flat_n = np.where(quant.coarse(steps, cfg.s0), cfg.flat_coarse_n, cfg.flat_n)
    else:
        flat_n = cfg.flat_coarse_n if quant.coarse(step, cfg.s0) else cfg.flat_n
    flat, run = _flat(v, state.last_v, state.same_run, flat_n)
    below = v_out < cfg.threshold_g
    if cfg.clip_raw is not None:
        clipped = any3(np.abs(vc) >= cfg.clip_raw)
        out = DetectorOutput(v_out, below, clipped, flat)
    else:  # nothing clips: the gate without it
        out = DetectorOutput(v_out, below, np.zeros(len(v), bool), flat, below & ~flat)
    return DetectorState(zi_hp, zi_lp, v[-1].copy(), run, True, step, changes), out


def _detect_one(cfg: DetectorConfig, state: DetectorState, v: np.ndarray
                ) -> tuple[DetectorState, DetectorOutput] | None:
    """`detect` for one sample (a live sensor's arrival) on Python floats: the same operations
    in the same order as the array path (`norm3`'s (x^2 + y^2) + z^2, `sosfilt`'s scalar
    loop), so the same bits, with a handful of numpy calls instead of dozens. None for a
    sample the array path must take (not finite)."""
    hp, lp, (zx, zy, zz), s0, threshold_g, clip, flat_run, coarse_run, coarse_raw = cfg.one
    x, y, z = vx, vy, vz = v[0].tolist()
    if zx or zy or zz:
        x, y, z = x - zx, y - zy, z - zz
    v_in = math.sqrt(x * x + y * y + z * z) / s0  # eq. 1
    if not math.isfinite(v_in):
        return None
    y_hp, zi_hp = sosfilt_one(hp, v_in, state.zi_hp.tolist())
    v_out, zi_lp = sosfilt_one(lp, abs(y_hp), state.zi_lp.tolist())  # eq. 2
    lx, ly, lz = state.last_v.tolist()
    same = vx == lx and vy == ly and vz == lz
    run = state.same_run + 1 if same else 0
    step, changes = state.step_raw, state.changes
    if not same and changes < quant.LATTICE_CHANGES:  # `quantization.observe`, one sample
        sx, sy, sz = step.tolist()
        dx, dy, dz = abs(vx - lx), abs(vy - ly), abs(vz - lz)  # NaN: no step (ignored)
        step = np.array([dx if 0 < dx < sx else sx, dy if 0 < dy < sy else sy,
                         dz if 0 < dz < sz else sz])
        changes += 1
    sx, sy, sz = step.tolist()
    coarse = sx >= coarse_raw and sy >= coarse_raw and sz >= coarse_raw and math.isfinite(
        sx + sy + sz)
    clipped = clip is not None and (abs(x) >= clip or abs(y) >= clip or abs(z) >= clip)
    below, flat = v_out < threshold_g, run >= (coarse_run if coarse else flat_run)
    out = DetectorOutput(np.array([v_out]), np.array([below]), np.array([clipped]),
                         np.array([flat]), np.array([below and not clipped and not flat]))
    return DetectorState(np.array(zi_hp), np.array(zi_lp), v[0].copy(), run, True, step,
                         changes), out


def _detect_finite(cfg: DetectorConfig, state: DetectorState, v: np.ndarray,
                   finite: np.ndarray) -> tuple[DetectorState, DetectorOutput]:
    """detect() as if the non-finite samples were missing; they get a NaN output, never still."""
    state, part = detect(cfg, state, v[finite])

    def spread(x: np.ndarray, fill: float | bool) -> np.ndarray:
        out = np.full(len(v), fill, x.dtype)
        out[finite] = x
        return out

    return state, DetectorOutput(spread(part.detector_g, np.nan),
                                 spread(part.below_threshold, False),
                                 spread(part.clipped, False), spread(part.flat, False))
