"""Row-wise reductions of triaxial (N,3) arrays, one column at a time.

numpy reduces `axis=1` of an (N,3) array with a generic strided loop that costs 3-5x as much
as three column operations (100 000 rows: `np.linalg.norm(v, axis=1)` 2.0 ms against 0.55 ms;
`np.isfinite(v).all(axis=1)` 1.8 ms against 0.35 ms). These run on every sample of a batch.
The sums are added in the same order as numpy's (x + y) + z, so the results are bit-identical
to `np.linalg.norm(v, axis=1)` and `np.add.reduce(v * v, axis=1)`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["all3", "any3", "norm3", "sum_sq3"]


def sum_sq3(v: np.ndarray) -> np.ndarray:
    """|v|^2 of each row of v (N,3)."""
    x = v * v
    s = x[:, 0] + x[:, 1]
    s += x[:, 2]
    return s


def norm3(v: np.ndarray) -> np.ndarray:
    """|v| of each row of v (N,3), bit-identical to np.linalg.norm(v, axis=1)."""
    s = sum_sq3(v)
    return np.sqrt(s, out=s)


def all3(m: np.ndarray) -> np.ndarray:
    """m.all(axis=1) for a boolean (N,3) array."""
    out = m[:, 0] & m[:, 1]
    out &= m[:, 2]
    return out


def any3(m: np.ndarray) -> np.ndarray:
    """m.any(axis=1) for a boolean (N,3) array."""
    out = m[:, 0] | m[:, 1]
    out |= m[:, 2]
    return out
