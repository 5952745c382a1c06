"""The settings of the whole in-use calibration (`PipelineConfig`): detector, windows, buffer,
estimator and re-fit rules in one frozen record, as a config file's [pipeline] table gives them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import cached_property

import numpy as np

from recal.core import detector as det
from recal.core.buffer import BufferConfig
from recal.core.estimator import EstimatorConfig
from recal.core.windower import WindowConfig
from recal.errors import ConfigError

__all__ = ["PipelineConfig"]


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the whole in-use calibration.

    Attributes:
        rate_hz: nominal sample rate (filters, gap detection).
        threshold_g, flat_s, hp_hz, lp_hz: detector settings (see `detector.DetectorConfig`).
        full_scale_g: the sensor's range; samples at 98 % of it count as clipped. None = off.
        window_s: length of a window mean. guard_s: how long a run must go on past a window.
        min_fill: fraction of a window's nominal samples it must hold.
        norm_tol_g: a window whose calibrated norm is further than this from 1 g is rejected.
        update_every: committed windows between estimator updates (tried: see next).
        max_update_interval_s: device time after which an update runs even when the windows
            since the last one agree with the estimate (`estimator.consistent`); until then a
            try is skipped when they agree, the estimate has settled and no new orientation
            cell or half-axis arrived. 0: every try updates (re-fit every update_every).
        bootstrap_min_cells: orientation cells needed before a sensor without prior is fitted
            (with five half-axes at least: five poses fit a sphere's four unknowns with one to
            spare, six cover all six half-axes and fit the diagonal model's six exactly).
    """

    rate_hz: float = 50.0
    threshold_g: float = det.DEFAULT_THRESHOLD_G
    flat_s: float = 1.0
    hp_hz: float = 0.5
    lp_hz: float = 0.5
    full_scale_g: float | None = None
    window_s: float = 2.0
    guard_s: float = 1.0
    min_fill: float = 0.8
    norm_tol_g: float = 0.1
    update_every: int = 5
    max_update_interval_s: float = 300.0
    bootstrap_min_cells: int = 5
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)

    def __post_init__(self) -> None:
        if not 0 < self.guard_s < self.window_s:
            raise ConfigError("guard_s must be positive and shorter than window_s")
        if self.rate_hz <= 0:
            raise ConfigError("rate_hz must be positive")
        positive = {"threshold_g": self.threshold_g, "flat_s": self.flat_s,
                    "norm_tol_g": self.norm_tol_g, "full_scale_g": self.full_scale_g or 1.0}
        bad = [k for k, v in positive.items() if not v > 0]  # inf: no limit (window_means)
        if bad:
            raise ConfigError(f"{', '.join(bad)} must be positive")
        nyquist = self.rate_hz / 2
        if not (0 < self.hp_hz < nyquist and 0 < self.lp_hz < nyquist):
            raise ConfigError(f"hp_hz and lp_hz must lie between 0 and half the sample rate "
                             f"({nyquist:g} Hz)")
        if not 0 < self.min_fill <= 1:
            raise ConfigError("min_fill must be in (0, 1]")
        if self.update_every < 1 or self.bootstrap_min_cells < 1:
            raise ConfigError("update_every and bootstrap_min_cells must be at least 1")
        if self.max_update_interval_s < 0:
            raise ConfigError("max_update_interval_s must be >= 0 (0: every try updates)")

    @cached_property
    def windows(self) -> WindowConfig:
        """The window rules (`core.windower`)."""
        return WindowConfig(self.rate_hz, self.window_s, self.guard_s, self.min_fill)

    def detector(self, s0: float, zero_raw: np.ndarray | Sequence[float] | None = None
                 ) -> det.DetectorConfig:
        """The detector's settings for a sensor of s0 raw units per g reading zero_raw at
        0 g (None: zero)."""
        clip = None if self.full_scale_g is None else 0.98 * self.full_scale_g * s0
        zero = (0.0, 0.0, 0.0) if zero_raw is None else tuple(float(x) for x in zero_raw)
        return det.DetectorConfig(rate_hz=self.rate_hz, threshold_g=self.threshold_g,
                                  hp_hz=self.hp_hz, lp_hz=self.lp_hz, s0=s0, clip_raw=clip,
                                  flat_s=self.flat_s, zero_raw=zero)  # type: ignore[arg-type]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PipelineConfig:
        d = dict(d)
        est = EstimatorConfig(**d.pop("estimator", {}))
        buf = BufferConfig(**d.pop("buffer", {}))
        return cls(**d, estimator=est, buffer=buf)
