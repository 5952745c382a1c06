"""GGIR's calibration error, batch by batch: the mean over the still 10 s windows of
| |window mean| - 1 g | (van Hees et al. 2014, "Autocalibration of accelerometer data for
free-living physical activity assessment using local gravity and temperature"; GGIR's
g.calibrate reports it before and after as ``cal.error.start`` / ``cal.error.end``).

Windows are non-overlapping 10 s on a grid from the recording's first sample; a window is still
when it holds at least 90 % of its samples and every axis's SD is under 13 mg (GGIR's
sdCriter) in the readings before calibration. Before and after are judged on the same windows.

Each batch gives its windows' sums (`batch_sums`, pure); `result` adds them up: memory grows
with the windows (a week at 10 s is 60 480) and the batches, never with the samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_FILL", "STILL_SD_G", "WINDOW_US", "StillError", "StillSums", "batch_sums", "result"]

WINDOW_US = 10_000_000  # GGIR's 10 s windows
STILL_SD_G = 0.013  # GGIR's sdCriter: every axis's SD under 13 mg
MIN_FILL = 0.9  # a window counts with at least 90 % of its samples


@dataclass(frozen=True)
class StillSums:
    """One batch's share of the windows it touches (``index``: their numbers on the grid,
    ascending; only those, so a clock that jumps ahead costs nothing for the windows it
    skips): samples, sums of the readings before (g) and of their squares (about ``ref_g``,
    the recording's first reading: no cancellation in the SD), sums of the calibrated
    readings (g)."""

    index: np.ndarray  # (w,) int64
    n: np.ndarray  # (w,)
    raw_sum: np.ndarray  # (w, 3)
    raw_sq: np.ndarray  # (w, 3)
    cal_sum: np.ndarray  # (w, 3)


@dataclass(frozen=True)
class StillError:
    """The still windows and the error in them before and after (mg; None without a still
    window)."""

    windows: int
    still: int
    before_mg: float | None
    after_mg: float | None


def batch_sums(t_us: np.ndarray, raw_g: np.ndarray, cal_g: np.ndarray, t0_us: int,
               ref_g: np.ndarray) -> StillSums:
    """One batch's sums: its times (µs), readings before (g) and after (g), on the grid from
    t0_us (the recording's first sample). Samples with a non-finite reading, or stamped
    before t0_us (a clock step back), are left out as missing."""
    index = (np.asarray(t_us, np.int64) - t0_us) // WINDOW_US
    ok = np.all(np.isfinite(raw_g), axis=1) & np.all(np.isfinite(cal_g), axis=1) & (index >= 0)
    index, raw_g, cal_g = index[ok], raw_g[ok] - ref_g, cal_g[ok]
    windows, local = np.unique(index, return_inverse=True)
    m = len(windows)

    def per_axis(v: np.ndarray) -> np.ndarray:
        return np.stack([np.bincount(local, v[:, k], minlength=m) for k in range(3)], 1)

    return StillSums(windows, np.bincount(local, minlength=m).astype(np.float64),
                     per_axis(raw_g), per_axis(raw_g**2), per_axis(cal_g))


def result(parts: list[StillSums], ref_g: np.ndarray, rate_hz: float) -> StillError:
    """The still windows (`module doc`) of a recording's batches' sums (ref_g: the origin
    they were taken about) and GGIR's error over them before and after."""
    parts = [p for p in parts if len(p.n)]
    if not parts:
        return StillError(0, 0, None, None)
    # the windows any batch touched, each batch's at their places (unique within a batch)
    _, at = np.unique(np.concatenate([p.index for p in parts]), return_inverse=True)
    size = int(at.max()) + 1
    n, raw_sum = np.zeros(size), np.zeros((size, 3))
    raw_sq, cal_sum = np.zeros((size, 3)), np.zeros((size, 3))
    for p, i in zip(parts, np.split(at, np.cumsum([len(p.n) for p in parts])[:-1]), strict=True):
        # one add per batch (a batch spans a few windows), not per sample
        n[i] += p.n
        raw_sum[i] += p.raw_sum
        raw_sq[i] += p.raw_sq
        cal_sum[i] += p.cal_sum
    windows = int(np.count_nonzero(n))
    mean_shifted = raw_sum / np.maximum(n, 1)[:, None]
    var = (raw_sq - n[:, None] * mean_shifted**2) / np.maximum(n - 1, 1)[:, None]
    sd = np.sqrt(np.clip(var, 0.0, None))
    still = (n >= MIN_FILL * rate_hz * WINDOW_US / 1e6) & np.all(sd < STILL_SD_G, axis=1)
    if not still.any():
        return StillError(windows, 0, None, None)
    before = mean_shifted[still] + ref_g
    after = cal_sum[still] / n[still, None]
    return StillError(windows, int(still.sum()),
                      1e3 * float(np.mean(np.abs(np.linalg.norm(before, axis=1) - 1.0))),
                      1e3 * float(np.mean(np.abs(np.linalg.norm(after, axis=1) - 1.0))))
