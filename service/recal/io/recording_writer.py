"""The recording writer: the topic layout of `recal.io.recording` written to MCAP as samples
arrive, flushed, fsynced and rotated, and kept going through a full disk.

Crash tolerance: chunks are small (32 KiB by default) and the open chunk is closed, the file
flushed and ``fsync``ed at least every ``flush_interval_s``, so a SIGKILL or power cut loses about
that much; ``repair`` turns the truncated file into a valid indexed one.

A full disk (``backlog_bytes``, the daemon's setting): a write the file refuses does not raise.
The file is cut back to the end of its last whole record (readable by ``repair`` as it stands),
and the refused output waits in memory, each chunk compressed once, until a later flush gets
it written in the same file; past ``backlog_bytes`` the oldest waiting chunks are dropped and
counted (``RecordingWriter.health``). Tools that write a file (replay, import) keep the default:
a refused write raises.

Batches are logged in the compact form (`messages.encode_raw_compact`,
`messages.encode_calibrated_compact`) and joined: the raw, calibrated and body batches of a topic
wait in memory and go into the file as one message at the next flush (or once
``log_batch_samples`` samples wait), so a sensor handled one sample per arrival costs one
message per topic and flush interval, not one per sample. A crash loses exactly what it lost
before (what arrived since the last flush, which was in the open chunk, in memory, anyway).
``write_raw`` and ``write_calibrated`` still return each batch encoded on its own in the
float64 form, for the bus. ``log_body`` logs a body batch as its times and the rotation that
turns the calibrated samples (`messages.encode_body_rotation`), joined while the rotation
stays.

Memory: the writer holds the open chunk and a few counters; the chunk indexes the summary needs
wait in a temporary file (a week flushed every second is ~600k chunks), so a recording of any
length is written in constant memory.

How it is laid out and why: docs/design.md (recordings).
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

from recal import __version__
from recal.errors import UsageError
from recal.io import messages, topics
from recal.io.mcap_file import COMPRESSION_TYPES, LIBRARY, Compression, McapFile
from recal.io.messages import SchemaSpec
from recal.io.recording import (
    GATEWAY,
    PathLike,
    part_path,
    recording_parts,
    sensor_topic,
    split_topic,
)
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["FILE_TO_FILE_FLUSH_S", "RecordingWriter", "WriteHealth"]

_TOPIC = re.compile(r"/[A-Za-z0-9][A-Za-z0-9_.\-]*/[A-Za-z0-9_.\-]+")
# the log's schema of each registered topic; a topic the registry does not know is logged as
# generic JSON (the writer is also a tool's: `recal import` and tests write topics of their own)
_SUFFIX_SCHEMAS: dict[str, SchemaSpec] = topics.log_schemas()
_MAX_U64 = 2**64 - 1
#: A batch longer than this (a file tool's) is logged in messages of this many samples.
_MAX_MESSAGE_SAMPLES = 16384


def _publish_ns(t_us: int | None, fallback_ns: int) -> int:
    if t_us is None:
        return fallback_ns
    # MCAP times are unsigned 64-bit; device clocks before their epoch are clamped, not lost.
    return min(max(int(t_us) * 1000, 0), _MAX_U64)


def _publish_ns_array(t_us: np.ndarray) -> np.ndarray:
    """`_publish_ns` of each device time (us), as uint64."""
    t = np.clip(np.asarray(t_us, np.int64), 0, None).astype(np.uint64)
    big = t > np.uint64(_MAX_U64 // 1000)
    out = t * np.uint64(1000)
    out[big] = _MAX_U64
    return out


def _check_calibrated_suffix(topic_suffix: str) -> None:
    """A calibrated batch may go on any suffix but one reserved for another schema."""
    if _SUFFIX_SCHEMAS.get(topic_suffix, messages.CALIBRATED_SCHEMA) is not \
            messages.CALIBRATED_SCHEMA:
        raise ValueError(f"topic suffix {topic_suffix!r} is reserved for another schema")


def _rotation_bytes(rotation: np.ndarray) -> bytes:
    """A body rotation (3 x 3, ``R @ a``) as the float64 bytes a waiting message keeps."""
    r = np.ascontiguousarray(rotation, np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must be 3 x 3, got shape {r.shape}")
    return r.tobytes()


def _check_log_time(log_time_ns: int) -> int:
    value = int(log_time_ns)
    if not 0 <= value <= _MAX_U64:
        raise ValueError(f"log_time_ns must be an unsigned 64-bit integer, got {log_time_ns}")
    return value


@dataclass
class _Pending:
    """Batches of one topic waiting to be logged as one message."""

    sensor_id: str
    raw: bool  # RawBatch (else CalibratedBatch)
    log_ns: int  # the first batch's log time: the message's
    publish_ns: int
    batches: list[Any]
    samples: int
    sizes: list[int]  # raw: samples of each arrival (a batch may hold several)
    log_times: list[int]  # raw: each arrival's log time (both kept in the message)
    rotation: bytes | None = None  # body in the log's form: the rotation (float64 bytes)


@dataclass(frozen=True)
class WriteHealth:
    """Whether the recording is being written, and what a refusing file cost so far.

    Attributes:
        failing: the file refuses writes (a full disk); messages wait in memory meanwhile.
        error: the last write or fsync error, as text (None if there was none).
        failing_since_s: when the current refusal began (the writer's clock), or None.
        failures: refusals so far (a refusal lasts until everything waiting is written).
        waiting_bytes: compressed bytes waiting for the file.
        dropped_messages, dropped_samples: dropped so far, oldest first, because more waited
            than ``backlog_bytes`` or because the file still refused at a close (raw samples
            in the dropped messages).
        fsync_errors: fsyncs that failed (the data may not be on the disk yet).
        unfinished: parts closed without their index (``recal repair`` reads them).
    """

    failing: bool
    error: str | None
    failing_since_s: float | None
    failures: int
    waiting_bytes: int
    dropped_messages: int
    dropped_samples: int
    fsync_errors: int
    unfinished: tuple[Path, ...]


#: flush_interval_s of a command that converts one file into another (replay, hindsight,
#: simulate, import): chunks end by size alone, not by the wall clock, so the same input
#: gives the same bytes on any machine; such a file is made again rather than recovered.
FILE_TO_FILE_FLUSH_S = float("inf")


class RecordingWriter:
    """Writes the topic layout above to MCAP, flushing and rotating as it goes.

    Thread-safe: one lock guards the file, so a background thread can flush while the owner
    writes. The caller's clock gives every message time; ``clock`` (monotonic seconds) is used
    only to decide when a flush is due.

    Args:
        path: the first file; rotated parts are ``<stem>-0001<suffix>``, ``-0002``, ...
        chunk_size: uncompressed bytes after which a chunk is closed. Small chunks bound what a
            crash loses (docs/design.md: what a killed writer loses).
        flush_interval_s: the open chunk is closed, the file flushed and fsynced when this long
            has passed since the last flush, checked on every write and by the flush thread.
        rotate_bytes: start a new part once the current file reached this size (checked before
            each write, so a part overshoots by at most one chunk and its index; with
            background_compression, also by the chunks still queued).
        rotate_s: start a new part once the log time passed the current part's first log
            time by this much.
        compression: chunk compression.
        clock: monotonic seconds, for flush timing only (inject a fake one in tests).
        background_flush: run a daemon thread that flushes when due even if no writes come.
        fsync: fsync after each flush (off only for benchmarks and tests on tmpfs).
        metadata: string pairs stored in each part's ``recal`` metadata record.
        overwrite: replace an existing file (and remove stale rotated parts of it); otherwise an
            existing file is an error.
        background_compression: compress and write finished chunks on a thread, beside the
            caller (replay: the calibration runs while the previous chunk is compressed). A
            flush still returns only once everything is in the file.
        backlog_bytes: None: a write the file refuses raises (a tool writing a file). A number
            (the daemon): it does not; the file is cut back to its last whole record, and what
            it refused waits in memory, compressed, and is written when the file takes it
            again (tried at every flush). Beyond this many bytes the oldest waiting chunks are
            dropped and counted; see :meth:`health`. Not with background_compression.
        log_batch_samples: a topic's waiting batches are logged as one message once this many
            samples wait (and at every flush and at close, whatever their number).
    """

    def __init__(self, path: PathLike, *, chunk_size: int = 32 * 1024,
                 flush_interval_s: float = 1.0, rotate_bytes: int | None = None,
                 rotate_s: float | None = None, compression: Compression = "zstd",
                 clock: Callable[[], float] = time.monotonic, background_flush: bool = True,
                 fsync: bool = True, metadata: Mapping[str, str] | None = None,
                 overwrite: bool = False, background_compression: bool = False,
                 backlog_bytes: int | None = None, log_batch_samples: int = 8192) -> None:
        if compression not in COMPRESSION_TYPES:
            raise UsageError(f"compression must be one of {sorted(COMPRESSION_TYPES)}")
        if chunk_size <= 0 or flush_interval_s <= 0:
            raise UsageError("chunk_size and flush_interval_s must be positive")
        if (rotate_bytes is not None and rotate_bytes <= 0) or (rotate_s is not None
                                                               and rotate_s <= 0):
            raise UsageError("rotate_bytes and rotate_s must be positive (or None)")
        if log_batch_samples < 1:
            raise UsageError("log_batch_samples must be >= 1")
        if backlog_bytes is not None and (backlog_bytes < 0 or background_compression):
            raise UsageError("backlog_bytes must be >= 0, and not with background_compression")
        self._base = Path(path)
        self._base.parent.mkdir(parents=True, exist_ok=True)
        self._prepare_target(overwrite)
        self._chunk_size = chunk_size
        self._flush_interval_s = float(flush_interval_s)
        self._rotate_bytes = rotate_bytes
        self._rotate_ns = None if rotate_s is None else round(rotate_s * 1e9)
        self._compression: Compression = compression
        self._background_compression = background_compression
        self._clock = clock
        self._fsync = fsync
        self._fsync_due = False  # flushed to the OS, not yet fsynced (see _flush_locked)
        self._metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._lock = threading.RLock()
        self._paths: list[Path] = []
        self._topic_specs: dict[str, SchemaSpec] = {}
        self._sequence: dict[str, int] = {}
        self._plot_phase: dict[str, int] = {}
        self._pending: dict[str, _Pending] = {}  # topic -> batches waiting for one message
        self._log_batch_samples = log_batch_samples
        self._topics: dict[tuple[str, str], str] = {}  # (sensor, suffix) -> checked topic
        self._messages_written = 0
        self._messages_flushed = 0
        self._flush_count = 0
        self._closed = False
        self._background_error: BaseException | None = None
        self._backlog_bytes = backlog_bytes
        self._parts_out = 0  # messages in the files of finished parts
        self._parts_dropped = (0, 0)  # messages, samples dropped in finished parts
        self._unfinished: list[Path] = []
        self._failures = 0
        self._failing_since_s: float | None = None
        self._last_error: str | None = None
        self._fsync_errors = 0
        self._open_part()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if background_flush and self._flush_interval_s != float("inf"):  # (never due)
            self._thread = threading.Thread(target=self._flush_loop, name="recal-mcap-flush",
                                            daemon=True)
            self._thread.start()

    # -- public API ---------------------------------------------------------------------------

    @property
    def paths(self) -> list[Path]:
        """Every file written so far, in order (the last one is open until close)."""
        return list(self._paths)

    @property
    def messages_written(self) -> int:
        return self._messages_written

    @property
    def messages_flushed(self) -> int:
        """Messages that were in the file at the last flush (what a crash now would keep)."""
        return self._messages_flushed

    @property
    def flush_count(self) -> int:
        return self._flush_count

    @property
    def backlog_bytes(self) -> int | None:
        """How much may wait in memory while the file refuses writes (None: refusals raise)."""
        return self._backlog_bytes

    def write_raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> bytes:
        """Log a raw batch on ``/<sensor>/raw`` (`log_raw`); returns the batch encoded on its
        own, float64 form (for the bus)."""
        self.log_raw(sensor_id, batch, log_time_ns)
        return messages.encode_raw(sensor_id, batch)

    def log_raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int,
                arrivals: messages.Arrivals | None = None) -> None:
        """Log a raw batch on ``/<sensor>/raw``: joined with the topic's next batches into one
        compact message at the next flush. ``arrivals``: the batch is several arrivals
        already joined, as `messages.decode_raw_arrivals` gives them (samples of each, log
        time of each in us after ``log_time_ns``); kept in the message as the writer keeps
        those it joins itself (replay logs a message's arrivals in one call)."""
        self._hold(self._sensor_topic(sensor_id, "raw"), sensor_id, batch,
                   _check_log_time(log_time_ns), raw=True, arrivals=arrivals)

    def write_calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                         topic_suffix: str = "calibrated") -> bytes:
        """Log a calibrated batch (`log_calibrated`); returns it encoded on its own, float64
        form (for the bus)."""
        self.log_calibrated(sensor_id, batch, log_time_ns, topic_suffix)
        return messages.encode_calibrated(sensor_id, batch)

    def log_calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                       topic_suffix: str = "calibrated") -> None:
        """Log a calibrated batch on ``/<sensor>/<topic_suffix>``, joined like `log_raw`'s."""
        _check_calibrated_suffix(topic_suffix)
        self._hold(self._sensor_topic(sensor_id, topic_suffix), sensor_id, batch,
                   _check_log_time(log_time_ns), raw=False)

    def log_body(self, sensor_id: str, calibrated: CalibratedBatch, rotation: np.ndarray,
                 log_time_ns: int) -> None:
        """Log on ``/<sensor>/body`` that these calibrated samples (as logged on
        ``/<sensor>/calibrated``) rotated by ``rotation`` (3 x 3: ``R @ a``) are the body
        frame's: the samples' times and the rotation, joined like `log_calibrated`'s batches
        while the rotation stays (`messages.encode_body_rotation`). The body stream without
        a value the calibrated stream and the alignment already say."""
        self._hold(self._sensor_topic(sensor_id, "body"), sensor_id, calibrated,
                   _check_log_time(log_time_ns), raw=False, rotation=_rotation_bytes(rotation))

    def log_body_many(self, sensor_id: str,
                      items: Sequence[tuple[CalibratedBatch, np.ndarray | None, int]]) -> None:
        """`log_body` (rotation given) or `log_calibrated` on ``body`` (rotation None: the
        batch is the body's values) of each (batch, rotation, log time) in turn, in one call:
        the same messages (replay hands a pipeline step's body batches over at once)."""
        topic = self._sensor_topic(sensor_id, "body")
        with self._lock:
            self._check_writable()
            for batch, rotation, log_ns in items:
                self._hold_locked(topic, sensor_id, batch, _check_log_time(log_ns), raw=False,
                                  rotation=None if rotation is None else
                                  _rotation_bytes(rotation))
            self._maybe_flush()

    def log_calibrated_many(self, sensor_id: str, batches: Sequence[CalibratedBatch],
                            log_times_ns: Sequence[int], topic_suffix: str = "calibrated"
                            ) -> None:
        """`log_calibrated` of each batch in turn, in one call (replay hands a pipeline
        step's batches over at once): the same messages, for a list append per batch."""
        _check_calibrated_suffix(topic_suffix)
        topic = self._sensor_topic(sensor_id, topic_suffix)
        with self._lock:
            self._check_writable()
            for batch, log_ns in zip(batches, log_times_ns, strict=True):
                self._hold_locked(topic, sensor_id, batch, _check_log_time(log_ns), raw=False)
            self._maybe_flush()

    def write_json(self, topic: str, obj: Any, log_time_ns: int) -> bytes:
        """Log a JSON object; the schema follows the topic suffix (calibration, events,
        anything else a permissive object schema). Returns the encoded bytes."""
        spec = _SUFFIX_SCHEMAS.get(split_topic(topic)[1], messages.GENERIC_JSON_SCHEMA)
        if spec.message_encoding != "json":
            raise ValueError(f"topic {topic!r} carries {spec.name}, not JSON")
        data = messages.encode_json(obj)
        t_us = obj.get("t_us") if isinstance(obj, Mapping) else None
        publish = _publish_ns(t_us if isinstance(t_us, (int, np.integer)) else None,
                              int(log_time_ns))
        self.write_encoded(topic, data, log_time_ns, publish, schema=spec)
        return data

    def write_calibration(self, sensor_id: str, state: Mapping[str, Any],
                          log_time_ns: int) -> bytes:
        """Log a calibration state dict on ``/<sensor>/calibration``."""
        return self.write_json(sensor_topic(sensor_id, "calibration"), state, log_time_ns)

    def write_event(self, kind: str, log_time_ns: int, *, sensor_id: str | None = None,
                    t_us: int | None = None, detail: Any = None) -> bytes:
        """Log an event on ``/<sensor>/events``, or ``/gateway/events`` without a sensor."""
        topic = f"/{GATEWAY}/events" if sensor_id is None else sensor_topic(sensor_id, "events")
        data = messages.encode_event(kind, t_us=t_us, sensor_id=sensor_id, detail=detail)
        self.write_encoded(topic, data, log_time_ns, _publish_ns(t_us, int(log_time_ns)),
                           schema=messages.EVENT_SCHEMA)
        return data

    def write_plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   every_n: int = 10, arrivals: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> int:
        """Log every ``every_n``-th sample as a plot message; returns how many were written.

        Decimation continues across batches (a per-sensor phase), so the plot rate is steady
        whatever the batch sizes. A sample's log time is its batch's, less its device-time
        distance to the batch's last sample. ``arrivals``: the batch is several batches
        joined (samples of each, log time of each in ns; ``log_time_ns`` is then unused):
        the same messages as one call per batch, in one (replay).
        """
        if every_n < 1:
            raise ValueError("every_n must be >= 1")
        topic = self._sensor_topic(sensor_id, "plot")
        log_ns = _check_log_time(log_time_ns)
        with self._lock:
            phase = self._plot_phase.get(sensor_id, 0)
            self._plot_phase[sensor_id] = (phase + len(batch)) % every_n
        first = (-phase) % every_n
        if first >= len(batch):
            return 0  # most calls when samples are handled as they arrive: no numpy at all
        indices = np.arange(first, len(batch), every_n)
        t_us = batch.t_us[indices]
        if arrivals is not None:
            return self._write_plot_arrivals(topic, batch, indices, arrivals)
        # Spread the samples back from the log time by their device-time distance to the end.
        last_us = int(batch.t_us[-1])
        if len(indices) <= 16:  # a few samples: packed one by one (no array set-up)
            items = [(data, lt, _publish_ns(t, lt)) for data, t in zip(
                messages.encode_plot(batch, indices), t_us.tolist(), strict=True)
                for lt in (max(log_ns - (last_us - t) * 1000, 0),)]
            self._write_many(topic, messages.PLOT_SCHEMA, items, log_ns)
            return len(items)
        log_times = np.clip(log_ns - (last_us - t_us) * 1000, 0, None)
        self._write_fixed(topic, messages.PLOT_SCHEMA, messages.plot_payloads(batch, indices),
                          log_times, _publish_ns_array(t_us), log_ns)
        return len(indices)

    def _write_plot_arrivals(self, topic: str, batch: CalibratedBatch, indices: np.ndarray,
                             arrivals: tuple[np.ndarray, np.ndarray]) -> int:
        """`write_plot`'s messages for a batch of several arrivals: each sample's log time
        from its own arrival's log time and last device time."""
        sizes = np.asarray(arrivals[0], np.int64)
        log_ns = np.asarray(arrivals[1], np.int64)
        if sizes.sum() != len(batch) or len(log_ns) != len(sizes) or (sizes < 0).any():
            raise ValueError("arrivals do not describe the batch")
        if len(log_ns) and not (log_ns.min() >= 0 and log_ns.max() <= _MAX_U64):
            raise ValueError("an arrival's log time is not an unsigned 64-bit integer")
        ends = np.cumsum(sizes)
        arrival = np.searchsorted(ends, indices, side="right")  # the arrival of each sample
        t_us = batch.t_us[indices]
        last_us = batch.t_us[ends[arrival] - 1]
        log_times = np.clip(log_ns[arrival] - (last_us - t_us) * 1000, 0, None)
        self._write_fixed(topic, messages.PLOT_SCHEMA, messages.plot_payloads(batch, indices),
                          log_times, _publish_ns_array(t_us), int(log_ns[arrival[0]]))
        return len(indices)

    def write_encoded(self, topic: str, data: bytes, log_time_ns: int,
                      publish_time_ns: int | None = None, *,
                      schema: SchemaSpec | None = None) -> None:
        """Log already-encoded bytes (e.g. exactly what went on the bus).

        The schema defaults to the one the topic suffix implies (see the layout above).
        """
        log_ns = _check_log_time(log_time_ns)
        if topic not in self._topic_specs and not _TOPIC.fullmatch(topic):
            raise ValueError(f"invalid topic {topic!r}: expected /<owner>/<name>")
        spec = schema or self._topic_specs.get(topic) or _SUFFIX_SCHEMAS.get(
            split_topic(topic)[1], messages.GENERIC_JSON_SCHEMA)
        publish = log_ns if publish_time_ns is None else min(max(int(publish_time_ns), 0),
                                                             _MAX_U64)
        self._write_many(topic, spec, [(data, log_ns, publish)], log_ns)

    def flush(self) -> None:
        """Close the open chunk, flush and fsync the file now."""
        with self._lock:
            self._raise_background_error()
            if not self._closed:
                self._flush_locked()
            fd = self._take_fsync()
        _fsync_and_close(fd)

    def close(self) -> None:
        """Flush, write the index (summary) and close the file. Idempotent.

        With ``backlog_bytes``, a file that still refuses writes does not raise: what waited is
        dropped (counted) and the part is left without its index (``health().unfinished``).
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        with self._lock:
            if self._closed:
                return
            self._emit_pending()
            self._closed = True
            self._finish_part()
        self._raise_background_error()

    def health(self) -> WriteHealth:
        """Whether writing works now, and what refusals cost so far (for the console)."""
        with self._lock:
            m = self._mcap
            # a finished part's drops are in _parts_dropped already
            open_dropped = (0, 0) if self._closed else (m.dropped_messages, m.dropped_samples)
            return WriteHealth(
                failing=m.failure is not None, error=self._last_error,
                failing_since_s=self._failing_since_s, failures=self._failures,
                waiting_bytes=m.waiting_bytes,
                dropped_messages=self._parts_dropped[0] + open_dropped[0],
                dropped_samples=self._parts_dropped[1] + open_dropped[1],
                fsync_errors=self._fsync_errors, unfinished=tuple(self._unfinished))

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------

    def _sensor_topic(self, sensor_id: str, suffix: str) -> str:
        """`sensor_topic`, checked once per (sensor, suffix): a gateway writes each sample as
        it arrives, and the check (a regex) would otherwise run per message."""
        topic = self._topics.get((sensor_id, suffix))
        if topic is None:
            topic = self._topics[(sensor_id, suffix)] = sensor_topic(sensor_id, suffix)
        return topic

    def _prepare_target(self, overwrite: bool) -> None:
        stale = recording_parts(self._base)[1:]
        if not overwrite and (self._base.exists() or stale):
            raise FileExistsError(f"{self._base} exists (pass overwrite=True to replace it)")
        # Old rotated parts would otherwise be read as parts of the new recording.
        for part in stale:
            part.unlink()

    def _open_part(self) -> None:
        path = part_path(self._base, len(self._paths))
        # Unbuffered: McapFile joins each chunk into one write itself, and a write the disk
        # refuses must leave nothing behind in a buffer (the file is cut back instead).
        self._file: IO[bytes] = open(path, "wb", buffering=0)  # closed in _finish_part
        self._mcap = McapFile(self._file, self._chunk_size, self._compression,
                               self._background_compression, self._backlog_bytes)
        self._mcap.start(profile="", library=LIBRARY)
        self._mcap.add_metadata("recal", {"version": __version__,
                                          "part": str(len(self._paths)), **self._metadata})
        self._paths.append(path)
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._part_messages = 0
        self._part_start_ns = 0
        self._last_flush_s = self._clock()

    def _finish_part(self) -> None:
        m = self._mcap
        try:
            finished = m.finish()
            self._file.flush()
            if self._fsync:
                self._fsync_checked(self._file.fileno())
        finally:
            self._file.close()
            self._parts_out += m.messages_out
            self._parts_dropped = (self._parts_dropped[0] + m.dropped_messages,
                                   self._parts_dropped[1] + m.dropped_samples)
        if not finished:
            self._unfinished.append(self._paths[-1])
            self._note_failure(m.failure)
        self._messages_flushed = self._parts_out

    def _fsync_checked(self, fd: int) -> None:
        """fsync; with a backlog budget a failure is counted, not raised."""
        try:
            os.fsync(fd)
        except OSError as exc:
            if self._backlog_bytes is None:
                raise
            self._fsync_errors += 1
            self._last_error = _describe(exc)

    def _note_failure(self, exc: OSError | None) -> None:
        if exc is not None:
            self._last_error = _describe(exc)

    def _rotation_due(self, log_ns: int) -> bool:
        if self._part_messages == 0 or self._mcap.failure is not None:
            return False  # never leave an empty part behind, nor finish one the disk refuses
        if self._rotate_bytes is not None and self._mcap.position >= self._rotate_bytes:
            return True
        return self._rotate_ns is not None and log_ns - self._part_start_ns >= self._rotate_ns

    def _channel_id(self, topic: str, spec: SchemaSpec) -> int:
        known = self._topic_specs.setdefault(topic, spec)
        if known.name != spec.name:
            raise ValueError(f"topic {topic!r} carries {known.name}, not {spec.name}")
        channel_id = self._channel_ids.get(topic)
        if channel_id is None:
            schema_id = self._schema_ids.get(spec.name)
            if schema_id is None:
                schema_id = self._mcap.register_schema(spec.name, spec.encoding, spec.data)
                self._schema_ids[spec.name] = schema_id
            channel_id = self._mcap.register_channel(topic, spec.message_encoding, schema_id)
            self._channel_ids[topic] = channel_id
        return channel_id

    def _write_many(self, topic: str, spec: SchemaSpec,
                    items: Sequence[tuple[bytes, int, int]], call_log_ns: int,
                    samples: int = 0) -> None:
        """Append (data, log_time_ns, publish_time_ns) messages to one topic, in order;
        ``samples``: raw samples they hold (counted if they are dropped)."""
        self._append(topic, spec, call_log_ns, len(items),
                     lambda channel_id, seq: self._mcap.add_messages(channel_id, items, seq),
                     samples)

    def _write_fixed(self, topic: str, spec: SchemaSpec, payloads: np.ndarray,
                     log_times: np.ndarray, publish_times: np.ndarray, call_log_ns: int) -> None:
        """Like `_write_many` for messages that are the rows of a structured array."""
        self._append(topic, spec, call_log_ns, len(payloads),
                     lambda channel_id, seq: self._mcap.add_fixed(
                         channel_id, payloads, log_times, publish_times, seq))

    def _append(self, topic: str, spec: SchemaSpec, call_log_ns: int, count: int,
                add: Callable[[int, int], int], samples: int = 0) -> None:
        """Rotate if due, then ``add(channel_id, first_sequence)`` -> next sequence; ``add``
        reads ``self._mcap`` when called, i.e. the part open after any rotation."""
        with self._lock:
            self._check_writable()
            if self._rotation_due(call_log_ns):
                self._finish_part()
                self._open_part()
            if self._part_messages == 0:
                self._part_start_ns = call_log_ns
            channel_id = self._channel_id(topic, spec)
            self._mcap.open_samples += samples  # before add: it may end the chunk
            self._sequence[topic] = add(channel_id, self._sequence.get(topic, 0))
            self._part_messages += count
            self._messages_written += count
            if self._mcap.failure is not None and self._failing_since_s is None:
                self._track_failure(self._clock())  # a chunk just ended was refused
            self._maybe_flush()

    def _hold(self, topic: str, sensor_id: str, batch: RawBatch | CalibratedBatch, log_ns: int,
              raw: bool, arrivals: messages.Arrivals | None = None,
              rotation: bytes | None = None) -> None:
        """Add a batch to its topic's waiting message (a list append per arrival: the join
        and the encoding happen once per message)."""
        with self._lock:
            self._check_writable()
            self._hold_locked(topic, sensor_id, batch, log_ns, raw, arrivals, rotation)
            self._maybe_flush()

    def _hold_locked(self, topic: str, sensor_id: str, batch: RawBatch | CalibratedBatch,
                     log_ns: int, raw: bool, arrivals: messages.Arrivals | None = None,
                     rotation: bytes | None = None) -> None:
        """`_hold` without the checks and the flush (lock held)."""
        p = self._pending.get(topic)
        if p is not None and (p.rotation != rotation
                              or _layout(p.batches[0], raw) != _layout(batch, raw)):
            self._emit(topic)  # one message holds one layout (and one rotation)
            p = None
        if p is None:
            first = int(batch.t_us[0]) if len(batch) else None
            p = self._pending[topic] = _Pending(sensor_id, raw, log_ns,
                                                _publish_ns(first, log_ns), [], 0, [], [],
                                                rotation)
        p.batches.append(batch)
        p.samples += len(batch)
        if raw and arrivals is None:  # (a calibrated message keeps no arrivals)
            p.sizes.append(len(batch))
            p.log_times.append(log_ns)
        elif raw and arrivals is not None:
            sizes, log_us = arrivals
            p.sizes += sizes.tolist()
            p.log_times += ([log_ns] * len(sizes) if log_us is None
                            else (log_ns + 1000 * log_us).tolist())
        if p.samples >= self._log_batch_samples:
            self._emit(topic)

    def _emit(self, topic: str) -> None:
        """Write a topic's waiting batches as one compact message (lock held)."""
        p = self._pending.pop(topic)  # first: the write may flush, which emits the rest
        if p.raw:
            batch = p.batches[0] if len(p.batches) == 1 else RawBatch.concat(p.batches)
            # the arrivals, so that a replay gives the node the batches the live node had
            arrivals = (p.sizes, [(t - p.log_ns) // 1000 for t in p.log_times])
            data = messages.encode_raw_compact(p.sensor_id, batch, arrivals)
            spec = messages.RAW_SCHEMA
            self._write_many(topic, spec, [(data, p.log_ns, p.publish_ns)], p.log_ns,
                             samples=len(batch))
            return
        if p.rotation is not None:  # the body in the log's form: times and the rotation
            t_us = np.concatenate([b.t_us for b in p.batches])
            r = np.frombuffer(p.rotation, np.float64).reshape(3, 3)
            self._write_many(topic, messages.CALIBRATED_SCHEMA,
                             [(messages.encode_body_rotation(p.sensor_id, t_us, r), p.log_ns,
                               p.publish_ns)], p.log_ns)
            return
        batch = p.batches[0] if len(p.batches) == 1 else CalibratedBatch.concat(p.batches)
        step = max(self._log_batch_samples, _MAX_MESSAGE_SAMPLES)  # (a file tool's batches)
        for i in range(0, max(len(batch), 1), step):
            part = batch if len(batch) <= step else batch[i:i + step]
            self._write_many(topic, messages.CALIBRATED_SCHEMA,
                             [(messages.encode_calibrated_compact(p.sensor_id, part), p.log_ns,
                               p.publish_ns)], p.log_ns)

    def _emit_pending(self) -> None:
        for topic in list(self._pending):
            if topic in self._pending:
                self._emit(topic)

    def _track_failure(self, now_s: float) -> None:
        """Note when the file began or stopped refusing writes (lock held)."""
        failure = self._mcap.failure
        if failure is None:
            self._failing_since_s = None
        else:
            if self._failing_since_s is None:
                self._failures += 1
                self._failing_since_s = now_s
            self._last_error = _describe(failure)

    def _maybe_flush(self) -> None:
        if self._clock() - self._last_flush_s >= self._flush_interval_s:
            self._flush_locked()

    def _flush_locked(self) -> None:
        self._last_flush_s = now_s = self._clock()
        self._emit_pending()  # (their writes see the flush just stamped, so do not recurse)
        m = self._mcap
        if self._messages_flushed == self._messages_written and not m.waiting_bytes:
            return  # nothing new: skip the fsync
        m.flush()  # ends the open chunk (and tries again what the disk refused)
        self._track_failure(now_s)
        if m.failure is not None:
            return  # nothing new in the file: no fsync
        # The fsync itself (milliseconds) happens outside the lock, on the flush thread: a
        # writer calling in to log a sample must not wait for the disk (the gateway's
        # latency p99 showed it). The data is with the OS already, so a killed process
        # loses nothing by this; a power cut may lose up to a quarter interval more.
        self._fsync_due = self._fsync
        self._messages_flushed = self._parts_out + m.messages_out
        self._flush_count += 1

    def _take_fsync(self) -> int | None:
        """With the lock held: a duplicate descriptor to fsync if one is due (the duplicate
        stays valid should the file be rotated or closed meanwhile), else None."""
        if not self._fsync_due or self._closed:
            return None
        self._fsync_due = False
        return os.dup(self._file.fileno())

    def _flush_loop(self) -> None:
        # Wakes several times per interval so a quiet writer is still flushed on time. It
        # outlives errors: a disk that was full takes data again, and fsync is still wanted.
        while not self._stop.wait(self._flush_interval_s / 4):
            fd = None
            with self._lock:
                if self._closed:
                    return
                try:
                    self._maybe_flush()
                    fd = self._take_fsync()
                except Exception as exc:
                    self._background_failed(exc)
                    continue
            try:
                _fsync_and_close(fd)
            except OSError as exc:
                with self._lock:
                    self._background_failed(exc)

    def _background_failed(self, exc: Exception) -> None:
        """An error on the flush thread (lock held): kept for the owner's next call, or with a
        backlog budget (where write refusals never raise) counted in ``health``."""
        if self._backlog_bytes is None:
            self._background_error = exc
            return
        if isinstance(exc, OSError):
            self._fsync_errors += 1
        self._last_error = _describe(exc) if isinstance(exc, OSError) else repr(exc)

    def _check_writable(self) -> None:
        """Raise what the background thread met, or that the writer is closed (lock held)."""
        self._raise_background_error()
        if self._closed:
            raise ValueError("recording writer is closed")

    def _raise_background_error(self) -> None:
        if self._background_error is not None:
            error, self._background_error = self._background_error, None
            raise RuntimeError("background flush of the recording failed") from error


def _layout(batch: RawBatch | CalibratedBatch, raw: bool) -> Any:
    """What batches must share to be joined: the channels, or which optional columns exist."""
    if raw:
        return batch.aux_names  # type: ignore[union-attr]
    return (batch.t_dev is None, batch.recorded)  # type: ignore[union-attr]


def _describe(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _fsync_and_close(fd: int | None) -> None:
    """fsync a duplicated descriptor (see ``RecordingWriter._take_fsync``) and close it."""
    if fd is None:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------------------------
# Reader
