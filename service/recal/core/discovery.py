"""Effect discovery: fit, look at what is left, find the effect the model lacks, add it.

A still sensor reads 1 g (Lötters 1998, eq. 8 and 14: xi = 1 g - |a|). On the quasi-static
window means of a recording (the live detector and windowing, `window_means.window_means`) or on
the rows of a static table, `discover`:

1. fits the current model by the batch form of Lötters eq. 11a (`model_fit.fit_model`,
   iterated Gauss-Newton), with the live estimator's default prior, over the parameters the
   poses can determine (`model_fit.free_params`: a gain needs its axis seen from both sides, an
   offset its axis seen at all);
2. analyses the residual (`residuals`): xi per window and its correlation with every auxiliary
   channel, with time and with the gravity direction; and, per candidate effect, the fraction
   of xi that the candidate's Jacobian columns (eq. 13a at the effect's nominal value,
   orthogonalized against the model's own columns) explain: a score test of what the residual
   looks like;
3. builds the candidates (`candidates`: the forms each registered effect proposes): for every
   auxiliary channel c, whatever it is called, an offset linear in c (3 parameters), a gain
   linear in c (3), the whole output ratiometric in c (1), and ratiometric in c with every
   other channel r as the reference rail (2); cross-axis with the rotation gauge fixed (3),
   per-axis quadratic nonlinearity (3), offset linear in time (3);
4. scores each candidate on held-out data: the windows are cut into `blocks` contiguous time
   blocks (rows in table order for a table) and each block is predicted by a fit on the
   others (from those blocks' own start, for every model alike: a score must not depend on
   the route to the model), so neighbouring windows, which share posture, temperature and
   drift, never sit on both sides of a split (boundaries move into the movement between
   still runs); a window in a pose that only its own block covers is not scored
   (`discovery_data.scorable`): no model can be tested where the others cannot see the gain;
5. accepts by this criterion: the relative reduction of the held-out sum of squares of xi,
   R = 1 - SS_candidate / SS_model, must exceed both t bootstrap standard errors (blocks
   resampled with replacement; t is Student's 97.5 % quantile for blocks - 1 degrees of
   freedom, 2.26 for 10 blocks) and `min_gain` (5 %); and what it explains, in mg, must exceed
   the noise of a window mean (`noise_mg`; times sqrt(2) for a pair: each of its effects must
   explain as much): below that the folds' own scatter reaches it, and an effect that small
   moves no output the user sees. Of the candidates that pass, the largest R wins, unless a
   simpler one passes too (fewer directions the data determine, then KIND_ORDER) and the winner
   does not beat it by the same criterion. When no candidate passes alone, pairs of those the
   score test ranks highest are tried (two effects whose channels drift together can each
   fail alone);
6. adds the winner, then removes an earlier addition that no longer passes the same test
   against the model without it (or reduces a ratiometric effect with a reference to one
   channel), and repeats until nothing passes. Last, a step in time of the model given
   (`time_step.best_step`: it fitted apart before and after a block boundary, a sensor swapped
   or knocked) must not leave clearly less (by min_gain, in-sample) than the model found: if
   it does, the additions explained a step, and none is kept (`DiscoveryResult.step_in_time`).

The result carries the extended model with its fitted values and a `Prior` (the fitted values,
the model's default spreads) for the live estimator to start from. Why held-out blocks and this
criterion: docs/design.md ("Effect discovery"); what it finds: docs/performance.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from recal.core.buffer import Windows
from recal.core.candidates import KIND_ORDER, smaller_models
from recal.core.candidates import candidates as proposed_on
from recal.core.discovery_criterion import explained_mg, noise_mg, paired_gain
from recal.core.discovery_data import (
    MAX_WINDOWS,
    DiscoveryData,
    data_from_windows,
    scorable,
    thinned,
    time_blocks,
)
from recal.core.effects import Effect, Scale
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.model_fit import (
    FitConfig,
    ModelFit,
    Scored,
    carry_params,
    free_params,
    norm_error_g,
    score_heldout,
    start_params,
)
from recal.core.residuals import (
    MisfitProfile,
    ResidualAnalysis,
    explained_fraction,
    misfit,
    residual_analysis,
)
from recal.core.time_step import TimeStep, best_step, in_sample_ss
from recal.errors import ConfigError, InputError

__all__ = [
    "CandidateScore",
    "DiscoveryConfig",
    "DiscoveryResult",
    "SelectedEffect",
    "Step",
    "candidates",
    "discover",
    "discover_pipeline",
    "n_se_for",
    "noise_mg",
]


@dataclass(frozen=True)
class DiscoveryConfig:
    """Settings of the selection.

    Attributes:
        blocks: contiguous time blocks (k-fold over blocks) for held-out scoring.
        min_gain: smallest relative reduction of the held-out sum of squares worth an effect
            (also the margin by which the model with it must leave less than a step in time).
        noise_floor: what an effect explains of the held-out error (RMS over the scored
            windows, mg) must exceed this many times the noise of a window mean (times the
            square root of the effects added at once).
        time_step: test each winner against a step in time (`time_step.best_step`).
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
        kinds: candidate kinds to try (any of `candidates.KIND_ORDER`: offset, gain,
            ratiometric, cross_axis, nonlinearity); `time` whether to try effects in time.
        max_windows: the selection runs on at most this many windows (`thinned`).
    """

    blocks: int = 10
    min_gain: float = 0.05
    noise_floor: float = 1.0
    time_step: bool = True
    n_se: float | None = None
    prefer_simpler: bool = True
    pairs: int = 4
    bootstrap: int = 2000
    seed: int = 0
    max_steps: int = 6
    prior_scale: float = FitConfig.prior_scale
    sigma_floor_g: float = FitConfig.sigma_floor_g
    max_iter: int = FitConfig.max_iter
    observable_ratio: float = 0.5
    kinds: tuple[str, ...] = KIND_ORDER
    time: bool = True
    max_windows: int = MAX_WINDOWS

    def __post_init__(self) -> None:
        if self.blocks < 3:
            raise ConfigError("discovery needs at least 3 blocks for held-out scoring")
        if not (self.min_gain >= 0 and self.noise_floor >= 0
                and (self.n_se is None or self.n_se >= 0) and self.bootstrap >= 10):
            raise ConfigError("min_gain, noise_floor and n_se must be >= 0 and bootstrap >= 10")

    def fit(self) -> FitConfig:
        """The settings of each fit."""
        return FitConfig(self.prior_scale, self.sigma_floor_g, self.max_iter)


def candidates(model: SensorModel, data: DiscoveryData,
               cfg: DiscoveryConfig = DiscoveryConfig()) -> list[tuple[Effect, float]]:
    """Every effect (with its covariate spread) the model could be extended by
    (`candidates.candidates` with the settings' kinds and time)."""
    return proposed_on(model, data, cfg.kinds, cfg.time)


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
        step_in_time: the step in time that left clearly less than the effects found
            (`stepped`), which were then dropped; None: no step did.
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
    step_in_time: TimeStep | None = None
    stepped: str = ""

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

    def misfit(self) -> MisfitProfile | None:
        """What the final fit leaves beyond the noise of the window means (`residuals.misfit`;
        None for a table, whose rows carry no noise)."""
        w = self.data.windows
        if self.data.source != "windows" or not len(w):
            return None
        noise2 = w.var / np.maximum(w.n, 1) / self.data.s0**2
        if not (np.all(np.isfinite(noise2)) and noise2.any()):
            return None
        return misfit(self.model.residual(self.p, w.v, self.data.cov), noise2, w.t_us,
                      a=self.corrected())

    def corrected(self, final: bool = True) -> np.ndarray:
        """The windows corrected by the final (or base) fit on all windows, g (M,3)."""
        model, p = (self.model, self.p) if final else (self.base_model, self.base_p)
        return model.correct(p, self.data.windows.v, self.data.cov)


def _rms_mg(xi: np.ndarray) -> float:
    return 1e3 * float(np.sqrt(np.mean(xi**2))) if len(xi) else float("nan")


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
    # in units of the data's own scale (the mean fitted one), as the report's model is
    # described (`pipeline.gain_reference` without a prior), not of s0, a median norm
    ref = float(np.mean(fit.p[model.slice(Scale())])) if model.has("scale") else model.s0
    return SelectedEffect(
        effect.kind, effect.covariate, getattr(effect, "reference", None), effect.label,
        effect.describe(theta, ref), dict(zip(names, map(float, theta), strict=True)),
        dict(zip(names, map(float, sd), strict=True)),
        {n: bool(s < cfg.observable_ratio * d)
         for n, s, d in zip(names, sd, prior_sd, strict=True)}, extra)


def n_se_for(cfg: DiscoveryConfig, n_blocks: int) -> float:
    """How many standard errors R must exceed (cfg.n_se, or Student's t, see above)."""
    if cfg.n_se is not None:
        return cfg.n_se
    from scipy import special  # here, as stats.t.ppf: scipy.stats costs ~0.5 s and ~60 MB
    return float(special.stdtrit(max(n_blocks - 1, 1), 0.975))


def _passes(gain: float, se: float, cfg: DiscoveryConfig, n_blocks: int,
            explained_mg: float = np.inf, noise_mg: float = 0.0) -> bool:
    return (gain > max(cfg.min_gain, n_se_for(cfg, n_blocks) * se)
            and explained_mg > cfg.noise_floor * noise_mg)


@dataclass
class _Search:
    """The state of one selection: data, blocks, settings and the model scored so far."""

    data: DiscoveryData
    blocks: np.ndarray
    cfg: DiscoveryConfig
    base: SensorModel
    current: Scored
    scored: np.ndarray
    starts: tuple[tuple[np.ndarray, ...], np.ndarray]  # the given model's, fold by fold; all
    noise_mg: float = 0.0

    @property
    def n_blocks(self) -> int:
        return int(self.blocks.max()) + 1

    def ss(self, sc: Scored) -> np.ndarray:
        return sc.block_ss(self.blocks, self.n_blocks, self.scored)

    def rms(self, sc: Scored) -> float:
        return _rms_mg(sc.heldout_xi[self.scored])

    def compare(self, small: Scored, big: Scored) -> tuple[float, float, bool]:
        """R of big over small, its SE, and whether big passes the criterion."""
        ss_s, ss_b = self.ss(small), self.ss(big)
        gain, se = paired_gain(ss_s, ss_b, self.cfg.bootstrap, self.cfg.seed)
        explained = explained_mg(ss_s, ss_b, int(self.scored.sum()))
        added = max(1, len(big.model.effects) - len(small.model.effects))
        return gain, se, _passes(gain, se, self.cfg, self.n_blocks, explained,
                                 self.noise_mg * np.sqrt(added))

    def rescore(self, model: SensorModel) -> Scored:
        """`model` scored from the given model's own starts (a fold's from its training blocks
        alone), other effects at nominal: never from another model's fit, also the prior's
        mean (a smaller model's fold gone astray held every larger one there)."""
        fresh, fresh_all = self.starts
        return score_heldout(model, self.data, self.blocks,
                             [carry_params(self.base, s, model) for s in fresh],
                             carry_params(self.base, fresh_all, model), self.cfg.fit())

    def _choose(self, scores: list[CandidateScore], scored: list[Scored]) -> int | None:
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
        xi_now = norm_error_g(cur.model, cur.fit.p, data)
        scored, scores = [], []
        for eff, spread in cands:
            sc = self.rescore(cur.model.with_effect(eff, spread))
            gain, se, ok = self.compare(cur, sc)
            scored.append(sc)
            scores.append(CandidateScore(
                eff.label, eff.kind, eff.covariate, getattr(eff, "reference", None), eff.size,
                sc.fit.n_observed - cur.fit.n_observed, self.rms(sc), gain, se,
                explained_fraction(cur.model, cur.fit.p, data, xi_now, eff, spread), ok))
        pick = self._choose(scores, scored)
        if pick is not None:
            new, eff = scored[pick], cands[pick][0]
            step = Step(_selected(new.model, new.fit, eff, cfg), self.rms(cur), self.rms(new),
                        scores[pick].gain, scores[pick].se, tuple(scores))
            self.current = new
            return step, tuple(scores)
        return self._pair(cands, scores, scored), tuple(scores)

    def _pair(self, cands: list[tuple[Effect, float]], scores: list[CandidateScore],
              scored: list[Scored]) -> Step | None:
        """For each of the `pairs` candidates the score test ranks highest, fitted, the
        partner the residual then points at most (score test again); the best pair that
        passes against the current model."""
        cur, cfg, data = self.current, self.cfg, self.data
        top = sorted(range(len(cands)), key=lambda i: -scores[i].explained)[:cfg.pairs]
        best: tuple[float, float, Scored, Effect, Effect] | None = None
        tried: set[frozenset[int]] = set()
        for i in top:
            first = scored[i]
            xi_i = norm_error_g(first.model, first.fit.p, data)
            partners = []
            for j, (e2, sp2) in enumerate(cands):
                e1 = cands[i][0]
                if j == i or (e1.kind == e2.kind == "ratiometric"
                              and set(e1.channels) & set(e2.channels)):
                    continue  # the same supply scaling twice
                if e2.key in {e.key for e in first.model.effects}:
                    continue
                partners.append(
                    (explained_fraction(first.model, first.fit.p, data, xi_i, e2, sp2), j))
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
            for action, alt, remaining in smaller_models(cur.model, eff, self.data):
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


def _step_instead(search: _Search, base: Scored) -> TimeStep | None:
    """The step in time of the given model (`time_step.best_step`) when it leaves clearly less,
    by min_gain, than the model discovery arrived at (in-sample), else None."""
    if not search.cfg.time_step:
        return None
    step = best_step(base.model, base.fit.p, search.data, search.blocks, search.cfg.fit())
    cur = search.current
    if step is None or step.ss_g2 >= (1.0 - search.cfg.min_gain) * in_sample_ss(
            cur.model, cur.fit.p, search.data):
        return None
    return step


def discover(data: DiscoveryData, model: SensorModel | None = None,
             p: np.ndarray | None = None,
             cfg: DiscoveryConfig = DiscoveryConfig()) -> DiscoveryResult:
    """Stepwise selection of effects by held-out error (see the module docstring): add the
    best candidate that passes (or the best passing pair when none passes alone), then drop
    an earlier addition the new one made redundant; stop when nothing passes.

    model: the current model (default: Lötters' diagonal one at the data's s0); p: its
    current values (default: an ellipsoid / sphere fit, or nominal for too few poses).
    The selection runs on at most cfg.max_windows windows, every k-th (`thinned`).
    """
    data = thinned(data, max(cfg.max_windows, 3 * cfg.blocks))
    n_blocks = min(cfg.blocks, len(data))
    if n_blocks < 3:
        raise InputError(f"{len(data)} windows are too few for held-out scoring (need 3)")
    if model is None:
        model = SensorModel.diagonal(data.s0)
    blocks = time_blocks(data.windows.t_us, n_blocks)
    p_all = start_params(model, data) if p is None else np.asarray(p, np.float64)
    starts = [start_params(model, data.subset(blocks != k)) for k in range(n_blocks)]
    base = score_heldout(model, data, blocks, starts, p_all, cfg.fit())
    scored = scorable(data, blocks, model.correct(base.fit.p, data.windows.v, data.cov))
    if not scored.any():
        raise InputError("no held-out window lies in a pose the other blocks saw")
    search = _Search(data, blocks, cfg, model, base, scored, (tuple(starts), p_all),
                     noise_mg(data, scored))
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
    new_effects = [e for e in search.current.model.effects
                   if e.key not in {b.key for b in model.effects}]
    step = _step_instead(search, base) if new_effects else None
    stepped = " + ".join(e.label for e in new_effects) if step is not None else ""
    if step is not None:  # the additions explained a step in time: none is kept
        search.current, steps, last_round, new_effects = base, [], (), []
    final_model, final = search.current.model, search.current.fit
    return DiscoveryResult(
        data=data, blocks=blocks, config=cfg, base_model=model, base_p=base.fit.p,
        model=final_model, p=final.p, cov=final.cov,
        prior=Prior.from_sd(final.p, final_model.prior_sd()),
        steps=tuple(steps), last_round=last_round,
        selected=tuple(_selected(final_model, final, e, cfg) for e in new_effects),
        heldout_xi_base=base.heldout_xi, heldout_xi_final=search.current.heldout_xi,
        scored=scored,
        analysis_base=residual_analysis(model, base.fit.p, data, candidates(model, data, cfg)),
        analysis_final=residual_analysis(final_model, final.p, data),
        step_in_time=step, stepped=stepped)


def discover_pipeline(windows: Windows, aux_names: tuple[str, ...], t0_us: int,
                      model: SensorModel, p: np.ndarray,
                      cfg: DiscoveryConfig = DiscoveryConfig()) -> DiscoveryResult:
    """Rediscovery on a live pipeline's buffer: its windows (time from the pipeline's origin),
    its model and current values as the starting point (the model's s0 is kept)."""
    data = data_from_windows(windows, aux_names, t0_us)
    data = replace(data, s0=model.s0)
    return discover(data, model, p, cfg)
