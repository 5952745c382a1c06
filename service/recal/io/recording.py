"""MCAP recordings: the topic layout every part of recal shares, and reading recordings back.

Topic layout (one MCAP file, or a rotated series ``rec.mcap``, ``rec-0001.mcap``, ...; each
suffix and its schema is a record of the registry, `recal.io.topics`):

| topic                 | schema (encoding)                 | one message is                    |
|-----------------------|-----------------------------------|-----------------------------------|
| /<sensor>/raw         | recal.RawBatch (protobuf)         | a batch of raw samples            |
| /<sensor>/calibrated  | recal.CalibratedBatch (protobuf)  | the batch calibrated, sensor frame|
| /<sensor>/body        | recal.CalibratedBatch (protobuf)  | the batch rotated to body frame:  |
|                       |                                   | times and the rotation (the log's)|
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
series) and yield messages in file order. Writing is `recal.io.recording_writer`, repairing a
damaged file `recal.io.repair`; the reasons behind the layout: docs/design.md (recordings).
"""

from __future__ import annotations

import fnmatch
import functools
import os
import re
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, NamedTuple

import lz4.frame
import numpy as np
import zstandard
from mcap.opcode import Opcode
from mcap.reader import McapReader, make_reader
from mcap.records import Channel, ChunkIndex, Schema
from mcap.summary import Summary
from mcap.writer import MCAP0_MAGIC

from recal.core.alignment import to_body
from recal.errors import RecordingError, UsageError
from recal.io import messages, topics
from recal.samples import CalibratedBatch, RawBatch

__all__ = [
    "GATEWAY",
    "LoggedMessage",
    "RecordingSummary",
    "TopicSummary",
    "iter_calibrated",
    "iter_json",
    "iter_messages",
    "iter_plot",
    "iter_raw",
    "iter_raw_logged",
    "metadata",
    "part_path",
    "pick_sensor",
    "read_all_calibrated",
    "read_all_raw",
    "recording_parts",
    "refuse_input_as_output",
    "sensor_topic",
    "sensors",
    "split_topic",
    "summary",
]

GATEWAY = "gateway"
"""Owner segment of the gateway's own topics (``/gateway/events``); not a valid sensor id."""

PathLike = str | os.PathLike[str]
Paths = PathLike | Sequence[PathLike]

_SENSOR_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")
_MAX_PARTS = 9999


# ---------------------------------------------------------------------------------------------
# Topics and paths
# ---------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4096)
def sensor_topic(sensor_id: str, suffix: str) -> str:
    """``/<sensor_id>/<suffix>``, after checking the sensor id is topic- and key-safe."""
    if not _SENSOR_ID.fullmatch(sensor_id) or sensor_id == GATEWAY:
        raise UsageError(f"invalid sensor id {sensor_id!r}: use [A-Za-z0-9][A-Za-z0-9_.-]* "
                         f"and not {GATEWAY!r}")
    if not suffix or "/" in suffix:
        raise ValueError(f"invalid topic suffix {suffix!r}")
    return f"/{sensor_id}/{suffix}"


def split_topic(topic: str) -> tuple[str, str]:
    """(owner, suffix) of ``/<owner>/<suffix>``; owner is a sensor id or ``gateway``."""
    owner, _, suffix = topic.lstrip("/").rpartition("/")
    return owner, suffix


def part_path(base: Path, index: int) -> Path:
    """Part ``index`` of the recording whose first file is ``base`` (0: ``base`` itself)."""
    return base if index == 0 else base.with_name(f"{base.stem}-{index:04d}{base.suffix}")


def recording_parts(path: PathLike) -> list[Path]:
    """The file ``path`` followed by its rotated parts ``stem-0001.mcap``, ... that exist."""
    base = Path(path)
    parts = [base]
    for index in range(1, _MAX_PARTS + 1):
        part = part_path(base, index)
        if not part.exists():
            break
        parts.append(part)
    return parts


def _as_paths(paths: Paths) -> list[Path]:
    if isinstance(paths, (str, os.PathLike)):
        return [Path(paths)]
    return [Path(p) for p in paths]

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
    _check_mcap_start(f, path)
    try:
        reader = make_reader(f)
        return reader, reader.get_summary()
    except Exception as exc:  # the mcap reader raises many types on a damaged tail
        raise RecordingError(f"{path} is not a finished MCAP file ({exc}); recover what it "
                             f"holds with: recal repair {path} --out FIXED.mcap") from exc


def _check_mcap_start(f: IO[bytes], path: Path) -> None:
    """RecordingError for a file that is not an MCAP recording at all (the repair hint is
    only for one that starts as MCAP and was not finished): a CSV or other text is what
    ``recal import`` is for."""
    head = f.read(512)
    f.seek(0)
    if head[:len(MCAP0_MAGIC)] == MCAP0_MAGIC[:len(head)]:  # MCAP, or cut before its magic
        return
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:  # cut inside a character at the end: still text
        text = head[:exc.start].decode("utf-8") if exc.start > len(head) - 4 else ""
    if text and "".join(text.split()).isprintable():  # whitespace and printable only
        first = text.splitlines()[0][:60]
        raise RecordingError(f"{path} is not an MCAP recording but text (first line "
                             f"{first!r}); a CSV becomes one with: recal import {path} "
                             f"--out RECORDING.mcap")
    raise RecordingError(f"{path} is not an MCAP recording (it does not start with the MCAP "
                         f"magic bytes)")


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

    Reads the chunk with one read and walks it with struct, reusing one zstd context: faster
    than the mcap reader's per-record stream reads, and reading speed is what replay and tests
    wait on (docs/design.md, "Figures behind choices").
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


def _batch_filter(suffix: str, sensor_id: str | None) -> Callable[[Channel, str], bool]:
    """The channels of one registered batch topic (its schema from `recal.io.topics`)."""
    schema = topics.topic(suffix).schema
    schema_name = "" if schema is None else schema.name

    def want(channel: Channel, name: str) -> bool:
        owner, topic_suffix = split_topic(channel.topic)
        return (topic_suffix == suffix and name == schema_name
                and (sensor_id is None or owner == sensor_id))
    return want


def iter_raw(path: Paths, sensor_id: str | None = None
             ) -> Iterator[tuple[str, RawBatch, int]]:
    """(sensor_id, batch, log_time_ns) of every raw batch, in file order."""
    for m in _iter(path, _batch_filter("raw", sensor_id)):
        yield split_topic(m.topic)[0], messages.decode_raw(m.data)[1], m.log_time_ns


def iter_raw_logged(path: Paths, sensor_id: str | None = None
                    ) -> Iterator[tuple[str, RawBatch, LoggedMessage, messages.Arrivals | None]]:
    """(sensor_id, batch, message as logged, its arrivals) of every raw batch, in file order,
    each message read once (`messages.decode_raw_arrivals`; arrivals None for a message of
    one arrival): what replay and hindsight need to hand the node the batches the live node
    had."""
    for m in _iter(path, _batch_filter("raw", sensor_id)):
        _, batch, arrivals = messages.decode_raw_arrivals(m.data)
        yield split_topic(m.topic)[0], batch, m, arrivals


def iter_calibrated(path: Paths, sensor_id: str | None = None,
                    topic_suffix: str = "calibrated"
                    ) -> Iterator[tuple[str, CalibratedBatch, int]]:
    """(sensor_id, batch, log_time_ns) of every calibrated (or ``body``) batch, in file order.

    A body message of the log's form (times and a rotation, `messages.encode_body_rotation`)
    is its samples of the calibrated topic rotated: the first such message reads that
    sensor's calibrated topic once (held in memory while the body is read).
    UnknownTopicError (at the call) if ``topic_suffix`` is not a registered calibrated-batch
    topic."""
    topics.require([topic_suffix], "calibrated")
    return _iter_calibrated(path, _batch_filter(topic_suffix, sensor_id),
                            topic_suffix == "body")


def _iter_calibrated(path: Paths, want: Callable[[Channel, str], bool], body: bool
                     ) -> Iterator[tuple[str, CalibratedBatch, int]]:
    calibrated: dict[str, CalibratedBatch] = {}
    for m in _iter(path, want):
        sid = split_topic(m.topic)[0]
        found = messages.decode_body_rotation(m.data) if body else None
        if found is None:
            yield sid, messages.decode_calibrated(m.data)[1], m.log_time_ns
            continue
        if sid not in calibrated:
            calibrated[sid] = read_all_calibrated(path, sid)
        yield sid, _rotated(calibrated[sid], found[1], found[2], m.topic), m.log_time_ns


def _rotated(cal: CalibratedBatch, t_us: np.ndarray, rotation: np.ndarray,
             topic: str) -> CalibratedBatch:
    """The calibrated samples at ``t_us`` turned by ``rotation`` (R @ a): a body message of the
    log's form read back; RecordingError if the calibrated topic lacks one of the times."""
    i = np.searchsorted(cal.t_us, t_us)
    if len(t_us) and (i[-1] >= len(cal) or not np.array_equal(cal.t_us[np.minimum(
            i, len(cal) - 1)], t_us)):
        raise RecordingError(f"{topic}: a body message names samples the calibrated topic "
                             "does not have")
    part = cal[i]
    return CalibratedBatch(part.t_us, to_body(rotation, part.a_g), part.quasi_static,
                           part.detector_g, part.status, part.sigma_mg, part.t_dev)


def iter_json(path: Paths, topic_glob: str) -> Iterator[tuple[str, Any, int]]:
    """(topic, decoded object, log_time_ns) of JSON messages on matching topics, in file order.

    ``topic_glob`` is an fnmatch pattern (``*`` also matches ``/``): ``"/*/calibration"``.
    """
    def want(channel: Channel, _: str) -> bool:
        return channel.message_encoding == "json" and fnmatch.fnmatchcase(channel.topic,
                                                                          topic_glob)
    for m in _iter(path, want):
        yield m.topic, messages.decode_json(m.data), m.log_time_ns


_PLOT_SCHEMA_NAME = topics.log_schemas()["plot"].name


def iter_plot(path: Paths, sensor_id: str | None = None) -> Iterator[tuple[str, dict, int]]:
    """(sensor_id, sample dict, log_time_ns) of every plot message, in file order (protobuf,
    or JSON in recordings written before the plot topic became protobuf)."""
    def want(channel: Channel, name: str) -> bool:
        owner, suffix = split_topic(channel.topic)
        return (suffix == "plot" and name == _PLOT_SCHEMA_NAME
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
                raise UsageError(f"{out} is the input {part}; write the output elsewhere "
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
        raise RecordingError(f"{path}: {'no sensors' if not found else 'several sensors'} "
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

