"""Static multi-position calibration (the lab mode of Bragge et al. and Georgieva et al.).

A table of still readings (one row per position, any unit) is fitted two ways:

* unknown orientations (Georgieva et al. approach 1, eq. 17): every row must have |a| = g. The
  same model and Gauss-Newton solver as the in-use estimator (Lötters eq. 11a) fit offsets and an
  upper-triangular inverse sensitivity (9 parameters, equivalent to Georgieva's shifts, scalings
  and three axis angles), started from the ellipsoid fit of `bootstrap`;
* known orientations (Bragge eq. 2-4, Georgieva approach 2): rows whose gravity direction is a
  signed sensor axis give the linear least-squares problem z = K a + O for all 12 parameters.

The figure of merit is each row's relative norm error | |a| - g | / g, reported over all rows,
including rows left out of the fit. Results on measured tables: docs/performance.md ("Static
tables").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

from recal.core.bootstrap import initial_params, off_by, zero_and_scale
from recal.core.buffer import Windows
from recal.core.effects import Covariates
from recal.core.estimator import EstimatorConfig, Prior, solve
from recal.core.model import SensorModel
from recal.core.pipeline import gain_reference
from recal.errors import InputError, UsageError

__all__ = ["MIN_DETERMINATION", "StaticFit", "determination", "fit_known_orientations",
           "fit_unknown_orientations", "nearest_axes"]


@dataclass(frozen=True, eq=False)
class StaticFit:
    """A static calibration: how to correct rows, and their relative norm errors."""

    method: str
    g: float
    params: dict
    a_g: np.ndarray  # (M,3) corrected rows, in g
    fit_rows: np.ndarray  # bool mask of the rows used in the fit

    @property
    def rel_norm_error(self) -> np.ndarray:
        return np.abs(np.linalg.norm(self.a_g, axis=1) - 1.0)


def _no_covariates(n: int) -> Covariates:
    return Covariates(np.zeros(n), np.zeros((n, 0)))


#: Rows a minimax round starts with and adds (the worst ones): the optimum is set by a few
#: rows, and SLSQP's cost grows with the number of constraints (a 361 000-row table, every row
#: two constraints, took minutes).
MINIMAX_ROWS = 200
MINIMAX_ROUNDS = 30

#: Smallest singular value over the largest of the fit's Jacobian (Lötters eq. 13a, columns
#: in units of each parameter's prior spread, rows normalized) below which the rows do not
#: determine the parameters: measured 9e-6 on 2 000 rows of one pose, 6e-5 on three faces,
#: 1e-3 on the six faces for the full model (faces say nothing of cross-axis angles), 0.036 -
#: 0.091 on the three measured phone tables (../shared/data/static_positions).
MIN_DETERMINATION = 2e-3


def _minimax(model: SensorModel, p: np.ndarray, v: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Chebyshev fit: minimize t subject to | 1 - |a_i| | <= t (epigraph form, SLSQP).

    The figure of merit of a static table is its *worst* row, so the fit minimizes exactly that,
    started from the least-squares solution. Only rows that can be worst are constraints: the
    MINIMAX_ROWS worst at the start, then, round by round, the worst of any row above the
    bound found (a cutting plane: the optimum on the rows kept is the optimum on all once no
    row exceeds it); a table of fewer rows is one problem with every row, as it always was."""
    cov_all = _no_covariates(len(v))

    def resid_all(z: np.ndarray) -> np.ndarray:
        return 1.0 - np.linalg.norm(model.correct(p + scale * z[:-1], v, cov_all), axis=1)

    r0 = resid_all(np.zeros(len(p) + 1))
    t0 = float(np.max(np.abs(r0)))
    keep = np.sort(np.argsort(-np.abs(r0), kind="stable")[:MINIMAX_ROWS])
    z = np.r_[np.zeros(len(p)), t0]
    for _ in range(MINIMAX_ROUNDS):
        z_new = _minimax_rows(model, p, v[keep], scale, z)
        if z_new is None:
            return p
        z = z_new
        r = np.abs(resid_all(z))
        over = np.flatnonzero(r > z[-1] * (1 + 1e-9) + 1e-12)
        if len(over) == 0:
            break
        worst = over[np.argsort(-r[over], kind="stable")[:MINIMAX_ROWS]]
        keep = np.union1d(keep, worst)
        z = np.r_[z[:-1], float(r.max())]  # a feasible start for the next round
    if not float(np.max(np.abs(resid_all(z)))) <= t0:
        return p
    return p + scale * z[:-1]


def _minimax_rows(model: SensorModel, p: np.ndarray, v: np.ndarray, scale: np.ndarray,
                  z0: np.ndarray) -> np.ndarray | None:
    """One SLSQP solve of the epigraph problem on the rows ``v``, from ``z0``; None if it
    failed or went non-finite."""
    cov = _no_covariates(len(v))

    def resid(z: np.ndarray) -> np.ndarray:
        return 1.0 - np.linalg.norm(model.correct(p + scale * z[:-1], v, cov), axis=1)

    res = optimize.minimize(
        lambda z: z[-1], z0, method="SLSQP",
        constraints=[{"type": "ineq", "fun": lambda z: z[-1] - resid(z)},
                     {"type": "ineq", "fun": lambda z: z[-1] + resid(z)}],
        options={"maxiter": 500, "ftol": 1e-12})
    ok = res.success and np.all(np.isfinite(res.x)) and res.x[-1] <= z0[-1]
    return res.x if ok else None


def determination(model: SensorModel, p: np.ndarray, v: np.ndarray) -> float:
    """How well rows ``v`` determine the parameters at ``p``: the smallest singular value of
    the Jacobian of |a| (Lötters eq. 13a; columns scaled by the parameters' prior spread) over
    the largest. Near 0: some combination of parameters leaves every row's norm unchanged (one
    pose, three faces: the axes and their angles are not determined)."""
    _, B = model.residual_jacobian(p, v, _no_covariates(len(v)))
    sv = np.linalg.svd(B * model.prior_sd(), compute_uv=False)
    return float(sv.min() / sv.max()) if sv.max() > 0 else 0.0


def fit_unknown_orientations(v: np.ndarray, fit_rows: np.ndarray, g: float | None = None,
                             full: bool = True, loss: str = "minimax") -> StaticFit:
    """Fit |a| = 1 g on the rows in `fit_rows`; g (the unit's gravity) only names the unit.

    loss: "l2" (Georgieva eq. 17, least squares) or "minimax" (least worst row, from the l2 fit).
    """
    if loss not in ("l2", "minimax"):
        raise UsageError(f"loss must be 'l2' or 'minimax', not {loss!r}")
    v = np.asarray(v, np.float64)
    g = float(np.median(np.linalg.norm(v, axis=1))) if g is None else float(g)
    base = SensorModel.full(g) if full else SensorModel.diagonal(g)
    n_fit = int(np.count_nonzero(fit_rows))
    if n_fit < base.size:  # fewer rows than unknowns: any table "fits" them exactly
        raise InputError(f"{n_fit} fitted rows cannot determine the {base.size} parameters of "
                         f"the {'full' if full else 'diagonal'} model; fit at least "
                         f"{base.size} rows" + (" (or 6 with --diagonal)" if full else ""))
    start = initial_params(base, v[fit_rows])
    model, p0 = start if start is not None else (base, base.nominal())
    s0 = g
    if start is not None and off_by(p0[model.slice(("offset", None))], model.s0, np.zeros(3), g):
        s0 = model.s0  # zero-g far from 0 (an unsigned ADC): the median norm is no scale
    model = SensorModel(model.effects, s0, model.spreads)
    # A very wide prior: only a tie-breaker for directions a degenerate table leaves open.
    prior = Prior.from_sd(model.nominal(), model.prior_sd() * 1e3)
    sel = v[fit_rows]
    w = Windows(sel, np.zeros((len(sel), 0)), np.zeros(len(sel), np.int64),
                np.ones(len(sel), np.int64), np.zeros(len(sel)))
    cfg = EstimatorConfig(sigma_floor_g=1e-3, max_iter=100, tol=1e-12)
    p = solve(model, prior, p0, w, _no_covariates(len(sel)), 0, cfg).p
    determined = determination(model, p, sel)
    if loss == "minimax" and determined >= MIN_DETERMINATION:
        # (rows that determine nothing have no worst row worth minimizing: the result is
        # refused anyway, and SLSQP wanders on the flat directions for long)
        p = _minimax(model, p, sel, model.prior_sd())
        determined = determination(model, p, sel)
    a = model.correct(p, v, _no_covariates(len(v)))
    ref = gain_reference(model, p, from_prior=False)
    params = {"model": model.to_dict(), "p": model.params_dict(p), "loss": loss,
              "gain_reference": ref, "described": model.describe(p, ref["counts_per_g"]),
              "determination": determined}
    if full:
        params["axis_angles_deg"] = model.axis_angles_deg(p)
    return StaticFit("unknown_orientations", g, params, a, np.asarray(fit_rows, bool))


def nearest_axes(v: np.ndarray, max_angle_deg: float = 25.0) -> np.ndarray:
    """Gravity direction of each row as the nearest signed sensor axis (unit vectors, (M,3)).

    Raises ValueError for a row further than max_angle_deg from every axis."""
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    ax = np.argmax(np.abs(u), axis=1)
    cos = np.abs(u[np.arange(len(u)), ax])
    bad = np.flatnonzero(cos < np.cos(np.radians(max_angle_deg)))
    if len(bad):
        raise InputError(f"rows {', '.join(str(i + 1) for i in bad)} are not near a sensor axis; "
                         "--known-orientations needs rows lying on a face")
    out = np.zeros_like(u)
    out[np.arange(len(u)), ax] = np.sign(u[np.arange(len(u)), ax])
    return out


def _zero_g(z: np.ndarray) -> np.ndarray:
    """Where a table's rows are centred (an unsigned ADC's point along the axes only from its
    zero-g, ~2048 counts): `bootstrap.zero_and_scale`, or for a table too short for its
    sphere, the midrange of each axis when that shows zero far from 0 (faces seen from both
    sides: the offsets)."""
    zero, s0 = zero_and_scale(z)
    if zero.any() or len(z) < 2:
        return zero
    mid = (z.max(axis=0) + z.min(axis=0)) / 2
    half = float(np.mean(np.ptp(z, axis=0))) / 2
    return mid if half > 0 and off_by(mid, half, np.zeros(3), s0) else zero


def fit_known_orientations(v: np.ndarray, fit_rows: np.ndarray,
                           g: float | None = None) -> StaticFit:
    """Bragge eq. 4: theta = (H^T H)^-1 H^T z with H from the known gravity directions."""
    v = np.asarray(v, np.float64)
    g = float(np.median(np.linalg.norm(v, axis=1))) if g is None else float(g)
    z = v[fit_rows]
    a_known = nearest_axes(z - _zero_g(z))  # in g
    H = np.hstack([a_known, np.ones((len(z), 1))])  # rows (a_x, a_y, a_z, 1), eq. 2 per axis
    if np.linalg.matrix_rank(H) < 4:
        raise InputError("known orientations must span 4 independent rows (Georgieva eq. 22)")
    theta, *_ = np.linalg.lstsq(H, z, rcond=None)  # eq. 3-4 solved for all three axes at once
    K, offset = theta[:3].T, theta[3]
    a = np.linalg.solve(K, (v - offset).T).T  # Bragge eq. 5
    params = {"K": K.tolist(), "O": offset.tolist(), "g": g}
    return StaticFit("known_orientations", g, params, a, np.asarray(fit_rows, bool))
