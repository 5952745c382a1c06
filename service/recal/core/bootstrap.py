"""Start from nothing: a batch ellipsoid fit for a sensor with no prior (unknown scale).

Still readings v lie on the ellipsoid (v - o)^T Q (v - o) = 1 (Lötters fig. 4b; Bragge eq. 1
with |a| = 1 g). Its algebraic fit is linear in the quadric's coefficients:

    A x^2 + B y^2 + C z^2 + 2D xy + 2E xz + 2F yz + 2G x + 2H y + 2I z = 1

From Q, o = -Q^-1 (G, H, I), and the Cholesky factor Q = U^T U with U upper-triangular gives the
correction a = U (v - o) in the same rotation gauge as `effects.CrossAxis`: s_i = 1 / U_ii and
M = U diag(s). The diagonal model fits the axis-aligned ellipsoid (D = E = F = 0).
"""

from __future__ import annotations

import numpy as np

from recal.core.effects import CrossAxis, Offset, Scale
from recal.core.model import SensorModel

__all__ = ["fit_ellipsoid", "fit_sphere", "initial_params"]


def fit_ellipsoid(v: np.ndarray, full: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """Fit still readings v (M,3); returns (offset o (3,), upper-triangular U (3,3)) with
    |U (v - o)| ~ 1, or None when the points do not pin down an ellipsoid."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    need = 9 if full else 6
    if len(v) < need + 1:
        return None
    c = v.mean(axis=0)
    span = float(np.max(np.abs(v - c))) or 1.0
    x, y, z = ((v - c) / span).T  # centred and scaled: keeps the design matrix well conditioned
    cols = [x * x, y * y, z * z]
    if full:
        cols += [2 * x * y, 2 * x * z, 2 * y * z]
    cols += [2 * x, 2 * y, 2 * z]
    H = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(H, np.ones(len(v)), rcond=None)
    if full:
        A, B, C, D, E, F, G, Hh, Ii = coef
    else:
        (A, B, C, G, Hh, Ii), D, E, F = coef, 0.0, 0.0, 0.0
    Q = np.array([[A, D, E], [D, B, F], [E, F, C]])
    try:
        o_n = -np.linalg.solve(Q, [G, Hh, Ii])
        k = 1.0 + o_n @ Q @ o_n
        U = np.linalg.cholesky(Q / k).T
    except np.linalg.LinAlgError:
        return None
    if not (k > 0 and np.all(np.isfinite(U))):
        return None
    return c + span * o_n, U / span


def fit_sphere(v: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre c and one radius r: |v|^2 = 2 c.v + (r^2 - |c|^2), linear in (c, k). Four
    parameters stay well conditioned when gravity has not been seen on every face."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    if len(v) < 5:
        return None
    H = np.hstack([2 * v, np.ones((len(v), 1))])
    sol, *_ = np.linalg.lstsq(H, np.sum(v * v, axis=1), rcond=None)
    c, k = sol[:3], sol[3]
    r2 = k + c @ c
    if not r2 > 0:
        return None
    return c, np.eye(3) / np.sqrt(r2)


def initial_params(model: SensorModel, v: np.ndarray,
                   sphere: bool = False) -> tuple[SensorModel, np.ndarray] | None:
    """Model with s0 set from the fit, and p from the ellipsoid (other effects at nominal).

    sphere=True fits only offsets and one common scale (for partial orientation coverage)."""
    fit = fit_sphere(v) if sphere else fit_ellipsoid(v, full=model.has("cross_axis"))
    if fit is None:
        return None
    o, U = fit
    s = 1.0 / np.diag(U)
    if np.any(s <= 0):
        return None
    fitted = SensorModel(model.effects, float(np.mean(s)), model.spreads)
    p = fitted.nominal()
    p[fitted.slice(Offset())] = o
    p[fitted.slice(Scale())] = s
    if model.has("cross_axis") and not sphere:
        M = U * s[None, :]
        p[fitted.slice(CrossAxis())] = [M[0, 1], M[0, 2], M[1, 2]]
    return fitted, p
