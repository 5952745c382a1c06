"""Window sums of channels a device logs at a low rate (temperature, battery, light: a value a
block or a minute), as sums of their values interpolated to the samples, without a value per
sample.

A device file's batches carry such a channel interpolated to every sample (``np.interp`` of
the sample's file time between the channel's stamps: `DeviceRecording.batch`), and a window
sums those values. Between two stamps the interpolation is a line, so the sum over the
window's samples i = a..b-1 in the stretch from stamp j (time T_j, value f_j) to stamp j + 1
is, in closed form,

    sum_i f(x_i) = (b - a) f_j + s_j * sum_i (x_i - T_j),   s_j = (f_{j+1} - f_j) / (T_{j+1} - T_j),

and before the first stamp or from the last on the value is the end's (np.interp's ends).
``sum_i (x_i - T_j)`` is exact in integer nanoseconds (a prefix sum that wraps modulo 2^64:
the difference of two is exact while the true sum fits in 63 bits). The sums are those of the
per-sample values to rounding (closer to exact, as the times are not first rounded to float),
for one integer pass over the samples' times instead of one interpolation per channel.

A sample's stretch is where its time falls among the stamps, as np.interp finds it; the
stretches are cut by the samples' running maximum of time (`Stretches.of`), which is that
wherever a sample's time is its running maximum. A file's times step back now and then (a
reader stamps a block's samples at the nominal rate from the block's time, and a device
running faster than nominal starts its next block before those stamps end); the few samples
behind the running maximum (`Stretches.behind`) are then set right one by one.

Valid where the stamps rise and the values are finite (`applies`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Stretches", "applies", "window_sums"]


@dataclass(frozen=True, eq=False)
class Stretches:
    """Channels sharing stamps t_ns (m,) with values (m, k), against a recording's samples:
    first[j] = the first sample whose running maximum of file time is at or past stamp j;
    behind: the samples whose time is below their running maximum (in order)."""

    t_ns: np.ndarray
    values: np.ndarray
    first: np.ndarray
    behind: np.ndarray

    @classmethod
    def of(cls, x_ns: np.ndarray, t_ns: np.ndarray, values: np.ndarray,
           rises: np.ndarray | None = None, chunk: int = 1 << 20) -> Stretches:
        """The stretches of stamps t_ns (rising) over samples at file times x_ns. rises: the
        first sample of each block within which the times rise (a device file's blocks:
        `block_times.block_starts` cuts them wherever a step is not the nominal period),
        which makes it a pass over the blocks; None: a pass over the samples, in chunks (no
        week-long temporary)."""
        t = np.asarray(t_ns, np.int64)
        vals = np.asarray(values, np.float64).reshape(len(t), -1)
        if rises is not None:
            return cls(t, vals, *_by_blocks(x_ns, t, np.asarray(rises, np.int64)))
        first = np.full(len(t), len(x_ns), np.int64)
        behind, done, top = [], 0, np.iinfo(np.int64).min
        for lo in range(0, len(x_ns), chunk):
            x = x_ns[lo:lo + chunk]
            run = np.maximum.accumulate(np.maximum(x, top))  # the running maximum
            behind.append(np.flatnonzero(x < run) + lo)
            top = run[-1]
            reached = int(np.searchsorted(t, top, side="right"))  # stamps <= the maximum
            if reached > done:
                first[done:reached] = np.searchsorted(run, t[done:reached], side="left") + lo
                done = reached
        return cls(t, vals, first, np.concatenate(behind) if behind else np.zeros(0, np.int64))

    def at(self, j: np.ndarray, x_ns: np.ndarray) -> np.ndarray:
        """The values (len(j), k) at times x_ns of stretch j (-1 and m - 1: the ends)."""
        m = len(self.t_ns)
        out = self.values[np.clip(j, 0, m - 1)].copy()
        inner = (j >= 0) & (j < m - 1)
        ji = j[inner]
        out[inner] += self._slope(ji) * (x_ns[inner] - self.t_ns[ji]).astype(np.float64)[:, None]
        return out

    def _slope(self, j: np.ndarray) -> np.ndarray:
        return (self.values[j + 1] - self.values[j]) / (
            self.t_ns[j + 1] - self.t_ns[j]).astype(np.float64)[:, None]


def _by_blocks(x_ns: np.ndarray, t: np.ndarray, start: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """`Stretches.of`'s first and behind where the times rise within each block (from
    ``start``): the running maximum at a block's end is the largest of the block ends so far;
    in block b it is max(the one before b, x_i); so the samples behind are a prefix of a block
    that starts below the maximum before it, and stamp j's first sample is the first at or
    past t_j in the first block whose end reaches it (binary searches within blocks)."""
    n = len(x_ns)
    end = np.append(start[1:], n)
    top = np.maximum.accumulate(x_ns[end - 1])  # the running maximum at each block's end
    before = np.concatenate(([np.iinfo(np.int64).min], top[:-1]))
    low = np.flatnonzero(x_ns[start] < before)  # blocks that start behind
    upto = _first_at_or_past(x_ns, start[low], end[low], before[low])
    behind = (np.concatenate([np.arange(a, b) for a, b in zip(start[low], upto, strict=True)])
              if len(low) else np.zeros(0, np.int64))
    b = np.searchsorted(top, t, side="left")  # the first block whose end reaches t_j
    inside = b < len(start)
    first = np.full(len(t), n, np.int64)
    first[inside] = _first_at_or_past(x_ns, start[b[inside]], end[b[inside]], t[inside])
    return first, behind.astype(np.int64)


def _first_at_or_past(x: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                      target: np.ndarray) -> np.ndarray:
    """For each (lo, hi, target): the first i in lo..hi-1 with x[i] >= target (x rising
    there), hi if none: binary searches side by side."""
    lo, hi = lo.astype(np.int64), hi.astype(np.int64)
    while True:
        open_ = lo < hi
        if not open_.any():
            return lo
        mid = (lo + hi) // 2
        below = open_ & (x[np.minimum(mid, len(x) - 1)] < target)
        lo = np.where(below, mid + 1, lo)
        hi = np.where(open_ & ~below, mid, hi)


def applies(t_ns: np.ndarray, values: np.ndarray) -> bool:
    """Whether the closed form holds: stamps rise, at least one, finite values (a sample
    whose channel is not finite must not count, which the per-sample path sees and masks)."""
    return (len(t_ns) > 0 and bool(np.all(np.diff(t_ns) > 0))
            and bool(np.all(np.isfinite(values))))


def window_sums(s: Stretches, x_ns: np.ndarray, lo: int, p0: np.ndarray,
                n: np.ndarray) -> np.ndarray:
    """Sums (W, k) of the channels interpolated to samples p0..p0+n-1 of each window
    (indices into the recording; windows that do not overlap, each within samples
    lo..lo + len(x_ns), whose file times x_ns are given)."""
    k = s.values.shape[1]
    if not len(p0):
        return np.zeros((0, k))
    order = np.argsort(p0, kind="stable")  # pieces in order of their samples
    p0, n = np.asarray(p0, np.int64)[order], np.asarray(n, np.int64)[order]
    m, p1 = len(s.t_ns), p0 + n
    # the stretch of a sample: j with first[j] <= i < first[j+1]; -1 before the first stamp
    j0 = np.searchsorted(s.first, p0, side="right") - 1
    j1 = np.searchsorted(s.first, p1 - 1, side="right") - 1
    pieces = j1 - j0 + 1
    win = np.repeat(np.arange(len(p0)), pieces)
    start = np.concatenate(([0], np.cumsum(pieces)[:-1]))
    j = j0[win] + (np.arange(len(win)) - start[win])
    ext = np.concatenate(([p0[0]], s.first, [p1.max()]))  # stretch -1 .. m-1 bounds
    a = np.maximum(p0[win], ext[j + 1])
    b = np.minimum(p1[win], ext[j + 2])
    count = (b - a).astype(np.float64)
    f = s.values[np.clip(j, 0, m - 1)]  # the ends: constant at the first / last value
    out = count[:, None] * f
    inner = (j >= 0) & (j < m - 1)
    if inner.any():
        ji = j[inner]
        rel = _time_sums(x_ns, a[inner] - lo, b[inner] - lo) - (b - a)[inner] * s.t_ns[ji]
        out[inner] += s._slope(ji) * rel.astype(np.float64)[:, None]
    sums = np.add.reduceat(out, start, axis=0)
    _set_behind_right(s, x_ns, lo, p0, p1, sums)
    result = np.empty_like(sums)
    result[order] = sums
    return result


def _time_sums(x_ns: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum(x_ns[a:b]) of each piece (pieces in order, not overlapping), wrapping modulo 2^64
    as int64 sums do: exact once the piece's count times its stamp is taken off."""
    idx = np.empty(2 * len(a), np.int64)
    idx[0::2], idx[1::2] = a, b
    if idx[-1] == len(x_ns):
        idx = idx[:-1]  # the last piece runs to the end
    sums = np.add.reduceat(x_ns, idx)[0::2]
    sums[a == b] = 0  # reduceat gives x[a] for an empty piece
    return sums


def _set_behind_right(s: Stretches, x_ns: np.ndarray, lo: int, p0: np.ndarray,
                      p1: np.ndarray, sums: np.ndarray) -> None:
    """A sample behind the running maximum was counted in its stretch by index; where its
    time falls in another (as np.interp finds it), its value there replaces it (p0 sorted)."""
    b = s.behind[np.searchsorted(s.behind, lo):np.searchsorted(s.behind, lo + len(x_ns))]
    if not len(b):
        return
    w = np.clip(np.searchsorted(p0, b, side="right") - 1, 0, None)
    inside = (b >= p0[w]) & (b < p1[w])
    b, w = b[inside], w[inside]
    x = x_ns[b - lo]
    by_index = np.searchsorted(s.first, b, side="right") - 1
    by_time = np.searchsorted(s.t_ns, x, side="right") - 1
    moved = by_index != by_time
    if moved.any():
        fix = s.at(by_time[moved], x[moved]) - s.at(by_index[moved], x[moved])
        np.add.at(sums, w[moved], fix)
