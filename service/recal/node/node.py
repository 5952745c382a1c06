"""Calibration node: one per sensor, between the bus or a recording and ``Pipeline.step``.

A :class:`CalibrationNode` takes raw batches and hands everything it derives to a
:class:`recal.node.sinks.Sink`: the calibrated batch, the calibration state whenever an update
happened, the decimated plot topic, events and, once the mounting is known, the acceleration
rotated into the body frame. The gateway (in-process), a node on another machine
(`recal.daemon.remote_node`) and ``replay`` (no Zenoh) run this same code, so a replay reproduces a
live run bit for bit. The messages and their fields: `recal.node.sinks`. Device time goes through
`recal.core.timebase` right before ``Pipeline.step`` (docs/design.md, device time); a model
that needs a channel the stream lacks is one ``missing_channel`` event at the stream's first
batch, then the node skips (``failed``). The alignment rules: `recal.node.align_requests`.

No calibration algebra here: the estimator is behind ``Pipeline``, the tilt math in
``recal.core.alignment``, the time base in ``recal.core.timebase``.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from recal.config import (
    AlignmentConfig,
    PipelineSection,
    RediscoveryConfig,
    SensorConfig,
    ServiceConfig,
    model_and_prior,
)
from recal.core import alignment as al
from recal.core import timebase as tb
from recal.core.channels import missing_channels, unnamed_for
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.outputs import StepOutput
from recal.core.pipeline import Pipeline
from recal.core.rate import infer_rate_hz
from recal.core.status import NOT_FINITE_SIGMA_MG, REOPEN_PROBATION_WINDOWS, Status
from recal.node.align_requests import AlignmentRequests
from recal.node.checkpoints import (
    CHECKPOINT_FORMAT,
    Checkpoints,
    estimate_problem,
    restore_pipeline,
)
from recal.node.rediscovery import Rediscovery as _Rediscovery
from recal.node.sinks import Sink
from recal.samples import CalibratedBatch, RawBatch, conform_channels

__all__ = [
    "CalibrationNode",
    "NodeSettings",
    "make_node",
    "model_name",
    "node_settings",
]

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 100.0  # only when a stream ends before its rate could be measured
ANOMALY_EVENT_US = 60_000_000  # time_anomalies events at most this often (device time)
# samples the clock's unit is read from when the rate is configured: the median of 7 steps
# (a repeated stamp or a wrap among the first two would decide it alone)
UNIT_SAMPLES = 8

# ---------------------------------------------------------------------------------------------
# Small pure helpers
# ---------------------------------------------------------------------------------------------

def model_name(model: SensorModel) -> str:
    """"diagonal", "full", or the effect labels joined by "+" for discovered models."""
    kinds = tuple(e.key for e in model.effects)
    if kinds == (("offset", None), ("scale", None)):
        return "diagonal"
    if kinds == (("offset", None), ("scale", None), ("cross_axis", None)):
        return "full"
    return "+".join(e.label for e in model.effects)


def _decade_reached(total: int, latest: int) -> bool:
    """Whether ``total`` reached 1, 10, 100, ... with its ``latest`` additions."""
    before = total - latest
    return before <= 0 or len(str(total)) > len(str(before))


# ---------------------------------------------------------------------------------------------
# The node
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class NodeSettings:
    """Everything a node needs to start a pipeline for one sensor.

    Attributes:
        sensor_id: the sensor.
        pipeline: shared calibration settings (threshold, window, mode, plot rate, ...).
        model: the sensor model; prior: the pre-calibration (None: bootstrap).
        rate_hz: nominal rate in Hz (None: measured from the first ``infer_samples`` samples).
        full_scale_g: sensor range for clipping detection (None: off).
        alignment: reference-posture and tilt-alarm settings.
        request_min_s: an alignment request uses the current still run if it lasted this long.
    """

    sensor_id: str
    pipeline: PipelineSection
    model: SensorModel
    prior: Prior | None
    rate_hz: float | None = None
    full_scale_g: float | None = None
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    infer_samples: int = 50
    request_min_s: float = 2.0
    rediscovery: RediscoveryConfig = field(default_factory=RediscoveryConfig)

#: Updates over which the same parameters stay unobserved before the console says so.
UNSEEN_SAY_UPDATES = 10


class CalibrationNode(AlignmentRequests):
    """Runs one sensor's pipeline and publishes what it produces (thread-safe).

    Args:
        settings: how to start the pipeline.
        sink: where the output goes.
        pipeline: a pipeline to continue (restored from a checkpoint or a recording's setup);
            None starts one from ``settings`` at the first batch.
        alignment: a known mounting (from a checkpoint).
        start: how the pipeline began: "prior", "bootstrap", "checkpoint", "recording".
        timebase: the device clock's time base to continue (a checkpoint's or a recording's
            setup; with a pipeline but none, device time is taken as microseconds).

    Device time goes through :mod:`recal.core.timebase` before ``Pipeline.step`` (unwrapped,
    units, reboots; never backwards), here where the live node and replay both pass: the raw
    log keeps the device's values, the calibrated output has the time base's.
    """

    def __init__(self, settings: NodeSettings, sink: Sink, *, pipeline: Pipeline | None = None,
                 alignment: al.Alignment | None = None, start: str | None = None,
                 timebase: tb.TimebaseState | None = None) -> None:
        self.settings = settings
        self.sensor_id = settings.sensor_id
        self.sink = sink
        self.pipeline = pipeline
        self.alignment = alignment
        self.start = start or ("prior" if settings.prior is not None else "bootstrap")
        self._lock = threading.RLock()
        self._pending: list[RawBatch] = []  # held until the rate is known (bounded)
        self._pending_n = 0
        self._tracker: al.StillTracker | None = None
        self._slip: al.SlipWatch | None = None  # the tilt alarm's check of later periods
        self._align_requested = False
        self._last_names: tuple[str, ...] | None = None
        self._started = False
        self._plot_every_at: tuple[float, int] | None = None  # (rate, plot_every) of `_plot_every`
        self.accepted_updates = 0
        self.samples = 0
        self.samples_skipped = 0
        # samples published per status (`core.status.Status`), and those zeroed (not finite)
        self.status_counts = np.zeros(len(Status), np.int64)
        self.samples_not_finite = 0
        self._status: Status | None = None  # of the last sample published
        self._tcfg: tb.TimebaseConfig | None = None  # the time base's, per rate
        self._said: Status | None = None  # the status the console last named
        self._unseen: tuple[tuple[str, ...], int, bool] = ((), 0, False)  # `_say_unseen`
        self.last_t_us: int | None = None
        self.last_state: dict[str, Any] | None = None
        self._next_discovery_us: int | None = None
        self._discovery: _Rediscovery | None = None  # a run in its thread
        self._offsets_known: tuple[Any, Any, bool] | None = None  # model, estimate, answer
        self._last_align_request_s: float | None = None  # monotonic time of the last accepted
        self.align_refused = 0  # requests refused by the rate limit, in all
        self._refused_unreported = 0  # ... since the last align_refused event
        self.timebase = timebase
        self._anomalies_said_us = -ANOMALY_EVENT_US  # device time of the last time_anomalies
        # the last state whose model, estimate and prior passed the restore checks
        # (`_vet`), and which (by identity) were checked last
        self._good: Pipeline | None = None
        self._vetted: tuple[Any, Any, Any] | None = None
        self.estimates_refused = 0
        #: why this sensor cannot be calibrated at all (a channel the model needs is missing
        #: from the stream), reported once as an event; None while it can
        self.failed: str | None = None
        #: where the operator's one-line notes go (the gateway's or node's console, prefixed
        #: with the sensor id): time units, reboots, first calibrated, suspect and back;
        #: None: the log only (replay)
        self.on_note: Callable[[str], None] | None = None
        if pipeline is not None:
            self._tracker = self._make_tracker(pipeline.cfg.rate_hz)
            if timebase is None:  # from before time bases were kept: microseconds, as then
                self.timebase = tb.TimebaseState(step_us=1e6 / pipeline.cfg.rate_hz)

    # -- public -------------------------------------------------------------------------------

    @property
    def rate_hz(self) -> float | None:
        return self.pipeline.cfg.rate_hz if self.pipeline is not None else self.settings.rate_hz

    def process(self, batch: RawBatch, log_time_ns: int) -> StepOutput | None:
        """Calibrate one raw batch and send the results to the sink.

        Returns the pipeline's output (None while samples are held to measure the rate, or
        when the batch cannot be calibrated, which is reported as an event).
        """
        if len(batch) == 0:
            return None
        with self._lock:
            if self.failed is not None:
                self.samples_skipped += len(batch)
                return None
            if self.pipeline is None:
                batch = self._hold_until_rate(batch, log_time_ns)
                if not len(batch):
                    return None
            if not self._started:
                self._announce(int(batch.t_us[0]), log_time_ns)
            return self._step(batch, log_time_ns)

    def process_many(self, items: Sequence[tuple[RawBatch, int]]) -> None:
        """`process` for consecutive (batch, log time) of this sensor, in one pipeline step.

        The output is exactly what `process` gives each batch in turn (per batch, with its
        log time: calibrated, plot, body, events, and the calibration state after updates,
        as of that batch's end); only the per-call costs are paid once, since the pipeline
        is batch-size invariant (replay joins a recording's small messages this way; bit for
        bit on integer readings such as ADC counts, else to the last bit of a window sum that
        a message end cuts, `core.windower`). Falls back to `process` one by one when the
        batches cannot share a step: pipeline not started, another channel layout, periodic
        rediscovery on.
        """
        items = [(b, t) for b, t in items if len(b)]
        with self._lock:
            while items and (self.pipeline is None or not self._started):
                self.process(*items.pop(0))  # until the rate is known and the pipeline runs
            pipe = self.pipeline
            if (len(items) < 2 or pipe is None or self.settings.rediscovery.enabled
                    or self.failed is not None
                    or any(b.aux_names != pipe.aux_names for b, _ in items)):
                for batch, log_ns in items:
                    self.process(batch, log_ns)
                return
            device = RawBatch.concat([b for b, _ in items])
            joined = self._device_time(device, items[0][1])
            lengths = [len(b) for b, _ in items]
            outs = pipe.step_joined(joined, lengths)
            self._last_names = pipe.aux_names
            devs = np.split(device.t_us, np.cumsum(lengths)[:-1])
            for (_, log_ns), out, dev in zip(items, outs, devs, strict=True):
                self._emit(out, log_ns, dev)

    def flush(self, log_time_ns: int) -> None:
        """End of stream: calibrate samples still held for rate measurement."""
        with self._lock:
            if self.pipeline is None and self._pending:
                batch = self._start_pipeline(True, log_time_ns)
                if len(batch):
                    self._announce(int(batch.t_us[0]), log_time_ns)
                    self._step(batch, log_time_ns)

    def port_reopened(self) -> None:
        """The device's port closed and opened again (unplugged and plugged in: perhaps
        another device under this id, whose clock need not restart): output is held until the
        first still window after it agrees with the calibration, suspect if it contradicts
        (`status.REOPEN_PROBATION_WINDOWS`)."""
        with self._lock:
            if self.pipeline is not None:  # still measuring the rate: nothing to doubt yet
                self.pipeline.doubt(REOPEN_PROBATION_WINDOWS)

    def status(self) -> dict[str, Any]:
        """The current calibration state (as published) plus node counters."""
        with self._lock:
            state = self._state(self.last_t_us, "status") if self.pipeline is not None else {
                "sensor_id": self.sensor_id, "t_us": None, "reason": "status",
                "params": None, "alignment": None}
            tbs = self.timebase
            state["node"] = {"start": self.start, "rate_hz": self.rate_hz,
                             "time": None if tbs is None else {"unit": tbs.unit,
                                                               **tbs.counts()},
                             "failed": self.failed,
                             "samples": self.samples, "samples_skipped": self.samples_skipped,
                             "samples_by_status": self.samples_by_status(),
                             "samples_not_finite": self.samples_not_finite,
                             "accepted_updates": self.accepted_updates,
                             "estimates_refused": self.estimates_refused,
                             "still_s": self._tracker.duration_s if self._tracker else 0.0,
                             "align_requested": self._align_requested,
                             "align_refused": self.align_refused}
            return state

    def samples_by_status(self) -> dict[str, int]:
        """Samples published so far per status label (only the statuses seen)."""
        return {Status(i).label: int(n) for i, n in enumerate(self.status_counts.tolist()) if n}

    @property
    def samples_not_calibrated(self) -> int:
        """Samples published with any status but calibrated."""
        return int(self.status_counts.sum() - self.status_counts[Status.CALIBRATED])

    def checkpoint(self) -> dict[str, Any] | None:
        """A JSON-able checkpoint of the node (None before its pipeline started)."""
        with self._lock:
            if self.pipeline is None:
                return None
            # a rediscovery still running is not saved: it is due again at once on restart,
            # rather than every_h after it, which a daemon restarted more often than every_h
            # would otherwise never reach
            due = (self._discovery.started_us if self._discovery is not None
                   else self._next_discovery_us)
            return {"format": CHECKPOINT_FORMAT, "sensor_id": self.sensor_id,
                    "saved_unix_s": time.time(), "t_us": self.last_t_us,
                    "pipeline": self.pipeline.state_dict(),
                    "alignment": self.alignment.to_dict() if self.alignment else None,
                    "next_discovery_us": due,
                    "timebase": self.timebase.to_dict() if self.timebase else None}

    @classmethod
    def from_checkpoint(cls, settings: NodeSettings, sink: Sink,
                        doc: dict[str, Any]) -> CalibrationNode:
        """Continue from :meth:`checkpoint` output (ValueError if it does not fit or cannot be
        trusted: `recal.node.checkpoints.restore_pipeline` checks the state)."""
        if doc.get("sensor_id") != settings.sensor_id:
            raise ValueError(f"checkpoint is for sensor {doc.get('sensor_id')!r}, "
                             f"not {settings.sensor_id!r}")
        pipe = restore_pipeline(doc.get("pipeline"), reference=(settings.model, settings.prior))
        kinds = [e.kind for e in pipe.model.effects]
        configured = [e.kind for e in settings.model.effects]
        grown = settings.rediscovery.enabled and {e.key for e in settings.model.effects} <= {
            e.key for e in pipe.model.effects}  # rediscovery extended the configured model
        if kinds != configured and not grown:
            raise ValueError(f"checkpoint model {model_name(pipe.model)} differs from the "
                             f"configured {model_name(settings.model)}")
        ali = doc.get("alignment")
        try:
            alignment = al.Alignment.from_dict(ali) if ali else None
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"checkpoint alignment: {type(exc).__name__}: {exc}") from None
        tbd = doc.get("timebase")  # absent in checkpoints from before it was kept
        try:
            timebase = tb.TimebaseState.from_dict(tbd) if isinstance(tbd, dict) else None
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"checkpoint time base: {type(exc).__name__}: {exc}") from None
        pipe.doubt()  # another device may be under this id now: its first windows must agree
        node = cls(settings, sink, pipeline=pipe, alignment=alignment, start="checkpoint",
                   timebase=timebase)
        due = doc.get("next_discovery_us")  # absent in checkpoints from before it was kept
        every_us = round(settings.rediscovery.every_h * 3.6e9)
        last = pipe.last_t_us or 0
        # one further ahead than a period never comes: scheduled again from the data
        node._next_discovery_us = (int(due) if isinstance(due, (int, float))
                                   and 0 <= due <= last + every_us else None)
        return node

    # -- starting -----------------------------------------------------------------------------

    def _hold_until_rate(self, batch: RawBatch, log_ns: int) -> RawBatch:
        """Keep samples until the rate and the clock's unit are known (``infer_samples``,
        or ``UNIT_SAMPLES`` with a nominal rate); then start the pipeline and return them."""
        self._pending.append(batch)
        self._pending_n += len(batch)
        need = self.settings.infer_samples if self.settings.rate_hz is None else UNIT_SAMPLES
        if self._pending_n < need:
            return RawBatch.empty(batch.aux_names)
        # time stamps that never advance give no rate: stop waiting (bounded memory)
        return self._start_pipeline(self._pending_n >= 20 * self.settings.infer_samples,
                                    log_ns)

    def _start_pipeline(self, force: bool, log_ns: int) -> RawBatch:
        names = self._pending[0].aux_names
        parts = [b if b.aux_names == names else conform_channels(b, names, ())
                 for b in self._pending]
        batch = RawBatch.concat([b for b in parts if isinstance(b, RawBatch)])
        self._pending, self._pending_n = [], 0
        s = self.settings
        missing = missing_channels(s.model, names)
        if missing:  # no batch of this stream can be calibrated: say so once, not per batch
            self.failed = (f"the model needs channel {missing[0]!r}, the stream has "
                           f"{list(names)}")
            self.samples_skipped += len(batch)
            self._event("missing_channel", int(batch.t_us[0]), log_ns, {
                "missing": missing, "stream": list(names), "error": self.failed})
            if self.on_note is not None:
                self.on_note(f"cannot calibrate: {self.failed}; its samples are skipped")
            return RawBatch.empty(names)
        tcfg = tb.TimebaseConfig(rate_hz=s.rate_hz)
        state, _ = tb.start(batch.t_us, tcfg)
        t_out = tb.step(state, batch.t_us, tcfg)[1]  # a look ahead, for the rate only
        rate = s.rate_hz or infer_rate_hz(t_out) or (DEFAULT_RATE_HZ if force else None)
        if rate is None:  # time stamps all equal: keep waiting for usable ones
            self._pending, self._pending_n = [batch], len(batch)
            return RawBatch.empty(names)
        # the step the nominal rate gives, so that wraps and reboots are judged by it
        self.timebase = replace(state, step_us=1e6 / rate)
        cfg = s.pipeline.pipeline_config(rate, s.full_scale_g)
        self.pipeline = Pipeline(cfg, s.model, s.prior, names)
        self._tracker = self._make_tracker(rate)
        return batch

    def _make_tracker(self, rate_hz: float) -> al.StillTracker:
        return al.StillTracker(self.settings.alignment.min_still_s, round(3e6 / rate_hz))

    def _announce(self, t_us: int, log_ns: int) -> None:
        """First output of a run: the setup (for replay), the starting state and an event."""
        assert self.pipeline is not None
        self._started = True
        self.sink.json(self.sensor_id, "setup", {
            "t_us": t_us, "sensor_id": self.sensor_id, "start": self.start,
            "timebase": self.timebase.to_dict() if self.timebase else None,
            "rate_hz": self.pipeline.cfg.rate_hz, "plot_every": self._plot_every(),
            "alignment_settings": asdict(self.settings.alignment),
            "alignment": self.alignment.to_dict() if self.alignment else None,
            # a string: JSON messages turn NaN into null, the checkpoint format keeps NaN
            "pipeline_state_json": json.dumps(self.pipeline.state_dict())}, log_ns)
        reason = "restored" if self.start in ("checkpoint", "recording") else "start"
        self._publish_state(t_us, reason, log_ns)
        self._event("node_started", t_us, log_ns, {
            "start": self.start, "rate_hz": self.pipeline.cfg.rate_hz,
            "model": model_name(self.pipeline.model), "aux_names": list(self.pipeline.aux_names)})

    def _plot_every(self) -> int:
        rate = self.rate_hz or DEFAULT_RATE_HZ
        cached = self._plot_every_at
        if cached is None or cached[0] != rate:  # asked at every arrival: once per rate
            cached = self._plot_every_at = (rate, self.settings.pipeline.plot_every(rate))
        return cached[1]

    # -- one batch ----------------------------------------------------------------------------

    def _step(self, batch: RawBatch, log_ns: int) -> StepOutput | None:
        pipe = self.pipeline
        assert pipe is not None
        fitted = self._fit_layout(batch, log_ns)
        if fitted is None:
            return None
        out = pipe.step(self._device_time(fitted, log_ns))
        self._emit(out, log_ns, fitted.t_us)
        return out

    def _emit(self, out: StepOutput, log_ns: int, t_dev: np.ndarray) -> None:
        """Everything a step's output produces: calibrated, plot, events, state, body; the
        state as of the batch's end is the output's (`StepOutput.model`, ``estimate``,
        ``state``), not the pipeline's, which may be some batches further (`process_many`).
        ``t_dev``: the batch's device time stamps as they came, kept on every calibrated
        sample (`CalibratedBatch.t_dev`) beside the time base's ``t_us``."""
        cal = self._guard(out.calibrated.with_device_time(t_dev), log_ns)
        self.samples += len(cal)
        self.last_t_us = int(cal.t_us[-1])
        if len(cal) == 1:  # one sample per arrival: a scalar count, no histogram
            self.status_counts[int(cal.status[0])] += 1
        else:
            self.status_counts += np.bincount(cal.status, minlength=len(Status))[:len(Status)]
        self.sink.calibrated(self.sensor_id, cal, log_ns)
        self.sink.plot(self.sensor_id, cal, log_ns, self._plot_every())
        self._report_watch(out, log_ns)
        self._report_status(cal, log_ns)
        self._report_updates(out, log_ns)
        self._maybe_rediscover(log_ns)
        self._track_alignment(cal, log_ns, out)
        if self.alignment is not None:
            self.sink.calibrated(self.sensor_id, self._body(cal, self.alignment), log_ns,
                                 "body")
        self._vet(self.last_t_us, log_ns)

    def _vet(self, t_us: int, log_ns: int) -> None:
        """Whatever the pipeline took on (a bootstrap, a reset, a new zero-g and scale, a
        rediscovered model) must pass the checks its checkpoint meets at the next start
        (`recal.node.checkpoints.estimate_problem`, bounds around the configured zero-g): a node
        never holds a state it could not save, and a stream no sensor of this configuration
        sends (a crafted one) cannot move it there. Refused: back to the last state that
        passed (else the configured start), an event ``estimate_refused`` and a line. Runs
        when the model, estimate or prior changed (by identity), not per batch."""
        pipe = self.pipeline
        assert pipe is not None
        vetted = self._vetted
        if (vetted is not None and pipe.model is vetted[0] and pipe.estimate is vetted[1]
                and pipe.prior is vetted[2]):
            return  # (every arrival: three identity checks)
        now = (pipe.model, pipe.estimate, pipe.prior)
        s = self.settings
        why = estimate_problem(pipe, (s.model, s.prior))
        if why is None:
            self._vetted, self._good = now, copy.deepcopy(pipe)
            return
        back = (copy.deepcopy(self._good) if self._good is not None
                else Pipeline(pipe.cfg, s.model, s.prior, pipe.aux_names))
        back.counts = dict(pipe.counts)  # totals of what happened, refused or not
        self.pipeline = back
        self._vetted = (back.model, back.estimate, back.prior)
        self.estimates_refused += 1
        to = "the last good state" if self._good is not None else "the configured start"
        if _decade_reached(self.estimates_refused, 1):
            self._event("estimate_refused", t_us, log_ns, {
                "reason": why, "back_to": to, "refused": self.estimates_refused})
            if self.on_note is not None:
                self.on_note(f"calibration refused ({why}): no sensor of this configuration "
                             f"gives it; back to {to} ({self.estimates_refused} refused in all)")
        self._publish_state(t_us, "estimate_refused", log_ns)

    def _device_time(self, batch: RawBatch, log_ns: int) -> RawBatch:
        """The batch on the time base (recal.core.timebase), its events reported."""
        assert self.timebase is not None and self.pipeline is not None
        tcfg = self._timebase_config(self.pipeline.cfg.rate_hz)
        unit_events: list[dict[str, Any]] = []
        if self.timebase.last_dev is None:  # the stream's first batch: say how time is read
            first, unit_events = tb.start(batch.t_us, tcfg)
            if first.unit_us != self.timebase.unit_us:
                unit_events = []
        self.timebase, t_us, events = tb.step(self.timebase, batch.t_us, tcfg)
        for ev in [*unit_events, *events]:
            self._time_event(ev, int(t_us[ev["index"]]), log_ns)
        if t_us is batch.t_us:  # the device's own microseconds (the time base's usual case)
            return batch
        return RawBatch(t_us, batch.v, batch.aux, batch.aux_names)

    def _timebase_config(self, rate_hz: float | None) -> tb.TimebaseConfig:
        # made once per rate, not per arrival (a frozen dataclass: building it is most of
        # what a one-sample batch costs the time base)
        cached = self._tcfg
        if cached is None or cached.rate_hz != rate_hz:
            cached = self._tcfg = tb.TimebaseConfig(rate_hz=rate_hz)
        return cached

    def _time_event(self, ev: dict[str, Any], t_us: int, log_ns: int) -> None:
        if ev["kind"] == "time_anomalies":
            # a millisecond clock above 1 kHz repeats every other stamp: one event a device
            # minute at most, with the totals (so a replay says the same)
            if t_us < self._anomalies_said_us + ANOMALY_EVENT_US:
                return
            self._anomalies_said_us = t_us
        d = ev["detail"]
        if ev["kind"] == "time_jump_refused" and not _decade_reached(d["refused"],
                                                                      d["in_batch"]):
            return  # a clock that jumps on every batch: said at 1, 10, 100, ... in all
        self._event(ev["kind"], t_us, log_ns, d)
        note = None
        if ev["kind"] == "time_units":
            note = (f"device time is in {d['unit']}, not microseconds (as microseconds it "
                    f"implies {d['implied_rate_hz_as_us']:.0f} Hz; read as {d['unit']}: "
                    f"{d['rate_hz']:.4g} Hz)")
        elif ev["kind"] == "time_implausible":
            note = (f"device time implies {d['implied_rate_hz']:.4g} Hz, outside "
                    f"{d['min_rate_hz']:g}-{d['max_rate_hz']:g} Hz in any unit: check the "
                    "time column")
        elif ev["kind"] == "time_reboot":
            if self.pipeline is not None:  # a reboot, or another device: windows must agree
                self.pipeline.doubt()
            note = (f"device time restarted ({d['device_before']} -> {d['device_after']} "
                    f"{d['unit']}): the device rebooted; output time continues")
        elif ev["kind"] == "time_jump_refused":
            note = (f"device time jumped {d['jump_s'] / 86_400:+.4g} days ({d['device_before']}"
                    f" -> {d['device_after']} {d['unit']}), beyond the {d['limit_s'] / 86_400:g}"
                    f" day a clock plausibly does: not taken as time, output time continues "
                    f"({d['refused']} such jump{'s' if d['refused'] > 1 else ''} in all)")
        if note is not None and self.on_note is not None:
            self.on_note(note)

    def _guard(self, cal: CalibratedBatch, log_ns: int) -> CalibratedBatch:
        """The last guard before the wire: a calibrated value that is not finite is never
        published. Its sample goes out as (0, 0, 0) g, status uncalibrated, sigma inf: a
        consumer that reads the status, or weighs by 1/sigma^2, cannot take it for data (NaN
        would be read by many as "missing", zeros alone as a vector). Counted, and said once
        per batch as an event. A non-finite sigma of a finite value is inf."""
        a = cal.a_g
        if len(a) == 1 and _finite_one(a[0], cal.sigma_mg[0]):
            return cal  # one sample per arrival, the usual case: scalar checks, no arrays
        bad = ~(np.isfinite(a[:, 0]) & np.isfinite(a[:, 1]) & np.isfinite(a[:, 2]))
        bad_sigma = ~np.isfinite(cal.sigma_mg) & ~np.isinf(cal.sigma_mg)
        if not bad.any() and not bad_sigma.any():
            return cal
        a, status, sigma = a.copy(), cal.status.copy(), cal.sigma_mg.copy()
        sigma[bad_sigma] = NOT_FINITE_SIGMA_MG
        n = int(bad.sum())
        if n:
            a[bad] = 0.0
            status[bad] = Status.UNCALIBRATED
            sigma[bad] = NOT_FINITE_SIGMA_MG
            self.samples_not_finite += n
            self._event("not_finite", int(cal.t_us[np.argmax(bad)]), log_ns, {
                "samples": n, "published_as": "zeros, status uncalibrated, sigma_mg inf",
                "total": self.samples_not_finite})
        return CalibratedBatch(cal.t_us, a, cal.quasi_static, cal.detector_g, status, sigma,
                               cal.t_dev)

    def _report_watch(self, out: StepOutput, log_ns: int) -> None:
        """The pipeline's self-watch events (`core.outputs.WatchEvent`) as events."""
        for w in out.watch:
            kind = "estimate_reset" if w.kind == "reset" else w.kind
            self._event(kind, w.t_us, log_ns, w.detail)

    def _report_status(self, cal: CalibratedBatch, log_ns: int) -> None:
        """One line (``on_note``) and an event ``status_changed`` when the status becomes or stops
        being suspect, and when the sensor is calibrated where the last line named another
        status (first, or after a suspect status that cleared to held)."""
        st = cal.status
        first_new = int(st[0]) != self._status
        if len(st) == 1:  # one sample per arrival: nothing within the batch to compare
            points = [0] if first_new else []
        else:
            change = np.flatnonzero(st[1:] != st[:-1]) + 1
            points = ([0] if first_new else []) + change.tolist()
        for i in points:
            old, new = self._status, Status(int(st[i]))
            self._status = new
            first = new == Status.CALIBRATED and self._said != Status.CALIBRATED
            if not (first or new == Status.SUSPECT or old == Status.SUSPECT):
                continue
            self._said = new
            why = (" (the still windows contradict the calibration: re-fitting)"
                   if new == Status.SUSPECT else "")
            self._event("status_changed", int(cal.t_us[i]), log_ns, {
                "status": new.label, "was": old.label if old is not None else None})
            if self.on_note is not None:
                self.on_note(f"{new.label}{why}")
        self._say_unseen()

    def _say_unseen(self) -> None:
        """One line when the data leave the same offsets or scales unobserved over
        UNSEEN_SAY_UPDATES updates (status held for it; a start learns them in fewer)."""
        pipe = self.pipeline
        if pipe is None:
            return
        unseen, updates = pipe.unobserved, int(pipe.counts["updates"])
        if unseen != self._unseen[0]:
            self._unseen = (unseen, updates, False)
        elif (unseen and not self._unseen[2]
              and updates - self._unseen[1] >= UNSEEN_SAY_UPDATES):
            self._unseen = (unseen, self._unseen[1], True)
            if self.on_note is not None:
                self.on_note(f"held: {', '.join(unseen)} not observed by the data (sigma "
                             "carries the prior's uncertainty on it)")

    def _fit_layout(self, batch: RawBatch, log_ns: int) -> RawBatch | None:
        """The batch in the pipeline's channel layout, or None (reported) if it cannot be."""
        assert self.pipeline is not None
        names = self.pipeline.aux_names
        if batch.aux_names == names:  # the usual case: nothing to map, nothing to say
            self._last_names = batch.aux_names
            return batch
        if unnamed_for(batch.aux_names, names):
            # a device that prints its header only at boot, heard after a restart: the same
            # count of channels, unnamed, are the ones the state was built with (else each
            # would be missing and its windows NaN)
            if batch.aux_names != self._last_names:
                self._event("layout_mapped", int(batch.t_us[0]), log_ns, {
                    "got": list(batch.aux_names), "mapped_to": list(names)})
                if self.on_note is not None:
                    self.on_note(f"channels {', '.join(batch.aux_names)} (no header heard) "
                                 f"taken as {', '.join(names)}, as before the restart")
            self._last_names = batch.aux_names
            return RawBatch(batch.t_us, batch.v, batch.aux, names)
        fitted = conform_channels(batch, names, self.pipeline.model.covariates)
        if batch.aux_names != self._last_names and batch.aux_names != names:
            self._event("layout_changed", int(batch.t_us[0]), log_ns, {
                "expected": list(names), "got": list(batch.aux_names),
                "calibrated": isinstance(fitted, RawBatch)})
        self._last_names = batch.aux_names
        if isinstance(fitted, str):
            self.samples_skipped += len(batch)
            return None
        return fitted

    def _maybe_rediscover(self, log_ns: int) -> None:
        """Every ``[discovery] every_h`` device hours, rerun effect discovery on a copy of the
        window buffer in a thread of its own (`_Rediscovery`); ``adopt_after_s`` device
        seconds later its result is taken on: a model it extends becomes the live one (with
        its fitted values as the estimate) and the state is published with reason
        "discovery"."""
        cfg, pipe = self.settings.rediscovery, self.pipeline
        if not cfg.enabled or pipe is None or self.last_t_us is None:
            return
        if self._discovery is not None:
            if self.last_t_us >= self._discovery.due_us:
                run, self._discovery = self._discovery, None
                self._adopt_discovery(run, log_ns)
            return  # one run at a time
        every_us = round(cfg.every_h * 3.6e9)
        if self._next_discovery_us is None:
            self._next_discovery_us = self.last_t_us + every_us
        if self.last_t_us < self._next_discovery_us:
            return
        self._next_discovery_us = self.last_t_us + every_us
        windows = pipe.buffer.windows()  # fresh arrays: the thread's own copy
        if not pipe.bootstrapped or len(windows) < cfg.min_windows:
            return
        self._discovery = _Rediscovery.start(
            self.sensor_id, windows, pipe, self.last_t_us,
            self.last_t_us + round(cfg.adopt_after_s * 1e6), cfg.blocks)
        if cfg.adopt_after_s <= 0:
            run, self._discovery = self._discovery, None
            self._adopt_discovery(run, log_ns)

    def _adopt_discovery(self, run: _Rediscovery, log_ns: int) -> None:
        assert self.pipeline is not None and self.last_t_us is not None
        res = run.result()  # waits if it is still running (a replay gets here sooner)
        if isinstance(res, Exception):
            self._event("discovery_failed", self.last_t_us, log_ns,
                        {"error": str(res), "started_t_us": run.started_us})
            return
        self._event("discovery", self.last_t_us, log_ns, {
            "effects_selected": [e.label for e in res.selected],
            "steps": [f"{s.action} {s.effect.label}" for s in res.steps],
            "heldout_error_mg": {"base": res.heldout_base_mg, "final": res.heldout_final_mg},
            "windows": len(res.data), "started_t_us": run.started_us})
        if res.selected and self.pipeline.model.names == run.model_names:
            self.pipeline.adopt(res.model, res.prior)
            self._publish_state(self.last_t_us, "discovery", log_ns)

    def _report_updates(self, out: StepOutput, log_ns: int) -> None:
        if not out.updates:
            return
        assert self.pipeline is not None
        model = out.model if out.model is not None else self.pipeline.model
        names = model.names
        for u in out.updates:
            if u.report.accepted:
                self.accepted_updates += 1
            else:
                self._event("update_rejected", u.t_us, log_ns, u.report.to_dict(names))
            if u.bootstrap:
                self._event("bootstrap", u.t_us, log_ns, {
                    "accepted": u.report.accepted, "s0": model.s0})
        last = out.updates[-1]
        self._publish_state(last.t_us, "bootstrap" if last.bootstrap else "update", log_ns,
                            out.state)

    def _track_alignment(self, cal: CalibratedBatch, log_ns: int, out: StepOutput) -> None:
        cfg = self.settings.alignment
        if self._tracker is None or not (cfg.enabled or self._align_requested):
            return
        if self._align_requested or self.alignment is None:
            armed = (self._align_requested or not cfg.require_update
                     or (self.accepted_updates > 0 and self._tilt_offsets_known(out)))
        else:
            armed = cfg.enabled  # aligned: every later still period is checked for a slip
        for hit in self._tracker.feed(cal.t_us, cal.a_g, cal.quasi_static, armed):
            if self._align_requested or self.alignment is None:
                self._take_reference(hit, log_ns)
            elif cfg.enabled:
                self._watch_slip(hit, log_ns)

    def _take_reference(self, hit: al.StillHit, log_ns: int) -> None:
        cfg = self.settings.alignment
        if not self._align_requested and al.tilt_from_z_deg(hit.mean_g) > cfg.upright_max_deg:
            # not upright (lying, or the sensor worn sideways): not a reference posture
            self._event("reference_skipped", hit.t_us, log_ns, {
                "tilt_deg": al.tilt_from_z_deg(hit.mean_g),
                "upright_max_deg": cfg.upright_max_deg})
            return
        source = "request" if self._align_requested else "reference"
        self._set_alignment(hit.mean_g, hit.n, hit.t_us, source, log_ns)

    def _watch_slip(self, hit: al.StillHit, log_ns: int) -> None:
        """The tilt alarm (rule and reason in ``recal.core.alignment``): raised when later
        upright still periods agree that the mounting moved beyond the limit, cleared when
        they agree it is back."""
        ali = self.alignment
        assert ali is not None
        if self._slip is None:  # a new reference, or one restored from a checkpoint
            self._slip = al.SlipWatch(ali.gravity_g, ali.limit_deg, alarmed=ali.alarm,
                                      upright_max_deg=self.settings.alignment.upright_max_deg)
        change = self._slip.observe(hit.mean_g, hit.t_us, hit.gap_s)
        if change is None:
            return
        detail = {**change.to_dict(), "limit_deg": ali.limit_deg}
        if change.kind == "slipped":
            self.alignment = replace(ali, moved_deg=change.moved_deg)
            self._event("tilt_alarm", change.t_us, log_ns, {**detail, "detail": (
                f"the mounting moved {change.moved_deg:.1f} deg since the reference (limit "
                f"{ali.limit_deg:g} deg; {change.periods} still periods agree): re-seat the "
                f"sensor, or query recal/{self.sensor_id}/align to make this the reference")})
        else:
            self.alignment = replace(ali, moved_deg=None)
            self._event("tilt_cleared", change.t_us, log_ns, {**detail, "detail": (
                f"the mounting is back within {ali.limit_deg:g} deg of the reference")})

    def _tilt_offsets_known(self, out: StepOutput) -> bool:
        """Whether the x/y offsets' posterior sd is below ``max_offset_sd_mg`` (tilt error), as
        of the end of the batch ``out`` is of."""
        if self.pipeline is None:
            return True
        model = out.model if out.model is not None else self.pipeline.model
        estimate = out.estimate if out.model is not None else self.pipeline.estimate
        if estimate is None or not model.has("offset"):
            return True  # nothing to wait for
        # asked every batch until a reference is found; it changes only with the estimate
        known = self._offsets_known
        if known is not None and known[0] is model and known[1] is estimate:
            return known[2]
        sl = model.slice(("offset", None))
        sd_mg = np.sqrt(np.diag(estimate.cov)[sl][:2]) / model.s0 * 1e3
        answer = bool(np.all(sd_mg <= self.settings.alignment.max_offset_sd_mg))
        self._offsets_known = (model, estimate, answer)
        return answer

    def _set_alignment(self, mean: np.ndarray, n: int, t_us: int | None, source: str,
                       log_ns: int) -> al.Alignment:
        ali = al.estimate_alignment(mean, self.settings.alignment.tilt_limit_deg, n, t_us)
        self.alignment = ali
        self._slip = None  # later periods are checked against this reference
        self._align_requested = False
        self._event("alignment", t_us, log_ns, {**ali.to_dict(), "source": source})
        return ali

    @staticmethod
    def _body(cal: CalibratedBatch, ali: al.Alignment) -> CalibratedBatch:
        # a rotation keeps each sample's status and the length of its error (sigma_mg); the
        # other arrays are the calibrated batch's, checked when it was made
        return CalibratedBatch.of_checked(
            cal.t_us, np.ascontiguousarray(al.to_body(ali.rotation, cal.a_g)), cal.quasi_static,
            cal.detector_g, cal.status, cal.sigma_mg, cal.t_dev)

    # -- state and events ---------------------------------------------------------------------

    def _state(self, t_us: int | None, reason: str,
               state: tuple[SensorModel, dict[str, Any]] | None = None) -> dict[str, Any]:
        """The calibration state message: the summary plus identity and alignment. ``state``:
        the model and summary to report (`StepOutput.state`); None: the pipeline's now."""
        assert self.pipeline is not None
        model, s = state if state is not None else (self.pipeline.model,
                                                     self.pipeline.summary())
        s = dict(s)
        spec = s.pop("model")
        rep = s.get("last_update") or {}
        rms = s.get("residual_rms_mg")
        return {"sensor_id": self.sensor_id, "t_us": t_us, "reason": reason,
                "model": model_name(model), "model_spec": spec,
                "param_names": list(model.names), **s,
                "residual_g": None if rms is None else rms / 1e3,
                "observable": rep.get("observable"),
                "update_count": int(s["counts"]["updates"]),
                "alignment": self.alignment.to_dict() if self.alignment else None}

    def _publish_state(self, t_us: int, reason: str, log_ns: int,
                       state: tuple[SensorModel, dict[str, Any]] | None = None) -> None:
        self.last_state = self._state(t_us, reason, state)
        self.sink.json(self.sensor_id, "calibration", self.last_state, log_ns)

    def _event(self, kind: str, t_us: int | None, log_ns: int, detail: Any) -> None:
        self.sink.json(self.sensor_id, "events", {"t_us": t_us, "kind": kind,
                                                  "sensor_id": self.sensor_id,
                                                  "detail": detail}, log_ns)


# ---------------------------------------------------------------------------------------------
# Building nodes from the service configuration
# ---------------------------------------------------------------------------------------------

def node_settings(sensor: SensorConfig, config: ServiceConfig,
                  model_path: str | Path | None = None) -> NodeSettings:
    """NodeSettings for one configured sensor (ConfigError for a bad prior or model file)."""
    model, prior = model_and_prior(sensor, config.pipeline, model_path)
    return NodeSettings(sensor.id, config.pipeline, model, prior, sensor.rate_hz,
                        sensor.full_scale_g, config.alignment, rediscovery=config.discovery)


def make_node(settings: NodeSettings, sink: Sink,
              checkpoints: Checkpoints | str | Path | None = None,
              on_problem: Callable[[str, dict[str, Any]], None] | None = None
              ) -> CalibrationNode:
    """A node that resumes from its checkpoint in ``checkpoints`` (a `Checkpoints`, or a state
    folder) if a usable one exists: ``<sensor>.json``, else ``<sensor>.json.prev``.

    A checkpoint that does not load, cannot be trusted or does not fit the configuration is
    moved aside and reported (the `Checkpoints`' console line and event, and through
    ``on_problem("checkpoint_invalid", detail)``); the node then starts from the prior.
    """
    keeper = checkpoints
    if keeper is not None and not isinstance(keeper, Checkpoints):
        keeper = Checkpoints(keeper, 60.0, out=log.warning)
    if keeper is None or not keeper.enabled:
        return CalibrationNode(settings, sink)
    node = keeper.load(settings.sensor_id,
                       lambda doc: CalibrationNode.from_checkpoint(settings, sink, doc),
                       on_problem=on_problem)
    return node if node is not None else CalibrationNode(settings, sink)


def _finite_one(a_g: np.ndarray, sigma_mg: float) -> bool:
    """Whether one sample's three values are finite and its sigma finite or inf (what
    `CalibrationNode._guard` lets through unchanged), with scalar checks."""
    x, y, z = a_g.tolist()
    s = float(sigma_mg)
    return (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
            and not math.isnan(s))
