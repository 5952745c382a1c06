"""A whole recording's quasi-static window means, as arrays (batch use: discovery, hindsight).

The same detector (Lötters eq. 1-2) and the same windower (`core.windower`) as the live
pipeline, so the windows are the pipeline's bit for bit for the same batches: runs of gated
samples without time gaps, windows of window_s from each run's start, a window kept once its
run has gone on guard_s past it and if it holds min_fill of its nominal samples. No norm gate
(nothing is calibrated yet).

Streaming in the manner of scipy.signal.sosfilt: `Windowing` carries the detector's and the
windower's state from one batch to the next, so a recording read batch by batch needs memory
for its windows (~100 bytes each), not for its samples (docs/performance.md).

A recording read at will (a device file in memory) can also be windowed in spans, each apart
from the others (on threads: `commands.span_windows`), with the same windows bit for bit:

1. the detector on segments at fixed samples, each started `warm_samples` early from a fresh
   state (`detect_segment`); a segment counts only if the state its warm-up reached at its
   first sample behaves as the one the segment before left there (`same_future`: the
   filters' state, the last reading and its run, bit for bit), else it is run again from
   that state (`Settler`);
2. the windower on spans that start at a sample the detector does not gate
   (`Segment.first_ungated`):
   nothing runs across such a sample, so the windower's state there is known (empty), and
   each span is cut apart (`Windowing.add_gated`) on the same batch boundaries as a reading
   from the start, so with the same sums.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import numpy as np

from recal.core import detector as det
from recal.core.buffer import Windows
from recal.core.channels import check_channels, usable
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.core.quantization import LATTICE_CHANGES, coarse
from recal.core.windower import WindowerState, WindowSums, cut
from recal.errors import InputError
from recal.samples import RawBatch, rebatch

__all__ = ["Segment", "Settler", "Windowing", "WindowsFn", "detect_segment", "in_order",
           "same_future", "warm_samples", "window_means", "window_span"]

#: Batches' window tables held apart before they are put in one (`Windowing.add`).
TABLES_KEPT = 64
#: How long a segment's detector runs before the segment's first sample (seconds): its
#: filters (0.5 Hz) forget their start within a minute, and 20 000 changed readings teach it
#: the sensor's step (`quantization.LATTICE_CHANGES`); at 100 Hz on measured files the state
#: matched the sequential one bit for bit from a quarter of this on.
WARM_S = 900.0


@dataclass(eq=False)
class Windowing:
    """Window sums of a recording fed batch by batch (`add`), the kept windows (`kept`).

    Args:
        cfg: the live pipeline's settings (detector, window_s, guard_s, min_fill, rate_hz).
        model: whose covariate channels must be finite for a sample to count (`usable`).
        s0: raw units per g for the detector.
        zero: the reading at 0 g (raw, 3 values) the detector takes off (None: zero).
    """

    cfg: PipelineConfig
    model: SensorModel
    s0: float
    zero: np.ndarray | None = None
    aux_names: tuple[str, ...] | None = field(default=None, init=False)  # the first batch's
    t0_us: int | None = field(default=None, init=False)  # the first sample's time
    _det: det.DetectorConfig = field(init=False)
    _state: det.DetectorState = field(init=False)
    _windower: WindowerState = field(default_factory=WindowerState, init=False)
    _tables: list[WindowSums] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self._det = self.cfg.detector(self.s0, self.zero)
        self._state = det.init_state(self._det)

    def add(self, b: RawBatch) -> None:
        """Detect, cut and sum one batch (the next in time order)."""
        if not len(b):
            return
        self._check(b)
        self._state, d = det.detect(self._det, self._state, b.v)
        self._cut(b, d.gate)

    def add_gated(self, b: RawBatch, gate: np.ndarray) -> None:
        """Cut and sum one batch whose detector gate is known (`detect_segment`)."""
        if len(b):
            self._check(b)
            self._cut(b, gate)

    def _check(self, b: RawBatch) -> None:
        if self.aux_names is None:
            check_channels(self.model, b.aux_names)
            self.aux_names, self.t0_us = b.aux_names, int(b.t_us[0])
        elif b.aux_names != self.aux_names:
            raise InputError(f"batch channels {b.aux_names} differ from {self.aux_names}")

    def _cut(self, b: RawBatch, detector_gate: np.ndarray) -> None:
        gate = usable(detector_gate, b, self.model)
        c, self._windower = cut(self.cfg.windows, self._windower, b.t_us, b.v, b.aux, gate)
        if c.sums is not None:
            self._tables.append(c.sums)
            if len(self._tables) >= TABLES_KEPT:  # a few arrays, not thousands of small ones
                self._tables = [WindowSums.concat(self._tables)]

    @property
    def step_raw(self) -> np.ndarray:
        """The sensor's step per axis as the detector learned it (raw units; inf: unknown)."""
        return self._state.step_raw

    def kept(self) -> WindowSums:
        """The windows the live pipeline would commit, in order."""
        if not self._tables:
            return WindowSums.empty(len(self.aux_names or ()))
        return WindowSums.concat(self._tables)


def window_means(batches: Iterable[RawBatch], cfg: PipelineConfig, s0: float,
                 zero: np.ndarray | None = None) -> tuple[Windows, tuple[str, ...], int]:
    """Every quasi-static window mean of a recording given batch by batch, by the live
    detector (in units of s0 raw per g, zero-g `zero` taken off) and windowing, with no norm
    gate (nothing is calibrated yet): the raw material of `core.discovery` and
    `core.hindsight`. Returns (windows, the channels, the first sample's time)."""
    w = Windowing(cfg, SensorModel.diagonal(float(s0)), float(s0), zero)
    for b in rebatch(batches):  # a recording's small messages, joined: fewer numpy calls
        w.add(b)
    if w.aux_names is None or w.t0_us is None:
        raise InputError("a recording needs samples to discover effects on")
    return w.kept().means()[0], w.aux_names, w.t0_us


#: (cfg, model, s0, zero) -> the kept windows' sums, their channels (None: no samples), the
#: first sample's time and the sensor's step as the detector learned it: a recording's
#: windows by the detector in units of s0, zero-g ``zero`` off (`in_order`, or on threads
#: `commands.span_windows`).
WindowsFn = Callable[[PipelineConfig, SensorModel, float, np.ndarray | None],
                     tuple[WindowSums, tuple[str, ...] | None, int | None, np.ndarray]]


def in_order(batches: Callable[[], Iterable[RawBatch]]) -> WindowsFn:
    """The windows of the recording ``batches()`` gives, read once from its start."""

    def windows(cfg: PipelineConfig, model: SensorModel, s0: float, zero: np.ndarray | None
                ) -> tuple[WindowSums, tuple[str, ...] | None, int | None, np.ndarray]:
        w = Windowing(cfg, model, s0, zero)
        for b in rebatch(batches()):  # a recording's small messages, joined: fewer calls
            w.add(b)
        return w.kept(), w.aux_names, w.t0_us, w.step_raw

    return windows


@dataclass(frozen=True, eq=False)
class Segment:
    """The detector over samples lo..lo + len(gate) (`detect_segment`): its state at lo (as
    its warm-up left it, or as given), each sample's gate, its state at the end."""

    lo: int
    state_in: det.DetectorState
    gate: np.ndarray
    state_out: det.DetectorState

    @property
    def hi(self) -> int:
        return self.lo + len(self.gate)

    @property
    def first_ungated(self) -> int | None:
        """The first sample (in the recording) the detector does not gate, where a span of
        the windower can start: no window runs across it (None: it gates them all)."""
        if not len(self.gate):
            return None
        first = int(np.argmin(self.gate))  # the first False, if there is one
        return None if self.gate[first] else self.lo + first


def warm_samples(rate_hz: float, batch: int) -> int:
    """WARM_S of samples, in whole batches."""
    return math.ceil(WARM_S * rate_hz / batch) * batch


def detect_segment(cfg: det.DetectorConfig, readings: Callable[[int, int], np.ndarray],
                   lo: int, hi: int, batch: int, warm: int,
                   state: det.DetectorState | None = None) -> Segment:
    """The detector over samples lo..hi (``readings(a, b)``: samples a..b, (N,3) float64),
    in batches on the recording's grid of ``batch`` samples (lo and warm are multiples of
    it, so a batch ends where a reading from the start ends one); from ``state``, or none
    given from a fresh state ``warm`` samples before lo."""
    if state is None:
        state = det.init_state(cfg)
        for a in range(max(0, lo - warm), lo, batch):
            state, _ = det.detect(cfg, state, readings(a, min(lo, a + batch)))
    state_in = state
    gate = np.empty(hi - lo, bool)
    for a in range(lo, hi, batch):
        b = min(hi, a + batch)
        state, d = det.detect(cfg, state, readings(a, b))
        gate[a - lo:b - lo] = d.gate
    return Segment(lo, state_in, gate, state)


def same_future(cfg: det.DetectorConfig, a: det.DetectorState, b: det.DetectorState) -> bool:
    """Whether the detector goes on alike from states a and b: the filters' states, the last
    reading and its run bit for bit, and the step as it is used (learned on both: only
    whether it is coarse; else the same step from the same count)."""
    eq = np.array_equal
    if not (a.started == b.started and a.same_run == b.same_run and eq(a.zi_hp, b.zi_hp)
            and eq(a.zi_lp, b.zi_lp) and eq(a.last_v, b.last_v, equal_nan=True)):
        return False
    if a.changes >= LATTICE_CHANGES and b.changes >= LATTICE_CHANGES:
        return bool(coarse(a.step_raw, cfg.s0) == coarse(b.step_raw, cfg.s0))
    return a.changes == b.changes and eq(a.step_raw, b.step_raw)


@dataclass(eq=False)
class Settler:
    """Segments checked in order, one at a time as they come: each against the
    state the one before left at its first sample (`same_future`), run ``again`` from that
    state where it differs. ``state``: the state at the last one's end, as one reading from
    the start leaves it (the learned step is the one learned first, kept for good)."""

    cfg: det.DetectorConfig
    state: det.DetectorState | None = None

    def add(self, s: Segment, again: Callable[[Segment, det.DetectorState], Segment]
            ) -> Segment:
        if self.state is not None and not same_future(self.cfg, s.state_in, self.state):
            s = again(s, self.state)
        end = s.state_out
        if self.state is not None and self.state.changes >= LATTICE_CHANGES:
            end = replace(end, step_raw=self.state.step_raw, changes=self.state.changes)
        self.state = end
        return s


def window_span(cfg: PipelineConfig, model: SensorModel, s0: float, zero: np.ndarray | None,
                batch_of: Callable[[int, int], RawBatch], gate: np.ndarray, lo: int, hi: int,
                batch: int) -> Windowing:
    """The windows of samples lo..hi (gates ``gate``: the whole recording's), lo a sample the
    detector does not gate (`Segment.first_ungated`) or 0, in batches on the recording's grid of
    ``batch`` samples (the first from lo)."""
    w = Windowing(cfg, model, s0, zero)
    a = lo
    while a < hi:
        b = min(hi, (a // batch + 1) * batch)
        w.add_gated(batch_of(a, b), gate[a:b])
        a = b
    return w
