"""The MCAP file under a recording: records laid out as mcap's Writer lays them out, written
fast, and kept readable when the disk refuses a write.

Why its own writer, and how the backlog for a full disk works: docs/design.md (recordings).
"""

from __future__ import annotations

import collections
import errno
import queue
import struct
import tempfile
import threading
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO, Any, Literal, NamedTuple

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import LIBRARY_IDENTIFIER, MCAP0_MAGIC, CompressionType

from recal import __version__

__all__ = ["COMPRESSION_TYPES", "LIBRARY", "Compression", "McapFile"]

Compression = Literal["zstd", "lz4", "none"]
COMPRESSION_TYPES = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                     "none": CompressionType.NONE}
"""mcap's compression type for each name recal accepts."""
LIBRARY = f"recal/{__version__}; {LIBRARY_IDENTIFIER}"
"""The MCAP header's library field of every file recal writes."""

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


#: A chunk of at most this many uncompressed bytes is compressed at zstd level
#: ``_SMALL_CHUNK_LEVEL`` (a sensor's second at 100 Hz is about 3.5 KiB: level 12 takes
#: ~0.1 ms on one and 2.3 % fewer bytes than level 3's ~0.03 ms; level 19 ~0.4 ms for 0.2 %
#: more), a larger one at zstd's default (3), whose cost per byte stays low.
_SMALL_CHUNK_BYTES = 16 * 1024
_SMALL_CHUNK_LEVEL = 12


@dataclass(slots=True)
class _OpenChunk:
    """The chunk being filled: its records, their size, and per channel the log times and
    offsets its message index will hold."""

    pieces: list[bytes] = field(default_factory=list)
    size: int = 0
    times: dict[int, list[int]] = field(default_factory=dict)
    offsets: dict[int, list[int]] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    defs: list[bytes] = field(default_factory=list)  # schema and channel records in it


@dataclass(slots=True)
class _SummaryState:
    """What the summary will say: schemas, channels, statistics, chunk and metadata indexes.
    Chunk indexes go to a temporary file until the summary is written: a week-long recording
    flushed every second has ~600k chunks, too many to keep in memory."""

    schemas: list[Schema] = field(default_factory=list)
    channels: list[Channel] = field(default_factory=list)
    spill: IO[bytes] | None = None
    chunks: int = 0
    metadata_indexes: list[MetadataIndex] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    messages: int = 0
    start_ns: int = 0
    end_ns: int = 0


@dataclass(frozen=True, slots=True)
class _Codec:
    """The chunk compression: its MCAP name and the zstd contexts, reused chunk after chunk."""

    name: str
    zstd: Any  # zstandard.ZstdCompressor | None
    # a small chunk (a live log's, ended by the flush every second) at a higher level:
    # 2 % fewer bytes for ~0.1 ms a chunk; a file tool's full chunks at the default
    zstd_small: Any

    @classmethod
    def of(cls, compression: Compression) -> _Codec:
        if compression != "zstd":
            return cls(_COMPRESSION_NAMES[compression], None, None)
        return cls("zstd", zstandard.ZstdCompressor(),
                   zstandard.ZstdCompressor(level=_SMALL_CHUNK_LEVEL))


class McapFile:
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
        self._codec = _Codec.of(compression)
        self.position = 0  # bytes written to the stream (by the thread, if there is one)
        self._chunk = _OpenChunk()
        self._summary = _SummaryState()
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
                self._summary.metadata_indexes.append(MetadataIndex(
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
        self._chunk.pieces.append(data)
        self._chunk.size += len(data)

    def _append_definition(self, record: bytes) -> None:
        self._append(record)
        self._chunk.defs.append(record)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._summary.schemas) + 1, name=name, encoding=encoding, data=data)
        self._summary.schemas.append(schema)
        self._append_definition(self._record(schema))
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(id=len(self._summary.channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id, metadata={})
        self._summary.channels.append(channel)
        self._summary.counts[channel.id] = 0
        self._append_definition(self._record(channel))
        return channel.id

    def _note(self, channel_id: int, log_times: list[int], offsets: list[int]) -> None:
        """Index and statistics for messages just appended (log times in write order)."""
        lo, hi = min(log_times), max(log_times)
        chunk, summary = self._chunk, self._summary
        if not chunk.times:  # first message of the chunk
            chunk.start_ns, chunk.end_ns = lo, hi
        else:
            chunk.start_ns = min(chunk.start_ns, lo)
            chunk.end_ns = max(chunk.end_ns, hi)
        if summary.messages == 0:
            summary.start_ns, summary.end_ns = lo, hi
        else:
            summary.start_ns, summary.end_ns = min(summary.start_ns, lo), max(summary.end_ns, hi)
        chunk.times.setdefault(channel_id, []).extend(log_times)
        chunk.offsets.setdefault(channel_id, []).extend(offsets)
        summary.counts[channel_id] += len(log_times)
        summary.messages += len(log_times)
        if chunk.size > self._chunk_size:
            self.end_chunk()

    def add_messages(self, channel_id: int, items: Sequence[tuple[bytes, int, int]],
                     sequence: int) -> int:
        """Append (data, log ns, publish ns) messages; returns the next sequence number."""
        if not items:
            return sequence
        pack, pieces = _MESSAGE_RECORD.pack, self._chunk.pieces
        offsets, log_times, size = [], [], self._chunk.size
        for data, log_ns, publish_ns in items:
            head = pack(Opcode.MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence,
                        log_ns, publish_ns)
            pieces.append(head)
            pieces.append(data)
            offsets.append(size)
            log_times.append(log_ns)
            size += len(head) + len(data)
            sequence = (sequence + 1) & 0xFFFFFFFF  # MCAP sequence is uint32
        self._chunk.size = size
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
        offsets = self._chunk.size + records.dtype.itemsize * np.arange(n)
        self._append(records.tobytes())
        self._note(channel_id, np.asarray(log_times, np.uint64).tolist(), offsets.tolist())
        return (sequence + n) & 0xFFFFFFFF

    def end_chunk(self) -> None:
        """Hand the open chunk and its message indexes to the output (nothing if empty)."""
        if not self._chunk.times:  # schema and channel records alone wait for the next chunk,
            return  # as in mcap's Writer (a chunk without messages is not written)
        self._submit(self._write_chunk, b"".join(self._chunk.pieces), self._chunk.start_ns,
                     self._chunk.end_ns, self._chunk.times, self._chunk.offsets, self.open_samples,
                     b"".join(self._chunk.defs))
        self._chunk.pieces, self._chunk.size = [], 0
        self._chunk.times, self._chunk.offsets = {}, {}
        self.open_samples, self._chunk.defs = 0, []

    def _write_chunk(self, data: bytes, start_ns: int, end_ns: int,
                     times: dict[int, list[int]], offsets: dict[int, list[int]],
                     samples: int, defs: bytes) -> None:
        """Compress the chunk (once, whatever happens to the write) and queue it with its
        message indexes; their file offsets are known when it is written."""
        if self._codec.zstd is not None and self._codec.zstd_small is not None:
            packed = (self._codec.zstd_small if len(data) <= _SMALL_CHUNK_BYTES
                      else self._codec.zstd).compress(data)
        elif self._codec.name == "lz4":
            packed = lz4.frame.compress(data)
        else:
            packed = data
        name = self._codec.name.encode()
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
        if self._summary.spill is None:
            self._summary.spill = tempfile.TemporaryFile(prefix="recal-chunk-index-")
        self._summary.spill.write(_CHUNK_INDEX_SPILL.pack(
            info.start_ns, info.end_ns, start, info.length, len(entry.data) - info.length,
            info.packed, info.size, len(info.index_offsets)) + b"".join(
                _CHANNEL_OFFSET.pack(c, start + o) for c, o in info.index_offsets.items()))
        self._summary.chunks += 1

    def _chunk_indexes(self) -> Iterator[ChunkIndex]:
        """The spilled chunk indexes, read back in order."""
        if self._summary.spill is None:
            return
        spill = self._summary.spill
        spill.flush()
        spill.seek(0)
        for _ in range(self._summary.chunks):
            start, end, offset, length, mi_length, packed, size, n = _CHUNK_INDEX_SPILL.unpack(
                spill.read(_CHUNK_INDEX_SPILL.size))
            pairs = spill.read(_CHANNEL_OFFSET.size * n)
            yield ChunkIndex(
                message_start_time=start, message_end_time=end, chunk_start_offset=offset,
                chunk_length=length,
                message_index_offsets=dict(_CHANNEL_OFFSET.iter_unpack(pairs)),
                message_index_length=mi_length, compression=self._codec.name,
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
            if self._summary.spill is not None:
                self._summary.spill.close()

    def _write_summary_section(self) -> None:
        self._write(self._record(DataEnd(data_section_crc=0)))
        summary_start = self.position
        sm = self._summary
        groups: list[tuple[int, Iterable[Any]]] = [
            (Opcode.SCHEMA, sm.schemas), (Opcode.CHANNEL, sm.channels),
            (Opcode.STATISTICS, [Statistics(
                message_count=sm.messages, schema_count=len(sm.schemas),
                channel_count=len(sm.channels), attachment_count=0,
                metadata_count=len(sm.metadata_indexes), chunk_count=sm.chunks,
                message_start_time=sm.start_ns, message_end_time=sm.end_ns,
                channel_message_counts=dict(sm.counts))]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes()),
            (Opcode.METADATA_INDEX, sm.metadata_indexes)]
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
