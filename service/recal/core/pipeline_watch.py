"""The pipeline's self-watch (`core.pipeline`; the rules: `core.status.Watch`): each committed
window against the estimate (a gross contradiction, the misfit), the events a change of its
verdict gives, the reset to the prior when the contradiction is sustained, and the heal of an
estimate that is not finite. Functions of the pipeline they change.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from recal.core.bootstrap import TURN_SD_G
from recal.core.buffer import Window, WindowBuffer
from recal.core.estimator import Estimate
from recal.core.outputs import UpdateEvent, WatchEvent
from recal.core.pipeline_fit import learned_step, refill_buffer, update_at
from recal.core.quantization import rounding_g2
from recal.core.refit import WindowChunk
from recal.core.sigma import predicted_sigma_mg
from recal.core.status import Watch, gross

if TYPE_CHECKING:
    from recal.core.pipeline_state import PipelineParts

__all__ = ["contradicts", "heal_if_not_finite", "reset_estimate", "watch_window"]


def contradicts(pipe: PipelineParts, chunk: WindowChunk, i: int, ok: bool, n: int,
                var: float) -> bool:
    """Window i of the chunk against the estimate: whether it contradicts grossly
    (`status.gross`); if not and it passed the norm gate, its residual feeds the misfit
    (`status.Misfit`), which goes on the output from this window on when it moved."""
    if pipe.estimate is None or chunk.norm is None:
        return False
    if chunk.sigma_mg is None:  # once per chunk, under the parameters it was cut with
        _, _, p, cov, form, *_ = pipe._segment_cache()
        w = chunk.w
        chunk.sigma_mg = predicted_sigma_mg(pipe.model, p, cov, w.v,
                                            pipe.covariates(w.t_us, w.aux), form)
    r_g = chunk.norm_at(i) - 1.0
    sigma_c_mg = chunk.sigma_at(i)
    s0 = pipe.model.s0
    noise_g2 = (var / max(n, 1) / (s0 * s0)
                + float(rounding_g2(np.array([var]), s0, learned_step(pipe))[0])
                if math.isfinite(var) else 0.0)
    misfit = pipe.watch.misfit
    # a window that turned while taken (two poses in one mean: `bootstrap.TURN_SD_G`)
    # says nothing of the calibration, however far its norm
    turned = math.isfinite(var) and var > (TURN_SD_G * s0) ** 2
    if not turned and gross(r_g, sigma_c_mg ** 2 + misfit.norm_mg2 + 1e6 * noise_g2):
        return True
    if ok and math.isfinite(sigma_c_mg):
        misfit.see(r_g, noise_g2 + (1e-3 * sigma_c_mg) ** 2 / 3.0)
    return False


def watch_window(pipe: PipelineParts, bad: bool, window: Window, idx: int, grossly: bool = False,
                 cell: int = -1) -> bool:
    """One committed window through the self-watch (`core.status.Watch`; bad: it failed
    the norm gate, its calibrated norm more than norm_tol_g from 1 g or not finite;
    grossly: `contradicts`): True when that became sustained (a reset runs at this window);
    a change of status or misfit applies from sample idx on."""
    seen = pipe.watch.see(bad, window, grossly, cell)
    if seen is None:  # the usual window: only the misfit may have moved
        if pipe.watch.misfit.restate():
            pipe._work.segs.append(pipe._segment(idx))
        return False
    t_us = int(window.t_us)
    if seen == "gross":
        pipe._work.watch_events.append(WatchEvent(idx, t_us, "suspect", {
            "reason": "a still window contradicts the estimate grossly"}))
    elif seen == "trusted":
        pipe._work.watch_events.append(WatchEvent(idx, t_us, "agrees", {
            "status": pipe.status.label, "after": "probation"}))
    elif seen == "clear":
        pipe._work.watch_events.append(WatchEvent(idx, t_us, "agrees", {
            "status": pipe.status.label}))
    if pipe.watch.misfit.restate() or seen in ("gross", "trusted", "clear"):
        pipe._work.segs.append(pipe._segment(idx))
    if seen == "trigger":
        pipe._work.reset_due = "still windows fail the norm gate under the estimate"
        return True
    return False


def reset_estimate(pipe: PipelineParts, idx: int, now_us: int) -> UpdateEvent | None:
    """The windows contradict the estimate beyond what the estimator absorbs: it is not
    this sensor's (another sensor under the same id, another sensor's checkpoint) or the
    sensor changed too much. Back to the prior, with a buffer of the recent windows only
    (the older ones are another sensor's, or the old one's), re-fitted at once."""
    reason, pipe._work.reset_due = pipe._work.reset_due, None
    recent = pipe.watch.to_refit(pipe.buffer.windows(), now_us)
    before = pipe.estimate
    assert pipe.prior is not None
    pipe.estimate = Estimate.from_prior(pipe.prior)
    pipe.informed, pipe.unobserved = False, ()
    pipe.buffer = WindowBuffer(pipe.cfg.buffer, len(pipe.aux_names))
    kept = refill_buffer(pipe, recent)
    pipe._work.watch_events.append(WatchEvent(idx, now_us, "suspect", {
        "reason": reason, "windows": len(recent), "refitted": kept,
        "resets": pipe.watch.triggers,
        "params_before": pipe.model.params_dict(before.p) if before is not None else None}))
    pipe.fresh, pipe.refit = [], pipe.refit.restarted()
    if len(recent) >= pipe.cfg.estimator.min_windows and 2 * kept < len(recent):
        # the prior does not fit most of them either (a sensor far from the datasheet):
        # no estimate, a bootstrap from the data (`try_bootstrap`), these windows first
        pipe.estimate, pipe.bootstrapped, pipe.from_prior = None, False, False
        pipe.buffer = WindowBuffer(pipe.cfg.buffer, len(pipe.aux_names))
        refill_buffer(pipe, recent, gate=False)
        return None
    if kept < pipe.cfg.estimator.min_windows:
        return None  # held at the prior until more windows come
    return update_at(pipe, idx, now_us)


def heal_if_not_finite(pipe: PipelineParts, t_us: int) -> None:
    """An estimate that is not finite (a damaged checkpoint) would make every sample NaN
    and every window fail the norm gate, for good: back to the prior if it is finite
    (status held), else to no estimate at all (a bootstrap from the data)."""
    est = pipe.estimate
    if est is None or est is pipe._work.finite_estimate:
        return
    if np.isfinite(est.p).all() and np.isfinite(est.cov).all():
        pipe._work.finite_estimate = est  # asked at every step: once per estimate
        return
    prior = pipe.prior
    usable_prior = (prior is not None and np.isfinite(prior.mean).all()
                    and np.isfinite(prior.info).all())
    pipe.buffer = WindowBuffer(pipe.cfg.buffer, len(pipe.aux_names))
    pipe.fresh, pipe.refit = [], pipe.refit.restarted()
    pipe.informed, pipe.watch, pipe.unobserved = False, Watch(), ()
    if usable_prior:
        assert prior is not None
        pipe.estimate = Estimate.from_prior(prior)
    else:
        pipe.estimate, pipe.prior, pipe.bootstrapped = None, None, False
        pipe.from_prior = False
    pipe._work.watch_events.append(WatchEvent(0, t_us, "reset", {
        "reason": "estimate not finite",
        "to": "prior" if usable_prior else "bootstrap"}))
