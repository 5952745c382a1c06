"""One calibration step: raw batch -> (gates, calibrated batch, updates). The only core entry
point the shell uses, so the daemon, replay and tests cannot drift apart (docs/design.md).

Per batch, each part in its module: the detector (`core.detector`, Lötters eq. 1-2) gates every
sample; the gated runs are cut into windows (`core.windower`); committed windows enter the
buffer (`core.buffer`) and, when a re-fit can tell anything new (`core.refit`), the estimator
updates (`core.estimator`, Lötters eq. 11a/11b); samples are corrected with the parameters in
force when they arrived (`core.correction`), with their status and predicted error
(`core.status`); the self-watch (`core.status.Watch`) marks the output suspect or resets the
estimate when the still windows keep contradicting it. This module only orchestrates them.

Everything is driven by the sample sequence alone (never by batch boundaries or clocks), so
feeding a recording in batches of 1, 10 or 1000 samples gives the same output.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import asdict, replace
from enum import Enum
from itertools import pairwise

import numpy as np

from recal.core import detector as det
from recal.core.bootstrap import (
    LOCATE_MIN_WINDOWS,
    TURN_SD_G,
    fit_poses,
    locate,
    off_by,
    reach,
    still_poses,
)
from recal.core.buffer import Coverage, WindowBuffer, Windows
from recal.core.channels import check_channels, usable
from recal.core.correction import Segment, calibrate
from recal.core.effects import Covariates, Offset, Scale
from recal.core.estimator import (
    Estimate,
    Prior,
    UpdateReport,
    innovations,
    update,
)
from recal.core.misfit import across_factor, direction_sums, unseen_cross_g2
from recal.core.model import SensorModel
from recal.core.outputs import JoinedStep, Marks, StepOutput, UpdateEvent, WatchEvent
from recal.core.pipeline_config import PipelineConfig
from recal.core.refit import (
    RefitState,
    WindowChunk,
    after_update,
    fresh_windows,
    must_update,
    next_update,
    tries,
)
from recal.core.status import (
    GAP_S,
    MISFIT_MOVE_SDS,
    PROBATION_WINDOWS,
    REOPEN_PROBATION_WINDOWS,
    UNPINNED_MG,
    RunningMisfit,
    Status,
    Watch,
    gross,
    offsets_and_scales,
    predicted_sigma_mg,
    refill,
    sigma_form,
    unsettled,
)
from recal.core.triaxial import norm3
from recal.core.windower import WindowerState, WindowSums, cut
from recal.errors import InputError
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["Lifecycle", "Pipeline", "from_state_dict", "gain_reference", "state_dict"]


class Lifecycle(Enum):
    """Where a pipeline is in its life; read from its state (`Pipeline.lifecycle`), never
    stored, so a checkpoint holds only the parts it is read from."""

    #: no detector yet: no prior and no sample (the first sample's norm sets the scale)
    AWAITING_SCALE = "awaiting_scale"
    #: the detector runs, no estimate yet: windows are collected for the first fit
    BOOTSTRAPPING = "bootstrapping"
    #: an estimate, re-fitted as windows come; the self-watch has no objection
    TRACKING = "tracking"
    #: an estimate the self-watch holds suspect (`core.status.Watch`)
    SUSPECT = "suspect"


# the members as module names: the pipeline asks at every step, and a class attribute of an
# Enum is a descriptor call in Python 3.11
_AWAITING_SCALE, _BOOTSTRAPPING, _TRACKING, _SUSPECT = (
    Lifecycle.AWAITING_SCALE, Lifecycle.BOOTSTRAPPING, Lifecycle.TRACKING, Lifecycle.SUSPECT)


#: Up to this many windows in the buffer before a bootstrap, its sphere fits run at every
#: window, not every update_every (`Pipeline._sphere_due`).
FEW_WINDOWS = 20

#: The pipeline's attributes that are never changed in place (replaced when they change): a
#: step's snapshot (`Pipeline._stepped`) keeps them as they are instead of copying them.
_SHARED = frozenset(("cfg", "windower", "refit", "_last_segment"))


class Pipeline:
    """Detector -> windows -> buffer -> estimator -> correction, for one sensor.

    Args:
        cfg: settings.
        model: the sensor model (effects and nominal s0 in raw units per g).
        prior: pre-calibration (Lötters' reference calibration, or a config's nominal
            sensitivity and zero-g). None bootstraps (`phase` "provisional" until then): zero-g
            and scale are first taken as 0 and the first sample's norm, for the detector and
            the orientation cells only; once the still windows pin down a sphere
            (`bootstrap.locate`) that shows them materially wrong (an analog part on an
            unsigned ADC: zero-g ~2048 counts), its centre and radius replace them, the
            windows off the sphere are dropped and the detector restarts centred; when the
            centred windows cover enough orientations an ellipsoid fit is the calibration.
        aux_names: the auxiliary channels the recording carries (the model may use some).
        t0_us: origin of the model's "time" covariate (default: the first sample's time).
    """

    def __init__(self, cfg: PipelineConfig, model: SensorModel, prior: Prior | None,
                 aux_names: tuple[str, ...] = (), t0_us: int | None = None) -> None:
        check_channels(model, tuple(aux_names))
        self.cfg = cfg
        self.model = model
        self.prior = prior
        self.aux_names = tuple(aux_names)
        self.t0_us = t0_us
        self.estimate = Estimate.from_prior(prior) if prior is not None else None
        self.bootstrapped = prior is not None
        #: the calibration's origin: a prior given (or adopted), else the bootstrap's fit
        self.from_prior = prior is not None
        #: zero-g (raw) assumed while no estimate exists (`phase` "provisional")
        self.centre0 = np.zeros(3)
        self._restart_at: int | None = None  # the detector restarts after this sample
        self.buffer = WindowBuffer(cfg.buffer, len(self.aux_names))
        self.fresh: list[tuple] = []  # windows committed since the last update (< update_every)
        self.det_cfg: det.DetectorConfig | None = None
        self.det_state: det.DetectorState | None = None
        if prior is not None:
            self._start_detector(model.s0, _zero_of(model, prior.mean))
        self.windower = WindowerState()  # the open and pending windows (`core.windower`)
        self.counts = {"samples": 0, "quasi_static": 0, "windows": 0, "windows_rejected": 0,
                       "updates": 0, "updates_rejected": 0}
        self.last_report: UpdateReport | None = None
        self.refit = RefitState()  # what the last update saw (`core.refit`)
        self._marks: Marks | None = None  # only during a step with marks
        # data informed the estimate (an accepted update observed a parameter): `status`
        self.informed = False
        self.watch = Watch()
        #: offsets and scales the data did not observe at the last accepted update and the
        #: prior does not pin (`_unobserved`): status held while any
        self.unobserved: tuple[str, ...] = ()
        self._segs: list[Segment] = []  # during a step: what is in force from where
        self._watch_events: list[WatchEvent] = []
        self._reset_due: str | None = None  # why the self-watch resets at the next update point
        self._last_segment: Segment | None = None  # `_segment`'s last, reused while it holds
        self._form_cache: tuple | None = None  # (model, estimate, ...) of the last segment
        self._finite_estimate: Estimate | None = None
        # (estimate, model, `status.unsettled`, unobserved, `converging`)
        self._converging_cache: tuple | None = None

    # --- public ------------------------------------------------------------------------------
    @property
    def params(self) -> np.ndarray:
        if self.estimate is not None:
            return self.estimate.p
        p = self.model.nominal()
        if self.model.has("offset") and self.centre0.any():
            p[self.model.slice(Offset())] = self.centre0
        return p

    @property
    def last_t_us(self) -> int | None:
        """The device time of the last sample stepped (None: none yet)."""
        return self.windower.last_t_us

    @property
    def lifecycle(self) -> Lifecycle:
        if self.det_state is None:
            return _AWAITING_SCALE
        if self.estimate is None:
            return _BOOTSTRAPPING
        return _SUSPECT if self.watch.suspect else _TRACKING

    @property
    def phase(self) -> str:
        """"prior": calibrated from a pre-calibration; "bootstrap": from the ellipsoid fit of
        its own still windows; "provisional": no calibration yet (zero-g and scale are
        guesses for the detector and the orientation cells, see the class doc)."""
        life = self.lifecycle
        if life is _AWAITING_SCALE or life is _BOOTSTRAPPING:
            return "provisional"
        return "prior" if self.from_prior else "bootstrap"

    def gain_reference(self) -> dict:
        """What the gains (`gain_*_pct`) are relative to: the prior's nominal sensitivity, or
        without a prior the mean of the three fitted scales (the data's own counts per g; a
        first sample's norm is no reference). One rule for replay, hindsight and discover."""
        return gain_reference(self.model, self.params, self.from_prior)

    @property
    def status(self) -> Status:
        """The status of output calibrated now (`core.status` defines each)."""
        life = self.lifecycle
        if life is _AWAITING_SCALE or life is _BOOTSTRAPPING:
            return Status.BOOTSTRAPPING if len(self.buffer) else Status.UNCALIBRATED
        if life is _SUSPECT:
            return Status.SUSPECT
        if not self.informed or self.watch.probation or self.unobserved or self.converging:
            return Status.HELD
        return Status.CALIBRATED

    @property
    def converging(self) -> tuple[str, ...]:
        """The offsets and scales the data observed but do not yet know to UNPINNED_MG at 1 g
        (`status.unsettled`): status held while any."""
        est = self.estimate
        if est is None:
            return ()
        cached = self._converging_cache
        unobserved = self.unobserved
        if (cached is None or cached[0] is not est or cached[1] is not self.model
                or cached[3] is not unobserved):  # asked at every step: once per estimate
            names = unsettled(self.model, est.cov)
            cached = self._converging_cache = (
                est, self.model, names, unobserved,
                tuple(n for n in names if n not in unobserved))
        return cached[4]

    def doubt(self, cells: int = PROBATION_WINDOWS) -> None:
        """A moment of doubt (the device's clock restarted, the state came from a checkpoint,
        another device may be under this id): output is held until still windows in ``cells``
        orientation cells agree with the estimate (`core.status`: probation; one after a port
        reopen, `status.REOPEN_PROBATION_WINDOWS`), suspect at the first that contradicts it
        grossly."""
        self.watch.doubt(cells)

    def step(self, batch: RawBatch) -> StepOutput:
        """Process one batch of raw samples (any size, in time order)."""
        s = self._stepped(batch, [])
        return StepOutput(s.calibrated, s.updates, len(s.commits), s.watch, self.model,
                          self.estimate)

    def step_many(self, batches: Sequence[RawBatch]) -> list[StepOutput]:
        """`step` for consecutive batches: one output per batch, exactly what stepping each in
        turn gives, with the per-call costs paid once (one step over the batches joined; the
        pipeline is batch-size invariant). Each output's ``state`` is the model and summary
        as of its batch's end when the batch holds an update (replay joins a recording's
        messages and still writes one calibration state per message, as the live node did)."""
        full = [b for b in batches if len(b)]
        if len(full) < 2:
            return [self.step(b) for b in batches]
        return self.step_joined(RawBatch.concat(full), [len(b) for b in batches])

    def step_joined(self, joined: RawBatch, lengths: Sequence[int]) -> list[StepOutput]:
        """`step_many` for batches the caller has joined already: ``joined`` holds them one
        after another, ``lengths`` says how many samples each has (0: an empty batch)."""
        if sum(lengths) != len(joined):
            raise InputError(f"batch lengths {sum(lengths)} != {len(joined)} samples joined")
        ends = np.cumsum([n for n in lengths if n]).tolist()
        model, estimate = self.model, self.estimate  # as of before the first batch
        return self._stepped(joined, ends).split(lengths, model, estimate)

    def _stepped(self, batch: RawBatch, marks: list[int]) -> JoinedStep:
        """`step` with the state recorded after each mark's samples (`step_many`), cut at each
        gap in device time longer than GAP_S: a doubt for REOPEN_PROBATION_WINDOWS from the
        sample after it, once an estimate exists to doubt. The cuts fall at those samples
        however the samples were batched, so live (a message at a time) and replay (messages
        joined) agree (cutting a step changes nothing else: the pipeline is batch-size
        invariant)."""
        gaps = self._gaps(batch)
        if not gaps:
            return self._stepped_whole(batch, marks)
        bounds = [0, *(g for g in gaps if g), len(batch)]
        out: JoinedStep | None = None
        for a, b in pairwise(bounds):
            if (a or gaps[0] == 0) and self.estimate is not None and self.bootstrapped:
                self.doubt(REOPEN_PROBATION_WINDOWS)
            part = self._stepped_whole(batch[a:b], [m - a for m in marks if a < m <= b])
            out = part if out is None else out.joined(part, a)
        assert out is not None
        return out

    def _gaps(self, batch: RawBatch) -> list[int]:
        """The samples of the batch that follow a gap in device time beyond GAP_S, in order
        (0: the gap lies before the batch's first sample)."""
        t, last, gap_us = batch.t_us, self.last_t_us, GAP_S * 1e6
        if not len(t):
            return []
        gaps = [0] if last is not None and int(t[0]) - last > gap_us else []
        if len(t) == 1:  # a live arrival: no gap inside it (and no numpy calls for none)
            return gaps
        return gaps + (np.flatnonzero(np.diff(t) > gap_us) + 1).tolist()

    def _stepped_whole(self, batch: RawBatch, marks: list[int]) -> JoinedStep:
        """`_stepped` for a batch without a gap inside (see there)."""
        if batch.aux_names != self.aux_names:
            raise InputError(f"batch channels {batch.aux_names} differ from {self.aux_names}")
        n = len(batch)
        if n == 0:
            return JoinedStep(CalibratedBatch.empty(), (), [], (), {})
        if self.t0_us is None:
            self.t0_us = int(batch.t_us[0])
        life = self.lifecycle
        if life is _AWAITING_SCALE:  # the first sample's norm is 1 g
            norms = np.linalg.norm(batch.v, axis=1)
            good = norms[np.isfinite(norms) & (norms > 0)]  # a NaN s0 would stick for good
            s0 = float(good[0]) if len(good) else 1.0
            self.model = SensorModel(self.model.effects, s0, self.model.spreads)
            self._start_detector(s0)
            life = self.lifecycle  # bootstrapping now
        # until an estimate exists, zero-g and scale may be found wrong at a window inside
        # the batch (`_relocate`): the detector then restarts after that sample, as it would
        # have had the batch come in two, so the state before the batch is kept to redo it
        snap = ({k: v if k in _SHARED else copy.deepcopy(v) for k, v in self.__dict__.items()
                 if k != "_marks"} if life is _BOOTSTRAPPING and n > 1 else None)
        out = self._step(batch, marks)
        at, self._restart_at = self._restart_at, None
        if at is None:
            return out
        if snap is None or at + 1 >= n:
            self._start_detector(self.model.s0, _zero_of(self.model, self.params))
            return out
        self.__dict__.update(snap)
        head = self._step(batch[:at + 1], [m for m in marks if m <= at + 1])
        self._restart_at = None
        self._start_detector(self.model.s0, _zero_of(self.model, self.params))
        tail = self._stepped(batch[at + 1:], [m - at - 1 for m in marks if m > at + 1])
        return head.joined(tail, at + 1)

    def _step(self, batch: RawBatch, marks: list[int]) -> JoinedStep:
        """`step` with the detector as it is (see there)."""
        n = len(batch)
        self._watch_events = []
        self._heal_if_not_finite(int(batch.t_us[0]))
        self.det_state, d = det.detect(self.det_cfg, self.det_state, batch.v)
        gate = usable(d.gate, batch, self.model)
        self._segs = [self._segment(0)]
        if marks:
            self._marks = Marks(list(marks), gate, self.counts["samples"],
                                 self.counts["quasi_static"])
        try:
            events, commits = self._windows(batch, gate)
            self._reach(n)  # the marks no later change came before
        finally:
            done, self._marks = self._marks, None
        cal, status, sigma = calibrate(self._segs, batch, self.covariates)
        self._segs = []
        self.counts["samples"] += n
        if n == 1:  # one sample per arrival: the arrays are made here, as the batch keeps them
            self.counts["quasi_static"] += int(gate[0])
            out = CalibratedBatch.of_checked(batch.t_us, cal, gate, d.detector_g, status, sigma)
        else:
            self.counts["quasi_static"] += int(gate.sum())
            out = CalibratedBatch(batch.t_us, cal, gate, d.detector_g, status, sigma)
        return JoinedStep(out, tuple(events), commits, tuple(self._watch_events),
                          done.at if done is not None else {})

    def state_dict(self) -> dict:
        """JSON-able checkpoint (see module function `state_dict`)."""
        return state_dict(self)

    @classmethod
    def from_state_dict(cls, d: dict) -> Pipeline:
        return from_state_dict(d)

    def covariates(self, t_us: np.ndarray, aux: np.ndarray) -> Covariates:
        return Covariates.from_samples(t_us, aux, self.aux_names, self.t0_us or 0)

    def coverage(self) -> Coverage:
        return self.buffer.coverage()

    def adopt(self, model: SensorModel, prior: Prior) -> None:
        """Continue with another model (one effect discovery extended): its prior becomes the
        pre-calibration and the estimate; detector, buffer and windows carry on."""
        check_channels(model, self.aux_names)
        self.model = model
        self.prior = prior
        self.estimate = Estimate.from_prior(prior)
        self.bootstrapped = True
        self._redirect()

    def _reach(self, idx: int) -> None:
        """Called before anything in the state changes at sample ``idx`` of the batch: the
        state now is the state after ``m`` samples for every mark m <= idx not yet passed."""
        if self._marks is not None:
            self._marks.reach(idx, self.model, self.estimate, self.summary)

    def summary(self) -> dict:
        """The calibration state: parameters by name, covariance, residual, coverage, ...
        Gains are relative to `gain_reference` (named in "gain_reference")."""
        p = self.params
        cov = self.estimate.cov if self.estimate is not None else None
        rep = self.last_report
        ref = self.gain_reference()
        return {
            "bootstrapped": self.bootstrapped,
            "phase": self.phase,
            "gain_reference": ref,
            "model": self.model.to_dict(),
            "params": self.model.params_dict(p),
            "described": self.model.describe(p, ref["counts_per_g"]),
            "sd": (dict(zip(self.model.names, np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(),
                            strict=True)) if cov is not None else None),
            "covariance": cov.tolist() if cov is not None else None,
            "residual_rms_mg": (1e3 * rep.residual_rms_after_g if rep else None),
            "last_update": rep.to_dict(self.model.names) if rep else None,
            "coverage": self.coverage().to_dict(),
            "counts": dict(self.counts),
            "status": self.status.label,  # of output calibrated now (core/status.py)
            "watch": {"suspect": self.watch.suspect, "resets": self.watch.triggers,
                      "probation": self.watch.probation},
            # parameters no data observed (status held), and sigma's share of misfit
            "unobserved": list(self.unobserved),
            # parameters observed but not yet known to UNPINNED_MG (status held)
            "converging": list(self.converging),
            "misfit_mg": math.sqrt(self.watch.misfit.said_mg2),
        }

    # --- windows -----------------------------------------------------------------------------
    def _windows(self, b: RawBatch, gate: np.ndarray) -> tuple[list[UpdateEvent], list[int]]:
        """Cut the gated runs into windows (`core.windower`) and commit the finished ones.

        Which windows finish and when they commit depends on the gates and times alone, so it
        is worked out first for the whole batch; committing them then depends on the
        parameters, which change only at updates (`_commit_all`)."""
        c, self.windower = cut(self.cfg.windows, self.windower, b.t_us, b.v, b.aux, gate)
        return self._commit_all(b, c.due, c.sums)

    def _commit_all(self, b: RawBatch, due: list[tuple[int, bool]],
                    table: WindowSums | None) -> tuple[list[UpdateEvent], list[int]]:
        """Commit the scheduled windows in order. Between updates the parameters hold, so the
        norm gate, directions and cells of the windows are worked out a chunk at a time
        (`refit.WindowChunk`), and `_scan` finds the next window after which an update runs from the
        chunk's arrays; the windows before it only enter the buffer (`_enter`)."""
        if not due:  # no window finished (most arrivals of a live sensor): nothing to do
            return [], []
        events: list[UpdateEvent] = []
        at = [idx for idx, window in due if window]  # commit sample of each window
        slot = [k for k, (_, window) in enumerate(due) if window]  # its place in due
        done = 0  # due entries handled
        if table is not None:
            w, runs = table.means()
            c, size, chunk = 0, 0, None
            while c < len(table):
                if chunk is None or c >= chunk.lo + len(chunk):
                    size = min(len(table) - c, max(64, 2 * size))
                    chunk = WindowChunk.of(
                        self.model, self.params, self.covariates,
                        self.cfg.norm_tol_g if self.bootstrapped else None,
                        self.cfg.buffer.grid, w, runs, c, c + size)
                e = self._scan(chunk, c, b.t_us, at)
                stop = chunk.lo + len(chunk) if e is None else e + 1
                done, opened = self._enter(chunk, c, stop, due, slot, done)
                e = opened if opened is not None else e
                c = stop if e is None else e + 1
                if e is None:
                    continue
                idx = at[e]
                now = int(b.t_us[idx])
                evs: list[UpdateEvent | None] = []
                if self._reset_due is None:  # (else the self-watch fired at this window)
                    evs.append(self._try_bootstrap(idx, now) if not self.bootstrapped
                               else self._update(idx, now))
                reset = self._reset_due is not None  # fired, or the update found a jump again
                if reset:
                    evs.append(self._reset(idx, now))
                events += [ev for ev in evs if ev is not None]
                if reset or evs[-1] is not None:
                    self._segs.append(self._segment(idx))
                    if self._marks is not None:
                        self._marks.dirty = True
                    chunk, size = None, 0  # the parameters changed: a new first chunk
        self._reject_short(due, done, len(due))
        return events, at

    def _enter(self, chunk: WindowChunk, c0: int, c1: int, due: list[tuple[int, bool]],
               slot: list[int], done: int) -> tuple[int, int | None]:
        """Windows c0..c1 of the batch enter the buffer (or count as rejected by their norm),
        each after the short windows scheduled before it. Returns the due entries handled,
        and the window at which an update must run because the buffer covers a cell it did
        not at the last update (`_scan`'s other reason; whether a window opens a cell or
        merges into the latest slot is the buffer's call, one window at a time)."""
        marks, ue, watch = self._marks, self.cfg.update_every, self.bootstrapped
        add, fresh, buf, counts = self.buffer.add, self.fresh, self.buffer, self.counts
        lo = chunk.lo
        for c, row in zip(range(c0, c1), chunk.rows(c0, c1), strict=True):
            k = slot[c]
            if k > done:  # short windows scheduled before this one
                done = self._reject_short(due, done, k)
            idx = due[k][0]
            if marks is not None:
                self._reach(idx)
            ok, v, aux, t_mid, n, var, direction, run, cell = row
            done = k + 1
            if watch and self._watch_window(not ok, (v, aux, t_mid, n, var), idx,
                                            self._grossly(chunk, c - lo, ok, n, var), cell):
                if ok:  # in the buffer it is about to replace: counted as the others
                    counts["windows"] += 1
                else:
                    counts["windows_rejected"] += 1
                return done, c  # a reset (`_reset`) at this window
            if not ok:
                counts["windows_rejected"] += 1
                continue
            opened = buf.cells_opened
            add(v, aux, t_mid, n, var, direction, run, cell)
            if watch and buf.cells_opened != opened and self._axis_newly_covered():
                fresh.append((v, aux, t_mid, n, var))
                counts["windows"] += 1
                return done, c  # a gain the last update could not see now can be: update
            if watch:  # before the bootstrap nothing tests them (and they would pile up)
                fresh.append((v, aux, t_mid, n, var))
            counts["windows"] += 1
            if not watch and self._segs and self._segs[-1].status is Status.UNCALIBRATED:
                self._segs.append(self._segment(idx))  # now bootstrapping
            if (watch and counts["windows"] % ue == 0
                    and buf.cells_opened != self.refit.coverage_at_update):
                return done, c
        return done, None

    def _axis_newly_covered(self) -> bool:
        """An axis the buffer now sees from both sides whose scale the last update could not
        observe (a sphere fitted to five half-axes, then the sixth): worth an update at once,
        whatever the window count (a six-pose stream ends right after its last pose)."""
        rep = self.last_report
        if rep is None or not self.model.has("scale") or not rep.observable:
            return False
        sl = self.model.slice(Scale())
        seen = rep.observable[sl.start:sl.stop]
        covered = self.buffer.coverage().axes_covered
        return any(c and not o for c, o in zip(covered, seen, strict=True))

    # --- self-watch --------------------------------------------------------------------------
    def _grossly(self, chunk: WindowChunk, i: int, ok: bool, n: int, var: float) -> bool:
        """Window i of the chunk against the estimate: whether it contradicts grossly
        (`status.gross`); if not and it passed the norm gate, its residual feeds the misfit
        (`status.Misfit`), which goes on the output from this window on when it moved."""
        if self.estimate is None or chunk.norm is None:
            return False
        if chunk.sigma_mg is None:  # once per chunk, under the parameters it was cut with
            _, _, p, cov, form, _ = self._segment_cache()
            w = chunk.w
            chunk.sigma_mg = predicted_sigma_mg(self.model, p, cov, w.v,
                                                self.covariates(w.t_us, w.aux), form)
        r_g = chunk.norm_at(i) - 1.0
        sigma_c_mg = chunk.sigma_at(i)
        s0 = self.model.s0
        noise_g2 = var / max(n, 1) / (s0 * s0) if math.isfinite(var) else 0.0
        misfit = self.watch.misfit
        # a window that turned while taken (two poses in one mean: `bootstrap.TURN_SD_G`)
        # says nothing of the calibration, however far its norm
        turned = math.isfinite(var) and var > (TURN_SD_G * s0) ** 2
        if not turned and gross(r_g, sigma_c_mg ** 2 + misfit.norm_mg2 + 1e6 * noise_g2):
            return True
        if ok and math.isfinite(sigma_c_mg):
            misfit.see(r_g, noise_g2 + (1e-3 * sigma_c_mg) ** 2 / 3.0)
        return False

    def _watch_window(self, bad: bool, window: tuple, idx: int, grossly: bool = False,
                      cell: int = -1) -> bool:
        """One committed window through the self-watch (`core.status.Watch`; bad: it failed
        the norm gate, its calibrated norm more than norm_tol_g from 1 g or not finite;
        grossly: `_grossly`): True when that became sustained (a reset runs at this window);
        a change of status or misfit applies from sample idx on."""
        seen = self.watch.see(bad, window, grossly, cell)
        if seen is None:  # the usual window: only the misfit may have moved
            if self.watch.misfit.restate():
                self._segs.append(self._segment(idx))
            return False
        t_us = int(window[2])
        if seen == "gross":
            self._watch_events.append(WatchEvent(idx, t_us, "suspect", {
                "reason": "a still window contradicts the estimate grossly"}))
        elif seen == "trusted":
            self._watch_events.append(WatchEvent(idx, t_us, "agrees", {
                "status": self.status.label, "after": "probation"}))
        elif seen == "clear":
            self._watch_events.append(WatchEvent(idx, t_us, "agrees", {
                "status": self.status.label}))
        if self.watch.misfit.restate() or seen in ("gross", "trusted", "clear"):
            self._segs.append(self._segment(idx))
        if seen == "trigger":
            self._reset_due = "still windows fail the norm gate under the estimate"
            return True
        return False

    def _watch_jump(self, before: Estimate, idx: int, now_us: int) -> None:
        """An accepted update that fitted a new offset jump (`estimator._jump`): suspect for
        JUMP_REPEAT_S at least. A knock fits one and the windows agree again; a sensor whose
        gains differ too (another sensor under this id, another sensor's checkpoint) jumps
        again at a new posture: a second jump within JUMP_REPEAT_S of the first resets."""
        step_us = self.estimate.step_us if self.estimate is not None else None
        if step_us is None or step_us == before.step_us:
            return
        seen = self.watch.jumped(step_us, now_us)
        if seen == "reset":
            self._reset_due = "the offsets jumped again"
        elif seen == "suspect":
            self._watch_events.append(WatchEvent(idx, now_us, "suspect", {
                "reason": "the offsets jumped", "jump_t_us": step_us}))

    def _reset(self, idx: int, now_us: int) -> UpdateEvent | None:
        """The windows contradict the estimate beyond what the estimator absorbs: it is not
        this sensor's (another sensor under the same id, another sensor's checkpoint) or the
        sensor changed too much. Back to the prior, with a buffer of the recent windows only
        (the older ones are another sensor's, or the old one's), re-fitted at once."""
        reason, self._reset_due = self._reset_due, None
        recent = self.watch.to_refit(self.buffer.windows(), now_us)
        before = self.estimate
        assert self.prior is not None
        self.estimate = Estimate.from_prior(self.prior)
        self.informed, self.unobserved = False, ()
        self.buffer = WindowBuffer(self.cfg.buffer, len(self.aux_names))
        kept = self._refill(recent)
        self._watch_events.append(WatchEvent(idx, now_us, "suspect", {
            "reason": reason, "windows": len(recent), "refitted": kept,
            "resets": self.watch.triggers,
            "params_before": self.model.params_dict(before.p) if before is not None else None}))
        self.fresh, self.refit = [], self.refit.restarted()
        if len(recent) >= self.cfg.estimator.min_windows and 2 * kept < len(recent):
            # the prior does not fit most of them either (a sensor far from the datasheet):
            # no estimate, a bootstrap from the data (`_try_bootstrap`), these windows first
            self.estimate, self.bootstrapped, self.from_prior = None, False, False
            self.buffer = WindowBuffer(self.cfg.buffer, len(self.aux_names))
            self._refill(recent, gate=False)
            return None
        if kept < self.cfg.estimator.min_windows:
            return None  # held at the prior until more windows come
        return self._update(idx, now_us)

    def _refill(self, recent: list[tuple], gate: bool = True) -> int:
        """`status.refill` of a new buffer under the estimate now (no norm gate: all)."""
        return refill(self.buffer, len(self.aux_names), self.model, self.params,
                      self.covariates, recent, self.cfg.norm_tol_g if gate else None,
                      self.cfg.buffer.grid)

    def _heal_if_not_finite(self, t_us: int) -> None:
        """An estimate that is not finite (a damaged checkpoint) would make every sample NaN
        and every window fail the norm gate, for good: back to the prior if it is finite
        (status held), else to no estimate at all (a bootstrap from the data)."""
        est = self.estimate
        if est is None or est is self._finite_estimate:
            return
        if np.isfinite(est.p).all() and np.isfinite(est.cov).all():
            self._finite_estimate = est  # asked at every step: once per estimate
            return
        prior = self.prior
        usable_prior = (prior is not None and np.isfinite(prior.mean).all()
                        and np.isfinite(prior.info).all())
        self.buffer = WindowBuffer(self.cfg.buffer, len(self.aux_names))
        self.fresh, self.refit = [], self.refit.restarted()
        self.informed, self.watch, self.unobserved = False, Watch(), ()
        if usable_prior:
            assert prior is not None
            self.estimate = Estimate.from_prior(prior)
        else:
            self.estimate, self.prior, self.bootstrapped = None, None, False
            self.from_prior = False
        self._watch_events.append(WatchEvent(0, t_us, "reset", {
            "reason": "estimate not finite",
            "to": "prior" if usable_prior else "bootstrap"}))

    def _reject_short(self, due: list[tuple[int, bool]], done: int, stop: int) -> int:
        """Due entries done..stop are windows too short to keep (`_finish`): counted."""
        if stop <= done:
            return done
        if self._marks is not None:
            for idx, _ in due[done:stop]:
                self._reach(idx)
                self.counts["windows_rejected"] += 1
        else:
            self.counts["windows_rejected"] += max(stop - done, 0)
        return max(done, stop)

    def _scan(self, chunk: WindowChunk, c0: int, t_us: np.ndarray, at: list[int]) -> int | None:
        """The first window from c0 in the chunk after which an update runs (`core.refit`).
        None: none in it. Before the bootstrap: every window that passes the norm gate."""
        if not self.bootstrapped:
            hits = np.flatnonzero(chunk.ok[c0 - chunk.lo:])
            return int(hits[0]) + c0 if len(hits) else None
        est, cfg = self.estimate, self.cfg
        assert est is not None
        checks, cum = tries(chunk, c0, self.counts["windows"], cfg.update_every)
        if not len(checks):
            return None
        if must_update(self.refit, est, cfg.max_update_interval_s):
            return int(checks[0]) + c0

        def late(checks: np.ndarray) -> np.ndarray:
            return (t_us[np.asarray(at[c0:c0 + len(chunk) - (c0 - chunk.lo)])[checks]]
                    - est.t_us >= cfg.max_update_interval_s * 1e6)

        def z_fresh(m0: int, m1: int) -> np.ndarray:
            w = fresh_windows(self.fresh[m0:m1], len(self.aux_names))
            return innovations(self.model, est, w, self.covariates(w.t_us, w.aux), cfg.estimator)

        e, self.refit = next_update(
            self.refit, chunk, c0, checks, cum, n_fresh=len(self.fresh), late=late,
            z_fresh=z_fresh,
            z_chunk=lambda: chunk.innovations(self.model, est, self.covariates, cfg.estimator))
        return e

    # --- estimation --------------------------------------------------------------------------
    def _update(self, idx: int, now_us: int, windows: Windows | None = None) -> UpdateEvent:
        # every window the buffer holds, re-fitted from the current estimate (estimator doc)
        w = windows if windows is not None else self.buffer.windows()
        self.fresh = []
        cov = self.covariates(w.t_us, w.aux)
        assert self.prior is not None and self.estimate is not None
        before = self.estimate
        # the same orientations as at the last update, every offset and scale observed: a
        # move is no lesson of new postures
        learnt = (self.refit.coverage_at_update == self.buffer.cells_opened and self.informed
                  and not self.unobserved)
        self.estimate, rep = update(self.model, self.prior, self.estimate, w, cov, now_us,
                                    self.cfg.estimator)
        self.refit = after_update(before, self.estimate, rep.accepted, self.buffer.cells_opened)
        if rep.accepted:
            self._watch_jump(before, idx, now_us)
        if rep.accepted and any(rep.observable):
            self.informed = True
        if rep.accepted:
            self.unobserved = _unobserved(self.model, self.estimate, rep.observable)
            s0 = self.model.s0
            noise_g2 = float(np.mean(w.var / np.maximum(w.n, 1))) / (s0 * s0) if len(w) else 0.0
            # how much more the vector can err than the buffer's norms show (`core.misfit`)
            a = self.model.correct(self.params, w.v, cov)
            sums = direction_sums(a)
            across = float(across_factor(sums, len(a)))
            # a diagonal model's cross-axis terms the postures leave unseen (`core.misfit`)
            unseen = (0.0 if self.model.has("cross_axis") else
                      unseen_cross_g2(sums, len(a), RunningMisfit.detect_g2(noise_g2)))
            self.watch.misfit.fitted(rep.residual_rms_after_g, noise_g2, across, unseen)
            # a fitted offset jump (a knock, a poisoned state) is an event, not a drift
            jumped = self.estimate is not None and self.estimate.step_us != before.step_us
            self.watch.misfit.moved(_moved_mg2(self.model, before, self.estimate)
                                    if learnt and not jumped else 0.0, now_us)
            self.watch.misfit.restate()
        self.counts["updates"] += 1
        if not rep.accepted:
            self.counts["updates_rejected"] += 1
        else:
            self._redirect(a)
        self.last_report = rep
        return UpdateEvent(idx, now_us, rep)

    def _try_bootstrap(self, idx: int, now_us: int) -> UpdateEvent | None:
        self._relocate(idx)
        slots = self.buffer.slots()  # windows that turned are no poses (`still_poses`)
        self.buffer.drop(slots[~still_poses(self.buffer.windows().var, self.model.s0)])
        cov = self.buffer.coverage()
        # five of the six half-axes: lying face down (-z for a hip sensor) may never happen
        half_axes = sum(cov.seen_pos) + sum(cov.seen_neg)
        if half_axes < 5 or cov.cells_filled < self.cfg.bootstrap_min_cells:
            return None
        w, slots = self.buffer.windows(), self.buffer.slots()
        if self.centre0.any():  # zero-g was found, roughly: coverage around the best centre
            if not self._sphere_due():
                return None
            loc = locate(w.v, self.cfg.buffer.grid)
            if loc is None or not loc.covers(cells=self.cfg.bootstrap_min_cells):
                return None
        fit = fit_poses(self.model, w.v, self.covariates(w.t_us, w.aux), not cov.full,
                        self.cfg.norm_tol_g)
        if fit is None:
            return None
        model, p, used, a = fit
        half, cells = reach(a[used], self.cfg.buffer.grid)
        if half < (5 if not cov.full else 6) or cells < self.cfg.bootstrap_min_cells:
            return None  # the windows that agree with the fit do not cover enough
        if not np.all((p[model.slice(Scale())] > 0.5 * self.model.s0)
                      & (p[model.slice(Scale())] < 2.0 * self.model.s0)):
            return None  # an ellipsoid far from the first sample's norm is not this sensor
        self.buffer.drop(slots[~used])  # off the fit: not still poses, never to be fitted
        # keep the detector's scale: its filters already run in the first sample's units
        # (`_relocate` restarted it if those were materially wrong)
        self.model = model
        self.prior = Prior.default(model, p)  # bounds and gates now relative to the fit
        self.estimate = Estimate.from_prior(self.prior)
        self.bootstrapped = True
        self._redirect()
        if off_by(p[model.slice(Offset())], model.s0, np.asarray(self.det_cfg.zero_raw),
                  self.det_cfg.s0):  # the detector's zero-g or scale was wrong: restart it
            self._restart_at = idx
        ev = self._update(idx, now_us, self.buffer.windows())  # the fit's own data
        return replace(ev, bootstrap=True)

    def _sphere_due(self) -> bool:
        """Whether a sphere fit of the buffer runs at this window: at every one while the
        buffer holds few (a lab's six positions may give no more), then every update_every
        windows (a wearer who never turns costs little)."""
        return (len(self.buffer) <= FEW_WINDOWS
                or self.counts["windows"] % self.cfg.update_every == 0)

    def _relocate(self, idx: int) -> None:
        """Before a bootstrap: if the still windows pin down zero-g and scale, roughly
        (`bootstrap.locate`: half-axes and cells of their centred directions), and the ones
        in use are materially wrong (`bootstrap.off_by`), use the found ones from the next
        sample on: the detector restarts centred at the found scale (`step`), and of the
        windows the wrong one gated only those on the sphere that did not turn stay, binned by
        their centred directions as later windows are; the bootstrap waits until those cover
        the orientations around the centre found (`_try_bootstrap`)."""
        if len(self.buffer) < LOCATE_MIN_WINDOWS or not self._sphere_due():
            return
        w = self.buffer.windows()
        loc = locate(w.v, self.cfg.buffer.grid)
        if (loc is None or len(loc.inliers) != len(w)
                or not loc.covers(cells=max(4, self.cfg.bootstrap_min_cells // 2))
                or not off_by(loc.centre, loc.scale, self.centre0, self.model.s0)):
            return
        self.centre0 = np.asarray(loc.centre, np.float64).copy()
        self.model = SensorModel(self.model.effects, loc.scale, self.model.spreads)
        # a detector that wrong (10x too loose on an unsigned part, blind along its offset)
        # let movement through: only the windows on the sphere that did not turn stay, binned
        # anew around the centre found (the bootstrap's fit drops those off it, `fit_poses`)
        keep = np.flatnonzero(loc.inliers & still_poses(w.var, loc.scale))
        self.buffer = WindowBuffer(self.cfg.buffer, len(self.aux_names))
        self._refill([(w.v[i], w.aux[i], int(w.t_us[i]), int(w.n[i]), float(w.var[i]))
                      for i in keep.tolist()], gate=False)
        self._restart_at = idx

    def _redirect(self, a_windows: np.ndarray | None = None) -> None:
        """Re-bin nothing, but refresh stored gravity directions with the new calibration.
        a_windows: the buffer's windows (`WindowBuffer.windows`, oldest first) corrected with
        the parameters now, if the caller has them (an update: the same numbers row by row)."""
        m = self.buffer.filled
        if not m.any():
            return
        if a_windows is not None:
            self.buffer.redirect(a_windows / norm3(a_windows)[:, None], self.buffer.slots())
            return
        cov = self.covariates(self.buffer.t_us[m], self.buffer.aux[m])
        a = self.model.correct(self.params, self.buffer.v[m], cov)
        self.buffer.redirect(a / norm3(a)[:, None])

    # --- correction --------------------------------------------------------------------------
    def _segment(self, idx: int) -> Segment:
        """What is in force from sample idx on (now): model, parameters, covariance (no
        estimate: the model's default prior spread around the provisional scale), status,
        misfit."""
        cache = self._segment_cache()
        extra = self.watch.misfit.said_mg2 if self.estimate is not None else 0.0
        status = self.status
        last = self._last_segment  # one per step: the same one while nothing in it changed
        if (last is not None and last.index == idx and last.p is cache[2]
                and last.status is status and last.extra_mg2 == extra):
            return last
        seg = self._last_segment = Segment(idx, cache[0], cache[2], cache[3], cache[4], status,
                                           extra, cache[5])
        return seg

    def _segment_cache(self) -> tuple:
        """(model, estimate, p, cov, sigma form, the form as lists) of the estimate in force,
        kept while it is."""
        est, model = self.estimate, self.model
        cache = self._form_cache
        if cache is None or cache[0] is not model or cache[1] is not est:
            p = self.params.copy()
            cov = est.cov if est is not None else np.diag(model.prior_sd() ** 2)
            form = sigma_form(model, p, cov) if np.isfinite(cov).all() else None
            rows = form.tolist() if form is not None else None
            cache = self._form_cache = (model, est, p, cov, form, rows)
        return cache

    def _start_detector(self, s0: float, zero_raw: np.ndarray | None = None) -> None:
        self.det_cfg = self.cfg.detector(s0, zero_raw)
        self.det_state = det.init_state(self.det_cfg)


def gain_reference(model: SensorModel, p: np.ndarray, from_prior: bool) -> dict:
    """The counts per g that gains are reported against (`Pipeline.gain_reference`): the
    prior's nominal sensitivity (model.s0), or without a prior the mean fitted scale."""
    if from_prior or not model.has("scale"):
        return {"source": "prior", "counts_per_g": float(model.s0)}
    return {"source": "fit", "counts_per_g": float(np.mean(p[model.slice(Scale())]))}


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


def _zero_of(model: SensorModel, p: np.ndarray) -> np.ndarray | None:
    """Zero-g (raw) the parameters p give, for the detector (None: the model has no offsets)."""
    return np.asarray(p[model.slice(Offset())], np.float64) if model.has("offset") else None


def _state_of_detector(cfg: det.DetectorConfig | None, st: det.DetectorState | None) -> dict | None:
    if cfg is None or st is None:
        return None
    return {"s0": cfg.s0, "zero_raw": list(cfg.zero_raw), "zi_hp": st.zi_hp.tolist(),
            "zi_lp": st.zi_lp.tolist(),
            "last_v": [None if np.isnan(x) else float(x) for x in st.last_v],
            "same_run": st.same_run, "started": st.started}


def state_dict(pipe: Pipeline) -> dict:
    """Everything needed to resume exactly where `pipe` stopped (JSON-able)."""
    rep = pipe.last_report
    win = pipe.windower.to_dict()
    return {
        "version": 1,
        "config": pipe.cfg.to_dict(),
        "model": pipe.model.to_dict(),
        "prior": pipe.prior.to_dict() if pipe.prior is not None else None,
        "estimate": pipe.estimate.to_dict() if pipe.estimate is not None else None,
        "bootstrapped": pipe.bootstrapped,
        "from_prior": pipe.from_prior,
        "centre0": pipe.centre0.tolist(),
        "aux_names": list(pipe.aux_names),
        "t0_us": pipe.t0_us,
        "buffer": pipe.buffer.state_dict(),
        "detector": _state_of_detector(pipe.det_cfg, pipe.det_state),
        "open": win["open"],
        "pending": win["pending"],
        "fresh": [[np.asarray(f[0]).tolist(), np.asarray(f[1]).tolist(), int(f[2]), int(f[3]),
                   float(f[4])] for f in pipe.fresh],
        "last_t_us": win["last_t_us"],
        "last_gate": win["last_gate"],
        "counts": dict(pipe.counts),
        "last_report": asdict(rep) if rep is not None else None,
        **pipe.refit.to_dict(),
        "informed": pipe.informed,
        "watch": pipe.watch.to_dict(),
        "unobserved": list(pipe.unobserved),
    }


def from_state_dict(d: dict) -> Pipeline:
    """Rebuild a pipeline from `state_dict`; it continues bit for bit."""
    if d.get("version") != 1:
        raise InputError(f"unknown checkpoint version {d.get('version')!r}")
    cfg = PipelineConfig.from_dict(d["config"])
    model = SensorModel.from_dict(d["model"])
    prior = Prior.from_dict(d["prior"]) if d["prior"] is not None else None
    pipe = Pipeline(cfg, model, prior, tuple(d["aux_names"]), d["t0_us"])
    pipe.model = model  # bootstrap may have replaced s0; the checkpoint's model is the truth
    pipe.estimate = Estimate.from_dict(d["estimate"]) if d["estimate"] is not None else None
    pipe.bootstrapped = bool(d["bootstrapped"])
    pipe.from_prior = bool(d.get("from_prior", prior is not None and pipe.bootstrapped))
    pipe.centre0 = np.asarray(d.get("centre0", [0.0] * 3), np.float64)
    pipe.buffer = WindowBuffer.from_state_dict(d["buffer"])
    ds = d["detector"]
    if ds is not None:
        pipe._start_detector(float(ds["s0"]), np.asarray(ds.get("zero_raw", [0.0] * 3), float))
        pipe.det_state = det.DetectorState(
            np.asarray(ds["zi_hp"], float), np.asarray(ds["zi_lp"], float),
            np.array([np.nan if x is None else x for x in ds["last_v"]], float),
            int(ds["same_run"]), bool(ds["started"]))
    else:
        pipe.det_cfg = pipe.det_state = None
    pipe.windower = WindowerState.from_dict(d)
    pipe.fresh = [(np.asarray(f[0], float), np.asarray(f[1], float), int(f[2]), int(f[3]),
                   float(f[4])) for f in d["fresh"]]
    pipe.counts = dict(d["counts"])
    pipe.refit = RefitState.from_dict(d)
    informed = d.get("informed")  # absent in checkpoints from before statuses
    pipe.informed = (bool(informed) if informed is not None
                     else pipe.estimate is not None and pipe.estimate.t_us is not None)
    pipe.watch = Watch.from_dict(d.get("watch"))
    pipe.unobserved = tuple(str(x) for x in d.get("unobserved", ()))  # absent in older ones
    rep = d.get("last_report")
    pipe.last_report = (UpdateReport(**{**rep, "observable": tuple(rep["observable"]),
                                        "free": tuple(rep["free"])}) if rep else None)
    return pipe
