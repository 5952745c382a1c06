"""One calibration step: raw batch -> (gates, calibrated batch, updates). The only core entry
point the shell uses, so the daemon, replay and tests cannot drift apart (docs/design.md).

Per batch, each part in its module: the detector (`core.detector`, Lötters eq. 1-2) gates every
sample; the gated runs are cut into windows (`core.windower`); committed windows enter the
buffer (`core.buffer`) and, when a re-fit can tell anything new (`core.refit`), the estimator
updates (`core.estimator`, Lötters eq. 11a/11b); samples are corrected with the parameters in
force when they arrived (`core.correction`), with their status and predicted error
(`core.status`); the self-watch (`core.status.Watch`) marks the output suspect or resets the
estimate when the still windows keep contradicting it. This module only orchestrates them:
the step, one sample or a batch, and what is in force; the pipeline's own parts are functions
of it in `core.pipeline_windows` (windows committed, re-fits due), `core.pipeline_watch` (the
self-watch at work), `core.pipeline_fit` (updates, bootstrap) and `core.pipeline_state` (the
checkpoint, a step's scratch and caches).

Everything is driven by the sample sequence alone (never by batch boundaries or clocks), so
feeding a recording in batches of 1, 10 or 1000 samples gives the same output.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import Enum
from itertools import pairwise

import numpy as np

from recal.core import detector as det
from recal.core.buffer import Coverage, Window, WindowBuffer, Windows
from recal.core.channels import check_channels, usable
from recal.core.correction import Segment, calibrate
from recal.core.effects import Covariates, Offset, Scale
from recal.core.estimator import Estimate, Prior, UpdateReport
from recal.core.model import SensorModel
from recal.core.outputs import JoinedStep, Marks, StepOutput
from recal.core.pending import PendingCandidate
from recal.core.pipeline_config import PipelineConfig
from recal.core.pipeline_fit import redirect, refill_buffer
from recal.core.pipeline_state import Work, load_state
from recal.core.pipeline_state import state_dict as state_dict
from recal.core.pipeline_watch import heal_if_not_finite
from recal.core.pipeline_windows import windows
from recal.core.refit import RefitState
from recal.core.sigma import sigma_form, with_floor
from recal.core.status import (
    PROBATION_WINDOWS,
    REOPEN_PROBATION_WINDOWS,
    RunningMisfit,
    Status,
    Watch,
    unsettled,
)
from recal.core.windower import WindowerState
from recal.errors import InputError, ModelError
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["Lifecycle", "Pipeline", "from_state_dict", "gain_reference", "state_dict"]


def learnt_prior(model: SensorModel, prior: Prior, cov: np.ndarray) -> Prior:
    """The pre-calibration an adopted model continues with: ``prior`` (default spreads about
    the discovery fit's values), each term beyond the offsets, scales and cross-axis (a
    temperature coefficient, a supply ratio) narrowed to its marginal sd in the discovery
    fit's covariance ``cov`` where that is tighter. Those terms are the sensor's physics and
    the evidence saw them over the covariates' whole range; the buffer's newest windows per
    orientation often do not (an hour at one temperature), and re-fitted under the default
    spread they left the offsets 5-30 mg uncertain for 20 min after adoption. Marginal sd,
    no correlations: the prior says no more of the offsets and scales than it did, and the
    buffer's windows, which the evidence also holds, count twice only in those terms."""
    sd = prior.sd.copy()
    base = np.zeros(model.size, bool)
    for key in (("offset", None), ("scale", None)):
        if model.has(key[0]):
            base[model.slice(key)] = True
    fit_sd = np.sqrt(np.clip(np.diag(np.asarray(cov, np.float64)), 0.0, None))
    # a cross-axis term moves the output across gravity, where no norm residual sees it: its
    # fit sd is what the evidence's postures told of it, and narrowed to that (with the same
    # windows refilled into the buffer) sigma went below the error (bench/sigma_honesty.py
    # --live, cross-axis: 7.6 % of calibrated seconds beyond 3 sigma, 1.6 % kept at its spread)
    base |= model.mask(("cross_axis",))
    narrow = ~base & np.isfinite(fit_sd) & (fit_sd > 0) & (fit_sd < sd)
    sd[narrow] = fit_sd[narrow]
    return Prior.from_sd(prior.mean, sd)


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
        self.buffer = WindowBuffer(cfg.buffer, len(self.aux_names))
        #: windows committed since the last update (< update_every)
        self.fresh: list[Window] = []
        #: the detector's settings and state (None: no scale yet, `Lifecycle.AWAITING_SCALE`)
        self.detector: det.Detector | None = None
        if prior is not None:
            self._start_detector(model.s0, _zero_of(model, prior.mean))
        self.windower = WindowerState()  # the open and pending windows (`core.windower`)
        self.counts = {"samples": 0, "quasi_static": 0, "windows": 0, "windows_rejected": 0,
                       "updates": 0, "updates_rejected": 0}
        self.last_report: UpdateReport | None = None
        self.refit = RefitState()  # what the last update saw (`core.refit`)
        # data informed the estimate (an accepted update observed a parameter): `status`
        self.informed = False
        self.watch = Watch()
        #: offsets and scales the data did not observe at the last accepted update and the
        #: prior does not pin (`pipeline_fit._unobserved`): status held while any
        self.unobserved: tuple[str, ...] = ()
        self._work = Work()  # a step's scratch and the caches (`pipeline_state.Work`)

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
        if self.detector is None:
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
        cached = self._work.converging
        unobserved = self.unobserved
        if (cached is None or cached[0] is not est or cached[1] is not self.model
                or cached[3] is not unobserved):  # asked at every step: once per estimate
            names = unsettled(self.model, est.cov)
            cached = self._work.converging = (
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
                          self.estimate, windows=s.windows)

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
        gap in device time longer than cfg.gap_doubt_s (GAP_S unless configured): a doubt for
        REOPEN_PROBATION_WINDOWS from the sample after it, once an estimate exists to doubt.
        The cuts fall at those samples however the samples were batched, so live (a message
        at a time) and replay (messages joined) agree (cutting a step changes nothing else:
        the pipeline is batch-size invariant)."""
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
        """The samples of the batch that follow a gap in device time beyond cfg.gap_doubt_s,
        in order (0: the gap lies before the batch's first sample)."""
        t, last, gap_us = batch.t_us, self.last_t_us, self.cfg.gap_doubt_s * 1e6
        if not len(t) or not gap_us:  # 0: no gap is a doubt
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
        if self.lifecycle is _AWAITING_SCALE:  # the first sample's norm is 1 g
            norms = np.linalg.norm(batch.v, axis=1)
            good = norms[np.isfinite(norms) & (norms > 0)]  # a NaN s0 would stick for good
            s0 = float(good[0]) if len(good) else 1.0
            self.model = SensorModel(self.model.effects, s0, self.model.spreads)
            self._start_detector(s0)
        # until an estimate exists (from the start, or from a reset of the self-watch inside
        # the batch), zero-g and scale may be found wrong at a window (`pipeline_fit._relocate`):
        # the detector then restarts after that sample, as it would have had the batch ended
        # there; the step ended there (`_step`), the rest is stepped anew
        head = self._step(batch, marks)
        at, self._work.restart_at = self._work.restart_at, None
        if at is None:
            return head
        self._start_detector(self.model.s0, _zero_of(self.model, self.params))
        if at + 1 >= n:
            return head
        tail = self._stepped(batch[at + 1:], [m - at - 1 for m in marks if m > at + 1])
        return head.joined(tail, at + 1)

    def _step(self, batch: RawBatch, marks: list[int]) -> JoinedStep:
        """`step` with the detector as it is (see there)."""
        n = len(batch)
        self._work.watch_events = []
        heal_if_not_finite(self, int(batch.t_us[0]))
        dr = self.detector
        dr.state, d = det.detect(dr.cfg, dr.state, batch.v)
        gate, det_g = usable(d.gate, batch, self.model), d.detector_g
        self._work.segs = [self._segment(0)]
        if marks:
            self._work.marks = Marks(list(marks), gate, self.counts["samples"],
                                     self.counts["quasi_static"])
        try:
            events, commits, committed = windows(self, batch, gate)
            at = self._work.restart_at
            if at is not None and at + 1 < n:
                # the detector restarts after sample `at`: this step ends there, the windows
                # after it uncommitted (`pipeline_windows.windows`), `_stepped_whole` steps
                # the rest
                n, batch, gate, det_g = at + 1, batch[:at + 1], gate[:at + 1], det_g[:at + 1]
            self._reach(n)  # the marks no later change came before
        finally:
            done, self._work.marks = self._work.marks, None
        cal, status, sigma = calibrate(self._work.segs, batch, self.covariates)
        self._work.segs = []
        self.counts["samples"] += n
        if n == 1:  # one sample per arrival: the arrays are made here, as the batch keeps them
            self.counts["quasi_static"] += int(gate[0])
            out = CalibratedBatch.of_checked(batch.t_us, cal, gate, det_g, status, sigma)
        else:
            self.counts["quasi_static"] += int(gate.sum())
            out = CalibratedBatch(batch.t_us, cal, gate, det_g, status, sigma)
        return JoinedStep(out, tuple(events), commits, tuple(self._work.watch_events),
                          done.at if done is not None else {}, committed)

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

    def adopt(self, model: SensorModel, prior: Prior, cov: np.ndarray | None = None,
              evidence: Windows | None = None) -> None:
        """Continue with another model (one effect discovery extended): its prior becomes the
        pre-calibration and the estimate, with ``cov`` as the estimate's covariance if given
        (the fit's that found the model: what its windows tell, not only the prior's
        spreads); detector and windows carry on; the self-watch starts afresh (it judged the
        model replaced), a waiting candidate is no longer. ``evidence``: the windows that
        fit found the model on (`core.evidence`, oldest first): the buffer is refilled from
        them (those within the norm gate under the new model), so the next update re-fits
        what showed the model, not only the postures of a buffer the old model's misfit
        kept resetting (docs/design.md, effect discovery: live); None: the buffer carries on."""
        check_channels(model, self.aux_names)
        self.model = model
        self.prior = prior if cov is None else learnt_prior(model, prior, cov)
        self.estimate = (Estimate.from_prior(prior) if cov is None
                         else Estimate(prior.mean.copy(), np.array(cov, np.float64)))
        if evidence is not None and len(evidence):
            self.buffer = WindowBuffer(self.cfg.buffer, len(self.aux_names))
            w = evidence
            refill_buffer(self, [Window(w.v[i], w.aux[i], int(w.t_us[i]), int(w.n[i]),
                                        float(w.var[i])) for i in range(len(w))])
            self.fresh = []
            self.refit = RefitState()  # the next try re-fits the new buffer
        # the self-watch judged the model this one replaces (its contradictions, its misfit):
        # it starts afresh, the first still window must agree before output is calibrated;
        # the wait for a candidate is over, whichever model was adopted
        m = self.watch.misfit
        self.watch = Watch(triggers=self.watch.triggers)
        self.watch.doubt(REOPEN_PROBATION_WINDOWS)
        self.bootstrapped = True
        # what the misfit measured, it measured under the model now replaced (kappa and the
        # unseen floor are the postures', kept until the next update recomputes them)
        self.watch.misfit = RunningMisfit(across=m.across, unseen_w=m.unseen_w)
        redirect(self)

    @property
    def pending(self) -> PendingCandidate | None:
        """The candidate model waiting to be adopted or rejected (`core.pending`), if any."""
        return self.watch.pending

    def set_pending(self, candidate: PendingCandidate | None) -> None:
        """A discovery run ended with a candidate model not adopted (yet): until
        ``set_pending(None)`` (rejected) or `adopt`, each sample's sigma carries how much the
        candidate's correction of it differs from the one in force (`core.pending`). Its
        model must read only channels this pipeline has and share the model's raw units."""
        if candidate is not None:
            check_channels(candidate.model, self.aux_names)
            if candidate.model.s0 != self.model.s0 or len(candidate.p) != candidate.model.size:
                raise ModelError(f"a candidate at s0 {candidate.model.s0:g} with "
                                 f"{len(candidate.p)} values for {candidate.model.size} "
                                 f"parameters does not fit a model at s0 {self.model.s0:g}")
        self.watch.pending = candidate

    def _reach(self, idx: int) -> None:
        """Called before anything in the state changes at sample ``idx`` of the batch: the
        state now is the state after ``m`` samples for every mark m <= idx not yet passed."""
        if self._work.marks is not None:
            self._work.marks.reach(idx, self.model, self.estimate, self.summary)

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
            # what the model misses along gravity (`RunningMisfit.along_mg2`: what discover's
            # held-out residual scores), and what the misfit adds to sigma in force
            "misfit_mg": math.sqrt(self.watch.misfit.along_mg2),
            "sigma_misfit_mg": math.sqrt(self.watch.misfit.said_mg2),
            # a candidate model waiting (`core.pending`): sigma carries where it disagrees
            "pending": self.watch.pending.label if self.watch.pending is not None else None,
        }

    # --- windows -----------------------------------------------------------------------------

    # --- self-watch --------------------------------------------------------------------------

    # --- estimation --------------------------------------------------------------------------

    # --- correction --------------------------------------------------------------------------
    def _segment(self, idx: int) -> Segment:
        """What is in force from sample idx on (now): model, parameters, covariance (no
        estimate: the model's default prior spread around the provisional scale), status,
        misfit."""
        cache = self._segment_cache()
        extra = self.watch.misfit.said_mg2 if self.estimate is not None else 0.0
        status = self.status
        last = self._work.last_segment  # one per step: the same one while nothing in it changed
        if (last is not None and last.index == idx and last.p is cache[2]
                and last.status is status and last.extra_mg2 == extra):
            return last
        seg = self._work.last_segment = Segment(idx, cache[0], cache[2], cache[3], cache[8],
                                                status, extra, cache[5], cache[6], cache[9])
        return seg

    def _segment_cache(self) -> tuple:
        """(model, estimate, p, cov, sigma form of C_e, the output's form as lists, pending
        candidate, the unseen floor's W as the misfit holds it, the output's form (C_e and
        the floor, `sigma.with_floor`), the floor's W where no form holds it) of the estimate
        in force, kept while it is."""
        est, model, pending = self.estimate, self.model, self.watch.pending
        unseen = self.watch.misfit.unseen_w if est is not None else None
        cache = self._work.form
        if (cache is None or cache[0] is not model or cache[1] is not est
                or cache[6] is not pending or cache[7] is not unseen):
            p = self.params.copy()
            cov = est.cov if est is not None else np.diag(model.prior_sd() ** 2)
            form = sigma_form(model, p, cov) if np.isfinite(cov).all() else None
            w = np.reshape(unseen, (3, 3)) if unseen is not None and any(unseen) else None
            out = form if w is None or form is None else with_floor(model, p, form, w)
            rows = out.tolist() if out is not None else None
            cache = self._work.form = (model, est, p, cov, form, rows, pending, unseen, out,
                                       w if out is None else None)
        return cache

    def _start_detector(self, s0: float, zero_raw: np.ndarray | None = None) -> None:
        self.detector = det.Detector(self.cfg.detector(s0, zero_raw))

    @property
    def det_cfg(self) -> det.DetectorConfig | None:
        """The detector's settings (None: no scale yet)."""
        return self.detector.cfg if self.detector is not None else None

    @property
    def det_state(self) -> det.DetectorState | None:
        """The detector's state (None: no scale yet)."""
        return self.detector.state if self.detector is not None else None


def gain_reference(model: SensorModel, p: np.ndarray, from_prior: bool) -> dict:
    """The counts per g that gains are reported against (`Pipeline.gain_reference`): the
    prior's nominal sensitivity (model.s0), or without a prior the mean fitted scale."""
    if from_prior or not model.has("scale"):
        return {"source": "prior", "counts_per_g": float(model.s0)}
    return {"source": "fit", "counts_per_g": float(np.mean(p[model.slice(Scale())]))}


def _zero_of(model: SensorModel, p: np.ndarray) -> np.ndarray | None:
    """Zero-g (raw) the parameters p give, for the detector (None: the model has no offsets)."""
    return np.asarray(p[model.slice(Offset())], np.float64) if model.has("offset") else None


def from_state_dict(d: dict) -> Pipeline:
    """Rebuild a pipeline from `state_dict`; it continues bit for bit."""
    if d.get("version") != 1:
        raise InputError(f"unknown checkpoint version {d.get('version')!r}")
    cfg = PipelineConfig.from_dict(d["config"])
    model = SensorModel.from_dict(d["model"])
    prior = Prior.from_dict(d["prior"]) if d["prior"] is not None else None
    pipe = Pipeline(cfg, model, prior, tuple(d["aux_names"]), d["t0_us"])
    pipe.model = model  # bootstrap may have replaced s0; the checkpoint's model is the truth
    load_state(pipe, d)
    return pipe
