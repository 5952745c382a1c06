"""The settings of the whole in-use calibration (`PipelineConfig`): detector, windows, buffer,
estimator and re-fit rules in one frozen record. A config file's [pipeline] table and a
checkpoint's "config" give them as flat keys (`PipelineConfig.of`, `to_dict`, `KEYS`): the
detector's (`DETECTOR_KEYS`) are its nested `DetectorConfig`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from functools import cached_property
from typing import Any

import numpy as np

from recal.core import detector as det
from recal.core.buffer import BufferConfig
from recal.core.estimator import EstimatorConfig
from recal.core.status import GAP_S
from recal.core.windower import WindowConfig
from recal.errors import ConfigError

__all__ = ["DETECTOR_KEYS", "KEYS", "PipelineConfig"]

#: The flat keys (a config file's, a checkpoint's) that are the detector's settings, fields of
#: `DetectorConfig` of the same names, in the order a checkpoint writes them.
DETECTOR_KEYS = ("threshold_g", "flat_s", "hp_hz", "lp_hz")


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the whole in-use calibration.

    Attributes:
        rate_hz: nominal sample rate (filters, gap detection).
        detection: the detector's settings (`detector.DetectorConfig`: threshold_g, flat_s,
            hp_hz, lp_hz, the filters' order); its rate is rate_hz, and the sensor's scale,
            zero-g and clip level are the sensor's (`detector`).
        full_scale_g: the sensor's range; samples at 98 % of it count as clipped. None = off.
        window_s: length of a window mean. guard_s: how long a run must go on past a window.
        min_fill: fraction of a window's nominal samples it must hold.
        norm_tol_g: a window whose calibrated norm is further than this from 1 g is rejected.
        update_every: committed windows between estimator updates (tried: see next).
        gap_doubt_s: a gap in device time longer than this is a moment of doubt (the output
            held until a still window agrees: a sensor out of radio range may come back
            another); 0: never (a device file, where one device recorded every sample and
            idle sleep is declared stillness).
        max_update_interval_s: device time after which an update runs even when the windows
            since the last one agree with the estimate (`estimator.consistent`); until then a
            try is skipped when they agree, the estimate has settled and no new orientation
            cell or half-axis arrived. 0: every try updates (re-fit every update_every).
        bootstrap_min_cells: orientation cells needed before a sensor without prior is fitted
            (with five half-axes at least: five poses fit a sphere's four unknowns with one to
            spare, six cover all six half-axes and fit the diagonal model's six exactly).
    """

    rate_hz: float = 50.0
    detection: det.DetectorConfig = field(default_factory=lambda: det.DetectorConfig(50.0))
    full_scale_g: float | None = None
    window_s: float = 2.0
    guard_s: float = 1.0
    min_fill: float = 0.8
    norm_tol_g: float = 0.1
    update_every: int = 5
    max_update_interval_s: float = 300.0
    gap_doubt_s: float = GAP_S
    bootstrap_min_cells: int = 5
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)

    def __post_init__(self) -> None:
        if self.detection.rate_hz is not self.rate_hz:  # the detector runs at the pipeline's rate
            object.__setattr__(self, "detection", replace(self.detection, rate_hz=self.rate_hz))
        if not 0 < self.guard_s < self.window_s:
            raise ConfigError("guard_s must be positive and shorter than window_s")
        if self.rate_hz <= 0:
            raise ConfigError("rate_hz must be positive")
        d = self.detection
        positive = {"threshold_g": d.threshold_g, "flat_s": d.flat_s,
                    "norm_tol_g": self.norm_tol_g, "full_scale_g": self.full_scale_g or 1.0}
        bad = [k for k, v in positive.items() if not v > 0]  # inf: no limit (window_means)
        if bad:
            raise ConfigError(f"{', '.join(bad)} must be positive")
        nyquist = self.rate_hz / 2
        if not (0 < d.hp_hz < nyquist and 0 < d.lp_hz < nyquist):
            raise ConfigError(f"hp_hz and lp_hz must lie between 0 and half the sample rate "
                             f"({nyquist:g} Hz)")
        if not 0 < self.min_fill <= 1:
            raise ConfigError("min_fill must be in (0, 1]")
        if self.update_every < 1 or self.bootstrap_min_cells < 1:
            raise ConfigError("update_every and bootstrap_min_cells must be at least 1")
        if not self.gap_doubt_s >= 0:
            raise ConfigError("gap_doubt_s must be >= 0 (0: a gap is never a doubt)")
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
        return replace(self.detection, s0=s0, clip_raw=clip, zero_raw=zero)

    @classmethod
    def of(cls, **keys: Any) -> PipelineConfig:
        """From flat keys (`KEYS`: a config file's [pipeline] table with the sensor's rate_hz
        and full_scale_g), the estimator's and buffer's settings as their records."""
        detection = {k: keys.pop(k) for k in DETECTOR_KEYS if k in keys}
        rate_hz = keys.get("rate_hz", 50.0)
        return cls(**keys, detection=det.DetectorConfig(rate_hz, **detection))

    def to_dict(self) -> dict:
        """Flat keys (`KEYS`, in that order), the estimator's and buffer's as tables: what a
        checkpoint has always held."""
        d = asdict(self)
        detection = d.pop("detection")
        return {"rate_hz": d.pop("rate_hz"), **{k: detection[k] for k in DETECTOR_KEYS}, **d}

    @classmethod
    def from_dict(cls, d: dict) -> PipelineConfig:
        d = dict(d)
        est = EstimatorConfig(**d.pop("estimator", {}))
        buf = BufferConfig(**d.pop("buffer", {}))
        return cls.of(**d, estimator=est, buffer=buf)


#: The flat keys of `PipelineConfig.of` and `to_dict` besides the estimator's and the buffer's
#: tables, in a checkpoint's order.
KEYS = ("rate_hz", *DETECTOR_KEYS, *(f.name for f in fields(PipelineConfig)
                                     if f.name not in ("rate_hz", "detection", "estimator",
                                                       "buffer")))
