"""A step in time, the competitor of every effect discovery would add.

A sensor swapped for another, knocked or re-mounted changes its offsets and gains at one
moment. Any covariate that trends with time (a board warming for an hour, a battery running
down, time itself) then "explains" part of that step as a slope, and passes a held-out test
that only compares models with and without the term. `best_step` fits the model in force apart
before and after each boundary between discovery's time blocks and keeps the boundary whose
two fits leave the least; where that leaves clearly less (in-sample, by min_gain) than the model
discovery found, discovery keeps none of its additions: a step is the self-watch's business,
never a new term's. A real
effect of a covariate follows the covariate up and down, which one step cannot; a step leaves
the two halves' own residuals to the noise, which a slope cannot. See docs/design.md (effect
discovery, step 6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recal.core.discovery_data import DiscoveryData
from recal.core.model import SensorModel
from recal.core.model_fit import FitConfig, fit_model, norm_error_g

__all__ = ["TimeStep", "best_step", "in_sample_ss"]


@dataclass(frozen=True)
class TimeStep:
    """The best step in time of a model: the boundary's time (hours from the data's origin),
    the in-sample sum of squares of |a| - 1 g (g^2) with the model fitted apart on each side,
    and the windows it counts."""

    t_h: float
    ss_g2: float
    windows: int

    @property
    def rms_mg(self) -> float:
        return 1e3 * float(np.sqrt(self.ss_g2 / max(self.windows, 1)))


def in_sample_ss(model: SensorModel, p: np.ndarray, data: DiscoveryData) -> float:
    """Sum of squares of |a| - 1 g over every window with the values p (g^2)."""
    return float(np.sum(norm_error_g(model, p, data) ** 2))


def best_step(model: SensorModel, p: np.ndarray, data: DiscoveryData, blocks: np.ndarray,
              cfg: FitConfig) -> TimeStep | None:
    """The boundary between consecutive blocks (time order) at which ``model`` fitted apart on
    each side (each fit from p, also its prior mean: what one side cannot determine stays at
    p) leaves the smallest in-sample sum of squares; None without time or blocks to split."""
    n_blocks = int(blocks.max()) + 1 if len(blocks) else 0
    if not data.has_time or n_blocks < 2:
        return None
    best: TimeStep | None = None
    t_h = data.cov.t_h
    for b in range(1, n_blocks):
        before = blocks < b
        ss = 0.0
        for side in (before, ~before):
            part = data.subset(side)
            ss += in_sample_ss(model, fit_model(model, p, part, cfg).p, part)
        if best is None or ss < best.ss_g2:
            best = TimeStep(float(t_h[blocks == b].min()), ss, len(data))
    return best
