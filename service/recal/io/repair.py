"""Repair: every complete message of a damaged (e.g. truncated) MCAP, copied into a valid
indexed file.

Why a killed writer leaves such a file, and what it loses: docs/design.md (recordings).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC
from mcap.writer import Writer as _McapWriter

from recal.errors import RecordingError
from recal.io.mcap_file import COMPRESSION_TYPES, LIBRARY, Compression
from recal.io.recording import PathLike, refuse_input_as_output

__all__ = ["RepairReport", "repair"]


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
            writer = _McapWriter(dst, chunk_size=1024 * 1024, compression=COMPRESSION_TYPES[
                compression])
            writer.start(profile="", library=LIBRARY)
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
