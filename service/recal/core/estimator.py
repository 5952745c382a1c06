"""Linearized minimum-variance unbiased estimator (Lötters 1998, eq. 5-14), in information form.

Lötters linearizes h(v, p) = |a(v, p)| around the previous estimate p(-) (eq. 9-10) and solves

    q = (B^T C_mu^-1 B)^-1 B^T C_mu^-1 xi        eq. 11a   (q = p - p(-), eq. 12)
    C_e = (B^T C_mu^-1 B)^-1                      eq. 11b

with xi = 1 g - h(v, p(-)) (eq. 14) and B = dh/dp (eq. 13a). This module iterates that step to
convergence (Gauss-Newton) and goes beyond the paper where it fails in use:

* Recursive, in information form: the previous estimate and its error covariance are the prior
  of the next update (Lambda = C_e^-1 is added to B^T C_mu^-1 B, Lambda (p(-) - p) to the
  right-hand side), and each update adds only the windows committed since the last one. Directions
  the data cannot observe (the paper's orientation-1 case: upright only) stay where they were,
  at the pre-calibration if they were never seen, instead of wandering.
* Process noise: parameters random-walk with Q per hour, C_e <- C_e + Q dt before each update,
  so the estimate follows offset drift over hours. The growth is capped at the initial prior
  covariance, so a direction unseen for weeks is never less certain than the pre-calibration.
* Coverage: the gains (and cross-axis terms) of an axis that gravity has not yet been seen on
  from both sides stay fixed (Lötters' offsets-only mode, per axis), as Schmidt "consider"
  parameters: they do not move, but their uncertainty stays in C_e, so the offsets do not grow
  confident about an error that belongs to an unobserved gain.

The recursive step is written in gain form, K = C_e B^T (B C_e B^T + C_mu)^-1, iterated on the
linearization point (iterated extended Kalman filter). With every parameter free this is
algebraically Lötters eq. 11a with the previous estimate's information Lambda = C_e^-1 as prior
rows (matrix inversion lemma); the gain form is what lets consider parameters keep K = 0.
* Gates: an update is rejected (the previous estimate kept) when it leaves physical bounds
  (|offset| > 0.5 g, gain outside 0.8-1.2 of nominal, ...), fails to lower the objective, or is
  not finite. Each update reports its residual, the condition of the data information and which
  parameters the data (not the prior) determined.
* Offsets-only mode (Lötters: "in case the sensitivities are assumed to be known and stable").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recal.core.buffer import Windows
from recal.core.effects import Covariates
from recal.core.model import SensorModel

__all__ = ["Estimate", "EstimatorConfig", "Prior", "UpdateReport", "predict", "solve", "update"]


#: An update whose weighted residual (data + prior) ends above this factor times its start is
#: rejected.
RESIDUAL_GATE = 1.05


@dataclass(frozen=True, eq=False)
class Prior:
    """Prior mean p_0 and information Lambda_0 = C_0^-1 (information form)."""

    mean: np.ndarray
    info: np.ndarray

    @classmethod
    def from_sd(cls, mean: np.ndarray, sd: np.ndarray) -> Prior:
        sd = np.asarray(sd, np.float64)
        return cls(np.asarray(mean, np.float64).copy(), np.diag(1.0 / sd**2))

    @classmethod
    def default(cls, model: SensorModel, mean: np.ndarray | None = None) -> Prior:
        return cls.from_sd(model.nominal() if mean is None else mean, model.prior_sd())

    @property
    def sd(self) -> np.ndarray:
        return 1.0 / np.sqrt(np.diag(self.info))

    def to_dict(self) -> dict:
        return {"mean": self.mean.tolist(), "info": self.info.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Prior:
        return cls(np.asarray(d["mean"], np.float64), np.asarray(d["info"], np.float64))


@dataclass(frozen=True)
class EstimatorConfig:
    """Estimator settings.

    Attributes:
        mode: "all" parameters, or "offsets" only (Lötters' two modes).
        sigma_floor_g: C_mu floor: how far from 1 g a quasi-static window mean may be for
            reasons other than sensor noise (sway, slow movement), in g.
        max_iter: Gauss-Newton iterations per update.
        tol: stop when every step is below tol x its prior standard deviation.
        observable_ratio: a parameter counts as observed when the data shrank its standard
            deviation below this fraction of the prior's.
        min_windows: fewer windows than this and no update is attempted.
        process_scale: multiplies every effect's random-walk process noise (0 = none).
    """

    mode: str = "all"
    sigma_floor_g: float = 0.001
    max_iter: int = 15
    tol: float = 1e-6
    observable_ratio: float = 0.5
    min_windows: int = 4
    process_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.mode not in ("all", "offsets"):
            raise ValueError(f"estimator mode must be 'all' or 'offsets', not {self.mode!r}")


@dataclass(frozen=True, eq=False)
class Estimate:
    """The current parameters p, their error covariance C_e (Lötters eq. 11b), and the device
    time of the update that produced them (None: the pre-calibration)."""

    p: np.ndarray
    cov: np.ndarray
    t_us: int | None = None

    @classmethod
    def from_prior(cls, prior: Prior) -> Estimate:
        return cls(prior.mean.copy(), np.linalg.inv(prior.info))

    def to_dict(self) -> dict:
        return {"p": self.p.tolist(), "cov": self.cov.tolist(), "t_us": self.t_us}

    @classmethod
    def from_dict(cls, d: dict) -> Estimate:
        t = d.get("t_us")
        return cls(np.asarray(d["p"], np.float64), np.asarray(d["cov"], np.float64),
                   None if t is None else int(t))


def predict(model: SensorModel, prior: Prior, estimate: Estimate, now_us: int,
            scale: float = 1.0) -> Estimate:
    """Process noise: C_e + Q dt, each standard deviation capped at the prior's."""
    if estimate.t_us is None:
        return estimate
    dt_h = max(now_us - estimate.t_us, 0) / 3.6e9
    cov = estimate.cov + np.diag((scale * model.process_sd_per_sqrt_h()) ** 2 * dt_h)
    cap = np.sqrt(np.minimum(1.0, np.diag(np.linalg.inv(prior.info)) / np.diag(cov)))
    return Estimate(estimate.p, cap[:, None] * cov * cap[None, :], estimate.t_us)


@dataclass(frozen=True)
class UpdateReport:
    """What one update did, for the calibration state and the log."""

    accepted: bool
    reason: str
    n_windows: int
    iterations: int = 0
    residual_rms_before_g: float = float("nan")
    residual_rms_after_g: float = float("nan")
    condition: float = float("nan")
    observable: tuple[bool, ...] = ()
    free: tuple[bool, ...] = field(default=())

    def to_dict(self, names: tuple[str, ...]) -> dict:
        return {"accepted": self.accepted, "reason": self.reason, "n_windows": self.n_windows,
                "iterations": self.iterations,
                "residual_rms_before_mg": 1e3 * self.residual_rms_before_g,
                "residual_rms_after_mg": 1e3 * self.residual_rms_after_g,
                "condition": self.condition,
                "observable": {n: bool(o) for n, o in zip(names, self.observable, strict=False)}}


def _window_variance(model: SensorModel, w: Windows, B: np.ndarray, now_us: int,
                     cfg: EstimatorConfig) -> np.ndarray:
    """C_mu diagonal per window: averaged sensor noise + floor + process noise since it was seen."""
    noise = w.var / np.maximum(w.n, 1) / model.s0**2
    age_h = np.maximum(now_us - w.t_us, 0) / 3.6e9
    q = (cfg.process_scale * model.process_sd_per_sqrt_h()) ** 2
    drift = age_h * np.einsum("np,p,np->n", B, q, B)  # a window seen earlier says less of now
    return noise + cfg.sigma_floor_g**2 + drift


def _objective(xi: np.ndarray, c_mu: np.ndarray, p: np.ndarray, prior: Prior) -> float:
    d = p - prior.mean
    return float(np.sum(xi**2 / c_mu) + d @ prior.info @ d)


@dataclass(frozen=True, eq=False)
class _Solution:
    p: np.ndarray
    cov_free: np.ndarray
    data_info: np.ndarray
    iterations: int
    objective_start: float
    objective_end: float
    xi_start: np.ndarray
    xi_end: np.ndarray
    cov_full: np.ndarray | None = None


def solve(model: SensorModel, prior: Prior, p_start: np.ndarray, windows: Windows,
          cov: Covariates, now_us: int, cfg: EstimatorConfig,
          free: np.ndarray | None = None) -> _Solution:
    """Iterate Lötters eq. 11a (with prior rows) from p_start until the step is negligible.

    `free` masks the parameters to estimate; the others stay at p_start.
    """
    free = np.ones(model.size, bool) if free is None else np.asarray(free, bool)
    D = prior.sd[free]  # scale parameters to their prior spread: conditions the normal equations
    L0 = prior.info[np.ix_(free, free)]
    p = np.asarray(p_start, np.float64).copy()
    xi, B = model.residual_jacobian(p, windows.v, cov)
    c_mu = _window_variance(model, windows, B, now_us, cfg)
    j_start = j = _objective(xi, c_mu, p, prior)
    xi_start, it = xi, 0
    for it in range(1, cfg.max_iter + 1):  # noqa: B007 - `it` is reported
        Bf = B[:, free] * D
        A = Bf.T @ (Bf / c_mu[:, None]) + D[:, None] * L0 * D[None, :]
        b = Bf.T @ (xi / c_mu) + D * (prior.info[free] @ (prior.mean - p))
        step = D * np.linalg.lstsq(A, b, rcond=1e-12)[0]  # eq. 11a, scaled
        for _ in range(12):  # halve the step until the objective falls (nonlinear h)
            trial = p.copy()
            trial[free] += step
            xi_t, B_t = model.residual_jacobian(trial, windows.v, cov)
            j_t = _objective(xi_t, c_mu, trial, prior)
            if np.isfinite(j_t) and j_t <= j:
                break
            step = step / 2
        else:
            break
        p, xi, B, j = trial, xi_t, B_t, j_t
        c_mu = _window_variance(model, windows, B, now_us, cfg)
        j = _objective(xi, c_mu, p, prior)
        if np.all(np.abs(step) <= cfg.tol * prior.sd[free]):
            break
    Bf = B[:, free]
    data_info = Bf.T @ (Bf / c_mu[:, None])
    cov_free = np.linalg.pinv(data_info + L0)  # eq. 11b with the prior's information
    return _Solution(p, cov_free, data_info, it, j_start, j, xi_start, xi)


def _observability(sol: _Solution, prior: Prior, free: np.ndarray,
                   cfg: EstimatorConfig) -> tuple[np.ndarray, float]:
    """Observed = the estimate's sd is below observable_ratio x the pre-calibration's; the
    condition number is that of the posterior information, scaled by the prior sd."""
    post_sd = np.sqrt(np.clip(np.diag(sol.cov_free), 0, None))
    observable = np.zeros(len(free), bool)
    observable[free] = post_sd < cfg.observable_ratio * prior.sd[free]
    D = prior.sd[free]
    ev = np.linalg.eigvalsh(D[:, None] * np.linalg.pinv(sol.cov_free) * D[None, :])
    condition = float(ev[-1] / max(ev[0], 1e-300)) if len(ev) else float("nan")
    return observable, condition


def update(model: SensorModel, prior: Prior, estimate: Estimate, windows: Windows,
           cov: Covariates, now_us: int, cfg: EstimatorConfig,
           free: np.ndarray | None = None) -> tuple[Estimate, UpdateReport]:
    """One gated in-use update with the windows committed since the last one.

    Args:
        prior: the pre-calibration (bounds the process noise; the reference for observability).
        estimate: the previous estimate p(-), C_e(-).
        windows: the new window means; cov: their covariates.
        free: parameters allowed to move (e.g. by coverage); the mode narrows it further.
    Returns the estimate to use next (the previous one if the update was rejected) and a report.
    """
    n = len(windows)
    free = np.ones(model.size, bool) if free is None else np.asarray(free, bool).copy()
    if cfg.mode == "offsets":
        free &= model.mask(["offset"]) & ~_covariate_mask(model)
    if n < cfg.min_windows:
        return estimate, UpdateReport(False, "too few windows", n)
    pred = predict(model, prior, estimate, now_us, cfg.process_scale)
    sol = _consider_update(model, pred, windows, cov, now_us, cfg, free)
    observable, condition = _observability(sol, prior, free, cfg)
    rms = (float(np.sqrt(np.mean(sol.xi_start**2))), float(np.sqrt(np.mean(sol.xi_end**2))))
    flags = (condition, tuple(map(bool, observable)), tuple(map(bool, free)))
    lo, hi = model.bounds()
    reason = None
    if not (np.all(np.isfinite(sol.p)) and np.all(np.isfinite(sol.cov_free))):
        reason = "not finite"
    elif np.any(sol.p < lo) or np.any(sol.p > hi):
        bad = [nm for nm, x, a, b in zip(model.names, sol.p, lo, hi, strict=True)
               if not a <= x <= b]
        reason = f"out of bounds: {', '.join(bad)}"
    elif sol.objective_end > RESIDUAL_GATE * sol.objective_start + 1e-9:
        # data + prior objective, with the prior term of the consider parameters at zero: a
        # Schmidt step may raise it a hair (it does not minimize over consider parameters), a
        # diverging one raises it a lot
        reason = "residual rose"
    if reason is not None:
        return estimate, UpdateReport(False, reason, n, sol.iterations, *rms, *flags)
    return Estimate(sol.p, sol.cov_full, now_us), UpdateReport(True, "ok", n, sol.iterations,
                                                                *rms, *flags)


def _consider_update(model: SensorModel, pred: Estimate, windows: Windows, cov: Covariates,
                     now_us: int, cfg: EstimatorConfig, free: np.ndarray) -> _Solution:
    """Iterated Schmidt-Kalman update: p = p(-) + K [xi(p_i) + B_i (p_i - p(-))], K = 0 on the
    consider (not free) parameters, C_e by the Joseph form (valid for any gain)."""
    P = pred.cov
    p = pred.p.copy()
    info = np.linalg.pinv(P)
    xi, B = model.residual_jacobian(p, windows.v, cov)
    c_mu = _window_variance(model, windows, B, now_us, cfg)
    j_start = _objective(xi, c_mu, p, Prior(pred.p, info))
    xi_start, K, it = xi, np.zeros((model.size, len(xi))), 0
    for it in range(1, cfg.max_iter + 1):  # noqa: B007 - `it` is reported
        S = B @ P @ B.T + np.diag(c_mu)
        K = np.linalg.solve(S, B @ P).T
        K[~free] = 0.0
        step = pred.p + K @ (xi + B @ (p - pred.p)) - p
        for _ in range(12):  # halve the step until the objective falls (nonlinear h)
            trial = p + step
            xi_t, B_t = model.residual_jacobian(trial, windows.v, cov)
            if np.all(np.isfinite(xi_t)) and (
                    _objective(xi_t, c_mu, trial, Prior(pred.p, info))
                    <= _objective(xi, c_mu, p, Prior(pred.p, info)) * (1 + 1e-12) + 1e-300):
                break
            step = step / 2
        p, xi, B = trial, xi_t, B_t
        c_mu = _window_variance(model, windows, B, now_us, cfg)
        if np.all(np.abs(step) <= cfg.tol * np.sqrt(np.clip(np.diag(P), 1e-300, None))):
            break
    S = B @ P @ B.T + np.diag(c_mu)
    K = np.linalg.solve(S, B @ P).T
    K[~free] = 0.0
    IKB = np.eye(model.size) - K @ B
    cov_full = IKB @ P @ IKB.T + K @ np.diag(c_mu) @ K.T  # Joseph form
    cov_full = 0.5 * (cov_full + cov_full.T)
    Bf = B[:, free]
    j_end = _objective(xi, c_mu, p, Prior(pred.p, info))
    return _Solution(p, cov_full[np.ix_(free, free)], Bf.T @ (Bf / c_mu[:, None]), it, j_start,
                     j_end, xi_start, xi, cov_full)


def _covariate_mask(model: SensorModel) -> np.ndarray:
    return np.concatenate([np.full(e.size, e.covariate is not None) for e in model.effects])
