"""Fitting a sensor model to discovery data: on all windows, and on k-1 of k time blocks to
predict the block held out.

The fit is the batch form of Lötters eq. 11a (`estimator.solve`, iterated Gauss-Newton) over the
parameters the poses can determine (`free_params`), with the live estimator's default prior.
See docs/design.md (effect discovery).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recal.core.bootstrap import initial_params
from recal.core.discovery_data import COVERAGE_LEVEL_G, DiscoveryData
from recal.core.estimator import EstimatorConfig, Prior, solve
from recal.core.model import SensorModel

__all__ = [
    "FitConfig",
    "ModelFit",
    "Scored",
    "carry_params",
    "fit_model",
    "free_params",
    "nominal",
    "norm_error_g",
    "score_heldout",
    "start_params",
]


@dataclass(frozen=True)
class FitConfig:
    """Settings of one fit.

    Attributes:
        prior_scale: prior standard deviations are the model's defaults times this.
        sigma_floor_g: C_mu floor of the fit (see EstimatorConfig).
        max_iter: Gauss-Newton iterations per fit.
    """

    prior_scale: float = 1.0
    sigma_floor_g: float = 1e-3
    max_iter: int = 30

    def estimator(self) -> EstimatorConfig:
        # no process noise: a batch fit, every window counts the same whatever its age
        return EstimatorConfig(sigma_floor_g=self.sigma_floor_g, max_iter=self.max_iter,
                               tol=1e-10, process_scale=0.0)


@dataclass(frozen=True, eq=False)
class ModelFit:
    """A fit: values, posterior covariance, prior spreads, which parameters moved."""

    p: np.ndarray
    cov: np.ndarray  # posterior covariance (raw units, Lötters eq. 11b); prior on fixed ones
    prior_sd: np.ndarray
    free: np.ndarray  # the parameters the poses let move (see free_params)
    data_info: np.ndarray  # B^T C_mu^-1 B of the windows alone, free parameters

    @property
    def n_observed(self) -> int:
        """Directions in which the data outweigh the prior: eigenvalues of the data
        information, scaled by the prior standard deviations, above 1."""
        d = self.prior_sd[self.free]
        return int(np.sum(np.linalg.eigvalsh(d[:, None] * self.data_info * d[None, :]) > 1.0))


def free_params(model: SensorModel, p: np.ndarray, data: DiscoveryData) -> np.ndarray:
    """Parameters the poses can determine, by the live pipeline's rule (a gain needs its axis
    seen from both sides, Effect.observable_with) and, for offsets, their axis seen from one
    side at least. In a single pose an offset across gravity moves |a| only to second order,
    and fitting it would tilt the gravity direction to soak up drift and noise."""
    a = model.correct(p, data.windows.v, data.cov)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    pos, neg = (u > COVERAGE_LEVEL_G).any(axis=0), (u < -COVERAGE_LEVEL_G).any(axis=0)
    free = model.observable_with(tuple(bool(x) for x in pos & neg))
    for e in model.effects:
        if e.kind == "offset":
            free[model.slice(e)] &= pos | neg
    return free


def fit_model(model: SensorModel, p0: np.ndarray, data: DiscoveryData,
              cfg: FitConfig) -> ModelFit:
    """Lötters eq. 11a iterated from p0 (also the prior mean) over the free parameters."""
    prior = Prior.from_sd(p0, model.prior_sd() * cfg.prior_scale)
    now = int(data.windows.t_us.max()) if len(data) else 0
    free = free_params(model, p0, data)
    sol = solve(model, prior, p0, data.windows, data.cov, now, cfg.estimator(), free)
    cov = np.diag(prior.sd**2)
    cov[np.ix_(free, free)] = sol.cov_free
    return ModelFit(sol.p, cov, prior.sd, free, sol.data_info)


def norm_error_g(model: SensorModel, p: np.ndarray, data: DiscoveryData) -> np.ndarray:
    """|a| - 1 g per window (the sign of Lötters eq. 14 flipped: positive = too long)."""
    return -model.residual(p, data.windows.v, data.cov)


def _half_axes(v: np.ndarray) -> int:
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    return int(np.sum(u > COVERAGE_LEVEL_G, axis=0).astype(bool).sum()
               + np.sum(u < -COVERAGE_LEVEL_G, axis=0).astype(bool).sum())


def start_params(model: SensorModel, data: DiscoveryData) -> np.ndarray:
    """Starting values: ellipsoid (all six half-axes seen) or sphere fit (five), else nominal
    (too few orientations: e.g. one still pose, where only the offset along gravity shows)."""
    v = data.windows.v
    seen = _half_axes(v - data.zero)  # on centred readings: an unsigned part's are all > 0
    fit = None
    if seen >= 5 and len(v) >= 12:
        fit = initial_params(model, v, sphere=seen < 6)
    if fit is not None:
        fitted, p = fit
        s = p[fitted.slice(("scale", None))]
        if np.all((s > 0.5 * data.s0) & (s < 2.0 * data.s0)):
            return carry_params(fitted, p, model)
    return nominal(model, data)


def nominal(model: SensorModel, data: DiscoveryData) -> np.ndarray:
    """The model's nominal parameters with the offsets at the data's zero-g."""
    p = model.nominal()
    if model.has("offset"):
        p[model.slice(("offset", None))] = data.zero
    return p


def carry_params(src: SensorModel, p: np.ndarray, dst: SensorModel) -> np.ndarray:
    """Values of dst's parameters taken from src where both have the effect, else nominal."""
    q = dst.nominal()
    have = {e.key: e for e in src.effects}
    for e in dst.effects:
        if have.get(e.key) == e:  # same key and the same stage (a reduced one starts anew)
            q[dst.slice(e)] = p[src.slice(e.key)]
    return q


@dataclass(frozen=True, eq=False)
class Scored:
    """A model, its fit on all data, and its k-fold fits and held-out residuals."""

    model: SensorModel
    fit: ModelFit
    fold_p: tuple[np.ndarray, ...]
    heldout_xi: np.ndarray

    def block_ss(self, blocks: np.ndarray, n_blocks: int, scored: np.ndarray) -> np.ndarray:
        return np.bincount(blocks, np.where(scored, self.heldout_xi, 0.0)**2,
                           minlength=n_blocks)


def score_heldout(model: SensorModel, data: DiscoveryData, blocks: np.ndarray,
                  starts: list[np.ndarray], p_all: np.ndarray, cfg: FitConfig) -> Scored:
    """Fit on all windows (from p_all) and, per block, on the other blocks (from starts[k],
    which came from those blocks alone: no held-out value leaks in through a start)."""
    fit = fit_model(model, p_all, data, cfg)
    held = np.empty(len(data))
    fold_p = []
    for k, p0 in enumerate(starts):
        test = blocks == k
        pk = fit_model(model, p0, data.subset(~test), cfg).p
        held[test] = norm_error_g(model, pk, data.subset(test))
        fold_p.append(pk)
    return Scored(model, fit, tuple(fold_p), held)
