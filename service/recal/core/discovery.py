"""Effect discovery: fit, look at what is left, find the effect the model lacks, add it.

A still sensor reads 1 g (Lötters 1998, eq. 8 and 14: xi = 1 g - |a|). On the quasi-static
window means of a recording (the live detector and windowing, `windowing.window_means`) or on
the rows of a static table, `discover`:

1. fits the current model by the batch form of Lötters eq. 11a (`estimator.solve`, iterated
   Gauss-Newton), with the live estimator's default prior, over the parameters the poses
   can determine (`free_params`: a gain needs its axis seen from both sides, an offset its axis
   seen at all);
2. analyses the residual: xi per window and its correlation with every auxiliary channel, with
   time and with the gravity direction; and, per candidate effect, the fraction of xi that the
   candidate's Jacobian columns (eq. 13a at the effect's nominal value, orthogonalized against
   the model's own columns) explain: a score test of what the residual looks like;
3. builds the candidates: for every auxiliary channel c, whatever it is called, an offset
   linear in c (3 parameters), a gain linear in c (3), the whole output ratiometric in c (1),
   and ratiometric in c with every other channel r as the reference rail (2); cross-axis with
   the rotation gauge fixed (3), per-axis quadratic nonlinearity (3), offset linear in time (3);
4. scores each candidate on held-out data: the windows are cut into `blocks` contiguous time
   blocks (rows in table order for a table) and each block is predicted by a fit on the
   others, so neighbouring windows, which share posture, temperature and drift, never sit on
   both sides of a split (boundaries move into the movement between still runs); a window in
   a pose that only its own block covers is not scored (`scorable`): no model can be tested
   where the others cannot see the gain;
5. accepts by this criterion: the relative reduction of the held-out sum of squares of xi,
   R = 1 - SS_candidate / SS_model, must exceed both t bootstrap standard errors (blocks
   resampled with replacement, so the spread is the block-to-block variation of the paired
   improvement; t is Student's 97.5 % quantile for blocks - 1 degrees of freedom, 2.26 for 10
   blocks, since an SE from a handful of blocks is itself uncertain) and `min_gain` (5 %: a
   gain below that is not worth a parameter in the live estimator). Of the candidates that
   pass, the largest R wins, unless a simpler one passes too (fewer directions the data
   determine, then KIND_ORDER) and the winner does not beat it by the same criterion: of two
   effects that explain the same residual, the smaller (ratiometric (1) rather than gain (3)
   in the supply). When no candidate passes alone, pairs of the candidates the score test
   ranks highest are tried (two effects whose channels drift together can each fail alone);
6. adds the winner, then removes an earlier addition that no longer passes the same test
   against the model without it (or reduces a ratiometric effect with a reference to one
   channel), and repeats until nothing passes. On data without an extra effect no
   candidate's held-out improvement stands out from its spread, and nothing is added.

The result carries the extended model with its fitted values and a `Prior` (the fitted values,
the model's default spreads) for the live estimator to start from.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from itertools import combinations, pairwise

import numpy as np
from scipy import stats

from recal.core.bootstrap import initial_params, off_by, zero_and_scale
from recal.core.buffer import Windows
from recal.core.effects import TIME, Covariates, CrossAxis, Effect, Nonlinearity, make_effect
from recal.core.estimator import EstimatorConfig, Prior, solve
from recal.core.model import SensorModel
from recal.core.pipeline import PipelineConfig
from recal.core.windowing import window_means
from recal.samples import RawBatch, rebatch

__all__ = [
    "CandidateScore",
    "DiscoveryConfig",
    "DiscoveryData",
    "DiscoveryResult",
    "ModelFit",
    "ResidualAnalysis",
    "SelectedEffect",
    "Step",
    "candidates",
    "data_from_batch",
    "data_from_batches",
    "data_from_table",
    "data_from_windows",
    "discover",
    "discover_pipeline",
    "fit_model",
    "free_params",
    "n_se_for",
    "orientation_features",
    "rate_and_scale",
    "residual_analysis",
    "scorable",
    "start_params",
    "time_blocks",
]

#: Gravity seen beyond this on a half-axis counts as that half-axis covered (as buffer.Coverage).
COVERAGE_LEVEL_G = 0.3
#: For held-out scoring an axis counts as covered by the training blocks only beyond this on
#: both sides: one pose just past 0.3 g leaves the gain barely determined.
SCORE_COVERAGE_G = 0.5
ORIENTATION_FEATURES = ("x", "y", "z", "xx", "yy", "zz", "xy", "xz", "yz")


@dataclass(frozen=True)
class DiscoveryConfig:
    """Settings of the selection.

    Attributes:
        blocks: contiguous time blocks (k-fold over blocks) for held-out scoring.
        min_gain: smallest relative reduction of the held-out sum of squares worth an effect.
        n_se: the reduction must also exceed this many bootstrap standard errors; None:
            Student's t 97.5 % quantile for (blocks - 1) degrees of freedom.
        prefer_simpler: of the passing candidates, prefer a simpler one (fewer observed
            directions, then KIND_ORDER) that the best does not beat by the criterion.
        pairs: when no candidate passes alone, try this many candidates the residual points
            at most, each with the partner its fit's residual then points at most (0: never).
        bootstrap: bootstrap resamples of the blocks; seed: their generator's seed.
        max_steps: most effects added.
        prior_scale: prior standard deviations are the model's defaults times this. The
            defaults (offsets 100 mg, gains 5 %, ...) are those of the live estimator: loose
            beside hundreds of windows, but they keep what the data cannot see (offsets across
            gravity in a single pose) at a sensor's plausible values instead of fitting noise.
        sigma_floor_g: C_mu floor of the fit (see EstimatorConfig).
        max_iter: Gauss-Newton iterations per fit.
        observable_ratio: a fitted parameter counts as observed when its posterior standard
            deviation is below this fraction of its prior one (as the live estimator).
        kinds: candidate kinds to try (any of offset, gain, ratiometric, cross_axis,
            nonlinearity); `time` whether to try the offset linear in time.
    """

    blocks: int = 10
    min_gain: float = 0.05
    n_se: float | None = None
    prefer_simpler: bool = True
    pairs: int = 4
    bootstrap: int = 2000
    seed: int = 0
    max_steps: int = 6
    prior_scale: float = 1.0
    sigma_floor_g: float = 1e-3
    max_iter: int = 30
    observable_ratio: float = 0.5
    kinds: tuple[str, ...] = ("offset", "gain", "ratiometric", "cross_axis", "nonlinearity")
    time: bool = True

    def __post_init__(self) -> None:
        if self.blocks < 3:
            raise ValueError("discovery needs at least 3 blocks for held-out scoring")
        if not (self.min_gain >= 0 and (self.n_se is None or self.n_se >= 0)
                and self.bootstrap >= 10):
            raise ValueError("min_gain and n_se must be >= 0 and bootstrap >= 10")

    def estimator(self) -> EstimatorConfig:
        # no process noise: a batch fit, every window counts the same whatever its age
        return EstimatorConfig(sigma_floor_g=self.sigma_floor_g, max_iter=self.max_iter,
                               tol=1e-10, process_scale=0.0)


# ---------------------------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------------------------

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


def _norms(v: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(v, np.float64).reshape(-1, 3), axis=1)


def _median_norm(v: np.ndarray) -> float:
    return float(np.median(_norms(v)))


def data_from_windows(windows: Windows, aux_names: tuple[str, ...], t0_us: int,
                      has_time: bool = True, max_sd_ratio: float | None = 5.0
                      ) -> DiscoveryData:
    """Window means (e.g. a live buffer's) with time measured from t0_us.

    A window whose samples scatter more than max_sd_ratio times the median window's is
    movement the detector let through (its 0.5 Hz low-pass reacts late: on the Xsens
    recording a few windows straddle a rotation, 60-180 mg against 1 mg still, and their means
    are tens of mg short of 1 g); it is dropped, so held-out errors are those of still poses.
    """
    if len(windows) == 0:
        raise ValueError("no quasi-static windows to discover effects on")
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
        raise ValueError("a recording needs samples to discover effects on")
    return data_from_batches(lambda: [batch], cfg, s0)


def data_from_batches(batches: Callable[[], Iterable[RawBatch]],
                      cfg: PipelineConfig | None = None, s0: float | None = None,
                      window_s: float | None = None) -> DiscoveryData:
    """`data_from_batch` of a recording read one batch at a time, in two passes (``batches()``
    is called once per pass): the rate and s0 from counts of every sample's time step and of
    its norm's bin (`_norm_bins`; memory by distinct steps and bins, not by samples), then the
    windows, the pipeline being batch-size invariant: the same s0, rate and windows as
    `data_from_batch` of the batches joined (a window cut by a batch end sums in two parts, so
    its mean may differ in the last bit).

    window_s: with the measured rate, windows of this length (guard half of it) instead of
    the default (ignored when cfg is given).
    """
    if cfg is None or s0 is None:
        rate_hz, median_norm = rate_and_scale(batches())
        cfg = cfg or (PipelineConfig(rate_hz=rate_hz) if window_s is None else
                      PipelineConfig(rate_hz=rate_hz, window_s=float(window_s),
                                     guard_s=float(window_s) / 2))
        s0 = median_norm if s0 is None else s0
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
        raise ValueError("a recording needs at least two samples")
    if not steps:
        raise ValueError("time stamps never advance: cannot measure the sample rate")
    if not bins:
        raise ValueError("no sample has a finite, nonzero reading: nothing to scale by")
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


# ---------------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class ModelFit:
    p: np.ndarray
    cov: np.ndarray  # posterior covariance (raw units, Lötters eq. 11b); prior on fixed ones
    prior_sd: np.ndarray
    free: np.ndarray  # the parameters the poses let move (see free_params)
    data_info: np.ndarray  # B^T C_mu^-1 B of the windows alone, free parameters

    @property
    def n_observed(self) -> int:
        """Directions in which the data outweigh the prior: eigenvalues of the data
        information, scaled by the prior standard deviations, above 1."""
        d = self.prior_sd[self.free]
        return int(np.sum(np.linalg.eigvalsh(d[:, None] * self.data_info * d[None, :]) > 1.0))


def free_params(model: SensorModel, p: np.ndarray, data: DiscoveryData) -> np.ndarray:
    """Parameters the poses can determine, by the live pipeline's rule (a gain needs its axis
    seen from both sides, Effect.observable_with) and, for offsets, their axis seen from one
    side at least. In a single pose an offset across gravity moves |a| only to second order,
    and fitting it would tilt the gravity direction to soak up drift and noise."""
    a = model.correct(p, data.windows.v, data.cov)
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    pos, neg = (u > COVERAGE_LEVEL_G).any(axis=0), (u < -COVERAGE_LEVEL_G).any(axis=0)
    free = model.observable_with(tuple(bool(x) for x in pos & neg))
    for e in model.effects:
        if e.kind == "offset":
            free[model.slice(e)] &= pos | neg
    return free


def fit_model(model: SensorModel, p0: np.ndarray, data: DiscoveryData,
              cfg: DiscoveryConfig) -> ModelFit:
    """Lötters eq. 11a iterated from p0 (also the prior mean) over the free parameters."""
    prior = Prior.from_sd(p0, model.prior_sd() * cfg.prior_scale)
    now = int(data.windows.t_us.max()) if len(data) else 0
    free = free_params(model, p0, data)
    sol = solve(model, prior, p0, data.windows, data.cov, now, cfg.estimator(), free)
    cov = np.diag(prior.sd**2)
    cov[np.ix_(free, free)] = sol.cov_free
    return ModelFit(sol.p, cov, prior.sd, free, sol.data_info)


def _xi(model: SensorModel, p: np.ndarray, data: DiscoveryData) -> np.ndarray:
    """|a| - 1 g per window (the sign of Lötters eq. 14 flipped: positive = too long)."""
    return -model.residual(p, data.windows.v, data.cov)


def _half_axes(v: np.ndarray) -> int:
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    return int(np.sum(u > COVERAGE_LEVEL_G, axis=0).astype(bool).sum()
               + np.sum(u < -COVERAGE_LEVEL_G, axis=0).astype(bool).sum())


def start_params(model: SensorModel, data: DiscoveryData) -> np.ndarray:
    """Starting values: ellipsoid (all six half-axes seen) or sphere fit (five), else nominal
    (too few orientations: e.g. one still pose, where only the offset along gravity shows)."""
    v = data.windows.v
    seen = _half_axes(v - data.zero)  # on centred readings: an unsigned part's are all > 0
    fit = None
    if seen >= 5 and len(v) >= 12:
        fit = initial_params(model, v, sphere=seen < 6)
    if fit is not None:
        fitted, p = fit
        s = p[fitted.slice(("scale", None))]
        if np.all((s > 0.5 * data.s0) & (s < 2.0 * data.s0)):
            return _carry(fitted, p, model)
    return nominal(model, data)


def nominal(model: SensorModel, data: DiscoveryData) -> np.ndarray:
    """The model's nominal parameters with the offsets at the data's zero-g."""
    p = model.nominal()
    if model.has("offset"):
        p[model.slice(("offset", None))] = data.zero
    return p


def _carry(src: SensorModel, p: np.ndarray, dst: SensorModel) -> np.ndarray:
    """Values of dst's parameters taken from src where both have the effect, else nominal."""
    q = dst.nominal()
    have = {e.key: e for e in src.effects}
    for e in dst.effects:
        if have.get(e.key) == e:  # same key and the same stage (a reduced one starts anew)
            q[dst.slice(e)] = p[src.slice(e.key)]
    return q


@dataclass(frozen=True, eq=False)
class _Scored:
    """A model, its fit on all data, and its k-fold fits and held-out residuals."""

    model: SensorModel
    fit: ModelFit
    fold_p: tuple[np.ndarray, ...]
    heldout_xi: np.ndarray

    def block_ss(self, blocks: np.ndarray, n_blocks: int, scored: np.ndarray) -> np.ndarray:
        return np.bincount(blocks, np.where(scored, self.heldout_xi, 0.0)**2,
                           minlength=n_blocks)


def _score(model: SensorModel, data: DiscoveryData, blocks: np.ndarray, starts: list[np.ndarray],
           p_all: np.ndarray, cfg: DiscoveryConfig) -> _Scored:
    """Fit on all windows (from p_all) and, per block, on the other blocks (from starts[k],
    which came from those blocks alone: no held-out value leaks in through a start)."""
    fit = fit_model(model, p_all, data, cfg)
    held = np.empty(len(data))
    fold_p = []
    for k, p0 in enumerate(starts):
        test = blocks == k
        pk = fit_model(model, p0, data.subset(~test), cfg).p
        held[test] = _xi(model, pk, data.subset(test))
        fold_p.append(pk)
    return _Scored(model, fit, tuple(fold_p), held)


# ---------------------------------------------------------------------------------------------
# Candidates and residual analysis
# ---------------------------------------------------------------------------------------------

def _spread(x: np.ndarray) -> float:
    """Typical range of a covariate: 5-95 % percentiles, the full range if that is 0."""
    lo, hi = np.percentile(x, [5, 95])
    return float(hi - lo) if hi > lo else float(np.ptp(x))


def _channels(data: DiscoveryData) -> dict[str, tuple[float, float]]:
    """Usable channels (finite, not constant) -> (reference = median, spread)."""
    out = {}
    for name in data.aux_names:
        c = data.cov.get(name)
        if len(c) and np.all(np.isfinite(c)) and _spread(c) > 0:
            out[name] = (float(np.median(c)), _spread(c))
    return out


def candidates(model: SensorModel, data: DiscoveryData,
               cfg: DiscoveryConfig = DiscoveryConfig()) -> list[tuple[Effect, float]]:
    """Every effect (with its covariate spread) the model could be extended by."""
    out: list[tuple[Effect, float]] = []
    chans = _channels(data)
    ratio_used = {c for e in model.effects if e.kind == "ratiometric" for c in e.channels}
    for name, (ref, spread) in chans.items():
        for kind in ("offset", "gain", "ratiometric"):
            if kind not in cfg.kinds or model.has(kind, name):
                continue
            if kind == "ratiometric" and name in ratio_used:
                continue
            out.append((make_effect(kind, name, ref), spread))
    if "ratiometric" in cfg.kinds:
        for a, b in combinations([c for c in chans if c not in ratio_used], 2):
            eff = make_effect("ratiometric", a, chans[a][0], b, chans[b][0])
            out.append((eff, min(chans[a][1], chans[b][1])))
    if "cross_axis" in cfg.kinds and not model.has("cross_axis"):
        out.append((CrossAxis(), 1.0))
    if "nonlinearity" in cfg.kinds and not model.has("nonlinearity"):
        out.append((Nonlinearity(), 1.0))
    if cfg.time and data.has_time and "offset" in cfg.kinds and not model.has("offset", TIME):
        t = data.cov.t_h
        if len(t) and _spread(t) > 0:
            out.append((make_effect("offset", TIME, float(np.median(t))), _spread(t)))
    return out


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


def _explained(model: SensorModel, p: np.ndarray, data: DiscoveryData, xi: np.ndarray,
               effect: Effect, spread: float) -> float:
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
    expl = {e.label: _explained(model, p, data, xi, e, sp) for e, sp in (cands or [])}
    return ResidualAnalysis(1e3 * float(np.sqrt(np.mean(xi**2))), corr, orient, expl)


# ---------------------------------------------------------------------------------------------
# Selection
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CandidateScore:
    """One candidate of one round: its parameters and how many new directions the data
    determine (n_observed: fewer than n_params where the poses cannot tell them apart), the
    held-out RMS with it, the relative reduction R of the held-out sum of squares against the
    model without it, R's bootstrap standard error, the score-test fraction it explains
    in-sample, and whether it passed the criterion."""

    label: str
    kind: str
    covariate: str | None
    reference: str | None
    n_params: int
    n_observed: int
    heldout_rms_mg: float
    gain: float
    se: float
    explained: float
    passed: bool


@dataclass(frozen=True)
class SelectedEffect:
    """An effect in the discovered model with its values from the final fit on all windows.

    params: physical units (Effect.describe); values / sd: raw parameter values and their
    posterior standard deviations by name; observable: which values the data determined
    (the others stayed at their start, e.g. offsets across gravity in a single pose);
    extra: the angles between the sensing axes for cross-axis (Georgieva et al.).
    """

    kind: str
    covariate: str | None
    reference: str | None
    label: str
    params: dict[str, float]
    values: dict[str, float]
    sd: dict[str, float]
    observable: dict[str, bool]
    extra: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Step:
    """One change of the model: the effect (values from the fit of that step), held-out RMS
    before and after, R and its SE, and every candidate's score in that round.

    action: "add" (forward; R is the reduction the effect brought), or, when a later addition
    took over what an earlier effect explained, "remove" or "reduce" (a ratiometric effect
    with a reference back to one channel; `effect` is then what remains, or the removed one):
    R is what the bigger model still gained over the smaller, below the criterion.
    """

    effect: SelectedEffect
    heldout_before_mg: float
    heldout_after_mg: float
    gain: float
    se: float
    candidates: tuple[CandidateScore, ...] = ()
    action: str = "add"
    together: tuple[SelectedEffect, ...] = ()


@dataclass(frozen=True, eq=False)
class DiscoveryResult:
    """Everything discovery found, and what to start the live estimator from.

    Attributes:
        data, blocks: the windows (or rows) and their block index.
        base_model, base_p: the model as given, fitted on all windows.
        model, p, cov: the discovered model, its fit on all windows and posterior covariance.
        prior: the live estimator's pre-calibration: mean p, the model's default spreads.
        steps: the accepted additions in order; last_round: the candidate scores of the
            round in which none passed (empty if max_steps stopped it).
        selected: the effects added, with values from the final fit.
        heldout_xi_base / heldout_xi_final: held-out |a| - 1 g per window (g).
        scored: the windows held-out errors count (see `scorable`).
        heldout_base_mg / heldout_final_mg: their RMS over the scored windows in mg;
            fit_*_mg: in-sample RMS.
        analysis_base / analysis_final: residual analysis before and after.
    """

    data: DiscoveryData
    blocks: np.ndarray
    config: DiscoveryConfig
    base_model: SensorModel
    base_p: np.ndarray
    model: SensorModel
    p: np.ndarray
    cov: np.ndarray
    prior: Prior
    steps: tuple[Step, ...]
    last_round: tuple[CandidateScore, ...]
    selected: tuple[SelectedEffect, ...]
    heldout_xi_base: np.ndarray
    heldout_xi_final: np.ndarray
    scored: np.ndarray
    analysis_base: ResidualAnalysis
    analysis_final: ResidualAnalysis

    @property
    def heldout_base_mg(self) -> float:
        return _rms_mg(self.heldout_xi_base[self.scored])

    @property
    def heldout_final_mg(self) -> float:
        return _rms_mg(self.heldout_xi_final[self.scored])

    @property
    def fit_base_mg(self) -> float:
        return self.analysis_base.rms_mg

    @property
    def fit_final_mg(self) -> float:
        return self.analysis_final.rms_mg

    def held_at_start(self) -> tuple[str, ...]:
        """Parameters of the final model the poses cannot determine (`free_params`: a gain needs its
        axis seen from both sides, an offset from one at least), so they kept their start
        value: e.g. every gain, and the offsets across gravity, of a recording in one pose."""
        free = free_params(self.model, self.p, self.data)
        return tuple(n for n, f in zip(self.model.names, free, strict=True) if not f)

    def corrected(self, final: bool = True) -> np.ndarray:
        """The windows corrected by the final (or base) fit on all windows, g (M,3)."""
        model, p = (self.model, self.p) if final else (self.base_model, self.base_p)
        return model.correct(p, self.data.windows.v, self.data.cov)


def _rms_mg(xi: np.ndarray) -> float:
    return 1e3 * float(np.sqrt(np.mean(xi**2))) if len(xi) else float("nan")


def _paired_gain(ss_m: np.ndarray, ss_c: np.ndarray, n_boot: int,
                 seed: int) -> tuple[float, float]:
    """R = 1 - SS_c / SS_m over blocks, and its standard error by resampling blocks (the same
    resamples for every comparison: a forward and a backward test of one pair agree)."""
    r = 1.0 - float(ss_c.sum()) / max(float(ss_m.sum()), 1e-300)
    idx = np.random.default_rng(seed).integers(0, len(ss_m), (n_boot, len(ss_m)))
    rb = 1.0 - ss_c[idx].sum(axis=1) / np.maximum(ss_m[idx].sum(axis=1), 1e-300)
    return r, float(np.std(rb, ddof=1))


#: Order of simplicity between candidates with as many observed directions (e.g. in a single
#: pose an offset, a gain and a ratiometric term in temperature all move |a| alike, one
#: direction each): the commoner effect first (offsets drift with temperature in every field
#: device; gains less; supply scaling needs a ratiometric part).
KIND_ORDER = ("offset", "gain", "ratiometric", "cross_axis", "nonlinearity")


#: Two candidates with as many observed directions whose R differ by less than this explain
#: the residual equally (a single pose: a temperature offset or a temperature scaling of |a|).
TIE_GAIN = 0.01


def _selected(model: SensorModel, fit: ModelFit, effect: Effect,
              cfg: DiscoveryConfig) -> SelectedEffect:
    sl = model.slice(effect)
    names = model.names[sl]
    theta = fit.p[sl]
    sd = np.sqrt(np.clip(np.diag(fit.cov), 0, None))[sl]
    prior_sd = fit.prior_sd[sl]
    extra = model.axis_angles_deg(fit.p) if effect.kind == "cross_axis" else {}
    return SelectedEffect(
        effect.kind, effect.covariate, getattr(effect, "reference", None), effect.label,
        effect.describe(theta, model.s0), dict(zip(names, map(float, theta), strict=True)),
        dict(zip(names, map(float, sd), strict=True)),
        {n: bool(s < cfg.observable_ratio * d)
         for n, s, d in zip(names, sd, prior_sd, strict=True)}, extra)


def n_se_for(cfg: DiscoveryConfig, n_blocks: int) -> float:
    """How many standard errors R must exceed (cfg.n_se, or Student's t, see above)."""
    if cfg.n_se is not None:
        return cfg.n_se
    return float(stats.t.ppf(0.975, max(n_blocks - 1, 1)))


def _passes(gain: float, se: float, cfg: DiscoveryConfig, n_blocks: int) -> bool:
    return gain > max(cfg.min_gain, n_se_for(cfg, n_blocks) * se)


@dataclass
class _Search:
    """The state of one selection: data, blocks, settings and the model scored so far."""

    data: DiscoveryData
    blocks: np.ndarray
    cfg: DiscoveryConfig
    base: SensorModel
    current: _Scored
    scored: np.ndarray

    @property
    def n_blocks(self) -> int:
        return int(self.blocks.max()) + 1

    def ss(self, sc: _Scored) -> np.ndarray:
        return sc.block_ss(self.blocks, self.n_blocks, self.scored)

    def rms(self, sc: _Scored) -> float:
        return _rms_mg(sc.heldout_xi[self.scored])

    def compare(self, small: _Scored, big: _Scored) -> tuple[float, float, bool]:
        """R of big over small, its SE, and whether big passes the criterion."""
        gain, se = _paired_gain(self.ss(small), self.ss(big), self.cfg.bootstrap, self.cfg.seed)
        return gain, se, _passes(gain, se, self.cfg, self.n_blocks)

    def rescore(self, model: SensorModel) -> _Scored:
        """`model` scored, each fit started from the current one's (shared effects)."""
        cur = self.current
        return _score(model, self.data, self.blocks,
                      [_carry(cur.model, fp, model) for fp in cur.fold_p],
                      _carry(cur.model, cur.fit.p, model), self.cfg)

    def _choose(self, scores: list[CandidateScore], scored: list[_Scored]) -> int | None:
        """The passing candidate with the largest R, unless a simpler passing one explains as
        much: one with fewer observed directions that the best does not beat by the same
        criterion (of two effects that explain the same residual, the smaller: ratiometric
        (1) rather than gain (3) in the supply), or one as big, earlier in KIND_ORDER, whose
        R is within TIE_GAIN. None if none passed."""
        passing = [i for i, s in enumerate(scores) if s.passed]
        if not passing:
            return None
        best = max(passing, key=lambda i: scores[i].gain)
        if not self.cfg.prefer_simpler:
            return best
        b = scores[best]

        def as_good_and_simpler(i: int) -> bool:
            a = scores[i]
            if a.n_observed < b.n_observed:
                return not self.compare(scored[i], scored[best])[2]
            return (a.n_observed == b.n_observed and b.gain - a.gain < TIE_GAIN
                    and KIND_ORDER.index(a.kind) < KIND_ORDER.index(b.kind))

        rivals = [i for i in passing if as_good_and_simpler(i)]
        return min(rivals, key=lambda i: (scores[i].n_observed, KIND_ORDER.index(scores[i].kind),
                                          -scores[i].gain)) if rivals else best

    def forward(self) -> tuple[Step | None, tuple[CandidateScore, ...]]:
        """Score every candidate against the current model; add the chosen one. When none
        passes alone, try pairs of the `pairs` candidates the residual points at most
        (score test): two effects that interact (a supply and a temperature term whose
        channels drift together) can each fail alone on held-out blocks."""
        cur, cfg, data = self.current, self.cfg, self.data
        cands = candidates(cur.model, data, cfg)
        xi_now = _xi(cur.model, cur.fit.p, data)
        scored, scores = [], []
        for eff, spread in cands:
            sc = self.rescore(cur.model.with_effect(eff, spread))
            gain, se, ok = self.compare(cur, sc)
            scored.append(sc)
            scores.append(CandidateScore(
                eff.label, eff.kind, eff.covariate, getattr(eff, "reference", None), eff.size,
                sc.fit.n_observed - cur.fit.n_observed, self.rms(sc), gain, se,
                _explained(cur.model, cur.fit.p, data, xi_now, eff, spread), ok))
        pick = self._choose(scores, scored)
        if pick is not None:
            new, eff = scored[pick], cands[pick][0]
            step = Step(_selected(new.model, new.fit, eff, cfg), self.rms(cur), self.rms(new),
                        scores[pick].gain, scores[pick].se, tuple(scores))
            self.current = new
            return step, tuple(scores)
        return self._pair(cands, scores, scored), tuple(scores)

    def _pair(self, cands: list[tuple[Effect, float]], scores: list[CandidateScore],
              scored: list[_Scored]) -> Step | None:
        """For each of the `pairs` candidates the score test ranks highest, fitted, the
        partner the residual then points at most (score test again); the best pair that
        passes against the current model."""
        cur, cfg, data = self.current, self.cfg, self.data
        top = sorted(range(len(cands)), key=lambda i: -scores[i].explained)[:cfg.pairs]
        best: tuple[float, float, _Scored, Effect, Effect] | None = None
        tried: set[frozenset[int]] = set()
        for i in top:
            first = scored[i]
            xi_i = _xi(first.model, first.fit.p, data)
            partners = []
            for j, (e2, sp2) in enumerate(cands):
                e1 = cands[i][0]
                if j == i or (e1.kind == e2.kind == "ratiometric"
                              and set(e1.channels) & set(e2.channels)):
                    continue  # the same supply scaling twice
                if e2.key in {e.key for e in first.model.effects}:
                    continue
                partners.append((_explained(first.model, first.fit.p, data, xi_i, e2, sp2), j))
            if not partners or frozenset((i, max(partners)[1])) in tried:
                continue
            j = max(partners)[1]
            tried.add(frozenset((i, j)))
            (e1, _), (e2, sp2) = cands[i], cands[j]
            sc = self.rescore(first.model.with_effect(e2, sp2))
            gain, se, ok = self.compare(cur, sc)
            if ok and (best is None or gain > best[0]):
                best = (gain, se, sc, e1, e2)
        if best is None:
            return None
        gain, se, new, e1, e2 = best
        step = Step(_selected(new.model, new.fit, e1, cfg), self.rms(cur), self.rms(new), gain,
                    se, tuple(scores), together=(_selected(new.model, new.fit, e2, cfg),))
        self.current = new
        return step

    def backward(self, keep: set[str]) -> Step | None:
        """An earlier addition that no longer earns its place against the model without it
        (or with its reduced form) goes; the effects just added (labels in `keep`) are not
        tested."""
        cur = self.current
        base_keys = {e.key for e in self.base.effects}
        for eff in cur.model.effects:
            if eff.key in base_keys or eff.label in keep:
                continue
            for action, alt, remaining in _alternatives(cur.model, eff, self.data):
                sc = self.rescore(alt)
                gain, se, ok = self.compare(sc, cur)
                if not ok:
                    shown = remaining if remaining is not None else eff
                    fit = sc.fit if remaining is not None else cur.fit
                    model = alt if remaining is not None else cur.model
                    self.current = sc
                    return Step(_selected(model, fit, shown, self.cfg), self.rms(cur),
                                self.rms(sc), gain, se, (), action)
        return None


def _alternatives(model: SensorModel, eff: Effect, data: DiscoveryData
                  ) -> list[tuple[str, SensorModel, Effect | None]]:
    """Smaller models than `model` without `eff`: "reduce" (a ratiometric effect with a
    reference back to one of its channels, tried first) and "remove"."""
    rest = [(e, sp) for e, sp in zip(model.effects, model.spreads, strict=True) if e != eff]
    without = SensorModel(tuple(e for e, _ in rest), model.s0, tuple(sp for _, sp in rest))
    out: list[tuple[str, SensorModel, Effect | None]] = []
    ref_channel = getattr(eff, "reference", None)
    if eff.kind == "ratiometric" and ref_channel is not None:
        chans = _channels(data)
        for ch in (eff.covariate, ref_channel):
            if ch in chans:
                single = make_effect("ratiometric", ch, chans[ch][0])
                out.append(("reduce", without.with_effect(single, chans[ch][1]), single))
    out.append(("remove", without, None))
    return out


def discover(data: DiscoveryData, model: SensorModel | None = None,
             p: np.ndarray | None = None,
             cfg: DiscoveryConfig = DiscoveryConfig()) -> DiscoveryResult:
    """Stepwise selection of effects by held-out error (see the module docstring): add the
    best candidate that passes (or the best passing pair when none passes alone), then drop
    an earlier addition the new one made redundant; stop when nothing passes.

    model: the current model (default: Lötters' diagonal one at the data's s0); p: its
    current values (default: an ellipsoid / sphere fit, or nominal for too few poses).
    """
    n_blocks = min(cfg.blocks, len(data))
    if n_blocks < 3:
        raise ValueError(f"{len(data)} windows are too few for held-out scoring (need 3)")
    if model is None:
        model = SensorModel.diagonal(data.s0)
    blocks = time_blocks(data.windows.t_us, n_blocks)
    p_all = start_params(model, data) if p is None else np.asarray(p, np.float64)
    starts = [start_params(model, data.subset(blocks != k)) for k in range(n_blocks)]
    base = _score(model, data, blocks, starts, p_all, cfg)
    scored = scorable(data, blocks, model.correct(base.fit.p, data.windows.v, data.cov))
    if not scored.any():
        raise ValueError("no held-out window lies in a pose the other blocks saw")
    search = _Search(data, blocks, cfg, model, base, scored)
    steps: list[Step] = []
    last_round: tuple[CandidateScore, ...] = ()
    added = 0
    while added < cfg.max_steps:
        step, scores = search.forward()
        if step is None:
            last_round = scores
            break
        steps.append(step)
        added += 1 + len(step.together)
        keep = {step.effect.label, *(e.label for e in step.together)}
        # each removal shrinks the model and an addition must pass the same paired test
        # that a removal failed, so this cannot cycle; bounded all the same
        for _ in range(len(search.current.model.effects)):
            back = search.backward(keep)
            if back is None:
                break
            steps.append(back)
    final_model, final = search.current.model, search.current.fit
    new_effects = [e for e in final_model.effects if e.key not in {b.key for b in model.effects}]
    return DiscoveryResult(
        data=data, blocks=blocks, config=cfg, base_model=model, base_p=base.fit.p,
        model=final_model, p=final.p, cov=final.cov,
        prior=Prior.from_sd(final.p, final_model.prior_sd()),
        steps=tuple(steps), last_round=last_round,
        selected=tuple(_selected(final_model, final, e, cfg) for e in new_effects),
        heldout_xi_base=base.heldout_xi, heldout_xi_final=search.current.heldout_xi,
        scored=scored,
        analysis_base=residual_analysis(model, base.fit.p, data, candidates(model, data, cfg)),
        analysis_final=residual_analysis(final_model, final.p, data))


def discover_pipeline(windows: Windows, aux_names: tuple[str, ...], t0_us: int,
                      model: SensorModel, p: np.ndarray,
                      cfg: DiscoveryConfig = DiscoveryConfig()) -> DiscoveryResult:
    """Rediscovery on a live pipeline's buffer: its windows (time from the pipeline's origin),
    its model and current values as the starting point (the model's s0 is kept)."""
    data = data_from_windows(windows, aux_names, t0_us)
    data = replace(data, s0=model.s0)
    return discover(data, model, p, cfg)
