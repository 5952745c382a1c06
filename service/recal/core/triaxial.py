"""Row-wise reductions of triaxial (N,3) arrays, and per-axis arithmetic, one column at a time.

These run on every sample of a batch, and numpy reduces `axis=1` of an (N,3) array, or
broadcasts one value per axis (3,) over it, with a loop per row of 3 that costs several times
as much as three column operations (docs/design.md, "Figures behind choices"). The sums are
added in the same order as numpy's (x + y) + z, so the results are bit-identical to
`np.linalg.norm(v, axis=1)` and `np.add.reduce(v * v, axis=1)`; the per-axis forms do the
same operations on the same numbers. See docs/design.md ("Smaller decisions").
"""

from __future__ import annotations

import numpy as np

__all__ = ["all3", "any3", "norm3", "per_axis", "per_row", "sum_sq3"]

#: Below this many rows the one broadcast call is cheaper than three column calls.
_PER_AXIS_MIN_ROWS = 256


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


def per_axis(op: np.ufunc, x: np.ndarray, theta: np.ndarray,
             out: np.ndarray | None = None) -> np.ndarray:
    """op(x, theta) for x (N,3) and one value per axis theta (3,), bit-identical; into
    ``out`` if given (which may be x itself)."""
    if len(x) < _PER_AXIS_MIN_ROWS or x.ndim != 2 or np.ndim(theta) != 1:
        return op(x, theta, out=out)
    if out is None:
        out = np.empty(x.shape, np.result_type(x, theta))
    for j in range(3):
        op(x[:, j], theta[j], out=out[:, j])
    return out


def per_row(op: np.ufunc, x: np.ndarray, w: np.ndarray,
            out: np.ndarray | None = None) -> np.ndarray:
    """op(x, w[:, None]) for x (N,3) and one value per row w (N,), bit-identical; into
    ``out`` if given (which may be x itself)."""
    if len(x) < _PER_AXIS_MIN_ROWS or x.ndim != 2:
        return op(x, w[:, None], out=out)
    if out is None:
        out = np.empty(x.shape, np.result_type(x, w))
    for j in range(3):
        op(x[:, j], w, out=out[:, j])
    return out
