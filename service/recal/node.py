"""Calibration node: one per sensor, between the bus or a recording and ``Pipeline.step``.

A :class:`CalibrationNode` takes raw batches and hands everything it derives to a
:class:`Sink`: the calibrated batch, the calibration state (``pipeline.summary()`` plus the
sensor id) whenever an update happened, the decimated per-sample plot topic, events (rejected
updates, bootstrap, alignment, tilt alarm) and, once the mounting is known, the acceleration
rotated into the body frame. Sinks exist for a recording (:class:`RecordingSink`), for Zenoh
(:class:`BusSink`) and for both (:class:`LoggedBusSink`, each message encoded once), so the
gateway (in-process), a node on another machine (:func:`run_node`, subscribed to
``recal/*/raw``) and ``replay`` (no Zenoh) run this same code.

No calibration algebra here: the estimator is behind ``Pipeline``, the tilt math in
``recal.core.alignment``.

Messages, by sink suffix (MCAP topic ``/<sensor>/<suffix>``, Zenoh key
``recal/<sensor>/<suffix>`` where the bus layout has one):

* ``calibrated`` (and ``body``): CalibratedBatch protobuf, each sample with its status and
  predicted error (`recal.core.status`). A sample whose calibrated value is not finite (a NaN
  or inf reading, a broken estimate) is never published as such: its x_g, y_g, z_g go out as
  0, its status uncalibrated and its sigma_mg inf, and it is counted (``samples_not_finite``).
* ``calibration``: JSON, the calibration state: ``sensor_id``, ``t_us`` (device time, us),
  ``reason`` (start | restored | update | bootstrap | status | discovery), ``model`` (name),
  ``model_spec``, ``param_names``, ``params`` (by name, raw units), ``described`` (mg, %),
  ``sd``, ``covariance``, ``residual_rms_mg``, ``residual_g``, ``last_update``, ``coverage``,
  ``counts``, ``update_count``, ``observable``, ``alignment``.
* ``events``: JSON ``{t_us, kind, sensor_id, detail}``.
* ``plot``: one JSON message per decimated sample (log only).
* ``setup``: JSON, once when the pipeline starts: the pipeline's full starting state
  (``pipeline_state_json``, so a replay reproduces the run bit for bit), the rate, the
  alignment, the device clock's time base (``timebase``) (log only).

Device time goes through :mod:`recal.core.timebase` right before ``Pipeline.step``: events
``time_units`` (a clock in ms or s), ``time_implausible``, ``time_wrap``, ``time_reboot``,
``time_anomalies`` (steps back, duplicates, jumps, counted per batch); the raw topic keeps
the device's values. A model that needs a channel the stream lacks is one ``missing_channel``
event at the stream's first batch; the node then skips (``failed``) instead of failing on
every batch.

Alignment (Zheng et al. sec. II.B): the reference posture is the first quasi-static run of
``min_still_s`` (10 s) within ``upright_max_deg`` of +z, after at least one accepted update;
a query on ``recal/<sensor>/align`` aligns at once on the current still run (if it lasted
``request_min_s``) or arms the next run of ``min_still_s`` as the reference. Every later
still run of ``min_still_s`` is checked for a slip of the mounting (``tilt_alarm`` and
``tilt_cleared`` events; the rule is ``recal.core.alignment.SlipWatch``'s).
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from recal.checkpoints import (
    CHECKPOINT_FORMAT,
    Checkpoints,
    CheckpointSchedule,
    SensorLockedError,
    checkpoint_path,
    load_checkpoint,
    restore_pipeline,
    save_checkpoint,
)
from recal.config import (
    AlignmentConfig,
    ConfigError,
    PipelineSettings,
    RediscoveryConfig,
    SensorConfig,
    ServiceConfig,
    load_config,
    model_and_prior,
)
from recal.core import alignment as al
from recal.core import timebase as tb
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline, StepOutput, missing_channels
from recal.core.status import NOT_FINITE_SIGMA_MG, Status
from recal.samples import CalibratedBatch, RawBatch

__all__ = [
    "BusSink",
    "CalibrationNode",
    "CheckpointSchedule",  # re-exported from recal.checkpoints, where the checkpoint code lives
    "EventSink",
    "LoggedBusSink",
    "NodeSettings",
    "NullSink",
    "RecordingSink",
    "SensorGate",
    "Sink",
    "align_handler",
    "checkpoint_path",
    "infer_rate_hz",
    "load_checkpoint",
    "main",
    "make_node",
    "model_name",
    "node_settings",
    "run_node",
    "save_checkpoint",
]

log = logging.getLogger(__name__)

NODE_READY_PREFIX = "recal node ready"
RECV_ROUND = 4096  # most raw messages a remote node takes from its receiver per round
# Raw messages a remote node buffers before Zenoh's thread waits (and after its 1 s wait,
# drops): gateways handling every arrival at once send a message per sample, so 1024 was
# 0.2 s of 50 sensors, and a node a second behind lost samples (bench/scale_out.py).
RECV_CAPACITY = 1 << 17
DEFAULT_RATE_HZ = 100.0  # only when a stream ends before its rate could be measured
ANOMALY_EVENT_US = 60_000_000  # time_anomalies events at most this often (device time)
# samples the clock's unit is read from when the rate is configured: the median of 7 steps
# (a repeated stamp or a wrap among the first two would decide it alone)
UNIT_SAMPLES = 8


# ---------------------------------------------------------------------------------------------
# Sinks: where a node's output goes
# ---------------------------------------------------------------------------------------------

class Sink(Protocol):
    """Receives a node's output; ``log_time_ns`` is the service clock (ns since the epoch)."""

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None: ...

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None: ...

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None: ...

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any],
             log_time_ns: int) -> None: ...


class NullSink:
    """Discards everything (a node used only for its state)."""

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        pass

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        pass

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        pass

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        pass


class EventSink(NullSink):
    """Keeps the node's events (``{t_us, kind, sensor_id, detail}``) in a list and discards the
    rest: a node watched for what it says (benches, tests, a library caller). Grows with the
    events, so for bounded runs only."""

    def __init__(self) -> None:
        self.events: list[dict[str, Any]] = []

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        if suffix == "events":
            self.events.append(obj)

    def of(self, kind: str) -> list[dict[str, Any]]:
        """The events of one kind, in order."""
        return [e for e in self.events if e["kind"] == kind]


class RecordingSink:
    """Writes to a :class:`recal.io.recording.RecordingWriter` (topic ``/<sensor>/<suffix>``)."""

    def __init__(self, writer: Any) -> None:
        self.writer = writer

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        self.writer.write_raw(sensor_id, batch, log_time_ns)

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        self.writer.write_calibrated(sensor_id, batch, log_time_ns, suffix)

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        self.writer.write_plot(sensor_id, batch, log_time_ns, every_n)

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        self.writer.write_json(f"/{sensor_id}/{suffix}", obj, log_time_ns)


class BusSink:
    """Publishes on a :class:`recal.io.bus.Bus` (``recal/<sensor>/<suffix>``).

    Suffixes without a bus key (plot, setup) are not published. A publish Zenoh refuses, or
    one after the bus closed, is counted in ``dropped`` and never raises.
    """

    def __init__(self, bus: Any) -> None:
        from recal.io import bus as _bus
        from recal.io import messages

        self.bus = bus
        self._key = _bus.key
        self._publishers: dict[tuple[str, str], Any] = {}
        self.topics = frozenset(_bus.TOPICS)
        self._messages = messages
        self.dropped = 0

    def put(self, sensor_id: str, suffix: str, data: bytes) -> None:
        """Publish encoded bytes on ``recal/<sensor>/<suffix>`` (counted in ``dropped`` if
        refused). The key is validated and the publisher looked up once per (sensor, suffix),
        not per message: with samples handled as they arrive, that is per sample."""
        pub = self._publishers.get((sensor_id, suffix))
        try:
            if self.bus.closed:
                raise RuntimeError("bus is closed")
            if pub is None:
                pub = self._publishers[(sensor_id, suffix)] = self.bus.publisher(
                    self._key(sensor_id, suffix))
            ok = pub.put(data)
        except RuntimeError:  # the bus closed under us (shutdown)
            ok = False
        if not ok:
            self.dropped += 1

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        self.put(sensor_id, "raw", self._messages.encode_raw(sensor_id, batch))

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        self.put(sensor_id, suffix, self._messages.encode_calibrated(sensor_id, batch))

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        pass  # the plot topic is for the log's Plot panel; the bus carries whole batches

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        if suffix in self.topics:
            self.put(sensor_id, suffix, self._messages.encode_json(obj))


class LoggedBusSink:
    """Logs to a recording, then publishes the very bytes it logged: a RecordingSink and a
    BusSink in one, with each message encoded once instead of twice (the gateway's sink; per
    sample at 100 Hz, the second encoding of a calibrated sample cost as much as its bus put)."""

    def __init__(self, writer: Any, bus: Any) -> None:
        self.writer = writer
        self.bus = BusSink(bus)

    @property
    def dropped(self) -> int:
        return self.bus.dropped

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        self.bus.put(sensor_id, "raw", self.writer.write_raw(sensor_id, batch, log_time_ns))

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        self.bus.put(sensor_id, suffix,
                     self.writer.write_calibrated(sensor_id, batch, log_time_ns, suffix))

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        self.writer.write_plot(sensor_id, batch, log_time_ns, every_n)

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        data = self.writer.write_json(f"/{sensor_id}/{suffix}", obj, log_time_ns)
        if suffix in self.bus.topics:
            self.bus.put(sensor_id, suffix, data)


# ---------------------------------------------------------------------------------------------
# Small pure helpers
# ---------------------------------------------------------------------------------------------

def infer_rate_hz(t_us: np.ndarray) -> float | None:
    """Sample rate in Hz from device time stamps (median positive step), None if unknown."""
    dt = np.diff(np.asarray(t_us, np.int64))
    dt = dt[dt > 0]
    if len(dt) == 0:
        return None
    return float(1e6 / np.median(dt))


def model_name(model: SensorModel) -> str:
    """"diagonal", "full", or the effect labels joined by "+" for discovered models."""
    kinds = tuple(e.key for e in model.effects)
    if kinds == (("offset", None), ("scale", None)):
        return "diagonal"
    if kinds == (("offset", None), ("scale", None), ("cross_axis", None)):
        return "full"
    return "+".join(e.label for e in model.effects)


def _conform(batch: RawBatch, names: tuple[str, ...], needed: Sequence[str]) -> RawBatch | str:
    """The batch with exactly the channels ``names`` (reordered; unused missing ones NaN), or
    the reason it cannot be calibrated (a channel the model needs is missing)."""
    if batch.aux_names == names:
        return batch
    cols = []
    for name in names:
        if name in batch.aux_names:
            cols.append(batch.aux[:, batch.aux_names.index(name)])
        elif name in needed:
            return f"the model needs channel {name!r}, the stream has {list(batch.aux_names)}"
        else:
            cols.append(np.full(len(batch), np.nan))
    aux = np.column_stack(cols) if cols else np.zeros((len(batch), 0))
    return RawBatch(batch.t_us, batch.v, aux, names)


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
    pipeline: PipelineSettings
    model: SensorModel
    prior: Prior | None
    rate_hz: float | None = None
    full_scale_g: float | None = None
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    infer_samples: int = 50
    request_min_s: float = 2.0
    rediscovery: RediscoveryConfig = field(default_factory=RediscoveryConfig)


class _Rediscovery:
    """One effect-discovery run on a copy of a node's buffer, in a daemon thread (the core is
    pure: it shares nothing with the node's pipeline); `result` waits for it."""

    def __init__(self, started_us: int, due_us: int, model_names: tuple[str, ...]) -> None:
        self.started_us = started_us
        self.due_us = due_us
        self.model_names = model_names
        self._done = threading.Event()
        self._result: Any = None

    @classmethod
    def start(cls, sensor_id: str, windows: Any, pipe: Pipeline, started_us: int,
              due_us: int, blocks: int) -> _Rediscovery:
        from recal.core import discovery

        run = cls(started_us, due_us, pipe.model.names)
        args = (windows, pipe.aux_names, pipe.t0_us or 0, pipe.model, pipe.params.copy(),
                discovery.DiscoveryConfig(blocks=blocks))

        def work() -> None:
            try:
                run._result = discovery.discover_pipeline(*args)
            except Exception as exc:  # reported as discovery_failed: the waiter must wake
                if not isinstance(exc, (ValueError, np.linalg.LinAlgError)):
                    log.exception("rediscovery of %s failed", sensor_id)
                run._result = exc
            finally:
                run._done.set()

        threading.Thread(target=work, name=f"recal-discover-{sensor_id}", daemon=True).start()
        return run

    def result(self) -> Any:
        self._done.wait()
        return self._result


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
        self.accepted_updates = 0
        self.samples = 0
        self.samples_skipped = 0
        # samples published per status (`core.status.Status`), and those zeroed (not finite)
        self.status_counts = np.zeros(len(Status), np.int64)
        self.samples_not_finite = 0
        self._status: Status | None = None  # of the last sample published
        self._calibrated_once = False
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
        a message end cuts, `core.windowing`). Falls
        back to `process` one by one when the batches cannot share a step: pipeline not
        started, another channel layout, periodic rediscovery on.
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
            joined = self._device_time(RawBatch.concat([b for b, _ in items]), items[0][1])
            outs = pipe.step_joined(joined, [len(b) for b, _ in items])
            self._last_names = pipe.aux_names
            for (_, log_ns), out in zip(items, outs, strict=True):
                self._emit(out, log_ns)

    def flush(self, log_time_ns: int) -> None:
        """End of stream: calibrate samples still held for rate measurement."""
        with self._lock:
            if self.pipeline is None and self._pending:
                batch = self._start_pipeline(True, log_time_ns)
                if len(batch):
                    self._announce(int(batch.t_us[0]), log_time_ns)
                    self._step(batch, log_time_ns)

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
                             "still_s": self._tracker.duration_s if self._tracker else 0.0,
                             "align_requested": self._align_requested,
                             "align_refused": self.align_refused}
            return state

    def samples_by_status(self) -> dict[str, int]:
        """Samples published so far per status label (only the statuses seen)."""
        return {Status(i).label: int(n) for i, n in enumerate(self.status_counts.tolist()) if n}

    @property
    def samples_uncalibrated(self) -> int:
        """Samples published with any status but calibrated."""
        return int(self.status_counts.sum() - self.status_counts[Status.CALIBRATED])

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
            wait_s = self._align_wait_s(now)
            if wait_s > 0:
                return self._refuse_alignment(wait_s, log_ns)
            self._last_align_request_s = now
            reply = self._accept_alignment(log_ns)
            self._event("align_request", self.last_t_us, log_ns, {
                "status": reply["status"], "refused_before": self._refused_unreported})
            self._refused_unreported = 0
            return reply

    def _align_wait_s(self, now_s: float) -> float:
        """Seconds until an alignment request may be accepted again (0: now)."""
        last = self._last_align_request_s
        if last is None:
            return 0.0
        return max(0.0, last + self.settings.alignment.request_interval_s - now_s)

    def _refuse_alignment(self, wait_s: float, log_ns: int) -> dict[str, Any]:
        self.align_refused += 1
        self._refused_unreported += 1
        if self._refused_unreported == 1:  # the first refusal of this interval
            self._event("align_refused", self.last_t_us, log_ns, {
                "retry_after_s": wait_s,
                "interval_s": self.settings.alignment.request_interval_s,
                "refused_total": self.align_refused})
        return {"status": "refused", "sensor_id": self.sensor_id,
                "retry_after_s": round(wait_s, 3), "refused": self._refused_unreported,
                "detail": f"at most one alignment request per "
                          f"{self.settings.alignment.request_interval_s:g} s"}

    def _accept_alignment(self, log_ns: int) -> dict[str, Any]:
        tr = self._tracker
        if tr is not None and tr.duration_s >= self.settings.request_min_s:
            mean = tr.mean()
            if mean is not None:
                ali = self._set_alignment(mean, tr.n, self.last_t_us, "request", log_ns)
                return {"status": "aligned", "sensor_id": self.sensor_id,
                        "alignment": ali.to_dict()}
        self._align_requested = True
        if tr is not None:
            tr.rearm()
        return {"status": "armed", "sensor_id": self.sensor_id,
                "detail": f"aligns on the next still period of "
                          f"{self.settings.alignment.min_still_s:g} s",
                "still_s": tr.duration_s if tr else 0.0}

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
        trusted: `recal.checkpoints.restore_pipeline` checks the state)."""
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
        parts = [b if b.aux_names == names else _conform(b, names, ()) for b in self._pending]
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
        return self.settings.pipeline.plot_every(self.rate_hz or DEFAULT_RATE_HZ)

    # -- one batch ----------------------------------------------------------------------------

    def _step(self, batch: RawBatch, log_ns: int) -> StepOutput | None:
        pipe = self.pipeline
        assert pipe is not None
        fitted = self._fit_layout(batch, log_ns)
        if fitted is None:
            return None
        out = pipe.step(self._device_time(fitted, log_ns))
        self._emit(out, log_ns)
        return out

    def _emit(self, out: StepOutput, log_ns: int) -> None:
        """Everything a step's output produces: calibrated, plot, events, state, body; the
        state as of the batch's end is the output's (`StepOutput.model`, ``estimate``,
        ``state``), not the pipeline's, which may be some batches further (`process_many`)."""
        cal = self._guard(out.calibrated, log_ns)
        self.samples += len(cal)
        self.last_t_us = int(cal.t_us[-1])
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

    def _device_time(self, batch: RawBatch, log_ns: int) -> RawBatch:
        """The batch on the time base (recal.core.timebase), its events reported."""
        assert self.timebase is not None and self.pipeline is not None
        tcfg = tb.TimebaseConfig(rate_hz=self.pipeline.cfg.rate_hz)
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

    def _time_event(self, ev: dict[str, Any], t_us: int, log_ns: int) -> None:
        if ev["kind"] == "time_anomalies":
            # a millisecond clock above 1 kHz repeats every other stamp: one event a device
            # minute at most, with the totals (so a replay says the same)
            if t_us < self._anomalies_said_us + ANOMALY_EVENT_US:
                return
            self._anomalies_said_us = t_us
        self._event(ev["kind"], t_us, log_ns, ev["detail"])
        d = ev["detail"]
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
            note = (f"device time restarted ({d['device_before']} -> {d['device_after']} "
                    f"{d['unit']}): the device rebooted; output time continues")
        if note is not None and self.on_note is not None:
            self.on_note(note)

    def _guard(self, cal: CalibratedBatch, log_ns: int) -> CalibratedBatch:
        """The last guard before the wire: a calibrated value that is not finite is never
        published. Its sample goes out as (0, 0, 0) g, status uncalibrated, sigma inf: a
        consumer that reads the status, or weighs by 1/sigma^2, cannot take it for data (NaN
        would be read by many as "missing", zeros alone as a vector). Counted, and said once
        per batch as an event. A non-finite sigma of a finite value is inf."""
        a = cal.a_g
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
        return CalibratedBatch(cal.t_us, a, cal.quasi_static, cal.detector_g, status, sigma)

    def _report_watch(self, out: StepOutput, log_ns: int) -> None:
        """The pipeline's self-watch events (`core.pipeline.WatchEvent`) as events."""
        for w in out.watch:
            kind = "estimate_reset" if w.kind == "reset" else w.kind
            self._event(kind, w.t_us, log_ns, w.detail)

    def _report_status(self, cal: CalibratedBatch, log_ns: int) -> None:
        """One line (``on_note``) and an event ``status_changed`` when the status becomes or stops
        being suspect, and when the sensor is first calibrated."""
        st = cal.status
        change = np.flatnonzero(st[1:] != st[:-1]) + 1
        points = ([0] if int(st[0]) != self._status else []) + change.tolist()
        for i in points:
            old, new = self._status, Status(int(st[i]))
            self._status = new
            first = new == Status.CALIBRATED and not self._calibrated_once
            if not (first or new == Status.SUSPECT or old == Status.SUSPECT):
                continue
            self._calibrated_once |= new == Status.CALIBRATED
            why = (" (the still windows contradict the calibration: re-fitting)"
                   if new == Status.SUSPECT else "")
            self._event("status_changed", int(cal.t_us[i]), log_ns, {
                "status": new.label, "was": old.label if old is not None else None})
            if self.on_note is not None:
                self.on_note(f"{new.label}{why}")

    def _fit_layout(self, batch: RawBatch, log_ns: int) -> RawBatch | None:
        """The batch in the pipeline's channel layout, or None (reported) if it cannot be."""
        assert self.pipeline is not None
        names = self.pipeline.aux_names
        fitted = _conform(batch, names, self.pipeline.model.covariates)
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
        # a rotation keeps each sample's status and the length of its error (sigma_mg)
        return CalibratedBatch(cal.t_us, al.to_body(ali.rotation, cal.a_g), cal.quasi_static,
                               cal.detector_g, cal.status, cal.sigma_mg)

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


# ---------------------------------------------------------------------------------------------
# A node on its own: subscribe to recal/*/raw (another process or machine)
# ---------------------------------------------------------------------------------------------

REJECT_REPORT_S = 10.0  # at most one console line and event this often about turned-away ids
REJECT_IDS_KEPT = 16  # example ids named in that line and event (bounded, whatever comes in)
NOTE_PREFIX = "recal node:"


class SensorGate:
    """Which sensor ids a node on the bus serves, and a count of what it turned away.

    Served: the ``named`` ids (config ``[[sensors]]`` or ``--sensor-id``) and, with
    ``accept_any``, up to ``max_sensors`` other ids, first come first served. Anything else
    is counted by reason (``not_served``, ``over_cap``, ``key_mismatch``: the payload names
    another sensor than its key) and dropped before it gets a node, a log channel, a topic or
    a checkpoint. Memory is bounded: counts, and at most ``REJECT_IDS_KEPT`` example ids
    between two reports.
    """

    REASONS = ("not_served", "over_cap", "key_mismatch")

    def __init__(self, named: Iterable[str], accept_any: bool = False,
                 max_sensors: int = 16) -> None:
        self.named = frozenset(named)
        self.accept_any = bool(accept_any)
        self.max_sensors = int(max_sensors)
        self.served: set[str] = set()
        self._extra = 0  # served ids not named (accept_any)
        self.rejected = dict.fromkeys(self.REASONS, 0)  # messages turned away, in all
        self._pending = dict.fromkeys(self.REASONS, 0)  # ... since the last report
        self._ids: set[str] = set()

    def admit(self, sid: str) -> bool:
        """Whether ``sid`` is served (counting it as turned away if not)."""
        if sid in self.served:
            return True
        if sid in self.named:
            self.served.add(sid)
            return True
        if self.accept_any and self._extra < self.max_sensors:
            self._extra += 1
            self.served.add(sid)
            return True
        self.reject(sid, "over_cap" if self.accept_any else "not_served")
        return False

    def reject(self, sid: str, reason: str) -> None:
        self.rejected[reason] += 1
        self._pending[reason] += 1
        if len(self._ids) < REJECT_IDS_KEPT:
            self._ids.add(sid)

    def take_report(self) -> dict[str, Any] | None:
        """What was turned away since the last call (None: nothing)."""
        n = sum(self._pending.values())
        if n == 0:
            return None
        report = {"messages": n, "by_reason": {k: v for k, v in self._pending.items() if v},
                  "sensor_ids": sorted(self._ids), "ids_listed_max": REJECT_IDS_KEPT,
                  "messages_total": sum(self.rejected.values())}
        self._pending = dict.fromkeys(self.REASONS, 0)
        self._ids = set()
        return report

    def describe(self) -> str:
        """One phrase for the console: what this gate lets in."""
        named = ", ".join(sorted(self.named)) or "none named"
        if self.accept_any:
            return f"{named}, and any other sensor up to {self.max_sensors} (accept_any)"
        return named


def align_handler(node: CalibrationNode, out: Callable[[str], None],
                  prefix: str = NOTE_PREFIX) -> Callable[[str, bytes | None], bytes]:
    """The ``recal/<sensor>/align`` queryable's handler: :meth:`CalibrationNode.
    request_alignment`, and a console line for each accepted request and for the first
    refusal of an interval (a flood of queries gives one line, not one per query)."""
    from recal.io import messages

    def handle(_key: str, _payload: bytes | None) -> bytes:
        reply = node.request_alignment()
        sid = node.sensor_id
        if reply["status"] != "refused":
            out(f"{prefix} {sid}: alignment requested on the bus ({reply['status']})")
        elif reply.get("refused") == 1:
            out(f"{prefix} {sid}: alignment request refused: at most one per "
                f"{node.settings.alignment.request_interval_s:g} s (next in "
                f"{reply['retry_after_s']:.0f} s); further refusals are counted in status")
        return messages.encode_json(reply)

    return handle


def run_node(config: ServiceConfig | str | Path | None = None,
             sensor_ids: Sequence[str] = (), mcap_out: str | Path | None = None,
             model_path: str | Path | None = None, stop_event: threading.Event | None = None,
             *, bus: Any = None, out: Callable[[str], None] | None = None,
             accept_any: bool | None = None, max_sensors: int | None = None) -> int:
    """Calibrate the sensors it serves whose raw streams arrive on ``recal/*/raw`` until stopped.

    Serves the sensors ``sensor_ids`` names, else those of the config's ``[[sensors]]``; with
    ``accept_any`` (default: config ``[node] accept_any``) any other sensor as well, at most
    ``max_sensors`` of them (default ``[node] max_sensors``). Other ids are counted and dropped
    (see :class:`SensorGate`), with a console line and a ``sensors_ignored`` event in the
    recording at most every ``REJECT_REPORT_S``. A node with nothing to serve is a
    configuration error. Publishes calibrated, body, calibration and events on the bus,
    answers ``recal/<sensor>/status`` and ``recal/<sensor>/align`` (rate-limited), optionally
    logs everything (raw included) to ``mcap_out``, and checkpoints like the gateway. Stops on
    ``stop_event`` or SIGINT/SIGTERM (main thread). Returns 0, or 2 for a configuration error.
    """
    from recal.gateway import ERROR_PREFIX, install_stop_signals, open_bus, open_recording

    emit = out or (lambda line: print(line, flush=True))
    fail = out or (lambda line: print(line, file=sys.stderr, flush=True))
    try:
        cfg = config if isinstance(config, ServiceConfig) else load_config(config)
    except ConfigError as exc:
        fail(f"{ERROR_PREFIX} {exc}")
        return 2
    own_bus = bus is None
    if own_bus and not cfg.zenoh.enabled:
        fail(f"{ERROR_PREFIX} a calibration node takes its samples from Zenoh, but the "
             f"config's [zenoh] enabled = false")
        return 2
    try:
        gate = _gate(cfg, sensor_ids, accept_any, max_sensors)
    except ConfigError as exc:
        fail(f"{ERROR_PREFIX} {exc}")
        return 2
    try:
        bus = open_bus(cfg) if own_bus else bus
    except Exception as exc:  # zenoh.ZError: bad endpoint, port in use, router down
        fail(f"{ERROR_PREFIX} cannot open Zenoh: {exc}")
        return 1
    try:
        writer = open_recording(cfg, mcap_out) if mcap_out is not None else None
    except (OSError, ValueError) as exc:
        if own_bus:
            bus.close()
        fail(f"{ERROR_PREFIX} cannot open the recording: {exc}")
        return 1
    stop = stop_event or threading.Event()
    restore = install_stop_signals(stop)
    runner = _NodeRunner(cfg, bus, writer, gate, model_path, emit)
    emit(f"{NOTE_PREFIX} checkpoints in {cfg.checkpoint.dir or '(none)'}")
    emit(f"{NODE_READY_PREFIX} mcap={writer.paths[0] if writer is not None else None}")
    emit(f"{NOTE_PREFIX} serving {gate.describe()}")
    watch = None if writer is None else _watch_recording(writer, emit, cfg.mcap.backlog_mb,
                                                         stop)
    try:
        runner.run(stop)
    finally:
        runner.close()
        if writer is not None:
            writer.close()
        if watch is not None:
            watch.closed()
        if own_bus:
            bus.close()
        restore()
    return 0


def _gate(cfg: ServiceConfig, sensor_ids: Sequence[str], accept_any: bool | None,
          max_sensors: int | None) -> SensorGate:
    """The node's SensorGate from the arguments and the config (ConfigError if it would
    serve nothing, or for a bad cap)."""
    from recal.io.bus import validate_sensor_id

    named = list(sensor_ids) or [s.id for s in cfg.sensors]
    for sid in named:
        try:
            validate_sensor_id(sid)
        except ValueError as exc:
            raise ConfigError(f"--sensor-id: {exc}") from None
    any_ = cfg.node.accept_any if accept_any is None else accept_any
    cap = cfg.node.max_sensors if max_sensors is None else max_sensors
    if cap < 1:
        raise ConfigError(f"--max-sensors: expected an integer >= 1, got {cap}")
    if not named and not any_:
        raise ConfigError("a calibration node serves only the sensors it is told about: name "
                          "them in [[sensors]] or with --sensor-id, or serve any that "
                          "publishes with [node] accept_any = true (or --accept-any)")
    return SensorGate(named, any_, cap)


def _watch_recording(writer: Any, emit: Callable[[str], None], budget_mb: float,
                     stop: threading.Event) -> Any:
    """A thread that tells the operator, once a second at most, when the node's recording
    stops being written (a full disk) and when it resumes (see gateway.RecordingWatch)."""
    from recal.gateway import RecordingWatch  # the gateway imports this module

    watch = RecordingWatch(writer, emit, budget_mb, prefix=NOTE_PREFIX)

    def event(kind: str, detail: dict[str, Any]) -> None:
        with contextlib.suppress(ValueError):  # the writer closed under us (the stop)
            writer.write_event(kind, time.time_ns(), detail=detail)

    def loop() -> None:
        while not stop.wait(1.0):
            watch.check(time.time_ns(), event)

    threading.Thread(target=loop, name="recal-recording-watch", daemon=True).start()
    return watch


class _NodeRunner:
    """The loop of :func:`run_node`: bus messages -> nodes, checkpoints on a timer.

    Messages are taken in rounds of whatever has arrived (up to ``RECV_ROUND``), and each
    sensor's messages of a round are logged and calibrated as one batch (the pipeline is
    batch-size invariant): under load, rounds grow and the per-batch costs are paid less
    often, as in the gateway's read loop. Only the sensors the :class:`SensorGate` admits get
    that far.
    """

    def __init__(self, cfg: ServiceConfig, bus: Any, writer: Any, gate: SensorGate,
                 model_path: str | Path | None, emit: Callable[[str], None]) -> None:
        from recal.io import bus as _bus
        from recal.io import messages

        self.cfg, self.bus, self.writer, self.gate = cfg, bus, writer, gate
        self.model_path, self.emit = model_path, emit
        self.nodes: dict[str, CalibrationNode] = {}
        self.sink: Sink = LoggedBusSink(writer, bus) if writer is not None else BusSink(bus)
        self._messages = messages
        self._bus_mod = _bus
        self.receiver = bus.receiver(_bus.key_pattern("raw"), capacity=RECV_CAPACITY)
        self.bad_messages = 0
        self.checkpoints = Checkpoints(cfg.checkpoint.dir, cfg.checkpoint.interval_s,
                                       cfg.checkpoint.after_update_s, out=emit,
                                       event=self._sensor_event, prefix=NOTE_PREFIX)
        self.refused: set[str] = set()  # sensors another process calibrates (locked)
        self._drops_reported = 0
        self._next_drop_report_s = 0.0
        self._next_reject_report_s = 0.0
        # key -> sensor id of served sensors only (bounded by the gate): parsing and
        # validating the key cost a tenth of decoding a one-sample message
        self._key_sid: dict[str, str] = {}

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self._handle_round(self.receiver.recv_batch(RECV_ROUND, timeout=0.1))
            self.checkpoints.save_due(self.nodes)  # a few sensors at a time, and after updates
            self._report_drops()
            self._report_rejects()
        while True:  # what already arrived
            msgs = self.receiver.recv_batch(RECV_ROUND, timeout=0.0)
            if not msgs:
                break
            self._handle_round(msgs)
        self._report_rejects(force=True)

    def _report_drops(self) -> None:
        """Say so (at most once a second) when the receive buffer overflowed: samples lost
        here are still in the gateways' logs, but this node's log and calibration miss them
        (it is slower than the gateways; give them a --batch-ms)."""
        dropped = self.receiver.dropped
        if dropped == self._drops_reported or time.monotonic() < self._next_drop_report_s:
            return
        self._next_drop_report_s = time.monotonic() + 1.0
        log.warning("%d raw messages dropped: the node is behind the gateways",
                    dropped - self._drops_reported)
        self.emit(f"recal node: {dropped} raw messages dropped so far (node behind)")
        self._drops_reported = dropped

    def _report_rejects(self, force: bool = False) -> None:
        """At most every REJECT_REPORT_S: one console line and one ``sensors_ignored`` event
        (the recording's service events, ``/gateway/events``; not on the bus, where it would
        need a key of its own) about the raw messages the gate turned away."""
        now = time.monotonic()
        if not force and now < self._next_reject_report_s:
            return
        report = self.gate.take_report()
        if report is None:
            return
        self._next_reject_report_s = now + REJECT_REPORT_S
        why = ", ".join(f"{k} {v}" for k, v in report["by_reason"].items())
        self.emit(f"{NOTE_PREFIX} ignored {report['messages']} raw messages ({why}) from "
                  f"sensor ids it does not serve: {', '.join(report['sensor_ids'])}"
                  f"{' ...' if len(report['sensor_ids']) >= REJECT_IDS_KEPT else ''} "
                  f"(serving {self.gate.describe()})")
        if self.writer is not None:
            self.writer.write_event("sensors_ignored", time.time_ns(), detail=report)

    def _handle_round(self, msgs: list[Any]) -> None:
        """Decode a round of messages and hand each served sensor its samples, in order."""
        from recal.gateway import join_by_layout

        by_sensor: dict[str, list[RawBatch]] = {}
        for msg in msgs:
            try:
                key_sid = self._key_sid.get(msg.key) or msg.sensor
                sid, batch = self._messages.decode_raw(msg.payload)
            except ValueError:
                self.bad_messages += 1
                continue
            if sid and sid != key_sid:
                # the key is what access control checks: a payload naming another sensor
                # would let a gateway allowed on one key write into another sensor's state
                self.gate.reject(key_sid, "key_mismatch")
                continue
            if self.gate.admit(key_sid):
                self._key_sid[msg.key] = key_sid
                by_sensor.setdefault(key_sid, []).append(batch)
        for sid, batches in by_sensor.items():
            for batch in join_by_layout(batches):
                self._handle(sid, batch)

    def _handle(self, sid: str, batch: RawBatch) -> None:
        node = self.nodes.get(sid) or self._add(sid)
        log_ns = time.time_ns()
        if self.writer is not None:
            self.writer.write_raw(sid, batch, log_ns)
        if node is not None:
            node.process(batch, log_ns)

    def _sensor_event(self, sid: str, kind: str, detail: Any) -> None:
        self.sink.json(sid, "events", {"t_us": None, "kind": kind, "sensor_id": sid,
                                       "detail": detail}, time.time_ns())

    def _add(self, sid: str) -> CalibrationNode | None:
        """A node for a sensor first heard; None (said once) when another process holds its
        checkpoint lock in the same state folder: it calibrates that sensor, not this one."""
        if sid in self.refused:
            return None
        try:
            self.checkpoints.acquire([sid])
        except (SensorLockedError, OSError) as exc:
            self.refused.add(sid)
            self.emit(f"{NOTE_PREFIX} not calibrating {sid}: {exc}")
            return None
        sensor = self.cfg.sensor(sid) or SensorConfig(id=sid)
        settings = node_settings(sensor, self.cfg, self.model_path)
        node = make_node(settings, self.sink, self.checkpoints)
        self.nodes[sid] = node
        self.checkpoints.add(sid, node.accepted_updates)
        k = self._bus_mod.key
        self.bus.queryable(k(sid, "status"),
                           lambda _k, _p, n=node: self._messages.encode_json(n.status()))
        self.bus.queryable(k(sid, "align"), align_handler(node, self.emit))
        node.on_note = lambda line, sid=sid: self.emit(f"{NOTE_PREFIX} {sid}: {line}")
        self.emit(f"recal node: calibrating {sid} (start: {node.start})")
        return node

    def checkpoint(self, sensor_ids: Sequence[str] | None = None) -> None:
        """Checkpoint these sensors (default: all); failures are reported, never raised."""
        self.checkpoints.save(self.nodes, sensor_ids)

    def close(self) -> None:
        now = time.time_ns()
        for node in self.nodes.values():
            node.flush(now)
        self.checkpoint()
        self.checkpoints.release()
        self.receiver.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m recal.node --config node.toml [--sensor-id ID ...] [--mcap out.mcap]``."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m recal.node",
                                 description="calibration node subscribed to recal/*/raw")
    ap.add_argument("--config", help="service TOML: [zenoh], [[sensors]] priors, [pipeline]")
    from recal.cli import add_serving_arguments

    add_serving_arguments(ap)
    ap.add_argument("--mcap", help="also log everything to this recording")
    ap.add_argument("--model", help="model file for every sensor")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return run_node(args.config, args.sensor_id, args.mcap, args.model,
                    accept_any=args.accept_any, max_sensors=args.max_sensors)


if __name__ == "__main__":
    raise SystemExit(main())
