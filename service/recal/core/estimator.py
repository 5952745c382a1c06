"""Linearized minimum-variance unbiased estimator (Lötters 1998, eq. 5-14), over the buffer.

Lötters linearizes h(v, p) = |a(v, p)| around the previous estimate p(-) (eq. 9-10) and solves

    q = (B^T C_mu^-1 B)^-1 B^T C_mu^-1 xi        eq. 11a   (q = p - p(-), eq. 12)
    C_e = (B^T C_mu^-1 B)^-1                      eq. 11b

with xi = 1 g - h(v, p(-)) (eq. 14) and B = dh/dp (eq. 13a). Each in-use update iterates that
step to convergence (Gauss-Newton, step halving on the nonlinear h) over every window mean the
orientation-balanced buffer holds (core/buffer.py), starting from the previous estimate. It goes
beyond the paper where the paper fails in use:

* Prior, information form: the pre-calibration's information Lambda_0 = C_0^-1 is added to
  B^T C_mu^-1 B and Lambda_0 (p_0 - p) to the right-hand side, so directions the buffer cannot
  observe (the paper's orientation-1 case: upright only) stay at the pre-calibration.
* Which parameters move is decided by the data: a parameter is estimated when the buffer informs
  it at least as much as the pre-calibration does (its marginal posterior sd, computed from the
  buffer's information at the current estimate, is below `observable_ratio` = 1/sqrt(2) of the
  prior's). The others stay exactly where they are (Lötters' offsets-only mode, per parameter).
* Ageing: parameters wander, so an old window says less about now. Each parameter random-walks
  with Q per hour (effects.py), so a window of age tau carries B Q B^T tau more variance in
  C_mu. And the offsets move smoothly: their rate of change r (3 values, prior sd
  `offset_rate_sd_g_per_h`) is fitted with them, a window of age tau saw the offsets o - r tau.
  That is what tracks a steady drift without lag (a random walk alone follows a ramp late).
* Jumps: when the latest windows contradict the estimate (each one's normalized innovation
  beyond 7 sigma, all to the same side: a knock, a re-mount), the offsets are given a step d at
  that time: older windows saw o - d, and the pre-calibration is then a prior on o - d. They
  keep telling the gains and cross-axis terms everything they did, and directions no new window
  informs keep their old offsets. Another jump moves the step to its time and drops the windows
  between the first jump and it (the long history before the first is kept).
* r and d are nuisances of the fit, not parameters of the sensor model (nothing in the model
  declares a drift or a knock; its parameters are the calibration now). They act exactly: the
  raw readings of a window are moved by its lag through the stages before the offsets.
* Gates: an update is rejected (the previous estimate kept) when it leaves physical bounds
  (an offset more than 0.5 g from the prior's zero-g, a gain outside 0.8-1.2 of nominal,
  ...), fails to lower the objective, or is not finite. Each update reports its residual,
  the condition of the posterior information and which parameters the data (not the prior)
  determined.
* Offsets-only mode (Lötters: "in case the sensitivities are assumed to be known and stable").

Why the whole buffer, re-linearized, rather than a recursive (Kalman) update of the fresh
windows: a recursive update keeps each window's information as linearized when it arrived, far
from the truth early on, and holds the cross-axis and gain terms of an axis not yet seen from
both sides fixed, so the offsets absorb them (docs/design.md, and its "Figures behind choices").

The pipeline tries an update every `update_every` committed windows but first asks
`consistent` (the new windows' normalized innovations, eq. 14, a chi-square and a mean test):
re-fitting windows that agree with the estimate would not move it (core/pipeline.py).

The records it reads and writes (`Prior`, `EstimatorConfig`, `Estimate`, `UpdateReport`) are
`core.estimate`'s, importable from here too.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from recal.core.buffer import Windows
from recal.core.effects import Covariates, Offset
from recal.core.estimate import Estimate, EstimatorConfig, Prior, UpdateReport
from recal.core.model import SensorModel

__all__ = ["Estimate", "EstimatorConfig", "Prior", "UpdateReport", "bounds_around", "consistent",
           "consistent_many", "innovations", "solve", "update"]


#: An update whose weighted residual (data + prior) ends above this factor times its start is
#: rejected (Gauss-Newton with step halving never raises it: this catches a broken model).
RESIDUAL_GATE = 1.05
#: The windows since the last update contradict the estimate (an offset jump: a knock) when each
#: one's normalized innovation squared exceeds this (7 sigma), all on the same side, judged on at
#: least JUMP_MIN_WINDOWS.
JUMP_NIS = 50.0
JUMP_MIN_WINDOWS = 3
JUMP_LOOKBACK_S = 60.0
#: Fresh windows agree with the estimate (`consistent`) when their normalized innovations pass
#: a chi-square test and a mean test at this false-alarm probability each.
CONSISTENT_ALPHA = 1e-3
#: Slots of at least this many windows measure how much window means disagree (`_window_variance`).
FLOOR_MIN_MERGED = 4
#: The median of a chi-square variable of one degree of freedom: a median of squared residuals
#: over it estimates their variance (`_posture_misfit_g2`).
CHI2_1_MEDIAN = 0.4549
#: The offsets' stage and key, asked at every residual (an `Offset()` made each time cost more)
_OFFSET_STAGE = Offset.stage
_OFFSET_KEY = ("offset", None)


def _window_variance(model: SensorModel, w: Windows, B: np.ndarray, now_us: int,
                     cfg: EstimatorConfig) -> np.ndarray:
    """C_mu diagonal per window: averaged sensor noise + floor + process noise since it was seen.

    The floor is per 2 s window, so a slot that merges k windows has floor^2 / k. Where the
    windows merged into a slot disagree in norm by more than the floor (a slow sway or
    vibration the detector let through: window means that follow it), the floor is raised to
    the median of that spread over the slots of at least FLOOR_MIN_MERGED windows: for every
    slot alike, so the short ones (whose spread is unknown) do not outweigh the long ones."""
    k = w.merged
    spread = (w.norm_var / model.s0**2)[k >= FLOOR_MIN_MERGED]
    floor2 = max(cfg.sigma_floor_g**2, _median(spread) if len(spread) else 0.0)
    noise = w.var / np.maximum(w.n, 1) / model.s0**2 + floor2 / k
    age_h = np.maximum(now_us - w.t_us, 0) / 3.6e9
    q = (cfg.process_scale * model.process_sd_per_sqrt_h()) ** 2
    drift = age_h * np.einsum("np,p,np->n", B, q, B)  # a window seen earlier says less of now
    return noise + drift


def _median(x: np.ndarray) -> float:
    """float(np.median(x)) of a non-empty 1-d float array, to the bit (the middle value, or the
    two middle ones' sum halved, as np.median's mean of them; NaN if any is), without
    np.median's per-call machinery: it ran at every update."""
    n = len(x)
    if np.isnan(x).any():
        return float("nan")
    h = n // 2
    if n % 2:
        return float(np.partition(x, h)[h])
    part = np.partition(x, (h - 1, h))
    return (float(part[h - 1]) + float(part[h])) / 2.0


@dataclass(frozen=True, eq=False)
class _Solution:
    p: np.ndarray
    cov_free: np.ndarray  # posterior covariance of the free parameters (nuisances marginalized)
    data_info: np.ndarray  # B^T C_mu^-1 B of the windows alone, free parameters
    iterations: int
    objective_start: float
    objective_end: float
    xi_start: np.ndarray
    xi_end: np.ndarray
    nuisance: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True, eq=False)
class _Offsets:
    """The in-use nuisances of the offsets (module doc), raw units: rate r per hour, and the
    step d that windows before step_us saw (o - d). Only the active ones are fitted: the rate
    when offset_rate_sd_g_per_h > 0, the step once a jump was detected."""

    rate: np.ndarray
    step: np.ndarray
    step_us: int | None

    def design(self, model: SensorModel, windows: Windows, now_us: int,
               cfg: EstimatorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per window, how much of each active nuisance its offsets lag by (M, blocks): its age
        in hours for the rate, 1 before the jump for the step; their start values and prior
        sd (3 per block)."""
        cols, start, sd = [np.zeros((len(windows), 0))], [np.zeros(0)], [np.zeros(0)]
        if model.has("offset"):
            if cfg.offset_rate_sd_g_per_h > 0:
                cols.append((np.maximum(now_us - windows.t_us, 0) / 3.6e9)[:, None])
                start.append(self.rate)
                sd.append(np.full(3, cfg.offset_rate_sd_g_per_h * model.s0))
            if self.step_us is not None:
                cols.append((windows.t_us < self.step_us).astype(float)[:, None])
                start.append(self.step)
                sd.append(model.prior_sd()[model.slice(Offset())])  # a jump: anything goes
        return np.hstack(cols), np.concatenate(start), np.concatenate(sd)

    def unpack(self, u: np.ndarray, cfg: EstimatorConfig) -> tuple[np.ndarray, np.ndarray]:
        """(rate, step) from the fitted values u (inactive ones as they were)."""
        rate, step, i = self.rate, self.step, 0
        if len(u) and cfg.offset_rate_sd_g_per_h > 0:
            rate, i = u[:3], 3
        if len(u) > i and self.step_us is not None:
            step = u[i:i + 3]
        return rate, step


@dataclass(frozen=True, eq=False)
class _Problem:
    """Everything fixed during one fit: the data, C_mu, the prior over x = [p, u] (u: the
    offsets' nuisances) and how much of u each window's offsets lag by (`_Offsets.design`)."""

    model: SensorModel
    windows: Windows
    cov: Covariates
    c_mu: np.ndarray
    mean: np.ndarray
    info: np.ndarray
    lag: np.ndarray  # (M, blocks)

    def _v(self, x: np.ndarray) -> np.ndarray:
        """Raw readings moved so that the model's offsets o act on each window as o - lag u
        (exact: through the stages before the offsets, which scale each row, e.g. ratiometric)."""
        P, nb = self.model.size, self.lag.shape[1]
        if nb == 0:
            return self.windows.v
        shift = self.lag @ x[P:].reshape(nb, 3)
        for e in self.model.effects:
            if e.stage >= _OFFSET_STAGE:
                break
            shift = shift / e.apply(np.ones_like(shift), self.cov, x[self.model.slice(e)])
        return self.windows.v + shift

    def residual(self, x: np.ndarray, jacobian: bool = False):
        P, nb = self.model.size, self.lag.shape[1]
        v = self._v(x)
        if not jacobian:
            return self.model.residual(x[:P], v, self.cov)
        xi, B = self.model.residual_jacobian(x[:P], v, self.cov)
        Bo = B[:, self.model.slice(_OFFSET_KEY)] if nb else np.zeros((len(xi), 3))
        # o_i = o - lag_i u: d|a|/du = -lag_i B_o
        return xi, np.hstack([B, *(-Bo * self.lag[:, b:b + 1] for b in range(nb))])

    def objective(self, xi: np.ndarray, x: np.ndarray) -> float:
        d = x - self.mean
        return float(np.sum(xi**2 / self.c_mu) + d @ self.info @ d)


def _problem(model: SensorModel, prior: Prior, p_start: np.ndarray, windows: Windows,
             cov: Covariates, now_us: int, cfg: EstimatorConfig,
             offsets: _Offsets | None) -> tuple[_Problem, np.ndarray, np.ndarray, np.ndarray]:
    """The fit's fixed parts, the start x = [p, u], and xi, B (with the nuisances) there."""
    if offsets is None:
        lag, u, sd = np.zeros((len(windows), 0)), np.zeros(0), np.zeros(0)
    else:
        lag, u, sd = offsets.design(model, windows, now_us, cfg)
    P, k = model.size, len(u)
    x = np.concatenate((np.asarray(p_start, np.float64), u))
    info = np.zeros((P + k, P + k))
    info[:P, :P] = prior.info
    info[P:, P:] = np.diag(1.0 / sd**2)  # nuisances: zero-mean priors
    if offsets is not None and offsets.step_us is not None and k >= 3:
        # the pre-calibration is a prior on the offsets before the jump, o - d (the last three
        # nuisances): where no window after the jump informs them, the offsets stay as they
        # were (d = 0), not halfway back to the pre-calibration
        T = np.eye(P + k)
        T[model.slice(Offset()), P + k - 3:] = -np.eye(3)
        info = T.T @ info @ T
    mean = np.concatenate((prior.mean, np.zeros(k)))
    pb = _Problem(model, windows, cov, np.ones(len(windows)), mean, info, lag)
    xi, B = pb.residual(x, jacobian=True)
    # C_mu from the parameters' own columns (the process noise of each parameter)
    pb = replace(pb, c_mu=_window_variance(model, windows, B[:, :P], now_us, cfg))
    return pb, x, xi, B


def solve(model: SensorModel, prior: Prior, p_start: np.ndarray, windows: Windows,
          cov: Covariates, now_us: int, cfg: EstimatorConfig,
          free: np.ndarray | None = None) -> _Solution:
    """Iterate Lötters eq. 11a (with prior rows) from p_start until the step is negligible: a
    plain batch fit (`static`, `discovery`). `free` masks the parameters to estimate; the
    others stay at p_start."""
    free = np.ones(model.size, bool) if free is None else np.asarray(free, bool)
    pb, x, xi, B = _problem(model, prior, p_start, windows, cov, now_us, cfg, None)
    return _fit(pb, x, xi, B, free, cfg)


def _fit(pb: _Problem, x: np.ndarray, xi: np.ndarray, B: np.ndarray, free_x: np.ndarray,
         cfg: EstimatorConfig) -> _Solution:
    """Gauss-Newton on the problem from x (xi, B there) over the free entries of x =
    [p, nuisances]; the covariance of the free model parameters marginalizes the nuisances."""
    P = pb.model.size
    fx = free_x
    if len(free_x) < len(x):
        fx = np.concatenate((free_x, np.ones(len(x) - len(free_x), bool)))
    D = 1.0 / np.sqrt(np.diag(pb.info))[fx]  # scale to the prior spread: conditions A
    L0 = pb.info[np.ix_(fx, fx)]
    j_start = j = pb.objective(xi, x)
    xi_start, it = xi, 0
    prior_a = D[:, None] * L0 * D[None, :]  # the same at every iteration
    info_f, tol_d = pb.info[fx], cfg.tol * D
    for it in range(1, cfg.max_iter + 1 if fx.any() else 1):  # noqa: B007 - `it` is reported
        Bf = B[:, fx] * D
        A = Bf.T @ (Bf / pb.c_mu[:, None]) + prior_a
        b = Bf.T @ (xi / pb.c_mu) + D * (info_f @ (pb.mean - x))
        step = D * np.linalg.lstsq(A, b, rcond=1e-12)[0]  # eq. 11a, scaled
        for _ in range(12):  # halve the step until the objective falls (nonlinear h)
            trial = x.copy()
            trial[fx] += step
            # the Jacobian only for a step taken that is not negligible (the next iteration's;
            # xi is the same with or without it)
            more = not np.all(np.abs(step) <= tol_d)
            xi_t, B_t = pb.residual(trial, jacobian=True) if more else (pb.residual(trial), B)
            j_t = pb.objective(xi_t, trial)
            if np.isfinite(j_t) and j_t <= j:
                break
            step = step / 2
        else:
            break
        x, j, xi = trial, j_t, xi_t
        if not more:
            break  # B of the last point serves for C_e: the step is negligible
        B = B_t
    Bf = B[:, fx]
    data_info = Bf.T @ (Bf / pb.c_mu[:, None])
    cov_x = _inv(data_info + L0)  # eq. 11b with the prior's information
    nf = int(fx[:P].sum())
    return _Solution(x[:P], cov_x[:nf, :nf], data_info[:nf, :nf], it, j_start, j,
                     xi_start, xi, x[P:])


def _informed(pb: _Problem, B: np.ndarray, ratio: float) -> np.ndarray:
    """Entries of x = [p, nuisances] the windows inform at least as much as their priors do
    (everything unknown, at the problem's start): marginal posterior sd < ratio x prior sd."""
    D = 1.0 / np.sqrt(np.diag(pb.info))
    Bs = B * D
    post = _inv(Bs.T @ (Bs / pb.c_mu[:, None]) + D[:, None] * pb.info * D[None, :])
    return np.sqrt(np.clip(np.diag(post), 0, None)) < ratio


def _observability(sol: _Solution, prior: Prior, free: np.ndarray,
                   cfg: EstimatorConfig) -> tuple[np.ndarray, float]:
    """Observed = the estimate's sd is below observable_ratio x the pre-calibration's; the
    condition number is that of the posterior information, scaled by the prior sd."""
    post_sd = np.sqrt(np.clip(np.diag(sol.cov_free), 0, None))
    observable = np.zeros(len(free), bool)
    D = prior.sd[free]
    observable[free] = post_sd < cfg.observable_ratio * D
    ev = np.linalg.eigvalsh(D[:, None] * _inv(sol.cov_free) * D[None, :])
    condition = float(ev[-1] / max(ev[0], 1e-300)) if len(ev) else 1.0  # nothing estimated
    return observable, condition


def _take(windows: Windows, cov: Covariates, m: np.ndarray) -> tuple[Windows, Covariates]:
    return (Windows(windows.v[m], windows.aux[m], windows.t_us[m], windows.n[m],
                    windows.var[m], windows.merged[m], windows.norm_var[m]),
            Covariates(cov.t_h[m], cov.aux[m], cov.aux_names))


def _posture_misfit_g2(model: SensorModel, estimate: Estimate, pb: _Problem,
                       xi: np.ndarray, cfg: EstimatorConfig, robust: bool = False) -> float:
    """What the model misses at a posture (g^2): the mean square of the norm residuals xi at
    the estimate beyond their noise (C_mu's averaged sensor noise and floor; not its ageing,
    which is the parameters' wander and would hide it), over the windows older than the jump
    test's look-back (in-sample: scaled by N / (N - P) for the P parameters fitted to them); 0
    while they are too few to say (N <= 2 P). A still posture's window means share its misfit
    (a cross-axis term or a gain the model lacks moves them all alike), so merging them
    (`core.buffer`) lowers their noise, not that: a model that misses 3 mg does so at each new
    posture. robust: the median excess over CHI2_1_MEDIAN instead of the mean (a few windows
    far off, another sensor's, do not move it)."""
    if estimate.t_us is None:
        return 0.0
    old = pb.windows.t_us <= estimate.t_us - round(JUMP_LOOKBACK_S * 1e6)
    n, k = int(old.sum()), model.size
    if n <= 2 * k:
        return 0.0
    w = pb.windows
    noise = (w.var[old] / np.maximum(w.n[old], 1) / model.s0**2
             + cfg.sigma_floor_g**2 / w.merged[old])
    excess_i = (xi[old] ** 2) * n / (n - k) - noise
    excess = _median(excess_i) / CHI2_1_MEDIAN if robust else float(np.mean(excess_i))
    return max(excess, 0.0)


def _z2_newest(model: SensorModel, estimate: Estimate, w: Windows, xi: np.ndarray,
               B: np.ndarray, cfg: EstimatorConfig, misfit_g2: float = 0.0) -> float:
    """An upper bound of the normalized innovation squared `_jump` finds for the newest of the
    windows w, from their xi and B (with the nuisances) at the estimate: its C_mu without the
    raised floor and the ageing terms of `_window_variance`, which only add to it. A relative
    margin covers rounding."""
    if not len(w):
        return 0.0
    i = int(np.argsort(w.t_us, kind="stable")[-1])
    Bi = B[i, :model.size]
    c_min = (w.var[i] / max(w.n[i], 1) / model.s0**2 + cfg.sigma_floor_g**2 / w.merged[i]
             + misfit_g2)
    return float(xi[i] ** 2 / (c_min + Bi @ estimate.cov @ Bi)) * (1.0 + 1e-9)


def _jump(model: SensorModel, estimate: Estimate, windows: Windows, cov: Covariates,
          now_us: int, cfg: EstimatorConfig, newest_z2: float,
          misfit_g2: float = 0.0) -> int | None:
    """The time of an offset jump (a knock), if the latest windows contradict the estimate:
    the newest ones (at least JUMP_MIN_WINDOWS, some since the last update) each with a
    normalized innovation xi^2 / (C_mu + B C_e B^T + m) above JUMP_NIS, all of the same sign
    (m: what the model misses at a posture, `_posture_misfit_g2`: a posture the buffer has
    not shown, where the model misses, is no jump). The
    jump is dated at the first of that run of windows, looking back up to JUMP_LOOKBACK_S
    before the last update (a jump in the middle of the previous update's windows). None: no
    jump, or too little fresh data to say. newest_z2: `_z2_newest` (the newest window must be
    one of that run, and this bound is cheap)."""
    if estimate.t_us is None or not model.has("offset") or newest_z2 <= JUMP_NIS:
        return None
    recent = windows.t_us > estimate.t_us - round(JUMP_LOOKBACK_S * 1e6)
    if windows.merged[windows.t_us > estimate.t_us].sum() < JUMP_MIN_WINDOWS:
        return None
    w, c = _take(windows, cov, recent)
    order = np.argsort(w.t_us, kind="stable")
    offsets = _Offsets(estimate.rate, estimate.step, estimate.step_us)
    pb, _, xi, B = _problem(model, Prior(estimate.p, np.eye(model.size)), estimate.p, w, c,
                            now_us, cfg, offsets)
    B = B[:, :model.size]
    z = (xi / np.sqrt(pb.c_mu + np.einsum("np,pq,nq->n", B, estimate.cov, B)
                      + misfit_g2))[order]
    # far off window after window: a shift of the offsets does that, shaking that passed the
    # detector (window means scattered around the truth, some close to it) does not
    off = z**2 > JUMP_NIS
    first = len(off) - int(np.argmin(off[::-1])) if not off.all() else 0
    run = order[first:]
    if (w.merged[run].sum() < JUMP_MIN_WINDOWS or not len(run)
            or not np.any(w.t_us[run] > estimate.t_us)):
        return None
    return int(w.t_us[run].min())


def _start(model: SensorModel, prior: Prior, start: Estimate, windows: Windows,
           cov: Covariates, now_us: int, cfg: EstimatorConfig
           ) -> tuple[_Offsets, _Problem, np.ndarray, np.ndarray, np.ndarray]:
    """The update's problem from `start` (`_problem`): without the windows between two jumps,
    whose offsets were neither the old nor the new ones."""
    if start.drop_us is not None:
        windows, cov = _take(windows, cov, (windows.t_us < start.drop_us)
                             | (windows.t_us >= start.step_us))
    offsets = _Offsets(start.rate, start.step, start.step_us)
    return offsets, *_problem(model, prior, start.p, windows, cov, now_us, cfg, offsets)


def update(model: SensorModel, prior: Prior, estimate: Estimate, windows: Windows,
           cov: Covariates, now_us: int, cfg: EstimatorConfig,
           free: np.ndarray | None = None, robust_misfit: bool = False
           ) -> tuple[Estimate, UpdateReport]:
    """One gated in-use update: the buffer's windows, from the previous estimate.

    Args:
        prior: the pre-calibration (the prior rows; the reference for observability).
        estimate: the previous estimate: the starting point, and what is kept on rejection.
        windows: every window the buffer holds; cov: their covariates.
        free: parameters allowed to move at all; the data (see `_informed`) and the mode narrow
            it further.
        robust_misfit: the jump test's allowance for what the model misses at a posture is
            the median's, not the mean's (`_posture_misfit_g2`): the self-watch asks whether a
            first jump repeats, and a swapped sensor's windows must not widen it.
    Returns the estimate to use next (the previous one if the update was rejected) and a report.
    """
    n = int(windows.merged.sum())
    free = np.ones(model.size, bool) if free is None else np.asarray(free, bool).copy()
    if cfg.mode == "offsets":
        free &= model.mask(["offset"]) & ~_covariate_mask(model)
    if n < cfg.min_windows:
        return estimate, UpdateReport(False, "too few windows", n)
    start, reason_ok = estimate, "ok"
    offsets, pb, x, xi, B = _start(model, prior, start, windows, cov, now_us, cfg)
    misfit_g2 = _posture_misfit_g2(model, estimate, pb, xi, cfg, robust_misfit)
    newest = _z2_newest(model, estimate, pb.windows, xi, B, cfg, misfit_g2)  # never dropped
    t_jump = _jump(model, estimate, windows, cov, now_us, cfg, newest, misfit_g2)
    if t_jump is not None:  # the older windows saw offsets a step away; an older step: dropped
        first = estimate.drop_us if estimate.drop_us is not None else estimate.step_us
        start = replace(estimate, step=np.zeros(3), step_us=t_jump, drop_us=first)
        reason_ok = "ok; the offsets jumped"
        offsets, pb, x, xi, B = _start(model, prior, start, windows, cov, now_us, cfg)
    informed = _informed(pb, B, cfg.observable_ratio)
    if start.step_us is not None:
        # after a jump the offsets are the old ones plus the step, whose prior keeps the
        # directions no new window informs where they were: estimate both, or the gains would
        # absorb what the jump did to the new windows
        informed[:model.size][model.mask(["offset"]) & ~_covariate_mask(model)] = True
        informed[-3:] = True
    free &= informed[:model.size]
    sol = _fit(pb, x, xi, B, np.concatenate((free, informed[model.size:])), cfg)
    observable, condition = _observability(sol, prior, free, cfg)
    rms = (float(np.sqrt(np.mean(sol.xi_start**2))), float(np.sqrt(np.mean(sol.xi_end**2))))
    flags = (condition, tuple(map(bool, observable)), tuple(map(bool, free)))
    reason = _gate(model, sol, prior)
    if reason is not None:
        return estimate, UpdateReport(False, reason, n, sol.iterations, *rms, *flags)
    cov_full = np.diag(prior.sd**2)  # a parameter not estimated is as uncertain as the prior
    cov_full[np.ix_(free, free)] = sol.cov_free
    rate, step = offsets.unpack(sol.nuisance, cfg)
    new = Estimate(sol.p, cov_full, now_us, rate, step, start.step_us, start.drop_us)
    return new, UpdateReport(True, reason_ok, n, sol.iterations, *rms, *flags)


def innovations(model: SensorModel, estimate: Estimate, windows: Windows, cov: Covariates,
                cfg: EstimatorConfig) -> np.ndarray:
    """Normalized innovations z of windows under the estimate: xi = 1 g - h(v, p) (Lötters
    eq. 14) over its variance C_mu + B C_e B^T (eq. 11b: the estimate's own uncertainty; eq.
    13a: B). Cheap: one Jacobian of the windows given, no fit. Non-finite: inf."""
    xi, B = model.residual_jacobian(estimate.p, windows.v, cov)
    s2 = (windows.var / np.maximum(windows.n, 1) / model.s0**2 + cfg.sigma_floor_g**2
          + np.einsum("np,pq,nq->n", B, estimate.cov, B))
    z = xi / np.sqrt(s2)
    return np.where(np.isfinite(z), z, np.inf)


def consistent(m: int, sum_z2: float, sum_z: float) -> bool:
    """Whether m windows with these sums of normalized innovations (`innovations`) agree with
    the estimate, so that re-fitting would not move it: two tests at CONSISTENT_ALPHA, sum z^2
    below the chi-square quantile with m degrees of freedom (scatter beyond the noise: a knock,
    a new effect) and |sum z| / sqrt(m) below the normal quantile (a common shift: the offsets
    drifting while the wearer holds one posture)."""
    return bool(consistent_many(np.array([m]), np.array([sum_z2]), np.array([sum_z]))[0])


def consistent_many(m: np.ndarray, sum_z2: np.ndarray, sum_z: np.ndarray) -> np.ndarray:
    """`consistent` for many (m, sums) at once (m = 0: nothing to contradict)."""
    m = np.asarray(m, np.float64)
    mm = np.maximum(m, 1.0)
    ok = (sum_z2 <= _chi2_quantile(mm)) & (np.abs(sum_z) <= _Z_ALPHA * np.sqrt(mm))
    return ok | (m == 0)


#: normal quantiles at CONSISTENT_ALPHA: two-sided (the mean test), one-sided (Wilson-Hilferty)
_Z_ALPHA = 3.2905
_Z_ONE_SIDED = 3.0902


def _chi2_quantile(m: np.ndarray) -> np.ndarray:
    """Chi-square 1 - CONSISTENT_ALPHA quantile, m degrees of freedom (Wilson-Hilferty: 1.7 %
    above the exact one at m = 3, within 0.6 % from m = 10 on; no scipy call per test)."""
    h = 2.0 / (9.0 * m)
    return m * (1.0 - h + _Z_ONE_SIDED * np.sqrt(h)) ** 3


def bounds_around(model: SensorModel, prior: Prior) -> tuple[np.ndarray, np.ndarray]:
    """The model's physical bounds (`SensorModel.bounds`), the offsets' around the prior's
    zero-g: an analog part on an unsigned ADC reads ~2048 counts at 0 g, and its offsets may
    move 0.5 g from there, not from 0. Gains are bounded around the model's s0 (the prior's
    nominal sensitivity, or the bootstrap's fitted scale)."""
    lo, hi = model.bounds()
    if model.has("offset"):
        sl = model.slice(Offset())
        lo[sl] += prior.mean[sl]
        hi[sl] += prior.mean[sl]
    return lo, hi


def _gate(model: SensorModel, sol: _Solution, prior: Prior) -> str | None:
    """Why an update must be rejected, or None."""
    lo, hi = bounds_around(model, prior)
    if not (np.all(np.isfinite(sol.p)) and np.all(np.isfinite(sol.cov_free))
            and np.all(np.isfinite(sol.nuisance))):
        return "not finite"
    if np.any(sol.p < lo) or np.any(sol.p > hi):
        bad = [nm for nm, x, a, b in zip(model.names, sol.p, lo, hi, strict=True)
               if not a <= x <= b]
        return f"out of bounds: {', '.join(bad)}"
    if sol.objective_end > RESIDUAL_GATE * sol.objective_start + 1e-9:
        return "residual rose"
    return None


def _inv(a: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric information or covariance matrix (the prior makes it positive
    definite; the pseudo-inverse only if it is singular all the same)."""
    try:
        return np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(a)


def _covariate_mask(model: SensorModel) -> np.ndarray:
    return np.concatenate([np.full(e.size, e.covariate is not None) for e in model.effects])
