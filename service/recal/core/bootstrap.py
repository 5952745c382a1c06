"""Start from nothing: a batch ellipsoid fit for a sensor with no prior (unknown scale).

Still readings v lie on the ellipsoid (v - o)^T Q (v - o) = 1 (Lötters fig. 4b; Bragge eq. 1
with |a| = 1 g). Its algebraic fit is linear in the quadric's coefficients:

    A x^2 + B y^2 + C z^2 + 2D xy + 2E xz + 2F yz + 2G x + 2H y + 2I z = 1

From Q, o = -Q^-1 (G, H, I), and the Cholesky factor Q = U^T U with U upper-triangular gives the
correction a = U (v - o) in the same rotation gauge as `effects.CrossAxis`: s_i = 1 / U_ii and
M = U diag(s). The diagonal model fits the axis-aligned ellipsoid (D = E = F = 0).

Before any of that, a sensor with no prior has no zero-g and no scale: an analog part on an
unsigned 12-bit ADC reads ~2048 counts at 0 g and ~372 counts per g, a phone ~9.8 m/s^2 per g,
a digital part 0 at 0 g and 256 to 16 384 counts per g. `locate` finds both from the still
window means alone (a robust sphere fit), and says whether they are pinned down: orientation
coverage is judged on the centred readings (v - centre), never on the raw ones, which for an
unsigned part all lie in one octant. See docs/design.md ("Any accelerometer: zero-g and scale
from the data").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recal.core.buffer import cell_of
from recal.core.effects import Covariates, CrossAxis, Offset, Scale
from recal.core.model import SensorModel

__all__ = ["LOCATE_MIN_WINDOWS", "Located", "fit_ellipsoid", "fit_poses", "fit_sphere",
           "initial_params", "locate", "off_by", "reach", "still_poses", "zero_and_scale"]

#: Window means further than this from the sphere (relative: 50 mg) are not still poses.
LOCATE_OUTLIER_G = 0.05
#: A sphere whose inliers are further than this from it (relative RMS) is none: the noise of
#: one still pose fits a tiny sphere around itself at ~0.42 (the chi distribution with 3
#: degrees of freedom), while a whole recording of a ratiometric part whose zero-g follows a
#: sagging supply is still a usable first guess at ~0.1.
LOCATE_MAX_RESIDUAL_G = 0.2
#: Fewest window means `locate` fits a sphere to: four unknowns, and two to judge it by (a lab's
#: six positions).
LOCATE_MIN_WINDOWS = 6
#: Passes of `locate`'s fit, each dropping the windows the one before put off the sphere.
LOCATE_PASSES = 6
#: Half-axes the centred directions must reach beyond COVERAGE_LEVEL_G for a fit to stand
#: (five of six: lying face down may never happen).
LOCATE_HALF_AXES = 5
COVERAGE_LEVEL_G = 0.3
#: A window whose raw samples spread more than this (sd per axis, in g) turned while it was
#: taken: the detector sees the norm (Lötters eq. 1), and a turn keeps the norm at 1 g, so a
#: stream cut together from single-pose recordings passes it whole. Still, the spread is the
#: sensor noise (a few mg; above ~20 mg the detector rejects the samples), while a window
#: that spans two poses 90 degrees apart spreads sqrt(2 f (1 - f) / 3) g for a fraction f in
#: the second: 50 mg already at f = 0.4 %, a norm ~4 mg short.
TURN_SD_G = 0.05
#: Passes of `fit_poses`, each dropping the windows the fit before put off its ellipsoid.
FIT_PASSES = 4


@dataclass(frozen=True, eq=False)
class Located:
    """Zero-g and scale found from still window means (`locate`).

    Attributes:
        centre: the reading at 0 g, raw units (3,).
        scale: raw units per g (the sphere's radius).
        inliers: the windows on the sphere (within LOCATE_OUTLIER_G), a mask over the input.
        half_axes: half-axes the centred inliers reach beyond COVERAGE_LEVEL_G.
        cells: cube-face grid cells (`buffer.cell_of`) the centred inliers fill.
        residual_g: RMS of |v - centre| / scale - 1 over the inliers.
    """

    centre: np.ndarray
    scale: float
    inliers: np.ndarray
    half_axes: int
    cells: int
    residual_g: float

    def covers(self, half_axes: int = LOCATE_HALF_AXES, cells: int = 1) -> bool:
        return self.half_axes >= half_axes and self.cells >= cells


def locate(v: np.ndarray, grid: int = 6) -> Located | None:
    """Zero-g and scale of still window means v (M,3) in any raw unit: a sphere fit
    (`fit_sphere`) repeated without the windows off it (movement a detector with a wrong scale
    let through: their means are short of or beyond 1 g), judged by how the centred inliers
    cover the orientations. None: too few windows, or no sphere through them (inliers further
    than LOCATE_MAX_RESIDUAL_G from it, RMS)."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    v = v[np.all(np.isfinite(v), axis=1)]
    keep = np.ones(len(v), bool)
    fit = None
    for _ in range(LOCATE_PASSES):
        if keep.sum() < LOCATE_MIN_WINDOWS:
            return None
        fit = fit_sphere(v[keep])
        if fit is None:
            return None
        c, r = fit[0], 1.0 / float(fit[1][0, 0])
        dev = np.abs(np.linalg.norm(v - c, axis=1) / r - 1.0)
        # a robust cut first (the fit may lean on movement), then the physical one
        cut = max(LOCATE_OUTLIER_G, 3.0 * float(np.median(dev[keep])))
        new = dev <= cut
        if np.array_equal(new, keep):
            break
        keep = new
    if fit is None or keep.sum() < LOCATE_MIN_WINDOWS:
        return None
    residual = float(np.sqrt(np.mean(dev[keep] ** 2)))
    if residual > LOCATE_MAX_RESIDUAL_G:  # no sphere: one pose's noise around a tiny one
        return None
    half, cells = reach(v[keep] - c, grid)
    return Located(c, r, keep, half, cells, residual)


def reach(a: np.ndarray, grid: int = 6) -> tuple[int, int]:
    """Half-axes the directions of a (M,3, centred) reach beyond COVERAGE_LEVEL_G, and the
    cube-face grid cells (`buffer.cell_of`) they fill."""
    u = np.asarray(a, np.float64).reshape(-1, 3)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    half = int((u > COVERAGE_LEVEL_G).any(axis=0).sum() + (u < -COVERAGE_LEVEL_G).any(axis=0).sum())
    return half, len(np.unique(cell_of(u, grid)))


def off_by(centre: np.ndarray, scale: float, centre0: np.ndarray, scale0: float,
           centre_g: float = 0.25, scale_ratio: float = 1.5) -> bool:
    """Whether zero-g and scale (centre0, scale0) are materially wrong against (centre, scale):
    the centre more than centre_g apart, or the scales more than scale_ratio. Within these
    the detector works as well (its threshold then 10-22 mg for 15 mg: within the 5-30 mg
    that works, detector.DEFAULT_THRESHOLD_G) and the orientation cells differ little."""
    ratio = scale / scale0 if scale0 > 0 else np.inf
    return bool(np.linalg.norm(np.asarray(centre) - np.asarray(centre0)) > centre_g * scale
                or not 1.0 / scale_ratio <= ratio <= scale_ratio)


def fit_ellipsoid(v: np.ndarray, full: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """Fit still readings v (M,3); returns (offset o (3,), upper-triangular U (3,3)) with
    |U (v - o)| ~ 1, or None when the points do not pin down an ellipsoid."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    need = 9 if full else 6
    if len(v) < need:  # six poses determine the diagonal model exactly
        return None
    c = v.mean(axis=0)
    span = float(np.max(np.abs(v - c))) or 1.0
    x, y, z = ((v - c) / span).T  # centred and scaled: keeps the design matrix well conditioned
    cols = [x * x, y * y, z * z]
    if full:
        cols += [2 * x * y, 2 * x * z, 2 * y * z]
    cols += [2 * x, 2 * y, 2 * z]
    H = np.stack(cols, axis=1)
    coef, _, rank, _ = np.linalg.lstsq(H, np.ones(len(v)), rcond=None)
    if rank < H.shape[1]:  # the poses do not tell the coefficients apart
        return None
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

    sphere=True fits only offsets and one common scale (for partial orientation coverage). A
    model with cross-axis terms starts from the axis-aligned fit when the windows are too few
    for the full one (fewer than ten: six clean poses), its cross-axis terms at nominal."""
    full = model.has("cross_axis") and len(v) >= 10
    fit = fit_sphere(v) if sphere else fit_ellipsoid(v, full=full)
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
    if full and not sphere:
        M = U * s[None, :]
        p[fitted.slice(CrossAxis())] = [M[0, 1], M[0, 2], M[1, 2]]
    return fitted, p


def still_poses(var: np.ndarray, s0: float) -> np.ndarray:
    """Which windows (their mean per-axis variance var, raw units squared) are still poses
    for a first fit: those that did not turn while taken (TURN_SD_G)."""
    return np.asarray(var, np.float64) <= (TURN_SD_G * s0) ** 2


def fit_poses(model: SensorModel, v: np.ndarray, cov: Covariates, sphere: bool, tol_g: float
              ) -> tuple[SensorModel, np.ndarray, np.ndarray, np.ndarray] | None:
    """`initial_params` on the window means v (M,3) that agree with it (cov: the windows'
    covariates, for the model's other effects at nominal): windows whose norm
    under the fit is further than tol_g from 1 g (a pose mixed with the next, movement) are
    dropped and the rest fitted again. A fit of few poses is exactly or nearly determined, so
    one such window bends it by tenths of a g (a six-pose stream cut together gave s_z 0.75
    of the truth and o_z 0.25 g), while the windows that agree fit it to their noise.
    Returns (model, p, the windows used, every window corrected by the fit, g (M,3)) or None
    (no fit through enough of them)."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(v), axis=1)
    for _ in range(FIT_PASSES):
        fit = initial_params(model, v[keep], sphere=sphere)
        if fit is None:
            return None
        fitted, p = fit
        a = fitted.correct(p, v, cov)
        new = keep & (np.abs(np.linalg.norm(a, axis=1) - 1.0) <= tol_g)
        if np.array_equal(new, keep):
            return fitted, p, keep, a
        keep = new
    return None


def zero_and_scale(v: np.ndarray) -> tuple[np.ndarray, float]:
    """Zero-g and raw units per g of still readings v (M,3): 0 and their median norm (a signed
    sensor), unless a sphere through them (`locate`, orientations covered) shows those
    materially wrong (`off_by`: an analog part on an unsigned ADC), then its centre and
    radius. The batch tools' rule (discover, hindsight, static); the live pipeline's is the
    same, applied as the windows come (`pipeline_fit._relocate`)."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    s0 = float(np.median(np.linalg.norm(v, axis=1))) if len(v) else 1.0
    loc = locate(v) if len(v) else None
    if loc is not None and loc.covers() and off_by(loc.centre, loc.scale, np.zeros(3), s0):
        return np.asarray(loc.centre, np.float64), float(loc.scale)
    return np.zeros(3), s0
