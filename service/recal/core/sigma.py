"""The predicted error of a calibrated sample (`predicted_sigma_mg`): the 1-sigma length of
the error of the calibrated vector that the parameters' uncertainty causes, the estimate's
covariance C_e (Lötters eq. 11b) through the correction's Jacobian J = da/dp at each sample,
sigma_C^2 = trace(J C_e J^T). For a model whose correction is affine in the reading and reads
no covariate, that is a quadratic form in [1, v] (`sigma_form`), made once per estimate.
What the status and the misfit add to it: `core.status`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from recal.core.effects import Covariates
from recal.core.model import SensorModel

__all__ = ["SMALL_BATCH", "correction_jacobian", "floor_mg2", "predicted_sigma_mg",
           "sigma_form", "sigma_one_mg", "with_floor"]


def correction_jacobian(model: SensorModel, p: np.ndarray, v: np.ndarray,
                        cov: Covariates) -> np.ndarray:
    """J = da/dp (N, 3, P) of the corrected readings a = f(v; p), by the chain rule through
    the model's stages (each stage's vector-Jacobian product with the unit rows of da/da)."""
    stages = [(e, model.slice(e)) for e in model.effects]
    xs = [np.asarray(v, np.float64)]
    for e, sl in stages:
        xs.append(e.apply(xs[-1], cov, p[sl]))
    n = len(xs[0])
    if model.axes_apart:
        return _unit_jacobian(stages, xs, cov, p, n, model.size)
    return _chain_jacobian(stages, xs, cov, p, n, model.size)


def _chain_jacobian(stages: list, xs: list[np.ndarray], cov: Covariates, p: np.ndarray,
                    n: int, size: int) -> np.ndarray:
    """`correction_jacobian` by every stage's full `vjp`, each unit row of da/da in turn
    (the general chain rule; `_unit_jacobian` is its short form for stages that keep the axes
    apart)."""
    J = np.empty((n, 3, size))
    for j in range(3):
        g = np.zeros((n, 3))
        g[:, j] = 1.0
        for k in range(len(stages) - 1, -1, -1):
            e, sl = stages[k]
            J[:, j, sl], g_in = e.vjp(g, xs[k], cov, p[sl], k > 0)
            g = g_in if k else g
    return J


def _unit_jacobian(stages: list, xs: list[np.ndarray], cov: Covariates, p: np.ndarray, n: int,
                   size: int) -> np.ndarray:
    """`correction_jacobian` for stages that keep the axes apart (`Effect.unit_vjp`): row j of
    J seeded with the unit vector e_j stays one column wide through every stage, so each stage
    gives its nonzero part alone. The same products as the full chain rule, to the bit (that
    adds only zeros to them; a non-finite reading's row has zeros where it had 0 x inf, and
    its sigma is NaN all the same), at a third of the work, without (N, 3, 3) arrays."""
    J = np.zeros((n, 3, size))
    for j in range(3):
        s: float | np.ndarray = 1.0
        for k in range(len(stages) - 1, -1, -1):
            e, sl = stages[k]
            b, s_in = e.unit_vjp(j, s, xs[k], cov, p[sl], k > 0)
            if e.per_axis_params:
                J[:, j, sl.start + j] = b
            else:
                J[:, j, sl] = b
            s = s_in if k else s
    return J


_BASIS = np.vstack([np.zeros(3), np.eye(3)])  # v = 0, then each axis
_NO_COVARIATES = Covariates(np.zeros(4), np.zeros((4, 0)))


def _quadratic_form(model: SensorModel, p: np.ndarray, cov_p: np.ndarray) -> np.ndarray:
    """Q (4, 4) with sigma^2(v) = [1, v] Q [1, v]^T, for a model whose correction is affine in
    v and reads no covariate: J(v) = G_0 + sum_k v_k G_k then, exactly."""
    J = correction_jacobian(model, p, _BASIS, _NO_COVARIATES)
    G = np.concatenate([J[:1], J[1:] - J[:1]]).reshape(4, -1)  # G_0, G_1..G_3, flattened
    # Q_mn = trace(G_m C G_n^T): the (3, P) blocks' rows against C
    C = np.kron(np.eye(3), cov_p)
    return G @ C @ G.T


def predicted_sigma_mg(model: SensorModel, p: np.ndarray, cov_p: np.ndarray, v: np.ndarray,
                       cov: Covariates, form: np.ndarray | None = None) -> np.ndarray:
    """The predicted 1-sigma error (mg) of each corrected reading: sqrt(trace(J C_e J^T)),
    J = da/dp at the sample, C_e the parameters' covariance (Lötters eq. 11b).

    ``form``: `sigma_form(model, p, cov_p)` when the caller has it (it depends only on the
    estimate); None computes it, or, for a model that reads covariates, uses the full
    per-sample Jacobian."""
    v = np.asarray(v, np.float64)
    if form is None:
        form = sigma_form(model, p, cov_p)
    with np.errstate(invalid="ignore", over="ignore"):  # a NaN reading: NaN (the shell's)
        if form is not None:
            # element by element, in a fixed order: each sample's sigma is the same bits
            # whatever batch it came in (a matrix product's rounding depends on its size);
            # a few samples (a live sensor's) as Python floats, the same operations
            q = form.tolist()
            if len(v) <= SMALL_BATCH:
                return np.array([sigma_one_mg(q, x, y, z) for x, y, z in v.tolist()],
                                np.float64).reshape(-1)
            s2 = _s2(q, v[:, 0], v[:, 1], v[:, 2])
        else:
            J = correction_jacobian(model, p, v, cov)
            s2 = np.einsum("nip,nip->n", np.matmul(J, cov_p), J)
        return 1e3 * np.sqrt(np.maximum(s2, 0.0))


#: Up to this many samples `predicted_sigma_mg` works in Python floats (fewer calls).
SMALL_BATCH = 32


def sigma_one_mg(q: list[list[float]], x: float, y: float, z: float) -> float:
    """`predicted_sigma_mg` of one reading (x, y, z) as a Python float, from its form as
    nested lists (``sigma_form(...).tolist()``)."""
    return 1e3 * math.sqrt(max(_s2(q, x, y, z), 0.0))


def _s2(q: list[list[float]], x: Any, y: Any, z: Any) -> Any:
    """[1, v] Q [1, v]^T for floats or arrays alike (the same operations in the same order)."""
    return (q[0][0] + 2.0 * (x * q[0][1] + y * q[0][2] + z * q[0][3])
            + x * x * q[1][1] + y * y * q[2][2] + z * z * q[3][3]
            + 2.0 * (x * y * q[1][2] + x * z * q[1][3] + y * z * q[2][3]))


def sigma_form(model: SensorModel, p: np.ndarray, cov_p: np.ndarray) -> np.ndarray | None:
    """`_quadratic_form` when the model's correction is affine in v without covariates
    (offsets, scales, cross-axis terms), else None (`predicted_sigma_mg` then goes sample by
    sample)."""
    # what `SensorModel.affine` accepts without divisors, asked of the stages (cheaper)
    if model.covariates or not all(e.affine and not e.divides_rows for e in model.effects):
        return None
    return _quadratic_form(model, p, cov_p)


def with_floor(model: SensorModel, p: np.ndarray, form: np.ndarray, w: np.ndarray
               ) -> np.ndarray:
    """The sigma form (`sigma_form`) widened by a floor a^T W a (g^2) at each corrected
    vector a (`misfit.unseen_cross_form`): for a correction affine in v without covariates,
    a = L [1, v] with L (3, 4) from the corrections of v = 0 and of each axis, so the floor is
    the quadratic form L^T W L in [1, v] and sigma stays one form per estimate."""
    a = model.correct(p, _BASIS, _NO_COVARIATES)
    L = np.concatenate([a[:1], a[1:] - a[:1]]).T  # columns: A_0, then A's
    return form + L.T @ w @ L


def floor_mg2(a_g: np.ndarray, w: np.ndarray) -> np.ndarray:
    """a^T W a (mg^2) of each corrected vector a (N, 3, g): the floor sample by sample, for a
    model without a sigma form (one that reads covariates)."""
    return 1e6 * np.einsum("ni,ij,nj->n", a_g, w, a_g)
