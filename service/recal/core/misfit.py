"""What the model cannot explain, one estimate for every tool: the still windows' norm residual
beyond their noise (`excess_g2`), and how much larger the error of the calibrated *vector* can
be than that residual, which sees along gravity only (`across_factor`).

The streaming pipeline keeps it as running means (`status.RunningMisfit`); hindsight and
discover pool a finished fit's residuals over time (`residuals.MisfitProfile`). Both take the
excess from `excess_g2` and widen sigma by `across_factor` of the windows' gravity directions.

Why a factor (docs/design.md, "sigma and what the model cannot explain"). A window at gravity
direction u (unit) shows r = |a| - 1 g = u . e(u) to first order, e(u) the calibrated vector's
error there; the error across gravity is not in r. Two kinds of effect a diagonal model
(offsets, scales) lacks, and the worst ratio of |e|^2 at any orientation to the mean of r^2
over the windows' directions u_i:

* offset-like (temperature or supply on the offsets): e = o, r_i = u_i . o, so
  mean r^2 = o^T S o >= lambda_min(S) |o|^2 with S = mean u_i u_i^T:
  kappa_o = 1 / lambda_min(S) (3 on the whole sphere);
* a symmetric off-diagonal term D (cross-axis: its antisymmetric part is a rotation, which
  gravity cannot see): e = D u, r_i = u_i^T D u_i = f_i . d with d = (d_xy, d_xz, d_yz) and
  f = 2 (u_x u_y, u_x u_z, u_y u_z). The fit absorbs what its own columns (u for the offsets,
  u_k^2 for the scales) explain of f, so mean r^2 = d^T M d, M the second moment of f after
  that projection, >= lambda_min(M) |d|^2; and |D u|^2 <= lambda_max(D)^2 <= 2/3 |D|_F^2 =
  4/3 |d|^2 (D traceless: lambda_1 = -(lambda_2 + lambda_3)). kappa_c = (4/3) / lambda_min(M)
  (5 on the whole sphere, where M = 4/15 I).

kappa = max(kappa_o, kappa_c), at most ACROSS_MAX: directions that do not span (a wearer
who never lies down) bound nothing across the unseen axis; the cap is where sigma stops
growing with that ignorance.

kappa multiplies a residual, and postures near the axes leave cross-axis terms none
(f_i ~ 0): for a model without them `unseen_cross_g2` gives the floor a prior on d
(CROSS_AXIS_PRIOR_SD) leaves where the directions do not rule d out.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ACROSS_MAX", "ACROSS_SPHERE", "CHANCE_SDS", "CROSS_AXIS_PRIOR_SD", "across_factor",
           "chance", "direction_features", "direction_sums", "excess_g2", "unseen_cross_form",
           "unseen_cross_g2"]

#: Most `across_factor` gives: directions so close to one plane or axis that the residual
#: bounds nothing across it (sigma then ~10x the residual's excess).
ACROSS_MAX = 100.0
#: `across_factor` of directions covering the whole sphere evenly (module doc).
ACROSS_SPHERE = 5.0
#: Up to this many windows' worth of moments do not span: `across_factor` is ACROSS_MAX.
_FEW = 3


#: The sd of each symmetric cross-axis term (g at 1 g) a diagonal model is taken to leave
#: unmodelled (`unseen_cross_g2`). Measured, not derived: of 0.2, 0.3 and 0.4 %, 0.3 % is the
#: least that keeps sensors with +-1.5 deg of non-orthogonality within 1 % beyond 3 sigma at
#: postures that do not show it, and the most that keeps sigma within 3x of the error on a
#: sensor without it (bench/sigma_honesty.py, docs/performance.md). Datasheets' cross-axis
#: sensitivity (+-1 % ADXL335 and ADXL345, +-2 % MPU-6050) also counts the die's rotation in
#: its package, which gravity cannot see and no calibration error is; a sensor whose axes
#: are further from orthogonal needs the cross-axis model (`recal discover` finds it where
#: the postures show it).
CROSS_AXIS_PRIOR_SD = 0.003
#: How far above the noise a mean of squared residuals may lie by chance, in its sd (`chance`).
CHANCE_SDS = 3.0


def chance(count: float | np.ndarray) -> float | np.ndarray:
    """What chance allows a mean of `count` squared residuals, relative to their expected
    value: 1 + CHANCE_SDS sd, the sd of a mean of count chi-square(1) variables being
    sqrt(2 / count) (a count below 1 allows anything)."""
    return 1.0 + CHANCE_SDS * np.sqrt(2.0 / np.maximum(np.asarray(count, np.float64), 1e-12))


def excess_g2(mean_r2_g2: float | np.ndarray, mean_noise2_g2: float | np.ndarray,
              chance: float = 1.0) -> float | np.ndarray:
    """The residual's mean square beyond `chance` x what the noise explains (g^2), never below
    0: the reduced chi-square beyond chance, as a variance (0 where the model fits)."""
    return np.maximum(np.asarray(mean_r2_g2) - chance * np.asarray(mean_noise2_g2), 0.0)


def direction_features(a: np.ndarray) -> np.ndarray:
    """(M, 9) per row of a (M, 3) (calibrated window means), of its unit direction u: u (3),
    u_k^2 (3), 2 (u_x u_y, u_x u_z, u_y u_z); their outer products summed over windows are
    what `across_factor` reads (`direction_sums`, or binned in time by the caller)."""
    a = np.asarray(a, np.float64).reshape(-1, 3)
    n = np.linalg.norm(a, axis=1, keepdims=True)
    x, y, z = (a / np.where(n > 0, n, 1.0)).T
    return np.stack([x, y, z, x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z], axis=1)


def direction_sums(a: np.ndarray) -> np.ndarray:
    """The sum over rows of a (M, 3) of their `direction_features`' outer products (9, 9)."""
    f = direction_features(a)
    return f.T @ f


def across_factor(moments: np.ndarray, count: np.ndarray | float | None = None
                  ) -> np.ndarray | float:
    """kappa (module doc) of mean direction moments (..., 9, 9), or of their sums over `count`
    windows (`direction_sums`); ACROSS_MAX where fewer than 3 windows."""
    g = np.asarray(moments, np.float64)
    if count is not None:
        c = np.asarray(count, np.float64)
        g = g / np.maximum(c, 1.0)[..., None, None]
    s = g[..., :3, :3]
    m = _cross_moment(g)
    lam_o = np.linalg.eigvalsh(s)[..., 0]
    lam_c = np.linalg.eigvalsh(0.5 * (m + np.swapaxes(m, -1, -2)))[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.maximum(1.0 / np.maximum(lam_o, 0.0), (4.0 / 3.0) / np.maximum(lam_c, 0.0))
    k = np.where(np.isfinite(k), np.minimum(k, ACROSS_MAX), ACROSS_MAX)
    if count is not None:
        k = np.where(np.asarray(count) < _FEW, ACROSS_MAX, k)
    return float(k) if np.ndim(k) == 0 else k


def _cross_moment(g: np.ndarray) -> np.ndarray:
    """M (..., 3, 3): the second moment of the cross-axis features f after projecting out what
    the diagonal model's own columns (u, u_k^2) explain of them (module doc), from mean
    direction moments g (..., 9, 9)."""
    a_aa, a_af, a_ff = g[..., :6, :6], g[..., :6, 6:], g[..., 6:, 6:]
    left = np.swapaxes(a_af, -1, -2) @ np.linalg.pinv(a_aa, rcond=1e-10, hermitian=True)
    return a_ff - left @ a_af  # the order of the products as before (the same bits)


def unseen_cross_g2(moments: np.ndarray, count: float, detect_g2: float,
                    prior_sd_g: float = CROSS_AXIS_PRIOR_SD) -> float:
    """What a diagonal model's error across gravity may hide from the residual (g^2): the
    vector error variance of symmetric cross-axis terms d (module doc) that a prior gives
    (sd prior_sd_g each, `CROSS_AXIS_PRIOR_SD`) and the windows' directions do not rule out.

    A residual within detect_g2 of the noise (what the misfit does not count) says
    d^T M d <= detect_g2; taken as a Gaussian observation of M^(1/2) d with that variance, d's
    covariance is P = (I / prior_sd^2 + M / detect_g2)^-1: the prior's where the directions
    do not span the cross-axis features (postures near the axes), shrinking as they do. The
    error D u at any orientation has |D u|^2 = |B(u) d|^2, B(u) linear in u with
    trace(B^T B) = 2 and |B(u) e|^2 <= 4/3 for a unit e; so its mean square is at most
    min(2 lambda_max(P), 4/3 trace(P)): 2 prior_sd^2 where nothing is seen. Moments: the sums
    over `count` windows of `direction_features`' outer products (`direction_sums`)."""
    p = _unseen_cov(moments, count, detect_g2, prior_sd_g)
    p_eig = np.linalg.eigvalsh(p)  # P's eigenvalues
    return float(min(2.0 * p_eig.max(), 4.0 / 3.0 * p_eig.sum()))


def _unseen_cov(moments: np.ndarray, count: float, detect_g2: float,
                prior_sd_g: float) -> np.ndarray:
    """P (3, 3), the covariance of the symmetric cross-axis terms d the prior and the windows'
    directions leave (`unseen_cross_g2`); the prior's where the directions tell nothing."""
    prior = np.eye(3) * prior_sd_g ** 2
    if count < _FEW or not (detect_g2 > 0.0 and prior_sd_g > 0.0):
        return prior
    g = np.asarray(moments, np.float64) / float(count)
    m = _cross_moment(g)
    info = np.eye(3) / prior_sd_g ** 2 + 0.5 * (m + m.T) / detect_g2
    lam, vec = np.linalg.eigh(info)
    if not np.all(np.isfinite(lam)) or lam[0] <= 0.0:
        return prior
    return (vec / lam) @ vec.T


def unseen_cross_form(moments: np.ndarray, count: float, detect_g2: float,
                      prior_sd_g: float = CROSS_AXIS_PRIOR_SD) -> np.ndarray:
    """W (3, 3) with E|D a|^2 = a^T W a (g^2) for a calibrated vector a (g): the expected
    squared error the unseen symmetric cross-axis terms d (covariance P, `unseen_cross_g2`)
    cause at that very vector, where `unseen_cross_g2` bounds it over every orientation.
    D a = B(a) d with B(a) = [[a_y, a_z, 0], [a_x, 0, a_z], [0, a_x, a_y]] (d = (d_xy, d_xz,
    d_yz)), so E|D a|^2 = trace(P B^T B), a quadratic form in a: an upright wearer's samples
    (a ~ z) carry only d_xz and d_yz's share, however little the postures showed d_xy."""
    p = _unseen_cov(moments, count, detect_g2, prior_sd_g)
    return np.array([[p[0, 0] + p[1, 1], p[1, 2], p[0, 2]],
                     [p[1, 2], p[0, 0] + p[2, 2], p[0, 1]],
                     [p[0, 2], p[0, 1], p[1, 1] + p[2, 2]]])
