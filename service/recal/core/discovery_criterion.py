"""The numbers discovery's held-out criterion compares (`discovery`, step 5): the relative
reduction of the held-out sum of squares with its block-bootstrap standard error, and the noise
of a window mean that what an effect explains must exceed. See docs/design.md (effect
discovery)."""

from __future__ import annotations

import numpy as np

from recal.core.discovery_data import DiscoveryData

__all__ = ["explained_mg", "noise_mg", "paired_gain"]


def paired_gain(ss_m: np.ndarray, ss_c: np.ndarray, n_boot: int,
                seed: int) -> tuple[float, float]:
    """R = 1 - SS_c / SS_m over blocks, and its standard error by resampling blocks (the same
    resamples for every comparison: a forward and a backward test of one pair agree)."""
    r = 1.0 - float(ss_c.sum()) / max(float(ss_m.sum()), 1e-300)
    idx = np.random.default_rng(seed).integers(0, len(ss_m), (n_boot, len(ss_m)))
    rb = 1.0 - ss_c[idx].sum(axis=1) / np.maximum(ss_m[idx].sum(axis=1), 1e-300)
    return r, float(np.std(rb, ddof=1))



def explained_mg(ss_small: np.ndarray, ss_big: np.ndarray, n_scored: int) -> float:
    """What the bigger model explains of the held-out error: sqrt of the fall of the mean
    square over the scored windows, mg (0 where it rose)."""
    return 1e3 * float(np.sqrt(max(float(ss_small.sum() - ss_big.sum()), 0.0)
                                / max(n_scored, 1)))


def noise_mg(data: DiscoveryData, scored: np.ndarray) -> float:
    """RMS over the scored windows of the noise of a window mean per axis (var / n of its
    samples), mg; 0 for a table, whose rows carry no noise."""
    w = data.windows
    if data.source != "windows" or not scored.any():
        return 0.0
    n2 = (w.var / np.maximum(w.n, 1))[scored] / data.s0**2
    return 1e3 * float(np.sqrt(np.mean(n2))) if np.all(np.isfinite(n2)) else 0.0
