"""Butterworth filters as cascaded second-order sections: design, steady state, filtering.

The detector's filters (Lötters eq. 2) need three things that ``scipy.signal`` offers
(``butter(..., output="sos")``, ``sosfilt_zi`` and ``sosfilt``), but importing ``scipy.signal``
costs a daemon about 75 MB of memory and about 1 s of start-up, for a few lines of arithmetic.
They are written here instead (docs/design.md, "The detector's filters"):

* `butter_sos`: the digital Butterworth low- or high-pass by the bilinear transform with the
  corner pre-warped, ``w_c = 2 f_s tan(pi f_c / f_s)``, as ``scipy.signal.butter`` designs it
  (the same response to about 1e-13). One section per conjugate pole pair of the analog
  prototype ``p_k = exp(i pi (2k + n + 1) / 2n)``, plus a first-order one for an odd order; each
  section scaled to unit gain in the pass band (z = 1 for a low-pass, z = -1 for a high-pass).
* `sos_zi`: the sections' state for a steady unit input, as ``scipy.signal.sosfilt_zi``.
* `sosfilt`: direct form II transposed, section by section, the state carried in and out
  like ``scipy.signal.sosfilt``'s ``zi``. A short batch (a live sensor's one sample per arrival)
  runs a scalar loop on Python floats, whose cost is a few hundred nanoseconds per sample and
  section, where an array call costs tens of microseconds; a long one (replay, a backlog) runs
  ``scipy.signal.sosfilt``, imported on first use. Both do the same operations in the same
  order, so on a machine whose compiled kernel does not fuse multiply-adds the two give the
  same bits (tests/test_sos_filter.py checks it on the machine it runs on).

Rows of a ``sos`` array are ``[b0, b1, b2, a0, a1, a2]`` with ``a0 = 1``, as in scipy.
"""

from __future__ import annotations

import cmath
import math

import numpy as np

__all__ = ["SCALAR_MAX_N", "butter_sos", "sos_rows", "sos_zi", "sosfilt", "sosfilt_one"]

#: Batches up to this many samples are filtered by the scalar loop; longer ones by scipy's
#: compiled kernel (about 1 ms of scalar loop per section at this length on this machine:
#: docs/design.md, "Figures behind choices").
SCALAR_MAX_N = 1024


def butter_sos(order: int, cutoff_hz: float, rate_hz: float, highpass: bool) -> np.ndarray:
    """A digital Butterworth filter of ``order`` at ``cutoff_hz`` as second-order sections."""
    if order < 1 or not 0.0 < cutoff_hz < rate_hz / 2.0:
        raise ValueError(f"Butterworth order {order} at {cutoff_hz} Hz needs order >= 1 and "
                         f"0 < cutoff < {rate_hz / 2.0} Hz (half of {rate_hz} Hz)")
    fs2 = 2.0 * rate_hz
    wc = fs2 * math.tan(math.pi * cutoff_hz / rate_hz)
    zero = 1.0 if highpass else -1.0  # the analog zeros (0 or infinity) land here
    rows = []
    for k in range(order // 2):
        p = cmath.exp(1j * math.pi * (2 * k + order + 1) / (2 * order))
        z = _bilinear(wc / p if highpass else wc * p, fs2)
        rows.append(_unit_gain([1.0, -2.0 * zero, 1.0], [1.0, -2.0 * z.real, abs(z) ** 2],
                               highpass))
    if order % 2:
        z = _bilinear(complex(-wc), fs2).real
        rows.append(_unit_gain([1.0, -zero, 0.0], [1.0, -z, 0.0], highpass))
    return np.array(rows)


def _bilinear(s: complex, fs2: float) -> complex:
    return (fs2 + s) / (fs2 - s)


def _unit_gain(b: list[float], a: list[float], highpass: bool) -> list[float]:
    """The section [b, a] with b scaled to gain 1 at the pass band's edge of the unit circle."""
    sign = -1.0 if highpass else 1.0
    gain = (b[0] + sign * b[1] + b[2]) / (a[0] + sign * a[1] + a[2])
    return [bi / gain for bi in b] + a


def sos_zi(sos: np.ndarray) -> np.ndarray:
    """The state (n_sections, 2) in which the cascade's output is steady for a unit input.

    For one section in direct form II transposed with steady input x and output y = g x,
    g = sum(b) / sum(a): z1 = b2 x - a2 y and z0 = y - b0 x; the next section sees g x.
    """
    zi = np.empty((len(sos), 2))
    scale = 1.0
    for s, (b0, b1, b2, a0, a1, a2) in enumerate(np.asarray(sos, np.float64).tolist()):
        g = (b0 + b1 + b2) / (a0 + a1 + a2)
        zi[s] = scale * ((b1 + b2) - (a1 + a2) * g), scale * (b2 - a2 * g)
        scale *= g
    return zi


def sosfilt(sos: np.ndarray, x: np.ndarray, zi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Filter 1-D ``x`` through the sections from state ``zi``; returns (y, final state)."""
    x = np.asarray(x, np.float64).reshape(-1)
    if len(x) > SCALAR_MAX_N:
        from scipy.signal import sosfilt as compiled  # a long batch: worth scipy's import

        return compiled(sos, x, zi=np.asarray(zi, np.float64))
    return _scalar(sos, x, zi)


def _scalar(sos: np.ndarray, x: np.ndarray, zi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Direct form II transposed on Python floats, in scipy's kernel's order of operations."""
    z = np.asarray(zi, np.float64).tolist()
    y = x.tolist()
    for s, (b0, b1, b2, _a0, a1, a2) in enumerate(np.asarray(sos, np.float64).tolist()):
        z0, z1 = z[s]
        for n, xn in enumerate(y):
            yn = b0 * xn + z0
            z0 = b1 * xn - a1 * yn + z1
            z1 = b2 * xn - a2 * yn
            y[n] = yn
        z[s] = [z0, z1]
    return np.array(y), np.array(z)


def sos_rows(sos: np.ndarray) -> tuple[tuple[float, ...], ...]:
    """The sections as Python floats, for `sosfilt_one` (make it once per design)."""
    return tuple(tuple(row) for row in np.asarray(sos, np.float64).tolist())


def sosfilt_one(rows: tuple[tuple[float, ...], ...], x: float, zi: list[list[float]]
                ) -> tuple[float, list[list[float]]]:
    """`sosfilt` of one sample on Python floats (``rows``: `sos_rows`; ``zi`` as nested lists):
    (y, final state), the operations of `_scalar` in its order, so the same bits."""
    z = []
    for (b0, b1, b2, _a0, a1, a2), (z0, z1) in zip(rows, zi, strict=True):
        y = b0 * x + z0
        z.append([b1 * x - a1 * y + z1, b2 * x - a2 * y])
        x = y
    return x, z
