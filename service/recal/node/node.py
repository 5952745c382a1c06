"""Calibration node: one per sensor, between the bus or a recording and ``Pipeline.step``.

A :class:`CalibrationNode` takes raw batches and hands everything it derives to a
:class:`recal.node.sinks.Sink`: the calibrated batch, the calibration state whenever an update
happened, the decimated plot topic, events and, once the mounting is known, the acceleration
rotated into the body frame. The gateway (in-process), a node on another machine
(`recal.daemon.remote_node`) and ``replay`` (no Zenoh) run this same code, so a replay reproduces a
live run bit for bit. The messages and their fields: `recal.node.sinks`.

The node keeps ``process`` and ``emit``; each other concern is a part it holds and calls
directly: the rate hold and the channel layout (`recal.node.layout`), device time
(`recal.node.device_time`: through `recal.core.timebase` right before ``Pipeline.step``), the
published samples' guard and status lines (`recal.node.published`), the estimate checks
(`recal.node.vetting`), effect discovery (`recal.node.rediscovery`), the mounting and its
requests (`recal.node.alignment`), the state message (`recal.node.state_message`) and the
checkpoint document (`recal.node.checkpoint_doc`). A model that needs a channel the stream
lacks is one ``missing_channel`` event at the stream's first batch, then the node skips
(``failed``).

No calibration algebra here: the estimator is behind ``Pipeline``, the tilt math in
``recal.core.alignment``, the time base in ``recal.core.timebase``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

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
from recal.core.channels import missing_channels
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.outputs import StepOutput
from recal.core.pipeline import Pipeline
from recal.core.status import REOPEN_PROBATION_WINDOWS, Status
from recal.io import topics
from recal.node.alignment import Aligner
from recal.node.checkpoint_doc import checkpoint_document, restore_document
from recal.node.device_time import DeviceClock
from recal.node.events import NodeEvents
from recal.node.layout import DEFAULT_RATE_HZ, ChannelLayout, RateHold
from recal.node.published import Published
from recal.node.rediscovery import NodeDiscovery
from recal.node.sinks import Sink
from recal.node.state_message import model_name, state_message
from recal.node.vetting import EstimateVet
from recal.samples import RawBatch

__all__ = [
    "CalibrationNode",
    "CheckpointSource",
    "NodeSettings",
    "make_node",
    "model_name",
    "node_settings",
]

log = logging.getLogger(__name__)

# What a node emits through its sink, by payload, checked against the topic registry when this
# module loads: a name the registry lacks stops the process at start, not at the first message.
EMITS = {
    "calibrated": ("calibrated", "body"),
    "json": ("events", "setup", "calibration"),
    "plot": ("plot",),
}
for _payload, _names in EMITS.items():
    topics.require(_names, _payload)  # type: ignore[arg-type]


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


class CalibrationNode:
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
        self.events = NodeEvents(settings.sensor_id, sink)
        self.pipeline = pipeline
        self.start = start or ("prior" if settings.prior is not None else "bootstrap")
        self._lock = threading.RLock()
        self._hold = RateHold(settings.rate_hz, settings.infer_samples)  # bounded
        self._layout = ChannelLayout(self.events)
        self.aligner = Aligner(settings.alignment, settings.request_min_s, self.events,
                               alignment)
        self.clock = DeviceClock(self.events, timebase)
        self.published = Published(self.events)
        self._vet = EstimateVet((settings.model, settings.prior), self.events)
        self.discovery = NodeDiscovery(settings.rediscovery, self.events)
        self._started = False
        self._plot_every_at: tuple[float, int] | None = None  # (rate, plot_every) of `_plot_every`
        self.accepted_updates = 0
        self.samples_skipped = 0
        self.last_t_us: int | None = None
        self.last_state: dict[str, Any] | None = None
        #: why this sensor cannot be calibrated at all (a channel the model needs is missing
        #: from the stream), reported once as an event; None while it can
        self.failed: str | None = None
        if pipeline is not None:
            self.aligner.start(pipeline.cfg.rate_hz)
            self.discovery.start(pipeline)
            if timebase is None:  # from before time bases were kept: microseconds, as then
                self.clock.state = tb.TimebaseState(step_us=1e6 / pipeline.cfg.rate_hz)

    # -- the parts' figures, as before they were parts ----------------------------------------

    @property
    def sensor_id(self) -> str:
        return self.settings.sensor_id

    @property
    def sink(self) -> Sink:
        return self.events.sink

    @property
    def on_note(self) -> Callable[[str], None] | None:
        """Where the operator's one-line notes go (`recal.node.events.NodeEvents`)."""
        return self.events.on_note

    @on_note.setter
    def on_note(self, out: Callable[[str], None] | None) -> None:
        self.events.on_note = out

    @property
    def alignment(self) -> al.Alignment | None:
        return self.aligner.alignment

    @property
    def timebase(self) -> tb.TimebaseState | None:
        return self.clock.state

    @property
    def samples(self) -> int:
        return self.published.samples

    @property
    def status_counts(self) -> np.ndarray:
        """Samples published per status (`core.status.Status`)."""
        return self.published.status_counts

    @property
    def samples_not_finite(self) -> int:
        return self.published.samples_not_finite

    @property
    def estimates_refused(self) -> int:
        return self._vet.refused

    @property
    def align_refused(self) -> int:
        return self.aligner.refused

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
        batches cannot share a step: pipeline not started, another channel layout. A step
        ends where discovery's schedule may start a run or take one on
        (`RediscoverySchedule.stop_us`), so it does both at the batch `process` would.
        """
        items = [(b, t) for b, t in items if len(b)]
        with self._lock:
            while items and (self.pipeline is None or not self._started):
                self.process(*items.pop(0))  # until the rate is known and the pipeline runs
            pipe = self.pipeline
            if (len(items) < 2 or pipe is None or pipe.t0_us is None
                    or self.failed is not None
                    or any(b.aux_names != pipe.aux_names for b, _ in items)):
                for batch, log_ns in items:
                    self.process(batch, log_ns)
                return
            device = RawBatch.concat([b for b, _ in items])
            joined = self.clock.apply(device, items[0][1], pipe)
            lengths = [len(b) for b, _ in items]
            cum = np.cumsum(lengths)
            ends_us = joined.t_us[cum - 1]
            self._layout.last_names = pipe.aux_names
            devs = np.split(device.t_us, cum[:-1])
            lo = 0
            while lo < len(items):  # bounded: each pass takes at least one batch
                assert self.pipeline is not None
                stop = self.discovery.stop_us(self.pipeline)
                hi = len(items) if stop is None else min(
                    len(items), int(np.searchsorted(ends_us[lo:], stop)) + lo + 1)
                a = int(cum[lo - 1]) if lo else 0
                outs = self.pipeline.step_joined(joined[a:int(cum[hi - 1])], lengths[lo:hi])
                for (_, log_ns), out, dev in zip(items[lo:hi], outs, devs[lo:hi],
                                                 strict=True):
                    self._emit(out, log_ns, dev)
                lo = hi

    def flush(self, log_time_ns: int) -> None:
        """End of stream: calibrate samples still held for rate measurement."""
        with self._lock:
            if self.pipeline is None and self._hold:
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

    def request_alignment(self, log_time_ns: int | None = None,
                          now_s: float | None = None) -> dict[str, Any]:
        """Align now on the current still run if it is long enough, else arm the next one.

        Returns ``{"status": "aligned", "alignment": {...}}`` or ``{"status": "armed", ...}``,
        or ``{"status": "refused", "retry_after_s": ...}`` within ``[alignment]
        request_interval_s`` of the last request accepted (``now_s``: a monotonic clock,
        default ``time.monotonic()``). Why: anyone who may query the key could otherwise
        reset the mounting reference at will. Accepted requests are events
        ``align_request``; refusals are counted and reported as ``align_refused`` events, at
        most one per interval (a flood of queries must not flood the log).
        """
        log_ns = time.time_ns() if log_time_ns is None else log_time_ns
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            return self.aligner.request(self.last_t_us, log_ns, now)

    def status(self) -> dict[str, Any]:
        """The current calibration state (as published) plus node counters."""
        with self._lock:
            state = self._state(self.last_t_us, "status") if self.pipeline is not None else {
                "sensor_id": self.sensor_id, "t_us": None, "reason": "status",
                "params": None, "alignment": None}
            tbs = self.clock.state
            state["node"] = {"start": self.start, "rate_hz": self.rate_hz,
                             "time": None if tbs is None else {"unit": tbs.unit,
                                                               **tbs.counts()},
                             "failed": self.failed,
                             "samples": self.samples, "samples_skipped": self.samples_skipped,
                             "samples_by_status": self.samples_by_status(),
                             "samples_not_finite": self.samples_not_finite,
                             "accepted_updates": self.accepted_updates,
                             "estimates_refused": self.estimates_refused,
                             "still_s": self.aligner.still_s,
                             "align_requested": self.aligner.requested,
                             "align_refused": self.aligner.refused}
            return state

    def samples_by_status(self) -> dict[str, int]:
        """Samples published so far per status label (only the statuses seen)."""
        return self.published.by_status()

    @property
    def samples_not_calibrated(self) -> int:
        """Samples published with any status but calibrated."""
        counts = self.published.status_counts
        return int(counts.sum() - counts[Status.CALIBRATED])

    def checkpoint(self) -> dict[str, Any] | None:
        """A JSON-able checkpoint of the node (None before its pipeline started):
        `recal.node.checkpoint_doc.checkpoint_document`."""
        with self._lock:
            if self.pipeline is None:
                return None
            return checkpoint_document(self.sensor_id, self.last_t_us, self.pipeline,
                                       self.aligner.alignment,
                                       self.discovery.schedule.due_us, self.clock.state,
                                       self.discovery.state())

    @classmethod
    def from_checkpoint(cls, settings: NodeSettings, sink: Sink,
                        doc: dict[str, Any]) -> CalibrationNode:
        """Continue from :meth:`checkpoint` output (ValueError if it does not fit or cannot be
        trusted: `recal.node.checkpoint_doc.restore_document` checks it)."""
        got = restore_document(doc, settings.sensor_id, (settings.model, settings.prior),
                               settings.rediscovery)
        node = cls(settings, sink, pipeline=got.pipeline, alignment=got.alignment,
                   start="checkpoint", timebase=got.timebase)
        node.discovery.restore(got.next_discovery_us, got.discovery_gap_us, got.evidence,
                               got.discovery_pending)
        return node

    # -- starting -----------------------------------------------------------------------------

    def _hold_until_rate(self, batch: RawBatch, log_ns: int) -> RawBatch:
        """Keep samples until the rate and the clock's unit are known (`RateHold`); then start
        the pipeline and return them."""
        if not self._hold.add(batch):
            return RawBatch.empty(batch.aux_names)
        # time stamps that never advance give no rate: stop waiting (bounded memory)
        return self._start_pipeline(self._hold.overdue, log_ns)

    def _start_pipeline(self, force: bool, log_ns: int) -> RawBatch:
        batch = self._hold.take()
        names = batch.aux_names
        s = self.settings
        missing = missing_channels(s.model, names)
        if missing:  # no batch of this stream can be calibrated: say so once, not per batch
            self.failed = (f"the model needs channel {missing[0]!r}, the stream has "
                           f"{list(names)}")
            self.samples_skipped += len(batch)
            self.events.event("missing_channel", int(batch.t_us[0]), log_ns, {
                "missing": missing, "stream": list(names), "error": self.failed})
            self.events.note(f"cannot calibrate: {self.failed}; its samples are skipped")
            return RawBatch.empty(names)
        measured = self._hold.measure(batch, force)
        if measured is None:  # time stamps all equal: keep waiting for usable ones
            self._hold.put_back(batch)
            return RawBatch.empty(names)
        rate, self.clock.state = measured
        cfg = s.pipeline.pipeline_config(rate, s.full_scale_g)
        self.pipeline = Pipeline(cfg, s.model, s.prior, names)
        self.aligner.start(rate)
        self.discovery.start(self.pipeline)
        return batch

    def _announce(self, t_us: int, log_ns: int) -> None:
        """First output of a run: the setup (for replay), the starting state and an event."""
        assert self.pipeline is not None
        self._started = True
        tbs, ali = self.clock.state, self.aligner.alignment
        self.events.sink.json(self.sensor_id, "setup", {
            "t_us": t_us, "sensor_id": self.sensor_id, "start": self.start,
            "timebase": tbs.to_dict() if tbs else None,
            "rate_hz": self.pipeline.cfg.rate_hz, "plot_every": self._plot_every(),
            "alignment_settings": asdict(self.settings.alignment),
            "alignment": ali.to_dict() if ali else None,
            # a string: JSON messages turn NaN into null, the checkpoint format keeps NaN
            "pipeline_state_json": json.dumps(self.pipeline.state_dict()),
            # discovery's evidence and schedule as this run began (a resumed node's): a replay
            # of the log then runs and adopts as this node does
            "discovery_json": json.dumps({"next_us": self.discovery.schedule.next_us,
                                          **(self.discovery.state() or {})})}, log_ns)
        reason = "restored" if self.start in ("checkpoint", "recording") else "start"
        self._publish_state(t_us, reason, log_ns)
        self.events.event("node_started", t_us, log_ns, {
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
        fitted = self._layout.fit(batch, pipe.aux_names, pipe.model, log_ns)
        if fitted is None:
            self.samples_skipped += len(batch)
            return None
        out = pipe.step(self.clock.apply(fitted, log_ns, pipe))
        self._emit(out, log_ns, fitted.t_us)
        return out

    def _emit(self, out: StepOutput, log_ns: int, t_dev: np.ndarray) -> None:
        """Everything a step's output produces: calibrated, plot, events, state, body; the
        state as of the batch's end is the output's (`StepOutput.model`, ``estimate``,
        ``state``), not the pipeline's, which may be some batches further (`process_many`).
        ``t_dev``: the batch's device time stamps as they came, kept on every calibrated
        sample (`CalibratedBatch.t_dev`) beside the time base's ``t_us``."""
        sid, sink, aligner = self.settings.sensor_id, self.events.sink, self.aligner
        cal = self.published.admit(out.calibrated.with_device_time(t_dev), log_ns)
        self.last_t_us = int(cal.t_us[-1])
        sink.calibrated(sid, cal, log_ns)
        sink.plot(sid, cal, log_ns, self._plot_every())
        for w in out.watch:  # the pipeline's self-watch (`core.outputs.WatchEvent`)
            self.events.event("estimate_reset" if w.kind == "reset" else w.kind, w.t_us,
                              log_ns, w.detail)
        self.published.report(cal, log_ns, self.pipeline)
        if out.updates:
            self._report_updates(out, log_ns)
        if self.discovery.step(self.pipeline, out, self.settings.model, self.last_t_us,
                               log_ns):
            self._publish_state(self.last_t_us, "discovery", log_ns)
        aligner.track(cal, log_ns, out, self.pipeline, self.accepted_updates)
        if aligner.alignment is not None:
            sink.calibrated(sid, aligner.body(cal, aligner.alignment), log_ns, "body")
        assert self.pipeline is not None
        back = self._vet.check(self.pipeline, self.last_t_us, log_ns)
        if back is not None:
            self.pipeline = back
            self._publish_state(self.last_t_us, "estimate_refused", log_ns)

    def _report_updates(self, out: StepOutput, log_ns: int) -> None:
        assert self.pipeline is not None
        model = out.model if out.model is not None else self.pipeline.model
        names = model.names
        for u in out.updates:
            if u.report.accepted:
                self.accepted_updates += 1
            else:
                self.events.event("update_rejected", u.t_us, log_ns, u.report.to_dict(names))
            if u.bootstrap:
                self.events.event("bootstrap", u.t_us, log_ns, {
                    "accepted": u.report.accepted, "s0": model.s0})
        last = out.updates[-1]
        self._publish_state(last.t_us, "bootstrap" if last.bootstrap else "update", log_ns,
                            out.state)

    # -- state messages -----------------------------------------------------------------------

    def _state(self, t_us: int | None, reason: str,
               state: tuple[SensorModel, dict[str, Any]] | None = None) -> dict[str, Any]:
        assert self.pipeline is not None
        return state_message(self.sensor_id, self.pipeline, self.aligner.alignment, t_us,
                             reason, state)

    def _publish_state(self, t_us: int, reason: str, log_ns: int,
                       state: tuple[SensorModel, dict[str, Any]] | None = None) -> None:
        self.last_state = self._state(t_us, reason, state)
        self.events.sink.json(self.sensor_id, "calibration", self.last_state, log_ns)


# ---------------------------------------------------------------------------------------------
# Building nodes from the service configuration
# ---------------------------------------------------------------------------------------------

def node_settings(sensor: SensorConfig, config: ServiceConfig,
                  model_path: str | Path | None = None) -> NodeSettings:
    """NodeSettings for one configured sensor (ConfigError for a bad prior or model file)."""
    model, prior = model_and_prior(sensor, config.pipeline, model_path)
    return NodeSettings(sensor.id, config.pipeline, model, prior, sensor.rate_hz,
                        sensor.full_scale_g, config.alignment, rediscovery=config.discovery)


class CheckpointSource(Protocol):
    """Where `make_node` finds a sensor's checkpoint (`recal.daemon.checkpoint_store.
    Checkpoints`, the daemon's side)."""

    @property
    def enabled(self) -> bool: ...

    def load(self, sensor_id: str, restore: Callable[[dict[str, Any]], Any],
             on_problem: Callable[[str, dict[str, Any]], None] | None = None) -> Any: ...


def make_node(settings: NodeSettings, sink: Sink, checkpoints: CheckpointSource | None = None,
              on_problem: Callable[[str, dict[str, Any]], None] | None = None
              ) -> CalibrationNode:
    """A node that resumes from its checkpoint in ``checkpoints`` if a usable one exists:
    ``<sensor>.json``, else ``<sensor>.json.prev``.

    A checkpoint that does not load, cannot be trusted or does not fit the configuration is
    moved aside and reported (the store's console line and event, and through
    ``on_problem("checkpoint_invalid", detail)``); the node then starts from the prior.
    """
    if checkpoints is None or not checkpoints.enabled:
        return CalibrationNode(settings, sink)
    node = checkpoints.load(settings.sensor_id,
                            lambda doc: CalibrationNode.from_checkpoint(settings, sink, doc),
                            on_problem=on_problem)
    return node if node is not None else CalibrationNode(settings, sink)
