"""A whole recording's quasi-static window means, as arrays (batch use: discovery, hindsight).

The same detector (Lötters eq. 1-2) and the same windower (`core.windower`) as the live
pipeline, so the windows are the pipeline's bit for bit for the same batches: runs of gated
samples without time gaps, windows of window_s from each run's start, a window kept once its
run has gone on guard_s past it and if it holds min_fill of its nominal samples. No norm gate
(nothing is calibrated yet).

Streaming in the manner of scipy.signal.sosfilt: `Windowing` carries the detector's and the
windower's state from one batch to the next, so a recording read batch by batch needs memory
for its windows (~100 bytes each), not for its samples (docs/performance.md).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from recal.core import detector as det
from recal.core.buffer import Windows
from recal.core.channels import check_channels, usable
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.core.windower import WindowerState, WindowSums, cut
from recal.errors import InputError
from recal.samples import RawBatch, rebatch

__all__ = ["Windowing", "window_means"]

#: Batches' window tables held apart before they are put in one (`Windowing.add`).
TABLES_KEPT = 64


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
        if self.aux_names is None:
            check_channels(self.model, b.aux_names)
            self.aux_names, self.t0_us = b.aux_names, int(b.t_us[0])
        elif b.aux_names != self.aux_names:
            raise InputError(f"batch channels {b.aux_names} differ from {self.aux_names}")
        self._state, d = det.detect(self._det, self._state, b.v)
        gate = usable(d.gate, b, self.model)
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
