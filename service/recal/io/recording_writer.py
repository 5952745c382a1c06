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
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

from recal import __version__
from recal.io import messages, topics
from recal.io.log_joins import (
    MAX_U64,
    Joins,
    check_log_time,
    joined_messages,
    plot_items,
    plot_log_times,
    publish_ns,
    publish_ns_array,
    rotation_bytes,
)
from recal.io.mcap_file import LIBRARY, Compression, McapFile
from recal.io.messages import SchemaSpec
from recal.io.recording import (
    GATEWAY,
    PathLike,
    part_path,
    recording_parts,
    sensor_topic,
    split_topic,
)
from recal.io.writer_state import (
    OpenPart,
    Tally,
    TopicBook,
    Trouble,
    WriteHealth,
    WriterOptions,
    fsync_and_close,
)
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["FILE_TO_FILE_FLUSH_S", "RecordingWriter", "WriteHealth"]

_TOPIC = re.compile(r"/[A-Za-z0-9][A-Za-z0-9_.\-]*/[A-Za-z0-9_.\-]+")
# the log's schema of each registered topic; a topic the registry does not know is logged as
# generic JSON (the writer is also a tool's: `recal import` and tests write topics of their own)
_SUFFIX_SCHEMAS: dict[str, SchemaSpec] = topics.log_schemas()


def _check_calibrated_suffix(topic_suffix: str) -> None:
    """A calibrated batch may go on any suffix but one reserved for another schema."""
    if _SUFFIX_SCHEMAS.get(topic_suffix, messages.CALIBRATED_SCHEMA) is not \
            messages.CALIBRATED_SCHEMA:
        raise ValueError(f"topic suffix {topic_suffix!r} is reserved for another schema")
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
        opts = WriterOptions.checked(
            chunk_size=chunk_size, flush_interval_s=flush_interval_s, rotate_bytes=rotate_bytes,
            rotate_s=rotate_s, compression=compression, fsync=fsync, metadata=metadata,
            background_compression=background_compression, backlog_bytes=backlog_bytes,
            log_batch_samples=log_batch_samples)
        self._base = Path(path)
        self._base.parent.mkdir(parents=True, exist_ok=True)
        self._prepare_target(overwrite)
        self._opts = opts
        self._clock = clock
        self._fsync_due = False  # flushed to the OS, not yet fsynced (see _flush_locked)
        self._lock = threading.RLock()
        self._paths: list[Path] = []
        self._topics = TopicBook()
        self._joins = Joins(opts.log_batch_samples)  # batches waiting for one message
        self._tally = Tally()
        self._trouble = Trouble()
        self._closed = False
        self._background_error: BaseException | None = None
        self._part: OpenPart
        self._last_flush_s = 0.0
        self._open_part()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if background_flush and self._opts.flush_interval_s != float("inf"):  # (never due)
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
        return self._tally.written

    @property
    def messages_flushed(self) -> int:
        """Messages that were in the file at the last flush (what a crash now would keep)."""
        return self._tally.flushed

    @property
    def flush_count(self) -> int:
        return self._tally.flushes

    @property
    def backlog_bytes(self) -> int | None:
        """How much may wait in memory while the file refuses writes (None: refusals raise)."""
        return self._opts.backlog_bytes

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
                   check_log_time(log_time_ns), raw=True, arrivals=arrivals)

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
                   check_log_time(log_time_ns), raw=False)

    def log_body(self, sensor_id: str, calibrated: CalibratedBatch, rotation: np.ndarray,
                 log_time_ns: int) -> None:
        """Log on ``/<sensor>/body`` that these calibrated samples (as logged on
        ``/<sensor>/calibrated``) rotated by ``rotation`` (3 x 3: ``R @ a``) are the body
        frame's: the samples' times and the rotation, joined like `log_calibrated`'s batches
        while the rotation stays (`messages.encode_body_rotation`). The body stream without
        a value the calibrated stream and the alignment already say."""
        self._hold(self._sensor_topic(sensor_id, "body"), sensor_id, calibrated,
                   check_log_time(log_time_ns), raw=False, rotation=rotation_bytes(rotation))

    def log_body_many(self, sensor_id: str,
                      items: Sequence[tuple[CalibratedBatch, np.ndarray | None, int]]) -> None:
        """`log_body` (rotation given) or `log_calibrated` on ``body`` (rotation None: the
        batch is the body's values) of each (batch, rotation, log time) in turn, in one call:
        the same messages (replay hands a pipeline step's body batches over at once)."""
        topic = self._sensor_topic(sensor_id, "body")
        with self._lock:
            self._check_writable()
            for batch, rotation, log_ns in items:
                self._joins.hold(topic, sensor_id, batch, check_log_time(log_ns), False, None,
                                 None if rotation is None else rotation_bytes(rotation),
                                 self._emit)
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
                self._joins.hold(topic, sensor_id, batch, check_log_time(log_ns), False, None,
                                 None, self._emit)
            self._maybe_flush()

    def write_json(self, topic: str, obj: Any, log_time_ns: int) -> bytes:
        """Log a JSON object; the schema follows the topic suffix (calibration, events,
        anything else a permissive object schema). Returns the encoded bytes."""
        spec = _SUFFIX_SCHEMAS.get(split_topic(topic)[1], messages.GENERIC_JSON_SCHEMA)
        if spec.message_encoding != "json":
            raise ValueError(f"topic {topic!r} carries {spec.name}, not JSON")
        data = messages.encode_json(obj)
        t_us = obj.get("t_us") if isinstance(obj, Mapping) else None
        publish = publish_ns(t_us if isinstance(t_us, (int, np.integer)) else None,
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
        self.write_encoded(topic, data, log_time_ns, publish_ns(t_us, int(log_time_ns)),
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
        log_ns = check_log_time(log_time_ns)
        with self._lock:
            phase = self._topics.plot_phase.get(sensor_id, 0)
            self._topics.plot_phase[sensor_id] = (phase + len(batch)) % every_n
        first = (-phase) % every_n
        if first >= len(batch):
            return 0  # most calls when samples are handled as they arrive: no numpy at all
        indices = np.arange(first, len(batch), every_n)
        if arrivals is None and len(indices) <= 16:  # a few samples: packed one by one
            items = plot_items(batch, indices, log_ns)
            self._write_many(topic, messages.PLOT_SCHEMA, items, log_ns)
            return len(items)
        log_times, call_log_ns = plot_log_times(batch, indices, log_ns, arrivals)
        self._write_fixed(topic, messages.PLOT_SCHEMA, messages.plot_payloads(batch, indices),
                          log_times, publish_ns_array(batch.t_us[indices]), call_log_ns)
        return len(indices)

    def write_encoded(self, topic: str, data: bytes, log_time_ns: int,
                      publish_time_ns: int | None = None, *,
                      schema: SchemaSpec | None = None) -> None:
        """Log already-encoded bytes (e.g. exactly what went on the bus).

        The schema defaults to the one the topic suffix implies (see the layout above).
        """
        log_ns = check_log_time(log_time_ns)
        if topic not in self._topics.specs and not _TOPIC.fullmatch(topic):
            raise ValueError(f"invalid topic {topic!r}: expected /<owner>/<name>")
        spec = schema or self._topics.specs.get(topic) or _SUFFIX_SCHEMAS.get(
            split_topic(topic)[1], messages.GENERIC_JSON_SCHEMA)
        publish = log_ns if publish_time_ns is None else min(max(int(publish_time_ns), 0),
                                                             MAX_U64)
        self._write_many(topic, spec, [(data, log_ns, publish)], log_ns)

    def flush(self) -> None:
        """Close the open chunk, flush and fsync the file now."""
        with self._lock:
            self._raise_background_error()
            if not self._closed:
                self._flush_locked()
            fd = self._take_fsync()
        fsync_and_close(fd)

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
            return self._trouble.health(self._tally, self._part.mcap, self._closed)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------

    def _sensor_topic(self, sensor_id: str, suffix: str) -> str:
        """`sensor_topic`, checked once per (sensor, suffix): a gateway writes each sample as
        it arrives, and the check (a regex) would otherwise run per message."""
        topic = self._topics.names.get((sensor_id, suffix))
        if topic is None:
            topic = self._topics.names[(sensor_id, suffix)] = sensor_topic(sensor_id, suffix)
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
        o = self._opts
        # Unbuffered: McapFile joins each chunk into one write itself, and a write the disk
        # refuses must leave nothing behind in a buffer (the file is cut back instead).
        file: IO[bytes] = open(path, "wb", buffering=0)  # closed in _finish_part
        mcap = McapFile(file, o.chunk_size, o.compression, o.background_compression,
                        o.backlog_bytes)
        mcap.start(profile="", library=LIBRARY)
        mcap.add_metadata("recal", {"version": __version__, "part": str(len(self._paths)),
                                    **o.metadata})
        self._paths.append(path)
        self._part = OpenPart(file, mcap)
        self._last_flush_s = self._clock()

    def _finish_part(self) -> None:
        m = self._part.mcap
        try:
            finished = m.finish()
            self._part.file.flush()
            if self._opts.fsync:
                self._fsync_checked(self._part.file.fileno())
        finally:
            self._part.file.close()
            self._tally.parts_out += m.messages_out
            self._tally.parts_dropped = (self._tally.parts_dropped[0] + m.dropped_messages,
                                   self._tally.parts_dropped[1] + m.dropped_samples)
        if not finished:
            self._trouble.unfinished.append(self._paths[-1])
            self._trouble.note(m.failure)
        self._tally.flushed = self._tally.parts_out

    def _fsync_checked(self, fd: int) -> None:
        """fsync; with a backlog budget a failure is counted, not raised."""
        try:
            os.fsync(fd)
        except OSError as exc:
            if self._opts.backlog_bytes is None:
                raise
            self._trouble.fsync_failed(exc)

    def _rotation_due(self, log_ns: int) -> bool:
        part, o = self._part, self._opts
        if part.messages == 0 or part.mcap.failure is not None:
            return False  # never leave an empty part behind, nor finish one the disk refuses
        if o.rotate_bytes is not None and part.mcap.position >= o.rotate_bytes:
            return True
        return o.rotate_ns is not None and log_ns - part.start_ns >= o.rotate_ns

    def _channel_id(self, topic: str, spec: SchemaSpec) -> int:
        known = self._topics.specs.setdefault(topic, spec)
        if known.name != spec.name:
            raise ValueError(f"topic {topic!r} carries {known.name}, not {spec.name}")
        channel_id = self._part.channel_ids.get(topic)
        if channel_id is None:
            schema_id = self._part.schema_ids.get(spec.name)
            if schema_id is None:
                schema_id = self._part.mcap.register_schema(spec.name, spec.encoding, spec.data)
                self._part.schema_ids[spec.name] = schema_id
            channel_id = self._part.mcap.register_channel(topic, spec.message_encoding, schema_id)
            self._part.channel_ids[topic] = channel_id
        return channel_id

    def _write_many(self, topic: str, spec: SchemaSpec,
                    items: Sequence[tuple[bytes, int, int]], call_log_ns: int,
                    samples: int = 0) -> None:
        """Append (data, log_time_ns, publish_time_ns) messages to one topic, in order;
        ``samples``: raw samples they hold (counted if they are dropped)."""
        self._append(topic, spec, call_log_ns, len(items),
                     lambda channel_id, seq: self._part.mcap.add_messages(channel_id, items, seq),
                     samples)

    def _write_fixed(self, topic: str, spec: SchemaSpec, payloads: np.ndarray,
                     log_times: np.ndarray, publish_times: np.ndarray, call_log_ns: int) -> None:
        """Like `_write_many` for messages that are the rows of a structured array."""
        self._append(topic, spec, call_log_ns, len(payloads),
                     lambda channel_id, seq: self._part.mcap.add_fixed(
                         channel_id, payloads, log_times, publish_times, seq))

    def _append(self, topic: str, spec: SchemaSpec, call_log_ns: int, count: int,
                add: Callable[[int, int], int], samples: int = 0) -> None:
        """Rotate if due, then ``add(channel_id, first_sequence)`` -> next sequence; ``add``
        reads ``self._part.mcap`` when called, i.e. the part open after any rotation."""
        with self._lock:
            self._check_writable()
            if self._rotation_due(call_log_ns):
                self._finish_part()
                self._open_part()
            if self._part.messages == 0:
                self._part.start_ns = call_log_ns
            channel_id = self._channel_id(topic, spec)
            self._part.mcap.open_samples += samples  # before add: it may end the chunk
            self._topics.sequence[topic] = add(channel_id, self._topics.sequence.get(topic, 0))
            self._part.messages += count
            self._tally.written += count
            failure = self._part.mcap.failure
            if failure is not None and self._trouble.since_s is None:
                self._trouble.track(failure, self._clock())  # a chunk just ended was refused
            self._maybe_flush()

    def _hold(self, topic: str, sensor_id: str, batch: RawBatch | CalibratedBatch, log_ns: int,
              raw: bool, arrivals: messages.Arrivals | None = None,
              rotation: bytes | None = None) -> None:
        """Add a batch to its topic's waiting message (a list append per arrival: the join
        and the encoding happen once per message)."""
        with self._lock:
            self._check_writable()
            self._joins.hold(topic, sensor_id, batch, log_ns, raw, arrivals, rotation,
                             self._emit)
            self._maybe_flush()

    def _emit(self, topic: str) -> None:
        """Write a topic's waiting batches as one compact message (lock held)."""
        p = self._joins.pending.pop(topic)  # first: the write may flush, which emits the rest
        spec, datas, samples = joined_messages(p, self._opts.log_batch_samples)
        for data in datas:
            self._write_many(topic, spec, [(data, p.log_ns, p.publish_ns)], p.log_ns,
                             samples=samples)

    def _emit_pending(self) -> None:
        for topic in list(self._joins.pending):
            if topic in self._joins.pending:
                self._emit(topic)

    def _maybe_flush(self) -> None:
        if self._clock() - self._last_flush_s >= self._opts.flush_interval_s:
            self._flush_locked()

    def _flush_locked(self) -> None:
        self._last_flush_s = now_s = self._clock()
        self._emit_pending()  # (their writes see the flush just stamped, so do not recurse)
        m = self._part.mcap
        if self._tally.flushed == self._tally.written and not m.waiting_bytes:
            return  # nothing new: skip the fsync
        m.flush()  # ends the open chunk (and tries again what the disk refused)
        self._trouble.track(m.failure, now_s)
        if m.failure is not None:
            return  # nothing new in the file: no fsync
        # The fsync itself (milliseconds) happens outside the lock, on the flush thread: a
        # writer calling in to log a sample must not wait for the disk (the gateway's
        # latency p99 showed it). The data is with the OS already, so a killed process
        # loses nothing by this; a power cut may lose up to a quarter interval more.
        self._fsync_due = self._opts.fsync
        self._tally.flushed = self._tally.parts_out + m.messages_out
        self._tally.flushes += 1

    def _take_fsync(self) -> int | None:
        """With the lock held: a duplicate descriptor to fsync if one is due (the duplicate
        stays valid should the file be rotated or closed meanwhile), else None."""
        if not self._fsync_due or self._closed:
            return None
        self._fsync_due = False
        return os.dup(self._part.file.fileno())

    def _flush_loop(self) -> None:
        # Wakes several times per interval so a quiet writer is still flushed on time. It
        # outlives errors: a disk that was full takes data again, and fsync is still wanted.
        while not self._stop.wait(self._opts.flush_interval_s / 4):
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
                fsync_and_close(fd)
            except OSError as exc:
                with self._lock:
                    self._background_failed(exc)

    def _background_failed(self, exc: Exception) -> None:
        """An error on the flush thread (lock held): kept for the owner's next call, or with a
        backlog budget (where write refusals never raise) counted in ``health``."""
        if self._opts.backlog_bytes is None:
            self._background_error = exc
            return
        self._trouble.background(exc)

    def _check_writable(self) -> None:
        """Raise what the background thread met, or that the writer is closed (lock held)."""
        self._raise_background_error()
        if self._closed:
            raise ValueError("recording writer is closed")

    def _raise_background_error(self) -> None:
        if self._background_error is not None:
            error, self._background_error = self._background_error, None
            raise RuntimeError("background flush of the recording failed") from error

