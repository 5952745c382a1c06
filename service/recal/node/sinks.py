"""Where a calibration node's output goes: nowhere, a list of events, a recording, the bus,
or the recording and the bus at once.

A :class:`recal.node.node.CalibrationNode` hands every message it derives to a :class:`Sink`; the
same node then runs in the gateway (:class:`LoggedBusSink`), on a machine of its own
(:class:`BusSink` or :class:`LoggedBusSink`) and in ``recal replay`` (:class:`RecordingSink`,
no Zenoh). The sinks are typed against what they use of a recording writer (:class:`Writer`)
and of a bus (:class:`Bus`), so that replay never loads Zenoh.

Which sink a process gets is :func:`make_sink` (a recording, a bus, both or neither). Each
suffix is a topic of the registry (`recal.io.topics`: schema, logged, published); a sink
resolves what it carries when it is built, and a suffix the registry does not know raises
:class:`recal.io.topics.UnknownTopicError` (a RecalError naming the known topics) at its first
message, before anything of it is logged or published.

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
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, Protocol

import numpy as np

from recal.core.alignment import to_body
from recal.io import messages, topics
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["BodyRotations", "Bus", "BusSink", "EventSink", "LoggedBusSink", "NullSink",
           "RecordingSink", "Sink", "Writer", "make_sink"]

# What a node may hand a sink, from the registry, resolved once at import (a set lookup per
# message then): the calibrated-batch outputs the log keeps and those the bus carries, and
# the JSON outputs (and those the log keeps).
_OUTPUTS = topics.require(topics.node_outputs())
_LOGGED_BATCHES = frozenset(t.suffix for t in _OUTPUTS if t.payload == "calibrated" and t.logged)
_PUBLISHED_BATCHES = frozenset(t.suffix for t in _OUTPUTS
                               if t.payload == "calibrated" and t.published)
_JSON = frozenset(t.suffix for t in _OUTPUTS if t.payload == "json")
_LOGGED_JSON = frozenset(t.suffix for t in _OUTPUTS if t.payload == "json" and t.logged)


def _batch_topic(suffix: str) -> None:
    """UnknownTopicError unless ``suffix`` is a registered calibrated-batch topic."""
    topics.require([suffix], "calibrated")


def _json_topic(suffix: str) -> None:
    """UnknownTopicError unless ``suffix`` is a registered JSON output."""
    if suffix not in _JSON:
        topics.require([suffix], "json")


class Sink(Protocol):
    """Receives a node's output; ``log_time_ns`` is the service clock (ns since the epoch)."""

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None: ...

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None: ...

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None: ...

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any],
             log_time_ns: int) -> None: ...


class Writer(Protocol):
    """What a sink uses of a :class:`recal.io.recording_writer.RecordingWriter`: each write returns
    the bytes it logged (so they can be published as they are)."""

    def write_raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> bytes: ...

    def write_calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                         topic_suffix: str = "calibrated") -> bytes: ...

    def log_raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None: ...

    def log_calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                       topic_suffix: str = "calibrated") -> None: ...

    def write_plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   every_n: int = 10) -> int: ...

    def log_body(self, sensor_id: str, calibrated: CalibratedBatch, rotation: np.ndarray,
                 log_time_ns: int) -> None: ...

    def write_json(self, topic: str, obj: Any, log_time_ns: int) -> bytes: ...


class Publisher(Protocol):
    """What a sink uses of a :class:`recal.io.bus.Publisher`."""

    def put(self, payload: bytes | Callable[[], bytes]) -> bool: ...


class Bus(Protocol):
    """What a sink uses of a :class:`recal.io.bus.Bus`."""

    @property
    def closed(self) -> bool: ...

    def publisher(self, key_expr: str) -> Publisher: ...


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


class BodyRotations:
    """Which rotation made a sensor's body batch from its calibrated batch, so that the log
    keeps the body stream as times and a rotation (`RecordingWriter.log_body`) instead of
    values the calibrated stream and the alignment already say.

    The node sends each batch calibrated, then (once the mounting is known) rotated; the
    rotation is in every message that says the alignment (the ``alignment`` event, the
    setup, the calibration states), which the node sends before the body batches it turns.
    A body batch is logged in that form only if rotating the calibrated batch just seen gives
    exactly its values and the rest of its columns are that batch's; otherwise (nothing
    known, another caller of the sink) as the batch it is."""

    def __init__(self) -> None:
        self._rotation: dict[str, np.ndarray] = {}
        self._last: dict[str, CalibratedBatch] = {}

    def note_json(self, sensor_id: str, suffix: str, obj: Any) -> None:
        ali = None
        if suffix == "events" and isinstance(obj, dict) and obj.get("kind") == "alignment":
            ali = obj.get("detail")
        elif suffix in ("setup", "calibration") and isinstance(obj, dict):
            ali = obj.get("alignment")
        if isinstance(ali, dict) and ali.get("rotation") is not None:
            try:
                r = np.asarray(ali["rotation"], np.float64).reshape(3, 3)
            except (TypeError, ValueError):
                return
            self._rotation[sensor_id] = r

    def note_calibrated(self, sensor_id: str, batch: CalibratedBatch) -> None:
        self._last[sensor_id] = batch

    def of(self, sensor_id: str, body: CalibratedBatch) -> tuple[CalibratedBatch,
                                                                  np.ndarray] | None:
        """(the calibrated batch, the rotation) that give ``body`` exactly, or None."""
        cal, r = self._last.get(sensor_id), self._rotation.get(sensor_id)
        if cal is None or r is None or len(cal) != len(body):
            return None
        if (cal.t_dev is None) != (body.t_dev is None) or not all(
                _same(u, v) for u, v in ((cal.t_us, body.t_us), (cal.status, body.status),
                                         (cal.quasi_static, body.quasi_static),
                                         (cal.detector_g, body.detector_g),
                                         (cal.sigma_mg, body.sigma_mg), (cal.t_dev, body.t_dev),
                                         (to_body(r, cal.a_g), body.a_g))):
            return None
        return cal, r


def _same(u: np.ndarray | None, v: np.ndarray | None) -> bool:
    """Equal arrays (NaN equal to NaN); a few values compared as Python numbers (a batch of
    one sample per arrival: cheaper than numpy's comparison)."""
    if u is v:
        return True
    if u is None or v is None:
        return False
    if u.size <= 16 and u.tolist() == v.tolist():
        return True
    return bool(np.array_equal(u, v, equal_nan=u.dtype.kind == "f"))


class RecordingSink:
    """Writes to a :class:`recal.io.recording_writer.RecordingWriter` (topic
    ``/<sensor>/<suffix>``); the body stream as times and a rotation when it can
    (:class:`BodyRotations`)."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.body = BodyRotations()

    @staticmethod
    def keeps(suffix: str) -> bool:
        """Whether the log keeps calibrated batches of ``suffix`` (the registry's ``logged``);
        UnknownTopicError if it is no registered calibrated-batch topic."""
        if suffix in _LOGGED_BATCHES:
            return True
        _batch_topic(suffix)
        return False

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        self.writer.log_raw(sensor_id, batch, log_time_ns)  # (no bus: no per-batch encoding)

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        if suffix == "calibrated":
            self.body.note_calibrated(sensor_id, batch)
        elif suffix not in _LOGGED_BATCHES:
            _batch_topic(suffix)  # unknown: raises; else a batch topic the log does not keep
            return
        elif suffix == "body":
            found = self.body.of(sensor_id, batch)
            if found is not None:
                self.writer.log_body(sensor_id, found[0], found[1], log_time_ns)
                return
        self.writer.log_calibrated(sensor_id, batch, log_time_ns, suffix)

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        self.writer.write_plot(sensor_id, batch, log_time_ns, every_n)

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        _json_topic(suffix)
        self.body.note_json(sensor_id, suffix, obj)
        if suffix in _LOGGED_JSON:
            self.writer.write_json(f"/{sensor_id}/{suffix}", obj, log_time_ns)


class BusSink:
    """Publishes on a :class:`recal.io.bus.Bus` (``recal/<sensor>/<suffix>``).

    Suffixes the registry does not publish (plot, setup: log only) are not published. A
    publish Zenoh refuses, or one after the bus closed, is counted in ``dropped`` and never
    raises.
    """

    def __init__(self, bus: Bus) -> None:
        # the key rule is recal.io.bus's; imported here, where a bus already exists, so that
        # this module (and replay, through RecordingSink) does not load Zenoh
        from recal.io import bus as _bus

        self.bus = bus
        self._key = _bus.key
        self._publishers: dict[tuple[str, str], Publisher] = {}
        self.topics = topics.published_topics()
        self.dropped = 0

    def put(self, sensor_id: str, suffix: str, data: bytes | Callable[[], bytes]) -> None:
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
        self.put(sensor_id, "raw", messages.encode_raw(sensor_id, batch))

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        if suffix not in _PUBLISHED_BATCHES:
            _batch_topic(suffix)  # unknown: raises; else a batch topic the bus does not carry
            return
        self.put(sensor_id, suffix, messages.encode_calibrated(sensor_id, batch))

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        pass  # the plot topic is for the log's Plot panel; the bus carries whole batches

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        _json_topic(suffix)
        if suffix in self.topics:
            self.put(sensor_id, suffix, messages.encode_json(obj))


class LoggedBusSink(RecordingSink):
    """Logs to a recording as a RecordingSink does, then publishes on the bus (the gateway's
    sink): a batch goes out in its own float64 form, encoded only when a subscriber matches
    its key, a JSON message as the very bytes logged (why it matters per sample:
    docs/design.md, "Figures behind choices")."""

    def __init__(self, writer: Writer, bus: Bus) -> None:
        super().__init__(writer)
        self.bus = BusSink(bus)

    @property
    def dropped(self) -> int:
        return self.bus.dropped

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        super().raw(sensor_id, batch, log_time_ns)
        self.bus.put(sensor_id, "raw", partial(messages.encode_raw, sensor_id, batch))

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        # the log keeps a body batch as times and a rotation when it can; the bus the values
        super().calibrated(sensor_id, batch, log_time_ns, suffix)
        if suffix in _PUBLISHED_BATCHES:
            self.bus.put(sensor_id, suffix, partial(messages.encode_calibrated, sensor_id, batch))

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        _json_topic(suffix)
        self.body.note_json(sensor_id, suffix, obj)
        data = (self.writer.write_json(f"/{sensor_id}/{suffix}", obj, log_time_ns)
                if suffix in _LOGGED_JSON else None)
        if suffix in self.bus.topics:
            self.bus.put(sensor_id, suffix, messages.encode_json(obj) if data is None else data)



def make_sink(writer: Writer | None, bus: Bus | None) -> Sink:
    """The sink of a process with this recording and this bus (either may be None): both, a
    LoggedBusSink (the gateway; a remote node that logs); a recording alone, a RecordingSink;
    a bus alone, a BusSink; neither, a NullSink."""
    if writer is not None and bus is not None:
        return LoggedBusSink(writer, bus)
    if writer is not None:
        return RecordingSink(writer)
    if bus is not None:
        return BusSink(bus)
    return NullSink()
