"""What a fit leaves: xi = |a| - 1 g per window (Lötters 1998, eq. 14, sign flipped) and what
it goes with (channels, time, gravity direction), and how much of it each candidate effect's
Jacobian columns explain (a score test). See docs/design.md (effect discovery).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from recal.core.discovery_data import DiscoveryData
from recal.core.effects import TIME, Effect
from recal.core.misfit import ACROSS_MAX, across_factor, chance, direction_features, excess_g2
from recal.core.model import SensorModel
from recal.core.model_fit import free_params

__all__ = [
    "LOCAL_SPAN_S",
    "ORIENTATION_FEATURES",
    "POOR_CHI2",
    "POOR_MIN_G",
    "MisfitProfile",
    "ResidualAnalysis",
    "explained_fraction",
    "misfit",
    "orientation_features",
    "residual_analysis",
]

ORIENTATION_FEATURES = ("x", "y", "z", "xx", "yy", "zz", "xy", "xz", "yz")


def _pearson(x: np.ndarray, y: np.ndarray) -> float:
    """Correlation coefficient; NaN when either does not vary (nothing to correlate)."""
    x = x - x.mean()
    y = y - y.mean()
    den = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y) / den if den > 1e-300 else float("nan")


@dataclass(frozen=True)
class ResidualAnalysis:
    """What is left after a fit: xi = |a| - 1 g per window and what it goes with.

    Attributes:
        rms_mg: RMS of xi over the windows (in-sample), mg.
        correlation: Pearson r of xi with each channel and with "time" (NaN: constant).
        orientation: Pearson r of xi with the gravity direction u: "x" = u_x (an offset's
            signature), "xx" = u_x^2 (a gain's), "xy" = u_x u_y (cross-axis), ...
        explained: per candidate label, the fraction of xi's variance its Jacobian columns
            explain beyond the model's own (a score test: what the residual looks like).
    """

    rms_mg: float
    correlation: dict[str, float]
    orientation: dict[str, float]
    explained: dict[str, float] = field(default_factory=dict)


def orientation_features(a: np.ndarray) -> np.ndarray:
    """Per row of a (M,3): u_x, u_y, u_z, u_x², u_y², u_z², u_x u_y, u_x u_z, u_y u_z of the
    unit gravity direction (the columns named by ORIENTATION_FEATURES)."""
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    x, y, z = u.T
    return np.stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], axis=1)


def explained_fraction(model: SensorModel, p: np.ndarray, data: DiscoveryData,
                       xi: np.ndarray, effect: Effect, spread: float) -> float:
    """Fraction of xi's variance in the span of the candidate's Jacobian columns, after
    removing what the model's own columns already span (Lötters eq. 13a at nominal)."""
    ext, q = model.extend(p, effect, spread)
    _, B = ext.residual_jacobian(q, data.windows.v, data.cov)
    free = free_params(ext, q, data)  # fixed columns would fit noise (see free_params)
    own = np.ones(ext.size, bool)
    own[ext.slice(effect)] = False
    Bo, Bc = B[:, own & free], B[:, ~own & free]
    if Bc.shape[1] == 0:
        return 0.0
    Bc = Bc - Bo @ np.linalg.lstsq(Bo, Bc, rcond=1e-10)[0]
    r = xi - xi.mean()
    fitted = Bc @ np.linalg.lstsq(Bc, r, rcond=1e-10)[0]
    den = float(r @ r)
    return float(fitted @ fitted) / den if den > 0 else 0.0


def residual_analysis(model: SensorModel, p: np.ndarray, data: DiscoveryData,
                      cands: list[tuple[Effect, float]] | None = None) -> ResidualAnalysis:
    """xi after the fit and its correlation with channels, time, orientation, candidates."""
    a = model.correct(p, data.windows.v, data.cov)
    xi = np.linalg.norm(a, axis=1) - 1.0
    corr = {name: _pearson(xi, data.cov.get(name)) for name in data.aux_names}
    if data.has_time:
        corr[TIME] = _pearson(xi, data.cov.t_h)
    feats = orientation_features(a)
    orient = {n: _pearson(xi, feats[:, i]) for i, n in enumerate(ORIENTATION_FEATURES)}
    expl = {e.label: explained_fraction(model, p, data, xi, e, sp) for e, sp in (cands or [])}
    return ResidualAnalysis(1e3 * float(np.sqrt(np.mean(xi**2))), corr, orient, expl)


#: Half-width of the time span over which `misfit` pools the residual around each window: a
#: few postures (20-180 s each), short enough to follow a temperature or a supply that moves
#: over tens of minutes.
LOCAL_SPAN_S = 300.0
#: Reduced chi-square beyond which a fit's residual is well above the noise (`MisfitProfile`): the
#: residual twice the noise. A model that fits stays near 1 (1.3 on a simulated wearer:
#: sway the windows' variance underrates).
POOR_CHI2 = 4.0
#: ... and an excess at least this (g): a sensor whose noise is a fraction of a mg is not
#: called poorly fitted for a residual nobody would see.
POOR_MIN_G = 0.0005


@dataclass(frozen=True, eq=False)
class MisfitProfile:
    """What a finished fit leaves beyond the sensor noise, around each window in time (the
    streaming pipeline's running form of the same estimate: `status.RunningMisfit`; both
    from `core.misfit`).

    xi = |a| - 1 g of a window mean holds the noise left in the mean (var / n of its samples,
    along gravity) and whatever the model cannot explain there. Pooled over the windows
    within LOCAL_SPAN_S of each: excess_g = sqrt(`misfit.excess_g2`(mean xi^2, mean
    noise^2, `misfit.chance` of their count)), the residual the noise and chance do not
    account for (0 where the model fits);
    overall_g the same over all windows, and chi2 = mean xi^2 / mean noise^2 over all windows
    (the reduced chi-square, ~1 where the model fits). The error of the calibrated vector
    that misfit implies is larger (it errs across gravity too, unseen): `misfit.across_factor`
    of the same windows' directions, across (local) and across_all (all windows).

    Attributes:
        t_us: window mid times, sorted.
        excess_g: the local excess at each (g, along gravity).
        noise_g: RMS noise of the window means (g, along gravity), all windows.
        chi2: reduced chi-square of the fit over all windows.
        overall_g: the excess over all windows (g).
        across: kappa of the windows within LOCAL_SPAN_S of each (None: directions not given,
            `misfit.ACROSS_MAX` then).
        across_all: kappa of all windows.
    """

    t_us: np.ndarray
    excess_g: np.ndarray
    noise_g: float
    chi2: float
    overall_g: float = 0.0
    across: np.ndarray | None = None
    across_all: float = ACROSS_MAX

    def at(self, t_us: np.ndarray) -> np.ndarray:
        """The local excess (g) at sample times t_us: linear between windows, the nearest
        window's beyond the first and last."""
        return self._interp(t_us, self.excess_g)

    def vector_var_g2(self, t_us: np.ndarray) -> np.ndarray:
        """The variance (g^2) the misfit adds to the calibrated vector's error at sample times
        t_us: kappa x excess^2, locally, or over the whole recording where that is larger (an
        effect whose error lies across gravity shows in the norm only at some postures: the
        minutes around a sample may not see it)."""
        local = self._interp(t_us, self.excess_g ** 2 * (
            self.across if self.across is not None else ACROSS_MAX))
        return np.maximum(local, self.across_all * self.overall_g ** 2)

    def _interp(self, t_us: np.ndarray, y: np.ndarray) -> np.ndarray:
        if not len(self.t_us):
            return np.zeros(len(t_us))
        return np.interp(np.asarray(t_us, np.float64), self.t_us.astype(np.float64), y)

    @property
    def well_above_noise(self) -> bool:
        """The residual is well above the noise (chi2 beyond POOR_CHI2, the residual twice
        the noise, and the excess beyond POOR_MIN_G): the model lacks an effect."""
        return self.chi2 > POOR_CHI2 and self.overall_g > POOR_MIN_G

    @property
    def max_excess_g(self) -> float:
        return float(self.excess_g.max()) if len(self.excess_g) else 0.0


def misfit(xi_g: np.ndarray, noise_var_g2: np.ndarray, t_us: np.ndarray,
           span_s: float = LOCAL_SPAN_S, a: np.ndarray | None = None) -> MisfitProfile:
    """`MisfitProfile` of residuals xi_g (M,) of windows at t_us whose means carry noise
    variance noise_var_g2 (M,) along gravity; a (M, 3): the windows' calibrated means (their
    directions give `misfit.across_factor`; None: ACROSS_MAX)."""
    order = np.argsort(t_us, kind="stable")
    t = np.asarray(t_us, np.int64)[order]
    x2 = np.asarray(xi_g, np.float64)[order] ** 2
    n2 = np.asarray(noise_var_g2, np.float64)[order]
    if not len(t):
        return MisfitProfile(t, np.zeros(0), 0.0, 1.0, 0.0)
    span = round(span_s * 1e6)
    lo = np.searchsorted(t, t - span, side="left")
    hi = np.searchsorted(t, t + span, side="right")
    cx, cn = np.concatenate(([0.0], np.cumsum(x2))), np.concatenate(([0.0], np.cumsum(n2)))
    k = hi - lo
    # beyond what chance allows a mean of k squares (`misfit.chance`): pure noise leaves 0
    excess2 = excess_g2((cx[hi] - cx[lo]) / k, (cn[hi] - cn[lo]) / k, chance(k))
    noise2 = float(np.mean(n2))
    chi2 = float(np.mean(x2)) / noise2 if noise2 > 0 else float("inf")
    overall = math.sqrt(float(excess_g2(float(np.mean(x2)), noise2, chance(len(t)))))
    across, across_all = None, ACROSS_MAX
    if a is not None:
        across, across_all = _across(np.asarray(a, np.float64)[order], t, span_s)
    return MisfitProfile(t, np.sqrt(excess2), math.sqrt(noise2), chi2, overall, across,
                         across_all)


#: `misfit` pools the directions in bins of this much time (the span rounded to them): the
#: memory is per bin, not per window (a week's recording: 10 080 bins of 81 numbers).
ACROSS_BIN_S = 60.0


def _across(a: np.ndarray, t_us: np.ndarray, span_s: float) -> tuple[np.ndarray, float]:
    """kappa (`misfit.across_factor`) of the windows within span_s of each (a: their
    calibrated means, t_us sorted), pooled by ACROSS_BIN_S bins, and of all windows."""
    f = direction_features(a)
    b = ((t_us - t_us[0]) // round(ACROSS_BIN_S * 1e6)).astype(np.int64)
    nb = int(b[-1]) + 1
    sums = np.empty((nb + 1, 9, 9))
    sums[0] = 0.0
    for i in range(9):  # 45 products, each binned: no (windows, 9, 9) array
        for j in range(i, 9):
            sums[1:, i, j] = sums[1:, j, i] = np.cumsum(np.bincount(b, f[:, i] * f[:, j], nb))
    count = np.concatenate(([0], np.cumsum(np.bincount(b, minlength=nb))))
    s = math.ceil(span_s / ACROSS_BIN_S)
    lo = np.clip(np.arange(nb) - s, 0, nb)
    hi = np.clip(np.arange(nb) + s + 1, 0, nb)
    per_bin = np.asarray(across_factor(sums[hi] - sums[lo], count[hi] - count[lo]))
    return per_bin[b], float(across_factor(sums[-1], len(a)))
