"""True sample times of a device file, from the times of its blocks.

Device files store a time per block (an Axivity sector of 40-120 samples, a GENEActiv page of
300, an ActiGraph second), not per sample. A reader that stamps a block's samples at the
nominal rate from the block's time (actfast does) leaves a jump at every block boundary,
because the device's real rate is off the nominal one (an AX3 at "100 Hz": 10 ms steps, then
21-34 ms across sectors). GGIRread and actipy instead spread each block's samples evenly
between its time and the next block's; so does this module, with two guards:

* a real gap (device off, ActiGraph idle sleep, a missing block: the next block starts much
  later than this block's samples last at the measured rate) stays a gap, and the block before
  it is stamped at the measured period, never stretched across it;
* a block that starts before the previous one's samples end at the measured period (the
  wall-clock was set back, or the stamp is wrong) continues the time axis at the measured
  period instead of going back; it is counted as a clock change.

Vectorized: one pass over the blocks, and a sample's time is its block's anchor plus its index
in the block times the block's period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BlockTimes", "block_starts", "block_times"]

#: a block whose span to the next is within these factors of its samples at the measured
#: period is continuous (interpolated); above: a gap; below: a clock set back
SPAN_LOW, SPAN_HIGH = 0.5, 1.5
#: a step between two samples that differs from the nominal period by more than this (ns)
#: starts a block (actfast's stamps in a block step by the nominal period rounded to 1 ns)
STAMP_TOLERANCE_NS = 2_000
#: samples whose steps are looked at together
CHUNK = 1 << 16


@dataclass(frozen=True)
class BlockTimes:
    """Per block: the first sample's index, the true time of that sample (ns, the file's
    clock), and the period of its samples (ns)."""

    start: np.ndarray      # (B,) int64 sample index
    anchor_ns: np.ndarray  # (B,) int64
    period_ns: np.ndarray  # (B,) float64
    measured_period_ns: float
    gaps: int
    gap_s: float
    clock_changes: int
    clock_change_s: float

    def times_ns(self, lo: int, hi: int, shift_ns: int = 0) -> np.ndarray:
        """The true times (ns) of samples lo..hi-1, less shift_ns."""
        if hi <= lo:
            return np.zeros(0, np.int64)
        # the blocks of lo..hi-1 are consecutive: each block's values repeated over its
        # samples in the range (no search per sample, no gather), worked in place; a
        # sample's index in its block as a float at once (exact: integers below 2^53)
        b0, b1 = np.searchsorted(self.start, [lo, hi - 1], side="right") - 1
        edges = np.clip(np.append(self.start[b0 + 1:b1 + 1], hi), lo, hi)
        reps = np.diff(np.append(lo, edges))
        dt = np.arange(lo, hi, dtype=np.float64)
        dt -= np.repeat(self.start[b0:b1 + 1].astype(np.float64), reps)
        dt *= np.repeat(self.period_ns[b0:b1 + 1], reps)
        t = np.rint(dt, out=dt).astype(np.int64)
        t += np.repeat(self.anchor_ns[b0:b1 + 1] - shift_ns, reps)
        return t


def block_starts(file_t_ns: np.ndarray, nominal_period_ns: float,
                 known_starts_ns: np.ndarray | None = None) -> np.ndarray:
    """Index of each block's first sample: where a table of block times (one row per block,
    e.g. actfast's low-frequency table) says a block starts, and wherever the file's stamps
    step otherwise than by the nominal period (either alone can miss one: a table row without
    samples, a block whose clock happened to match)."""
    n = len(file_t_ns)
    if n == 0:
        return np.zeros(0, np.int64)
    nominal = np.int64(round(nominal_period_ns))
    parts = [np.zeros(1, np.int64)]
    tol = STAMP_TOLERANCE_NS
    for lo in range(0, n - 1, CHUNK):  # in chunks: a week's steps never all in memory at once
        # |step - nominal| > tol as one unsigned comparison: step - (nominal - tol) outside
        # [0, 2 tol] (a negative difference wraps to a huge unsigned one)
        off = np.diff(file_t_ns[lo:lo + CHUNK + 1])
        off -= nominal - tol
        parts.append(np.flatnonzero(off.view(np.uint64) > 2 * tol).astype(np.int64) + lo + 1)
    if known_starts_ns is not None and len(known_starts_ns):
        idx = np.searchsorted(file_t_ns, np.asarray(known_starts_ns, np.int64), side="left")
        ok = idx < n
        idx = idx[ok]
        # a table time that is a sample's own stamp starts a block there
        parts.append(idx[file_t_ns[idx] == np.asarray(known_starts_ns, np.int64)[ok]])
    # two sorted runs merged (a stable sort merges runs in linear time; np.unique hashes
    # every value, several times slower at a week's half million blocks), then deduplicated
    merged = np.sort(np.concatenate(parts), kind="stable")
    return merged[np.append(True, merged[1:] != merged[:-1])]


def block_times(file_t_ns: np.ndarray, start: np.ndarray,
                nominal_period_ns: float) -> BlockTimes:
    """Each block's samples spread evenly to the next block's time where the two are
    continuous; at the measured period before a gap, at the end and after a clock change."""
    n_total = len(file_t_ns)
    t0 = file_t_ns[start].astype(np.int64)
    count = np.diff(np.append(start, n_total)).astype(np.float64)
    span = np.diff(t0).astype(np.float64)             # (B-1,)
    before = count[:-1]
    period = _measured_period(span, before, nominal_period_ns)
    expected = before * period
    continuous = (span >= SPAN_LOW * expected) & (span <= SPAN_HIGH * expected)
    gap = span > SPAN_HIGH * expected
    back = span < SPAN_LOW * expected
    # a clock set back: this block continues where the previous one's samples end
    correction = np.zeros(len(t0), np.float64)
    correction[1:][back] = expected[back] - span[back]
    anchor = t0 + np.rint(np.cumsum(correction)).astype(np.int64)
    per = np.full(len(t0), period)
    per[:-1][continuous] = span[continuous] / before[continuous]
    return BlockTimes(start.astype(np.int64), anchor, per, period, int(gap.sum()),
                      float((span[gap] - expected[gap]).sum() / 1e9), int(back.sum()),
                      float(correction.sum() / 1e9))


def _measured_period(span: np.ndarray, count: np.ndarray, nominal_period_ns: float) -> float:
    """The device's real sample period: the time of the blocks that are continuous at the
    nominal rate over their samples (a gap or a clock change left out)."""
    ok = (span >= SPAN_LOW * count * nominal_period_ns) & (
        span <= SPAN_HIGH * count * nominal_period_ns) & (count > 0)
    if not ok.any():
        return float(nominal_period_ns)
    return float(span[ok].sum() / count[ok].sum())
