"""The pipeline's estimation (`core.pipeline`): an update of the estimate from the buffer's
windows (`core.estimator`, Lötters eq. 11a/11b) and what it tells the self-watch, the bootstrap
of a sensor without a prior (zero-g and scale located, then an ellipsoid fit: `core.bootstrap`),
and the refresh of the buffer's stored directions under new parameters. Functions of the
pipeline they change, called at the window an update runs after (`core.pipeline_windows`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from recal.core.bootstrap import LOCATE_MIN_WINDOWS, fit_poses, locate, off_by, reach, still_poses
from recal.core.buffer import Window, WindowBuffer, Windows
from recal.core.effects import Offset, Scale
from recal.core.estimator import Estimate, Prior, update
from recal.core.misfit import across_factor, direction_sums, unseen_cross_form
from recal.core.model import SensorModel
from recal.core.outputs import UpdateEvent, WatchEvent
from recal.core.quantization import rounding_g2
from recal.core.refit import after_update
from recal.core.status import (
    JUMP_REPEAT_S,
    MISFIT_MOVE_SDS,
    UNPINNED_MG,
    RunningMisfit,
    offsets_and_scales,
    refill,
)
from recal.core.triaxial import norm3

if TYPE_CHECKING:
    from recal.core.pipeline_state import PipelineParts

__all__ = ["learned_step", "redirect", "refill_buffer", "try_bootstrap", "update_at"]

#: Without a prior, a located scale within this factor of s0 (the first sample's norm) may be
#: the sensor's (`_plausible_scale`)
RELOCATE_MAX_RATIO = 100.0

#: Up to this many windows in the buffer before a bootstrap, its sphere fits run at every
#: window, not every update_every (`_sphere_due`).
FEW_WINDOWS = 20


def learned_step(pipe: PipelineParts) -> np.ndarray | None:
    """The sensor's step per axis as its detector learned it (raw units; None: no detector)."""
    return pipe.detector.state.step_raw if pipe.detector is not None else None


def update_at(pipe: PipelineParts, idx: int, now_us: int,
              windows: Windows | None = None) -> UpdateEvent:
    """An update of the estimate at sample idx (device time now_us) from the buffer's windows
    (or ``windows``), and what it tells the self-watch and the status."""
    # every window the buffer holds, re-fitted from the current estimate (estimator doc)
    w = windows if windows is not None else pipe.buffer.windows()
    pipe.fresh = []
    cov = pipe.covariates(w.t_us, w.aux)
    assert pipe.prior is not None and pipe.estimate is not None
    before = pipe.estimate
    # the same orientations as at the last update, every offset and scale observed: a
    # move is no lesson of new postures
    learnt = (pipe.refit.coverage_at_update == pipe.buffer.cells_opened and pipe.informed
              and not pipe.unobserved)
    # after a first jump, a second within JUMP_REPEAT_S tells another sensor (`_watch_jump`):
    # the allowance for what the model misses at a posture is then the median's, which the
    # windows of a swapped sensor under a compromise fit do not move as they move the mean
    first_jump_us = pipe.watch.jump_us
    asking = first_jump_us is not None and now_us - first_jump_us <= JUMP_REPEAT_S * 1e6
    pipe.estimate, rep = update(pipe.model, pipe.prior, pipe.estimate, w, cov, now_us,
                                pipe.cfg.estimator, robust_misfit=asking)
    pipe.refit = after_update(before, pipe.estimate, rep.accepted, pipe.buffer.cells_opened)
    if rep.accepted:
        _watch_jump(pipe, before, idx, now_us)
    if rep.accepted and any(rep.observable):
        pipe.informed = True
    if rep.accepted:
        pipe.unobserved = _unobserved(pipe.model, pipe.estimate, rep.observable)
        s0 = pipe.model.s0
        noise_g2 = (float(np.mean(w.var / np.maximum(w.n, 1))) / (s0 * s0)
                    + float(np.mean(rounding_g2(w.var, s0, learned_step(pipe))))
                    if len(w) else 0.0)
        # how much more the vector can err than the buffer's norms show (`core.misfit`)
        a = pipe.model.correct(pipe.params, w.v, cov)
        sums = direction_sums(a)
        across = float(across_factor(sums, len(a)))
        # a diagonal model's cross-axis terms the postures leave unseen (`core.misfit`)
        unseen = (0.0 if pipe.model.has("cross_axis") else
                  unseen_cross_form(sums, len(a), RunningMisfit.detect_g2(noise_g2)))
        pipe.watch.misfit.fitted(*_one_set_rms(pipe.estimate, w, a, s0), across, unseen)
        # a fitted offset jump (a knock, a poisoned state) is an event, not a drift
        jumped = pipe.estimate is not None and pipe.estimate.step_us != before.step_us
        pipe.watch.misfit.moved(_moved_mg2(pipe.model, before, pipe.estimate)
                                if learnt and not jumped else 0.0, now_us)
        pipe.watch.misfit.restate()
    pipe.counts["updates"] += 1
    if not rep.accepted:
        pipe.counts["updates_rejected"] += 1
    else:
        redirect(pipe, a)
    pipe.last_report = rep
    return UpdateEvent(idx, now_us, rep)


def _one_set_rms(est: Estimate, w: Windows, a: np.ndarray, s0: float) -> tuple[float, float]:
    """The rms (g) of the buffer's norm residuals under one set of parameters, those in force
    (`a`: its windows corrected with them; the estimator's offset rate and ageing left out,
    which follow a drifting effect and hide it), and their windows' mean noise variance (g^2):
    what the model misses (`status.RunningMisfit`). After a fitted offset jump, the windows
    since it only (those before saw other offsets: a knock is no misfit)."""
    keep = w.t_us >= est.step_us if est.step_us is not None else np.ones(len(w), bool)
    if not keep.any():
        return 0.0, 0.0
    xi = norm3(a[keep]) - 1.0
    noise_g2 = float(np.mean(w.var[keep] / np.maximum(w.n[keep], 1))) / (s0 * s0)
    return float(np.sqrt(np.mean(xi * xi))), noise_g2


def _watch_jump(pipe: PipelineParts, before: Estimate, idx: int, now_us: int) -> None:
    """An accepted update that fitted a new offset jump (`estimator._jump`): suspect for
    JUMP_REPEAT_S at least. A knock fits one and the windows agree again; a sensor whose
    gains differ too (another sensor under this id, another sensor's checkpoint) jumps
    again at a new posture: a second jump within JUMP_REPEAT_S of the first resets."""
    step_us = pipe.estimate.step_us if pipe.estimate is not None else None
    if step_us is None or step_us == before.step_us:
        return
    seen = pipe.watch.jumped(step_us, now_us)
    if seen == "reset":
        pipe._work.reset_due = "the offsets jumped again"
    elif seen == "suspect":
        pipe._work.watch_events.append(WatchEvent(idx, now_us, "suspect", {
            "reason": "the offsets jumped", "jump_t_us": step_us}))


def try_bootstrap(pipe: PipelineParts, idx: int, now_us: int) -> UpdateEvent | None:
    _relocate(pipe, idx)
    slots = pipe.buffer.slots()  # windows that turned are no poses (`still_poses`)
    pipe.buffer.drop(slots[~still_poses(pipe.buffer.windows().var, pipe.model.s0)])
    cov = pipe.buffer.coverage()
    # five of the six half-axes: lying face down (-z for a hip sensor) may never happen
    half_axes = sum(cov.seen_pos) + sum(cov.seen_neg)
    if half_axes < 5 or cov.cells_filled < pipe.cfg.bootstrap_min_cells:
        return None
    w, slots = pipe.buffer.windows(), pipe.buffer.slots()
    if pipe.centre0.any():  # zero-g was found, roughly: coverage around the best centre
        if not _sphere_due(pipe):
            return None
        loc = locate(w.v, pipe.cfg.buffer.grid)
        if loc is None or not loc.covers(cells=pipe.cfg.bootstrap_min_cells):
            return None
    fit = fit_poses(pipe.model, w.v, pipe.covariates(w.t_us, w.aux), not cov.full,
                    pipe.cfg.norm_tol_g)
    if fit is None:
        return None
    model, p, used, a = fit
    half, cells = reach(a[used], pipe.cfg.buffer.grid)
    if half < (5 if not cov.full else 6) or cells < pipe.cfg.bootstrap_min_cells:
        return None  # the windows that agree with the fit do not cover enough
    if not np.all((p[model.slice(Scale())] > 0.5 * pipe.model.s0)
                  & (p[model.slice(Scale())] < 2.0 * pipe.model.s0)):
        return None  # an ellipsoid far from the first sample's norm is not this sensor
    pipe.buffer.drop(slots[~used])  # off the fit: not still poses, never to be fitted
    # keep the detector's scale: its filters already run in the first sample's units
    # (`_relocate` restarted it if those were materially wrong)
    pipe.model = model
    pipe.prior = Prior.default(model, p)  # bounds and gates now relative to the fit
    pipe.estimate = Estimate.from_prior(pipe.prior)
    pipe.bootstrapped = True
    redirect(pipe)
    if off_by(p[model.slice(Offset())], model.s0, np.asarray(pipe.det_cfg.zero_raw),
              pipe.det_cfg.s0):  # the detector's zero-g or scale was wrong: restart it
        pipe._work.restart_at = idx
    ev = update_at(pipe, idx, now_us, pipe.buffer.windows())  # the fit's own data
    return replace(ev, bootstrap=True)


def _sphere_due(pipe: PipelineParts) -> bool:
    """Whether a sphere fit of the buffer runs at this window: at every one while the
    buffer holds few (a lab's six positions may give no more), then every update_every
    windows (a wearer who never turns costs little)."""
    return (len(pipe.buffer) <= FEW_WINDOWS
            or pipe.counts["windows"] % pipe.cfg.update_every == 0)


def _relocate(pipe: PipelineParts, idx: int) -> None:
    """Before a bootstrap: if the still windows pin down zero-g and scale, roughly
    (`bootstrap.locate`: half-axes and cells of their centred directions), and the ones
    in use are materially wrong (`bootstrap.off_by`), use the found ones from the next
    sample on: the detector restarts centred at the found scale (`step`), and of the
    windows the wrong one gated only those on the sphere that did not turn stay, binned by
    their centred directions as later windows are; the bootstrap waits until those cover
    the orientations around the centre found (`try_bootstrap`)."""
    if len(pipe.buffer) < LOCATE_MIN_WINDOWS or not _sphere_due(pipe):
        return
    w = pipe.buffer.windows()
    loc = locate(w.v, pipe.cfg.buffer.grid)
    if (loc is None or len(loc.inliers) != len(w)
            or not loc.covers(cells=max(4, pipe.cfg.bootstrap_min_cells // 2))
            or not off_by(loc.centre, loc.scale, pipe.centre0, pipe.model.s0)
            or not _plausible_scale(pipe, loc.scale)):
        return
    pipe.centre0 = np.asarray(loc.centre, np.float64).copy()
    pipe.model = SensorModel(pipe.model.effects, loc.scale, pipe.model.spreads)
    # a detector that wrong (10x too loose on an unsigned part, blind along its offset)
    # let movement through: only the windows on the sphere that did not turn stay, binned
    # anew around the centre found (the bootstrap's fit drops those off it, `fit_poses`)
    keep = np.flatnonzero(loc.inliers & still_poses(w.var, loc.scale))
    pipe.buffer = WindowBuffer(pipe.cfg.buffer, len(pipe.aux_names))
    refill_buffer(pipe, [Window(w.v[i], w.aux[i], int(w.t_us[i]), int(w.n[i]),
                                float(w.var[i])) for i in keep.tolist()], gate=False)
    pipe._work.restart_at = idx


def _plausible_scale(pipe: PipelineParts, scale: float) -> bool:
    """Whether a located sphere's radius (raw units per g) can be this sensor's scale. A
    sphere fit through windows that are mostly one pose finds a tiny sphere in that pose's
    noise (an analog 12-bit part after a reset into a bootstrap: 1.2 counts per g for 372),
    and taking it would restart the detector and rebin the windows at a scale no later
    state can keep (the node's vetting refuses it and rolls back). With a prior (configured,
    or a fit's that a reset went back to) the scale is known: the located one must lie within
    the model's scale bounds (`SensorModel.bounds`). Without one, s0 is the first sample's
    norm, which on an unsigned ADC is ~10x the scale (zero-g ~2048 counts of 12 bits, ~370
    counts per g; ~50x for a +-16 g part): within RELOCATE_MAX_RATIO of it."""
    s0 = pipe.model.s0
    if pipe.prior is not None and pipe.model.has("scale"):
        lo, hi = pipe.model.bounds()
        sl = pipe.model.slice(Scale())
        return bool(np.all(lo[sl] <= scale) and np.all(scale <= hi[sl]))
    return bool(s0 / RELOCATE_MAX_RATIO <= scale <= s0 * RELOCATE_MAX_RATIO)


def redirect(pipe: PipelineParts, a_windows: np.ndarray | None = None) -> None:
    """Re-bin nothing, but refresh stored gravity directions with the new calibration.
    a_windows: the buffer's windows (`WindowBuffer.windows`, oldest first) corrected with
    the parameters now, if the caller has them (an update: the same numbers row by row)."""
    m = pipe.buffer.filled
    if not m.any():
        return
    if a_windows is not None:
        pipe.buffer.redirect(a_windows / norm3(a_windows)[:, None], pipe.buffer.slots())
        return
    cov = pipe.covariates(pipe.buffer.t_us[m], pipe.buffer.aux[m])
    a = pipe.model.correct(pipe.params, pipe.buffer.v[m], cov)
    pipe.buffer.redirect(a / norm3(a)[:, None])


def refill_buffer(pipe: PipelineParts, recent: list[Window], gate: bool = True) -> int:
    """`status.refill` of a new buffer under the estimate now (no norm gate: all)."""
    return refill(pipe.buffer, len(pipe.aux_names), pipe.model, pipe.params,
                  pipe.covariates, recent, pipe.cfg.norm_tol_g if gate else None,
                  pipe.cfg.buffer.grid)


def _unobserved(model: SensorModel, est: Estimate | None,
                observable: Sequence[bool]) -> tuple[str, ...]:
    """The offsets and scales an accepted update did not observe (`UpdateReport.observable`)
    whose sd (of the estimate) is worth more than UNPINNED_MG at 1 g: what the data left to
    the prior, and the prior does not know well."""
    if est is None or len(observable) != model.size:
        return ()
    sd_mg = 1e3 * np.sqrt(np.clip(np.diag(est.cov), 0, None)) / model.s0
    return tuple(model.names[i] for i in offsets_and_scales(model)
                 if not observable[i] and sd_mg[i] > UNPINNED_MG)


def _moved_mg2(model: SensorModel, before: Estimate, after: Estimate | None) -> float:
    """How far an update moved the offsets and scales beyond what their covariance before it
    allows (within it the data taught the estimate, correlations included; beyond it the
    truth moved): |dp|^2 (mg at 1 g) x max(0, 1 - MISFIT_MOVE_SDS^2 k / d^2), d^2 the move's
    Mahalanobis length under the covariance before, k the parameters."""
    if after is None:
        return 0.0
    idx = offsets_and_scales(model)
    if not idx:
        return 0.0
    dp = (after.p - before.p)[idx]
    c = before.cov[np.ix_(idx, idx)]
    if not (np.isfinite(dp).all() and np.isfinite(c).all()):
        return 0.0
    d2 = float(dp @ np.linalg.pinv(c) @ dp)
    if d2 <= MISFIT_MOVE_SDS ** 2 * len(idx):
        return 0.0
    return float(np.sum((1e3 * dp / model.s0) ** 2)) * (1.0 - MISFIT_MOVE_SDS ** 2 * len(idx) / d2)
