"""What discovery fits: a recording's quasi-static window means, or a static table's rows.

The windows come from the live detector and windowing (`window_means.window_means`), scaled by
the recording's median sample norm measured from counts in one pass (`rate_and_scale`), and are
cut into contiguous time blocks for held-out scoring (`time_blocks`, `scorable`). See
docs/design.md (effect discovery).
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from itertools import pairwise

import numpy as np

from recal.core.batch_windows import window_means
from recal.core.bootstrap import off_by, zero_and_scale
from recal.core.buffer import Windows
from recal.core.effects import Covariates
from recal.core.pipeline_config import PipelineConfig
from recal.errors import InputError
from recal.samples import RawBatch, rebatch

__all__ = [
    "COVERAGE_LEVEL_G",
    "MAX_WINDOWS",
    "SCORE_COVERAGE_G",
    "DiscoveryData",
    "centred_data",
    "covariate_spread",
    "data_from_batch",
    "data_from_batches",
    "data_from_table",
    "data_from_windows",
    "rate_and_scale",
    "scorable",
    "thinned",
    "time_blocks",
    "usable_channels",
]

#: Gravity seen beyond this on a half-axis counts as that half-axis covered (as buffer.Coverage).
COVERAGE_LEVEL_G = 0.3
#: For held-out scoring an axis counts as covered by the training blocks only beyond this on
#: both sides: one pose just past 0.3 g leaves the gain barely determined.
SCORE_COVERAGE_G = 0.5
#: Most windows discovery's selection runs on (`thinned`): a week of wear has a quarter of a
#: million, and the selection's cost grows with them while its power for an effect above a
#: window's noise hardly does: of 4096 spread over the recording, each of 10 held-out blocks
#: keeps about 400, whose mean leaves a window's noise (about 0.3 mg) at about 0.015 mg.
MAX_WINDOWS = 4096


@dataclass(frozen=True, eq=False)
class DiscoveryData:
    """What discovery fits: window means (or table rows) with their covariates.

    Attributes:
        windows: raw means v (M,3), aux (M,K), mid time t_us, samples n, variance var.
        cov: covariates per window: time in hours since the recording's first sample (the
            live pipeline's origin for "time"), channels by name.
        s0: nominal raw units per g (median norm of the means, or the radius of their sphere
            when its centre is far from 0: `bootstrap.locate`).
        has_time: False for a static table (rows have no time; no drift candidate).
        source: "windows" or "table".
        dropped: windows screened out as movement (see `data_from_windows`).
        zero: the reading at 0 g (raw, (3,)): the sphere's centre where it is far from 0 (an
            analog part on an unsigned ADC), else zero.
    """

    windows: Windows
    cov: Covariates
    s0: float
    has_time: bool = True
    source: str = "windows"
    dropped: int = 0
    zero: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __len__(self) -> int:
        return len(self.windows)

    @property
    def aux_names(self) -> tuple[str, ...]:
        return self.cov.aux_names

    def subset(self, mask: np.ndarray) -> DiscoveryData:
        w = self.windows
        win = Windows(w.v[mask], w.aux[mask], w.t_us[mask], w.n[mask], w.var[mask])
        return replace(self, windows=win, cov=self.cov[mask])


def thinned(data: DiscoveryData, most: int) -> DiscoveryData:
    """At most ``most`` of the windows: every k-th in time order, k the least that fits, so
    they still cover the recording's time, poses and covariates as the whole does."""
    step = -(-len(data) // max(1, most))
    if step <= 1:
        return data
    return data.subset(np.arange(0, len(data), step))


def _norms(v: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(v, np.float64).reshape(-1, 3), axis=1)


def data_from_windows(windows: Windows, aux_names: tuple[str, ...], t0_us: int,
                      has_time: bool = True, max_sd_ratio: float | None = 5.0
                      ) -> DiscoveryData:
    """Window means (e.g. a live buffer's) with time measured from t0_us.

    A window whose samples scatter more than max_sd_ratio times the median window's is
    movement the detector let through (its 0.5 Hz low-pass reacts late, so a window may
    straddle a rotation and its mean fall short of 1 g); it is dropped, so held-out errors are
    those of still poses.
    """
    if len(windows) == 0:
        raise InputError("no quasi-static windows to discover effects on")
    keep = np.ones(len(windows), bool)
    if max_sd_ratio is not None:
        sd = np.sqrt(np.maximum(windows.var, 0.0))
        keep = sd <= max_sd_ratio * float(np.median(sd))
    w = windows
    kept = Windows(w.v[keep], w.aux[keep], w.t_us[keep], w.n[keep], w.var[keep])
    cov = Covariates.from_samples(kept.t_us, kept.aux, tuple(aux_names), int(t0_us))
    zero, s0 = zero_and_scale(kept.v)
    return DiscoveryData(kept, cov, s0, has_time, dropped=int((~keep).sum()), zero=zero)


def data_from_batch(batch: RawBatch, cfg: PipelineConfig | None = None,
                    s0: float | None = None) -> DiscoveryData:
    """The quasi-static window means of a recording, by the live detector and windowing.

    cfg: pipeline settings (default: PipelineConfig at the rate measured from the time
    stamps); s0: raw units per g for the detector (default: the median sample norm, to
    1.2e-4; non-finite samples left out).
    """
    if len(batch) < 2:
        raise InputError("a recording needs samples to discover effects on")
    return data_from_batches(lambda: [batch], cfg, s0)


def data_from_batches(batches: Callable[[], Iterable[RawBatch]],
                      cfg: PipelineConfig | None = None, s0: float | None = None,
                      window_s: float | None = None, rate_hz: float | None = None
                      ) -> DiscoveryData:
    """`data_from_batch` of a recording read one batch at a time, in two passes (``batches()``
    is called once per pass): the rate and s0 from counts of every sample's time step and of
    its norm's bin (`_norm_bins`; memory by distinct steps and bins, not by samples), then the
    windows, the pipeline being batch-size invariant: the same s0, rate and windows as
    `data_from_batch` of the batches joined (a window cut by a batch end sums in two parts, so
    its mean may differ in the last bit).

    window_s: with the measured rate, windows of this length (guard half of it) instead of
    the default (ignored when cfg is given). rate_hz: the rate when the source knows it better
    than its stamps' median step (with s0 too, the first pass is not needed).
    """
    if cfg is None or s0 is None:
        if rate_hz is None or s0 is None:
            measured_hz, median_norm = rate_and_scale(batches())
            rate_hz = measured_hz if rate_hz is None else rate_hz
            s0 = median_norm if s0 is None else s0
        cfg = cfg or (PipelineConfig(rate_hz=rate_hz) if window_s is None else
                      PipelineConfig(rate_hz=rate_hz, window_s=float(window_s),
                                     guard_s=float(window_s) / 2))
    return centred_data(batches, cfg, s0)


def centred_data(batches: Callable[[], Iterable[RawBatch]], cfg: PipelineConfig,
                 s0: float) -> DiscoveryData:
    """The recording's window means by a detector in units of s0; when they show zero-g far
    from 0 or the scale far from s0 (`zero_and_scale`: a detector so wrong lets movement
    through and runs on the offset's norm), again by a detector centred at the zero-g found
    and in its units (one more pass)."""
    w, aux_names, t0_us = window_means(batches(), cfg, s0)
    data = data_from_windows(w, aux_names, t0_us)
    if not off_by(data.zero, data.s0, np.zeros(3), s0):
        return data
    w, aux_names, t0_us = window_means(batches(), cfg, data.s0, data.zero)
    return data_from_windows(w, aux_names, t0_us)


def rate_and_scale(batches: Iterable[RawBatch]) -> tuple[float, float]:
    """A recording's sample rate (1 / the median time step) and median sample norm (raw units
    per g, to 1.2e-4), in one pass from counts of every time step and norm bin (`_norm_bins`):
    memory by distinct steps and bins, not by samples."""
    bins: collections.Counter[int] = collections.Counter()  # norm bin -> how often
    steps: collections.Counter[int] = collections.Counter()  # time step (us) -> how often
    last_t: int | None = None
    samples = 0
    for b in rebatch(batches):
        if not len(b):
            continue
        samples += len(b)
        _count(bins, _norm_bins(b.v))
        t = b.t_us if last_t is None else np.concatenate(([last_t], b.t_us))
        dt = np.diff(t)  # across batches too: the same as over the whole
        _count(steps, dt[dt > 0])
        last_t = int(b.t_us[-1])
    if samples < 2:
        raise InputError("a recording needs at least two samples")
    if not steps:
        raise InputError("time stamps never advance: cannot measure the sample rate")
    if not bins:
        raise InputError("no sample has a finite, nonzero reading: nothing to scale by")
    lo, hi = _median_keys(bins)
    return 1e6 / _median_of_counts(steps), (_bin_middle(lo) + _bin_middle(hi)) / 2


def _count(counts: collections.Counter[int], keys: np.ndarray) -> None:
    """Add how often each integer key occurs in ``keys`` to ``counts``."""
    values, n = np.unique(keys, return_counts=True)
    counts.update(dict(zip(values.tolist(), n.tolist(), strict=True)))


def _median_of_counts(counts: collections.Counter[int]) -> float:
    """np.median of the values ``counts`` holds, each as often as counted (a sampler has few
    distinct time steps: memory by values, not by samples)."""
    lo, hi = _median_keys(counts)
    return (lo + hi) / 2


def _median_keys(counts: collections.Counter[int]) -> tuple[int, int]:
    """The middle one or two of the values ``counts`` holds, each as often as counted."""
    values = sorted(counts)
    cum = np.cumsum([counts[v] for v in values])
    n = int(cum[-1])
    lo = values[int(np.searchsorted(cum, (n - 1) // 2, side="right"))]
    hi = values[int(np.searchsorted(cum, n // 2, side="right"))]
    return lo, hi


#: Mantissa bits of a sample's norm that its bin keeps (`_norm_bins`): 4096 bins per octave,
#: so the median norm that scales the detector is within 1.2e-4 of the exact one, from counts
#: per bin (a few thousand bins, whatever the recording's length) instead of every norm.
NORM_BITS = 12
_SHIFT = 52 - NORM_BITS


def _norm_bins(v: np.ndarray) -> np.ndarray:
    """The bin of each finite, nonzero sample norm: the top bits of its float64 pattern, which
    orders positive floats as integers. A non-finite sample has no norm."""
    n = _norms(v)
    n = n[np.isfinite(n) & (n > 0)]
    return n.view(np.int64) >> _SHIFT


def _bin_middle(key: int) -> float:
    """The norm in the middle of bin `key`."""
    return float(np.array([(key << _SHIFT) | (1 << (_SHIFT - 1))], np.int64).view(np.float64)[0])


def data_from_table(v: np.ndarray) -> DiscoveryData:
    """Rows of a static table (one still reading per pose, any unit; no time, no channels)."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    m = len(v)
    # rows keep table order through the stable sort of equal times (blocks of rows)
    w = Windows(v, np.zeros((m, 0)), np.zeros(m, np.int64), np.ones(m, np.int64), np.zeros(m))
    cov = Covariates(np.zeros(m), np.zeros((m, 0)), ())
    zero, s0 = zero_and_scale(v)
    return DiscoveryData(w, cov, s0, has_time=False, source="table", zero=zero)


def time_blocks(t_us: np.ndarray, n_blocks: int) -> np.ndarray:
    """Block index per window: n_blocks contiguous stretches of about equal count in time
    order. A boundary moves to the nearest gap between still runs (windows of one run follow
    each other at the window length; a movement leaves a longer gap) when one is within half
    a block, so one posture does not sit on both sides of a split."""
    t = np.asarray(t_us, np.int64)
    m = len(t)
    order = np.argsort(t, kind="stable")
    dt = np.diff(t[order])
    pos = dt[dt > 0]
    run_starts = (np.flatnonzero(dt > 1.5 * np.median(pos)) + 1 if len(pos)
                  else np.zeros(0, np.int64))
    edges = [0]
    for i in range(1, n_blocks):
        target = round(i * m / n_blocks)
        edge = target
        if len(run_starts):
            near = int(run_starts[np.argmin(np.abs(run_starts - target))])
            if abs(near - target) <= m / (2 * n_blocks):
                edge = near
        edges.append(edge if edges[-1] < edge < m else target)
    edges.append(m)
    if any(b <= a for a, b in pairwise(edges)):
        edges = [round(i * m / n_blocks) for i in range(n_blocks + 1)]  # equal counts
    sorted_block = np.repeat(np.arange(n_blocks), np.diff(edges))
    out = np.empty(m, np.int64)
    out[order] = sorted_block
    return out


def scorable(data: DiscoveryData, blocks: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Windows a held-out score can use: not those that lean (beyond 0.3 g) on an axis whose
    gain the whole recording determines (gravity beyond 0.3 g on both sides) but the other
    blocks do not (on either side they must reach 0.5 g, or as far as the whole recording
    goes if that is less). Without both sides an axis' gain is not observable (the live
    rule, Effect.observable_with): a fit on those blocks keeps it at its start, or pins it on
    one pose barely past 0.3 g, and every model would only guess there. (A wearer who lay face
    down once, in one block, leaves z uncovered in the fit without that block.) An axis the
    whole recording never covers (a single pose) is fixed in every fit alike: its windows
    count. The mask is fixed once (from the base fit), so every model is scored alike."""
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    leans = np.abs(u) > COVERAGE_LEVEL_G
    reach_pos, reach_neg = u.max(axis=0), (-u).max(axis=0)
    everywhere = (reach_pos > COVERAGE_LEVEL_G) & (reach_neg > COVERAGE_LEVEL_G)
    need_pos = np.minimum(SCORE_COVERAGE_G, reach_pos)
    need_neg = np.minimum(SCORE_COVERAGE_G, reach_neg)
    ok = np.ones(len(data), bool)
    for k in np.unique(blocks):
        test = blocks == k
        if test.all():
            continue
        covered = (u[~test].max(axis=0) >= need_pos) & ((-u[~test]).max(axis=0) >= need_neg)
        ok[test] = ~np.any(leans[test] & everywhere & ~covered, axis=1)
    return ok


def covariate_spread(x: np.ndarray) -> float:
    """Typical range of a covariate: 5-95 % percentiles, the full range if that is 0."""
    lo, hi = np.percentile(x, [5, 95])
    return float(hi - lo) if hi > lo else float(np.ptp(x))


def usable_channels(data: DiscoveryData) -> dict[str, tuple[float, float]]:
    """Usable channels (finite, not constant) -> (reference = median, spread)."""
    out = {}
    for name in data.aux_names:
        c = data.cov.get(name)
        if len(c) and np.all(np.isfinite(c)) and covariate_spread(c) > 0:
            out[name] = (float(np.median(c)), covariate_spread(c))
    return out
