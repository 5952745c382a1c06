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
from recal.core.model import SensorModel
from recal.core.model_fit import free_params

__all__ = [
    "ORIENTATION_FEATURES",
    "ResidualAnalysis",
    "explained_fraction",
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
