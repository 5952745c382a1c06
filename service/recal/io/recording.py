"""MCAP recordings: topic layout, a crash-tolerant writer, fast readers, and repair.

Topic layout (one MCAP file, or a rotated series ``rec.mcap``, ``rec-0001.mcap``, ...):

| topic                 | schema (encoding)                 | one message is                    |
|-----------------------|-----------------------------------|-----------------------------------|
| /<sensor>/raw         | recal.RawBatch (protobuf)         | a batch of raw samples            |
| /<sensor>/calibrated  | recal.CalibratedBatch (protobuf)  | the batch calibrated, sensor frame|
| /<sensor>/body        | recal.CalibratedBatch (protobuf)  | the batch rotated to body frame   |
| /<sensor>/calibration | recal.CalibrationState (json)     | calibration state after an update |
| /<sensor>/plot        | recal.PlotSample (protobuf)       | one calibrated sample (decimated) |
| /<sensor>/events      | recal.Event (json)                | a sensor event                    |
| /gateway/events       | recal.Event (json)                | a gateway event                   |

Sensor ids are ``[A-Za-z0-9][A-Za-z0-9_.-]*`` and not ``gateway``, so they are safe in MCAP
topics and Zenoh key expressions alike. Protobuf schemas are stored as a serialized
``FileDescriptorSet`` and JSON schemas as JSON Schema, which Foxglove decodes.

Times: ``log_time`` is when the gateway logged the message (ns, the caller's clock);
``publish_time`` is the device time of the batch's first sample (ns), or of the sample for
plot messages, or the log time when there is none. Plot messages are an exception for
``log_time``: each sample gets the batch's log time moved back by its device-time distance to
the batch's last sample, so Foxglove's Plot panel (which plots against log time) draws the
samples spread out instead of stacked. ``sequence`` counts messages per topic from 0, across
rotated files, so gaps and duplicates are visible.

Readers take one file or a sequence of files (``recording_parts(path)`` lists a rotated
series) and yield messages in file order; ``repair`` works on one file at a time.

Crash tolerance: chunks are small (32 KiB by default) and the open chunk is closed, the file
flushed and ``fsync``ed at least every ``flush_interval_s``, so a SIGKILL or power cut loses about
that much; ``repair`` turns the truncated file into a valid indexed one.

A full disk (``backlog_bytes``, the daemon's setting): a write the file refuses does not raise.
The file is cut back to the end of its last whole record (readable by ``repair`` as it stands),
and the refused output waits in memory, each chunk compressed once, until a later flush gets
it written in the same file; past ``backlog_bytes`` the oldest waiting chunks are dropped and
counted (``RecordingWriter.health``). Tools that write a file (replay, import) keep the default:
a refused write raises.

Memory: the writer holds the open chunk and a few counters; the chunk indexes the summary needs
wait in a temporary file (a week flushed every second is ~600k chunks), so a recording of any
length is written in constant memory.
"""

from __future__ import annotations

import collections
import errno
import fnmatch
import functools
import os
import queue
import re
import struct
import tempfile
import threading
import time
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal, NamedTuple

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.reader import McapReader, make_reader
from mcap.records import (
    Attachment,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import StreamReader
from mcap.summary import Summary
from mcap.writer import LIBRARY_IDENTIFIER, MCAP0_MAGIC, CompressionType
from mcap.writer import Writer as _McapWriter

from recal import __version__
from recal.io import messages
from recal.io.messages import SchemaSpec
from recal.samples import CalibratedBatch, RawBatch

__all__ = [
    "GATEWAY",
    "LoggedMessage",
    "RecordingError",
    "RecordingSummary",
    "RecordingWriter",
    "RepairReport",
    "TopicSummary",
    "WriteHealth",
    "iter_calibrated",
    "iter_json",
    "iter_messages",
    "iter_plot",
    "iter_raw",
    "iter_raw_logged",
    "metadata",
    "pick_sensor",
    "read_all_calibrated",
    "read_all_raw",
    "recording_parts",
    "refuse_input_as_output",
    "repair",
    "sensor_topic",
    "sensors",
    "split_topic",
    "summary",
]

GATEWAY = "gateway"
"""Owner segment of the gateway's own topics (``/gateway/events``); not a valid sensor id."""

Compression = Literal["zstd", "lz4", "none"]
PathLike = str | os.PathLike[str]
Paths = PathLike | Sequence[PathLike]

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}
_SENSOR_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")
_TOPIC = re.compile(r"/[A-Za-z0-9][A-Za-z0-9_.\-]*/[A-Za-z0-9_.\-]+")
_SUFFIX_SCHEMAS: dict[str, SchemaSpec] = {
    "raw": messages.RAW_SCHEMA,
    "calibrated": messages.CALIBRATED_SCHEMA,
    "body": messages.CALIBRATED_SCHEMA,
    "calibration": messages.CALIBRATION_STATE_SCHEMA,
    "plot": messages.PLOT_SCHEMA,
    "events": messages.EVENT_SCHEMA,
}
_MAX_U64 = 2**64 - 1
_MAX_PARTS = 9999
_LIBRARY = f"recal/{__version__}; {LIBRARY_IDENTIFIER}"


class RecordingError(ValueError):
    """A file that is not a readable, finished MCAP recording (try ``repair``)."""


# ---------------------------------------------------------------------------------------------
# Topics and paths
# ---------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4096)
def sensor_topic(sensor_id: str, suffix: str) -> str:
    """``/<sensor_id>/<suffix>``, after checking the sensor id is topic- and key-safe."""
    if not _SENSOR_ID.fullmatch(sensor_id) or sensor_id == GATEWAY:
        raise ValueError(f"invalid sensor id {sensor_id!r}: use [A-Za-z0-9][A-Za-z0-9_.-]* "
                         f"and not {GATEWAY!r}")
    if not suffix or "/" in suffix:
        raise ValueError(f"invalid topic suffix {suffix!r}")
    return f"/{sensor_id}/{suffix}"


def split_topic(topic: str) -> tuple[str, str]:
    """(owner, suffix) of ``/<owner>/<suffix>``; owner is a sensor id or ``gateway``."""
    owner, _, suffix = topic.lstrip("/").rpartition("/")
    return owner, suffix


def _part_path(base: Path, index: int) -> Path:
    return base if index == 0 else base.with_name(f"{base.stem}-{index:04d}{base.suffix}")


def recording_parts(path: PathLike) -> list[Path]:
    """The file ``path`` followed by its rotated parts ``stem-0001.mcap``, ... that exist."""
    base = Path(path)
    parts = [base]
    for index in range(1, _MAX_PARTS + 1):
        part = _part_path(base, index)
        if not part.exists():
            break
        parts.append(part)
    return parts


def _as_paths(paths: Paths) -> list[Path]:
    if isinstance(paths, (str, os.PathLike)):
        return [Path(paths)]
    return [Path(p) for p in paths]


# ---------------------------------------------------------------------------------------------
# MCAP file writer (records)
# ---------------------------------------------------------------------------------------------

_RECORD_HEADER = np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel_id", "<u2"),
                           ("sequence", "<u4"), ("log_time", "<u8"), ("publish_time", "<u8")])
_MESSAGE_RECORD = struct.Struct("<BQHIQQ")  # the same 31 bytes, one message at a time
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # message record fields before the data
_CHUNK_FIXED = struct.Struct("<BQQQQI")  # opcode, length, start, end, uncompressed size, crc
_MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, length, channel id, records length
_COMPRESSION_NAMES = {"zstd": "zstd", "lz4": "lz4", "none": ""}
# start, end, offset, length, message index length, compressed size, size, channels
_CHUNK_INDEX_SPILL = struct.Struct("<QQQQQQQH")
_CHANNEL_OFFSET = struct.Struct("<HQ")  # channel id, its message index record's offset


class _ChunkInfo(NamedTuple):
    """What a chunk's index needs besides its position in the file."""

    start_ns: int
    end_ns: int
    length: int  # the chunk record, without its message indexes
    packed: int  # compressed size
    size: int  # uncompressed size
    index_offsets: dict[int, int]  # channel id -> its message index, from the chunk's start


@dataclass
class _Pending:
    """Bytes for the file, in order: loose records (header, metadata, schema and channel
    definitions), or a compressed chunk followed by its message indexes."""

    data: bytes
    chunk: _ChunkInfo | None = None
    metadata_name: str | None = None
    messages: int = 0
    samples: int = 0  # raw samples in those messages
    defs: bytes = b""  # schema and channel records inside the chunk


class _McapFile:
    """MCAP records, laid out as ``mcap.writer.Writer`` lays them out: schemas, channels and
    messages in chunks, a message index per channel after each chunk, then a summary
    (schemas, channels, statistics, chunk and metadata indexes, summary offsets) and footer.

    Why not that Writer: it builds a Python object and several small writes per message, which
    cost more than calibrating the samples. Here a message is one ``struct.pack`` and a batch
    of fixed-size messages (the plot topic) one numpy array, the chunk is joined once, and one
    zstd context is reused.

    With ``background``, a thread compresses finished chunks and writes everything to the
    stream, in order (zstd, lz4, crc32 and file writes release the GIL, so this runs beside
    the caller on another core). At most ``_QUEUED_CHUNKS`` chunks wait, so memory stays
    bounded; ``flush`` and ``finish`` wait until the thread has written everything, and an
    error in the thread is raised by the next call.

    With ``backlog_bytes`` (not with ``background``), a write the file refuses (a full disk)
    does not raise: the file is cut back to the end of its last whole record, so it stays
    readable and repairable, and what was refused waits, in order and compressed once, until
    :meth:`retry` gets it written. Beyond ``backlog_bytes`` the oldest waiting chunks are
    dropped and counted (``dropped_messages``, ``dropped_samples``). ``stream`` must then be
    unbuffered (a buffered writer keeps refused bytes and cannot be cut back).
    """

    _QUEUED_CHUNKS = 4

    def __init__(self, stream: IO[bytes], chunk_size: int, compression: Compression,
                 background: bool = False, backlog_bytes: int | None = None) -> None:
        if background and backlog_bytes is not None:
            raise ValueError("a write backlog needs the writes on the caller's thread")
        self._out = stream
        self._chunk_size = chunk_size
        self._compression = _COMPRESSION_NAMES[compression]
        self._zstd = zstandard.ZstdCompressor() if compression == "zstd" else None
        self.position = 0  # bytes written to the stream (by the thread, if there is one)
        self._pieces: list[bytes] = []  # records of the open chunk
        self._size = 0
        self._times: dict[int, list[int]] = {}  # per channel: log times, chunk offsets
        self._offsets: dict[int, list[int]] = {}
        self._chunk_start = self._chunk_end = 0
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        # Chunk indexes go to a temporary file until the summary is written: a week-long
        # recording flushed every second has ~600k chunks, too many to keep in memory.
        self._chunk_spill: IO[bytes] | None = None
        self._chunks = 0
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._messages = 0
        self._start_ns = self._end_ns = 0
        self._error: BaseException | None = None
        # Output waiting for the file, in order; empty except while the file refuses writes.
        self._backlog: collections.deque[_Pending] = collections.deque()
        self._backlog_size = 0
        self._backlog_limit = backlog_bytes
        self.failure: OSError | None = None  # the refusal that writing waits on, if any
        self.dropped_messages = 0  # dropped from the backlog (over its budget, or at finish)
        self.dropped_samples = 0  # raw samples in those messages
        self.messages_out = 0  # messages in the file
        self.open_samples = 0  # raw samples in the open chunk (the owner adds them)
        self._open_defs: list[bytes] = []  # schema and channel records in the open chunk
        self._jobs: queue.Queue[tuple[Callable[..., None], tuple] | None] | None = None
        self._thread: threading.Thread | None = None
        if background:
            self._jobs = queue.Queue(self._QUEUED_CHUNKS)
            self._thread = threading.Thread(target=self._work, name="recal-mcap-chunks",
                                            daemon=True)
            self._thread.start()

    # -- output, in order, on the caller's thread or the writer thread ------------------------
    def _submit(self, job: Callable[..., None], *args: Any) -> None:
        self._raise_error()
        if self._jobs is None:
            job(*args)
        else:
            self._jobs.put((job, args))

    def _work(self) -> None:
        assert self._jobs is not None
        while True:
            item = self._jobs.get()
            try:
                if item is None:
                    return
                if self._error is None:  # after a failure the file is broken: drop the rest
                    item[0](*item[1])
            except BaseException as exc:  # handed to the owner's next call
                self._error = exc
            finally:
                self._jobs.task_done()

    def _drain(self) -> None:
        """Wait until every submitted write is in the stream."""
        if self._jobs is not None:
            self._jobs.join()
        self._raise_error()

    def _raise_error(self) -> None:
        if self._error is not None:
            raise RuntimeError("writing the recording failed") from self._error

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:  # an unbuffered file may take part of it (the last room on a disk)
            n = self._out.write(view)
            if not n:
                raise OSError(errno.EIO, "the file took no bytes")
            view = view[n:]
        self.position += len(data)

    # -- output that waits (a full disk) ------------------------------------------------------
    @property
    def waiting_bytes(self) -> int:
        """Bytes refused by the file and waiting for it."""
        return self._backlog_size

    @property
    def waiting_messages(self) -> int:
        return sum(e.messages for e in self._backlog)

    def _queue(self, entry: _Pending) -> None:
        """Output in order: written now, unless earlier output still waits."""
        self._backlog.append(entry)
        self._backlog_size += len(entry.data)
        if self.failure is None:
            self._pump()
        if self._backlog_limit is not None:
            self._trim(self._backlog_limit)

    def _pump(self) -> bool:
        """Write what waits, in order; False if the file refused (it is cut back to its last
        whole record, and the rest keeps waiting). Raises without a backlog budget."""
        while self._backlog:
            entry = self._backlog[0]
            start = self.position
            try:
                self._write(entry.data)
                if entry.chunk is not None:
                    self._index_chunk(start, entry)
            except OSError as exc:
                if self._backlog_limit is None:
                    raise
                self._cut_back(start)
                self.failure = exc
                return False
            if entry.metadata_name is not None:
                self._metadata_indexes.append(MetadataIndex(
                    offset=start, length=len(entry.data), name=entry.metadata_name))
            self._backlog.popleft()
            self._backlog_size -= len(entry.data)
            self.messages_out += entry.messages
        self.failure = None
        return True

    def retry(self) -> bool:
        """Try the waiting output again; True once nothing waits."""
        if not self._backlog:  # (all of it may have been dropped)
            self.failure = None
            return True
        return self._pump()

    def _cut_back(self, position: int) -> None:
        """End the file at ``position`` (a record boundary): a refused write may have left
        part of a record, which would make everything after it unreadable."""
        self.position = position
        self._out.seek(position)
        self._out.truncate(position)

    def _trim(self, limit: int) -> None:
        """Drop the oldest waiting chunks until at most ``limit`` bytes wait. Schema and channel
        records a dropped chunk carried stay, as records of their own: later chunks need them."""
        i = 0
        while self._backlog_size > limit and i < len(self._backlog):
            entry = self._backlog[i]
            if not entry.messages:
                i += 1
                continue
            self.dropped_messages += entry.messages
            self.dropped_samples += entry.samples
            self._backlog_size -= len(entry.data)
            if entry.defs:
                self._backlog[i] = _Pending(entry.defs)
                self._backlog_size += len(entry.defs)
                i += 1
            else:
                del self._backlog[i]

    @staticmethod
    def _record(rec: Any) -> bytes:
        builder = RecordBuilder()
        rec.write(builder)
        return builder.end()

    # -- records outside chunks ---------------------------------------------------------------
    def start(self, profile: str, library: str) -> None:
        self._submit(self._queue, _Pending(MCAP0_MAGIC + self._record(Header(
            profile=profile, library=library))))

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        self._submit(self._queue, _Pending(self._record(Metadata(name=name, metadata=dict(
            data))), metadata_name=name))

    # -- records inside chunks ----------------------------------------------------------------
    def _append(self, data: bytes) -> None:
        self._pieces.append(data)
        self._size += len(data)

    def _append_definition(self, record: bytes) -> None:
        self._append(record)
        self._open_defs.append(record)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._append_definition(self._record(schema))
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id, metadata={})
        self._channels.append(channel)
        self._counts[channel.id] = 0
        self._append_definition(self._record(channel))
        return channel.id

    def _note(self, channel_id: int, log_times: list[int], offsets: list[int]) -> None:
        """Index and statistics for messages just appended (log times in write order)."""
        lo, hi = min(log_times), max(log_times)
        if not self._times:  # first message of the chunk
            self._chunk_start, self._chunk_end = lo, hi
        else:
            self._chunk_start = min(self._chunk_start, lo)
            self._chunk_end = max(self._chunk_end, hi)
        if self._messages == 0:
            self._start_ns, self._end_ns = lo, hi
        else:
            self._start_ns, self._end_ns = min(self._start_ns, lo), max(self._end_ns, hi)
        self._times.setdefault(channel_id, []).extend(log_times)
        self._offsets.setdefault(channel_id, []).extend(offsets)
        self._counts[channel_id] += len(log_times)
        self._messages += len(log_times)
        if self._size > self._chunk_size:
            self.end_chunk()

    def add_messages(self, channel_id: int, items: Sequence[tuple[bytes, int, int]],
                     sequence: int) -> int:
        """Append (data, log ns, publish ns) messages; returns the next sequence number."""
        if not items:
            return sequence
        pack, pieces = _MESSAGE_RECORD.pack, self._pieces
        offsets, log_times, size = [], [], self._size
        for data, log_ns, publish_ns in items:
            head = pack(Opcode.MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence,
                        log_ns, publish_ns)
            pieces.append(head)
            pieces.append(data)
            offsets.append(size)
            log_times.append(log_ns)
            size += len(head) + len(data)
            sequence = (sequence + 1) & 0xFFFFFFFF  # MCAP sequence is uint32
        self._size = size
        self._note(channel_id, log_times, offsets)
        return sequence

    def add_fixed(self, channel_id: int, payloads: np.ndarray, log_times: np.ndarray,
                  publish_times: np.ndarray, sequence: int) -> int:
        """Append one message per row of a structured array (each row is a message's bytes),
        built as one array of records; returns the next sequence number."""
        n = len(payloads)
        if n == 0:
            return sequence
        records = np.empty(n, [("head", _RECORD_HEADER), ("body", payloads.dtype)])
        head = records["head"]
        head["opcode"] = Opcode.MESSAGE
        head["length"] = _MESSAGE_FIXED + payloads.dtype.itemsize
        head["channel_id"] = channel_id
        head["sequence"] = (sequence + np.arange(n, dtype=np.uint64)) & 0xFFFFFFFF
        head["log_time"] = log_times
        head["publish_time"] = publish_times
        records["body"] = payloads
        offsets = self._size + records.dtype.itemsize * np.arange(n)
        self._append(records.tobytes())
        self._note(channel_id, np.asarray(log_times, np.uint64).tolist(), offsets.tolist())
        return (sequence + n) & 0xFFFFFFFF

    def end_chunk(self) -> None:
        """Hand the open chunk and its message indexes to the output (nothing if empty)."""
        if not self._times:  # schema and channel records alone wait for the next chunk,
            return  # as in mcap's Writer (a chunk without messages is not written)
        self._submit(self._write_chunk, b"".join(self._pieces), self._chunk_start,
                     self._chunk_end, self._times, self._offsets, self.open_samples,
                     b"".join(self._open_defs))
        self._pieces, self._size = [], 0
        self._times, self._offsets = {}, {}
        self.open_samples, self._open_defs = 0, []

    def _write_chunk(self, data: bytes, start_ns: int, end_ns: int,
                     times: dict[int, list[int]], offsets: dict[int, list[int]],
                     samples: int, defs: bytes) -> None:
        """Compress the chunk (once, whatever happens to the write) and queue it with its
        message indexes; their file offsets are known when it is written."""
        if self._zstd is not None:
            packed = self._zstd.compress(data)
        elif self._compression == "lz4":
            packed = lz4.frame.compress(data)
        else:
            packed = data
        name = self._compression.encode()
        body_len = 8 + 8 + 8 + 4 + 4 + len(name) + 8 + len(packed)
        pieces = [_CHUNK_FIXED.pack(Opcode.CHUNK, body_len, start_ns, end_ns, len(data),
                                    zlib.crc32(data)),
                  struct.pack("<I", len(name)), name, struct.pack("<Q", len(packed)), packed]
        chunk_length = 1 + 8 + body_len
        index_offsets = {}  # channel id -> its message index, relative to the chunk's start
        at = chunk_length
        for channel_id, log_times in times.items():
            pairs = np.empty((len(log_times), 2), "<u8")
            pairs[:, 0] = log_times
            pairs[:, 1] = offsets[channel_id]
            index_offsets[channel_id] = at
            pieces.append(_MESSAGE_INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 6 + pairs.nbytes,
                                                   channel_id, pairs.nbytes) + pairs.tobytes())
            at += _MESSAGE_INDEX_HEAD.size + pairs.nbytes
        self._queue(_Pending(b"".join(pieces), _ChunkInfo(
            start_ns, end_ns, chunk_length, len(packed), len(data), index_offsets),
            messages=sum(len(t) for t in times.values()), samples=samples, defs=defs))

    def _index_chunk(self, start: int, entry: _Pending) -> None:
        """The chunk index of a chunk just written at ``start``, to the spill file."""
        info = entry.chunk
        assert info is not None
        if self._chunk_spill is None:
            self._chunk_spill = tempfile.TemporaryFile(prefix="recal-chunk-index-")
        self._chunk_spill.write(_CHUNK_INDEX_SPILL.pack(
            info.start_ns, info.end_ns, start, info.length, len(entry.data) - info.length,
            info.packed, info.size, len(info.index_offsets)) + b"".join(
                _CHANNEL_OFFSET.pack(c, start + o) for c, o in info.index_offsets.items()))
        self._chunks += 1

    def _chunk_indexes(self) -> Iterator[ChunkIndex]:
        """The spilled chunk indexes, read back in order."""
        if self._chunk_spill is None:
            return
        spill = self._chunk_spill
        spill.flush()
        spill.seek(0)
        for _ in range(self._chunks):
            start, end, offset, length, mi_length, packed, size, n = _CHUNK_INDEX_SPILL.unpack(
                spill.read(_CHUNK_INDEX_SPILL.size))
            pairs = spill.read(_CHANNEL_OFFSET.size * n)
            yield ChunkIndex(
                message_start_time=start, message_end_time=end, chunk_start_offset=offset,
                chunk_length=length,
                message_index_offsets=dict(_CHANNEL_OFFSET.iter_unpack(pairs)),
                message_index_length=mi_length, compression=self._compression,
                compressed_size=packed, uncompressed_size=size)

    def flush(self) -> None:
        """End the open chunk, wait until it is written (or, with a backlog, try again what
        waits), flush the stream."""
        if self.failure is not None and not self.retry():
            return  # still refused: the open chunk keeps filling (fewer, better chunks wait)
        self.end_chunk()
        if self._jobs is None:  # with the thread, it alone writes
            self.retry()
        self._drain()
        self._out.flush()

    def finish(self) -> bool:
        """The last chunk, data end, summary, footer and closing magic; stops the thread.

        Returns False, with a backlog budget, when the file refused to take it all: what still
        waited is dropped (counted), and the file ends at its last whole record, without a
        summary (``repair`` reads it).
        """
        try:
            self.end_chunk()
            self._drain()
        finally:
            if self._jobs is not None and self._thread is not None:
                self._jobs.put(None)
                self._thread.join()
                self._jobs = None
        try:
            if not self.retry():
                self._trim(0)
                return False
            data_end = self.position
            try:
                self._write_summary_section()
            except OSError as exc:
                if self._backlog_limit is None:
                    raise
                self._cut_back(data_end)
                self.failure = exc
                return False
            return True
        finally:
            if self._chunk_spill is not None:
                self._chunk_spill.close()

    def _write_summary_section(self) -> None:
        self._write(self._record(DataEnd(data_section_crc=0)))
        summary_start = self.position
        groups: list[tuple[int, Iterable[Any]]] = [
            (Opcode.SCHEMA, self._schemas), (Opcode.CHANNEL, self._channels),
            (Opcode.STATISTICS, [Statistics(
                message_count=self._messages, schema_count=len(self._schemas),
                channel_count=len(self._channels), attachment_count=0,
                metadata_count=len(self._metadata_indexes),
                chunk_count=self._chunks, message_start_time=self._start_ns,
                message_end_time=self._end_ns, channel_message_counts=dict(self._counts))]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes()),
            (Opcode.METADATA_INDEX, self._metadata_indexes)]
        crc = 0
        offsets = []
        for opcode, records in groups:  # written as they are built: the summary can be big
            group_start = self.position
            builder = RecordBuilder()
            for record in records:
                record.write(builder)
                if builder.count >= 1 << 20:
                    crc = self._write_summary(builder.end(), crc)
            crc = self._write_summary(builder.end(), crc)
            if self.position > group_start:
                offsets.append(SummaryOffset(group_opcode=opcode, group_start=group_start,
                                             group_length=self.position - group_start))
        offset_start = self.position
        builder = RecordBuilder()
        for offset in offsets:
            offset.write(builder)
        crc = self._write_summary(builder.end(), crc)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start),
                         crc)
        footer = Footer(summary_start=summary_start, summary_offset_start=offset_start,
                        summary_crc=crc)
        self._write(self._record(footer) + MCAP0_MAGIC)
        self._out.flush()

    def _write_summary(self, data: bytes, crc: int) -> int:
        self._write(data)
        return zlib.crc32(data, crc)


# ---------------------------------------------------------------------------------------------
# Writer
# ---------------------------------------------------------------------------------------------

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


def _check_log_time(log_time_ns: int) -> int:
    value = int(log_time_ns)
    if not 0 <= value <= _MAX_U64:
        raise ValueError(f"log_time_ns must be an unsigned 64-bit integer, got {log_time_ns}")
    return value


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


class RecordingWriter:
    """Writes the topic layout above to MCAP, flushing and rotating as it goes.

    Thread-safe: one lock guards the file, so a background thread can flush while the owner
    writes. The caller's clock gives every message time; ``clock`` (monotonic seconds) is used
    only to decide when a flush is due.

    Args:
        path: the first file; rotated parts are ``<stem>-0001<suffix>``, ``-0002``, ...
        chunk_size: uncompressed bytes after which a chunk is closed. Small chunks bound what a
            crash loses; see platform facts (1 MiB chunks lost 45 % of a killed file).
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
    """

    def __init__(self, path: PathLike, *, chunk_size: int = 32 * 1024,
                 flush_interval_s: float = 1.0, rotate_bytes: int | None = None,
                 rotate_s: float | None = None, compression: Compression = "zstd",
                 clock: Callable[[], float] = time.monotonic, background_flush: bool = True,
                 fsync: bool = True, metadata: Mapping[str, str] | None = None,
                 overwrite: bool = False, background_compression: bool = False,
                 backlog_bytes: int | None = None) -> None:
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}")
        if chunk_size <= 0 or flush_interval_s <= 0:
            raise ValueError("chunk_size and flush_interval_s must be positive")
        if (rotate_bytes is not None and rotate_bytes <= 0) or (rotate_s is not None
                                                               and rotate_s <= 0):
            raise ValueError("rotate_bytes and rotate_s must be positive (or None)")
        if backlog_bytes is not None and (backlog_bytes < 0 or background_compression):
            raise ValueError("backlog_bytes must be >= 0, and not with background_compression")
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
        if background_flush:
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
        """Log a raw batch on ``/<sensor>/raw``; returns the encoded bytes (for the bus)."""
        data = messages.encode_raw(sensor_id, batch)
        first = int(batch.t_us[0]) if len(batch) else None
        log_ns = _check_log_time(log_time_ns)
        self._write_many(self._sensor_topic(sensor_id, "raw"), messages.RAW_SCHEMA,
                         [(data, log_ns, _publish_ns(first, log_ns))], log_ns,
                         samples=len(batch))
        return data

    def write_calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                         topic_suffix: str = "calibrated") -> bytes:
        """Log a calibrated batch on ``/<sensor>/<topic_suffix>``; returns the encoded bytes."""
        if _SUFFIX_SCHEMAS.get(topic_suffix, messages.CALIBRATED_SCHEMA) is not \
                messages.CALIBRATED_SCHEMA:
            raise ValueError(f"topic suffix {topic_suffix!r} is reserved for another schema")
        data = messages.encode_calibrated(sensor_id, batch)
        first = int(batch.t_us[0]) if len(batch) else None
        self.write_encoded(self._sensor_topic(sensor_id, topic_suffix), data, log_time_ns,
                           _publish_ns(first, int(log_time_ns)),
                           schema=messages.CALIBRATED_SCHEMA)
        return data

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
                   every_n: int = 10) -> int:
        """Log every ``every_n``-th sample as a plot message; returns how many were written.

        Decimation continues across batches (a per-sensor phase), so the plot rate is steady
        whatever the batch sizes.
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
        path = _part_path(self._base, len(self._paths))
        # Unbuffered: _McapFile joins each chunk into one write itself, and a write the disk
        # refuses must leave nothing behind in a buffer (the file is cut back instead).
        self._file: IO[bytes] = open(path, "wb", buffering=0)  # closed in _finish_part
        self._mcap = _McapFile(self._file, self._chunk_size, self._compression,
                               self._background_compression, self._backlog_bytes)
        self._mcap.start(profile="", library=_LIBRARY)
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
            self._raise_background_error()
            if self._closed:
                raise ValueError("recording writer is closed")
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
        m = self._mcap
        if self._messages_flushed == self._messages_written and not m.waiting_bytes:
            return  # nothing new: skip the fsync
        m.flush()  # ends the open chunk (and tries again what the disk refused)
        self._track_failure(now_s)
        if m.failure is not None:
            return  # nothing new in the file: no fsync
        # The fsync itself (~6 ms here) happens outside the lock, on the flush thread: a
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

    def _raise_background_error(self) -> None:
        if self._background_error is not None:
            error, self._background_error = self._background_error, None
            raise RuntimeError("background flush of the recording failed") from error


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
# ---------------------------------------------------------------------------------------------

class LoggedMessage(NamedTuple):
    """One message as logged, undecoded."""

    topic: str
    schema_name: str
    message_encoding: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int


def _open_summary(f: IO[bytes], path: Path) -> tuple[McapReader, Summary | None]:
    try:
        reader = make_reader(f)
        return reader, reader.get_summary()
    except Exception as exc:  # the mcap reader raises many types on a damaged tail
        raise RecordingError(f"{path} is not a finished MCAP file ({exc}); recover what it "
                             f"holds with: recal repair {path} --out FIXED.mcap") from exc


def _iter_file(path: Path, want: Callable[[Channel, str], bool]) -> Iterator[LoggedMessage]:
    with open(path, "rb") as f:
        reader, info = _open_summary(f, path)
        if info is None or not info.chunk_indexes:
            yield from _iter_unindexed(reader, want)
            return
        wanted = {cid: (c.topic, _schema_name(info.schemas.get(c.schema_id)),
                        c.message_encoding)
                  for cid, c in info.channels.items()
                  if want(c, _schema_name(info.schemas.get(c.schema_id)))}
        if not wanted:
            return
        decompressor = zstandard.ZstdDecompressor()
        for index in sorted(info.chunk_indexes, key=lambda i: i.chunk_start_offset):
            # Message indexes say which channels a chunk holds; skip chunks without ours.
            if index.message_index_offsets and not wanted.keys() & index.message_index_offsets:
                continue
            for cid, sequence, log_ns, publish_ns, data in _chunk_messages(
                    f, index, decompressor, path):
                meta = wanted.get(cid)
                if meta is not None:
                    yield LoggedMessage(*meta, data, log_ns, publish_ns, sequence)


def _iter_unindexed(reader: McapReader, want: Callable[[Channel, str], bool]
                    ) -> Iterator[LoggedMessage]:
    """Files without chunk indexes (unchunked writers): the mcap reader scans them."""
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        name = _schema_name(schema)
        if want(channel, name):
            yield LoggedMessage(channel.topic, name, channel.message_encoding, message.data,
                                message.log_time, message.publish_time, message.sequence)


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def _chunk_messages(f: IO[bytes], index: ChunkIndex, decompressor: Any, path: Path
                    ) -> Iterator[tuple[int, int, int, int, bytes]]:
    """(channel id, sequence, log ns, publish ns, data) of the messages in one chunk.

    Reads the chunk with one read and walks it with struct, reusing one zstd context: about
    twice as fast as the mcap reader's per-record stream reads, and reading speed is what
    replay and tests wait on.
    """
    f.seek(index.chunk_start_offset)
    blob = f.read(index.chunk_length)
    try:
        opcode, _ = _RECORD_HEAD.unpack_from(blob, 0)
        if opcode != Opcode.CHUNK:
            raise ValueError(f"opcode {opcode} where the index points to a chunk")
        pos = _RECORD_HEAD.size
        _, _, raw_size, _, name_len = _CHUNK_HEAD.unpack_from(blob, pos)
        pos += _CHUNK_HEAD.size
        compression = blob[pos:pos + name_len].decode()
        (data_len,) = struct.unpack_from("<Q", blob, pos + name_len)
        pos += name_len + 8
        body = _decompress(compression, blob[pos:pos + data_len], raw_size, decompressor)
    except (ValueError, struct.error, zstandard.ZstdError, RuntimeError) as exc:
        raise RecordingError(f"{path}: damaged chunk at byte {index.chunk_start_offset} "
                             f"({exc})") from exc
    pos, end = 0, len(body)
    head, message_head = _RECORD_HEAD.size, _MESSAGE_HEAD.size
    while pos + head <= end:
        opcode, length = _RECORD_HEAD.unpack_from(body, pos)
        pos += head
        if pos + length > end:
            raise RecordingError(f"{path}: record runs past its chunk at byte "
                                 f"{index.chunk_start_offset}")
        if opcode == Opcode.MESSAGE and length >= message_head:
            cid, sequence, log_ns, publish_ns = _MESSAGE_HEAD.unpack_from(body, pos)
            yield cid, sequence, log_ns, publish_ns, body[pos + message_head:pos + length]
        pos += length


def _decompress(compression: str, data: bytes, raw_size: int, decompressor: Any) -> bytes:
    if compression == "zstd":
        return decompressor.decompress(data, max_output_size=raw_size)
    if compression == "lz4":
        return lz4.frame.decompress(data)
    if compression == "":
        return data
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _schema_name(schema: Schema | None) -> str:
    return "" if schema is None else schema.name


def _iter(paths: Paths, want: Callable[[Channel, str], bool]) -> Iterator[LoggedMessage]:
    for path in _as_paths(paths):
        yield from _iter_file(path, want)


def iter_messages(path: Paths, topic_glob: str = "*") -> Iterator[LoggedMessage]:
    """Every message whose topic matches the glob, undecoded, in file order.

    ``path`` is a file or a sequence of files (e.g. ``recording_parts(path)``).
    """
    return _iter(path, lambda c, _: fnmatch.fnmatchcase(c.topic, topic_glob))


def _batch_filter(suffix: str, schema_name: str, sensor_id: str | None
                  ) -> Callable[[Channel, str], bool]:
    def want(channel: Channel, name: str) -> bool:
        owner, topic_suffix = split_topic(channel.topic)
        return (topic_suffix == suffix and name == schema_name
                and (sensor_id is None or owner == sensor_id))
    return want


def iter_raw(path: Paths, sensor_id: str | None = None
             ) -> Iterator[tuple[str, RawBatch, int]]:
    """(sensor_id, batch, log_time_ns) of every raw batch, in file order."""
    for m in _iter(path, _batch_filter("raw", messages.RAW_MESSAGE_NAME, sensor_id)):
        yield split_topic(m.topic)[0], messages.decode_raw(m.data)[1], m.log_time_ns


def iter_raw_logged(path: Paths, sensor_id: str | None = None
                    ) -> Iterator[tuple[str, RawBatch, LoggedMessage]]:
    """(sensor_id, batch, message as logged) of every raw batch, in file order: for copying
    the raw topic into another recording byte for byte (replay)."""
    for m in _iter(path, _batch_filter("raw", messages.RAW_MESSAGE_NAME, sensor_id)):
        yield split_topic(m.topic)[0], messages.decode_raw(m.data)[1], m


def iter_calibrated(path: Paths, sensor_id: str | None = None,
                    topic_suffix: str = "calibrated"
                    ) -> Iterator[tuple[str, CalibratedBatch, int]]:
    """(sensor_id, batch, log_time_ns) of every calibrated (or ``body``) batch, in file order."""
    want = _batch_filter(topic_suffix, messages.CALIBRATED_MESSAGE_NAME, sensor_id)
    for m in _iter(path, want):
        yield split_topic(m.topic)[0], messages.decode_calibrated(m.data)[1], m.log_time_ns


def iter_json(path: Paths, topic_glob: str) -> Iterator[tuple[str, Any, int]]:
    """(topic, decoded object, log_time_ns) of JSON messages on matching topics, in file order.

    ``topic_glob`` is an fnmatch pattern (``*`` also matches ``/``): ``"/*/calibration"``.
    """
    def want(channel: Channel, _: str) -> bool:
        return channel.message_encoding == "json" and fnmatch.fnmatchcase(channel.topic,
                                                                          topic_glob)
    for m in _iter(path, want):
        yield m.topic, messages.decode_json(m.data), m.log_time_ns


def iter_plot(path: Paths, sensor_id: str | None = None) -> Iterator[tuple[str, dict, int]]:
    """(sensor_id, sample dict, log_time_ns) of every plot message, in file order (protobuf,
    or JSON in recordings written before the plot topic became protobuf)."""
    def want(channel: Channel, name: str) -> bool:
        owner, suffix = split_topic(channel.topic)
        return (suffix == "plot" and name == messages.PLOT_SCHEMA.name
                and (sensor_id is None or owner == sensor_id))
    for m in _iter(path, want):
        obj = (messages.decode_json(m.data) if m.message_encoding == "json"
               else messages.decode_plot(m.data))
        yield split_topic(m.topic)[0], obj, m.log_time_ns


def read_all_raw(path: Paths, sensor_id: str) -> RawBatch:
    """Every raw sample of one sensor, concatenated in file order."""
    return RawBatch.concat([b for _, b, _ in iter_raw(path, sensor_id)])


def read_all_calibrated(path: Paths, sensor_id: str,
                        topic_suffix: str = "calibrated") -> CalibratedBatch:
    """Every calibrated sample of one sensor, concatenated in file order."""
    return CalibratedBatch.concat([b for _, b, _ in iter_calibrated(path, sensor_id,
                                                                    topic_suffix)])


def refuse_input_as_output(out: PathLike, *inputs: PathLike) -> None:
    """Raise if ``out`` names one of ``inputs`` (or a rotated part of one): writing there would
    destroy what is being read (``recal repair x.mcap --out x.mcap`` did)."""
    target = Path(out)
    if not target.exists():
        return
    for given in inputs:
        for part in recording_parts(given) if str(given).endswith(".mcap") else [Path(given)]:
            if part.exists() and os.path.samefile(part, target):
                raise ValueError(f"{out} is the input {part}; write the output elsewhere "
                                 "(an input is never overwritten)")


def metadata(path: PathLike) -> dict[str, str]:
    """The ``recal`` metadata record of a recording's first part (version, part, and what the
    writer was given, e.g. ``units`` from `recal import`); empty if it has none."""
    with open(path, "rb") as f:
        reader, _ = _open_summary(f, Path(path))
        for record in reader.iter_metadata():
            if record.name == "recal":
                return dict(record.metadata)
    return {}


def _channels(path: Path) -> list[Channel]:
    with open(path, "rb") as f:
        _, info = _open_summary(f, path)
    if info is not None:
        return list(info.channels.values())
    seen: dict[str, Channel] = {}
    for m in _iter_file(path, lambda c, _: True):
        seen.setdefault(m.topic, Channel(0, m.topic, m.message_encoding, 0, {}))
    return list(seen.values())


def sensors(path: Paths) -> list[str]:
    """Sorted ids of the sensors that have any topic in the recording."""
    owners = {split_topic(c.topic)[0] for p in _as_paths(path) for c in _channels(p)}
    owners.discard(GATEWAY)
    return sorted(o for o in owners if _SENSOR_ID.fullmatch(o))


def pick_sensor(path: PathLike, found: list[str], sensor_id: str | None) -> str:
    """``sensor_id`` if given, else the recording's only sensor (``found``: `sensors`); a
    recording with none or several needs one named (commands that read one sensor)."""
    if sensor_id is not None:
        return sensor_id
    if len(found) != 1:
        raise ValueError(f"{path}: {'no sensors' if not found else 'several sensors'} "
                         f"({', '.join(found) or 'none'}); pick one with --sensor-id")
    return found[0]


@dataclass
class TopicSummary:
    """Counts and time ranges of one topic.

    ``sample_count`` is the number of samples in batch topics, the number of messages on the
    plot topic, and 0 for other JSON topics. Device times (``*_t_us``) are known for batch and
    plot topics only.
    """

    topic: str
    schema_name: str
    message_count: int = 0
    sample_count: int = 0
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None
    first_t_us: int | None = None
    last_t_us: int | None = None


@dataclass
class RecordingSummary:
    """What a recording holds, per topic, and its overall log-time range."""

    paths: list[Path]
    topics: dict[str, TopicSummary] = field(default_factory=dict)

    @property
    def message_count(self) -> int:
        return sum(t.message_count for t in self.topics.values())

    @property
    def start_log_time_ns(self) -> int | None:
        times = [t.first_log_time_ns for t in self.topics.values()
                 if t.first_log_time_ns is not None]
        return min(times) if times else None

    @property
    def end_log_time_ns(self) -> int | None:
        times = [t.last_log_time_ns for t in self.topics.values()
                 if t.last_log_time_ns is not None]
        return max(times) if times else None

    @property
    def sensors(self) -> list[str]:
        owners = {split_topic(t)[0] for t in self.topics} - {GATEWAY}
        return sorted(o for o in owners if _SENSOR_ID.fullmatch(o))


def _extent(m: LoggedMessage) -> tuple[int, int | None, int | None]:
    if m.schema_name in (messages.RAW_MESSAGE_NAME, messages.CALIBRATED_MESSAGE_NAME):
        return messages.batch_extent(m.data)
    if m.schema_name == messages.PLOT_SCHEMA.name:
        if m.message_encoding == "json":  # recordings from before the plot became protobuf
            t_us = messages.decode_json(m.data).get("t_us")
        else:
            t_us = messages.decode_plot(m.data)["t_us"]
        return 1, t_us, t_us
    return 0, None, None


def _min(a: int | None, b: int | None) -> int | None:
    return b if a is None else a if b is None else min(a, b)


def _max(a: int | None, b: int | None) -> int | None:
    return b if a is None else a if b is None else max(a, b)


def summary(path: Paths) -> RecordingSummary:
    """Message and sample counts per topic and time ranges, from one pass over the messages.

    Batch messages are not decoded; only their time field is read.
    """
    result = RecordingSummary(_as_paths(path))
    for m in _iter(path, lambda c, _: True):
        topic = result.topics.get(m.topic)
        if topic is None:
            topic = result.topics[m.topic] = TopicSummary(m.topic, m.schema_name)
        count, first_us, last_us = _extent(m)
        topic.message_count += 1
        topic.sample_count += count
        topic.first_log_time_ns = _min(topic.first_log_time_ns, m.log_time_ns)
        topic.last_log_time_ns = _max(topic.last_log_time_ns, m.log_time_ns)
        topic.first_t_us = _min(topic.first_t_us, first_us)
        topic.last_t_us = _max(topic.last_t_us, last_us)
    return result


# ---------------------------------------------------------------------------------------------
# Repair
# ---------------------------------------------------------------------------------------------

@dataclass
class RepairReport:
    """What ``repair`` recovered.

    Attributes:
        input_bytes: size of the damaged file.
        bytes_read: input bytes up to the end of the last complete record recovered.
        truncated: the input did not end with a valid footer and magic (a killed writer).
        messages_per_topic: recovered message count per topic.
        error: why reading stopped early, if it did.
    """

    input_path: Path
    output_path: Path
    input_bytes: int
    bytes_read: int = 0
    truncated: bool = True
    messages_per_topic: dict[str, int] = field(default_factory=dict)
    error: str | None = None

    @property
    def messages_recovered(self) -> int:
        return sum(self.messages_per_topic.values())


class _Copier:
    """Re-registers schemas and channels lazily, so only those with messages are written."""

    def __init__(self, writer: _McapWriter) -> None:
        self.writer = writer
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.new_schema_ids: dict[int, int] = {}
        self.new_channel_ids: dict[int, int] = {}

    def channel_id(self, old_id: int) -> int | None:
        new_id = self.new_channel_ids.get(old_id)
        if new_id is not None:
            return new_id
        channel = self.channels.get(old_id)
        if channel is None:
            return None
        schema_id = 0
        if channel.schema_id:
            schema = self.schemas.get(channel.schema_id)
            if schema is None:
                return None
            schema_id = self.new_schema_ids.get(schema.id, 0)
            if not schema_id:
                schema_id = self.writer.register_schema(schema.name, schema.encoding,
                                                        schema.data)
                self.new_schema_ids[schema.id] = schema_id
        new_id = self.writer.register_channel(channel.topic, channel.message_encoding,
                                              schema_id, dict(channel.metadata))
        self.new_channel_ids[old_id] = new_id
        return new_id

    def copy(self, record: object, report: RepairReport) -> bool:
        """Copy one record; True if it was the footer (the input ended properly)."""
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            channel_id = self.channel_id(record.channel_id)
            if channel_id is not None:  # a message without its channel cannot be decoded
                self.writer.add_message(channel_id, record.log_time, record.data,
                                        record.publish_time, record.sequence)
                topic = self.channels[record.channel_id].topic
                report.messages_per_topic[topic] = report.messages_per_topic.get(topic, 0) + 1
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, dict(record.metadata))
        elif isinstance(record, Attachment):
            self.writer.add_attachment(record.create_time, record.log_time, record.name,
                                       record.media_type, record.data)
        return isinstance(record, Footer)


def repair(broken_path: PathLike, fixed_path: PathLike, *,
           compression: Compression = "zstd") -> RepairReport:
    """Copy every complete message of a damaged (e.g. truncated) MCAP into a valid indexed file.

    Reads records sequentially and stops at the first one that cannot be read; a chunk is
    recovered whole or not at all (its CRC is checked). A file that is not MCAP at all (wrong
    magic) is an error; one shorter than the magic yields an empty recording.
    """
    src_path, dst_path = Path(broken_path), Path(fixed_path)
    size = src_path.stat().st_size
    refuse_input_as_output(dst_path, src_path)
    report = RepairReport(src_path, dst_path, size)
    with open(src_path, "rb") as src:
        head = src.read(8)
        if head != MCAP0_MAGIC[:len(head)]:
            raise RecordingError(f"{src_path} is not an MCAP file")
        src.seek(0)
        with open(dst_path, "wb") as dst:
            writer = _McapWriter(dst, chunk_size=1024 * 1024, compression=_COMPRESSION[
                compression])
            writer.start(profile="", library=_LIBRARY)
            copier = _Copier(writer)
            footer_seen = False
            # A length beyond the file is damage, not a reason to allocate gigabytes.
            reader = StreamReader(src, validate_crcs=True, record_size_limit=max(size, 1))
            try:
                for record in reader.records:
                    footer_seen = copier.copy(record, report) or footer_seen
                    report.bytes_read = src.tell()
                report.bytes_read = src.tell()  # the closing magic, after the footer
            except Exception as exc:  # damage surfaces as struct, mcap, zstd, lz4 errors...
                report.error = f"{type(exc).__name__}: {exc}".rstrip(": ")
            report.truncated = not footer_seen or report.error is not None
            writer.finish()
    return report
