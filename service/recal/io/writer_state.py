"""The recording writer's state in named parts: its options, the part being written, the
topics it registered, its counts, and what a refusing file did so far (`WriteHealth`).
The writer is `recal.io.recording_writer`."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from recal.errors import UsageError
from recal.io.mcap_file import COMPRESSION_TYPES, Compression, McapFile
from recal.io.schemas import SchemaSpec

__all__ = ["OpenPart", "Tally", "TopicBook", "Trouble", "WriteHealth", "WriterOptions",
           "describe", "fsync_and_close"]


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


@dataclass(frozen=True)
class WriterOptions:
    """How the writer writes (the constructor's settings, see :class:`RecordingWriter`)."""

    chunk_size: int
    flush_interval_s: float
    rotate_bytes: int | None
    rotate_ns: int | None
    compression: Compression
    background_compression: bool
    fsync: bool
    metadata: dict[str, str]
    backlog_bytes: int | None
    log_batch_samples: int

    @classmethod
    def checked(cls, *, chunk_size: int, flush_interval_s: float, rotate_bytes: int | None,
                rotate_s: float | None, compression: Compression, fsync: bool,
                metadata: Mapping[str, str] | None, background_compression: bool,
                backlog_bytes: int | None, log_batch_samples: int) -> WriterOptions:
        """The options, after checking them (UsageError)."""
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
        return cls(chunk_size, float(flush_interval_s), rotate_bytes,
                   None if rotate_s is None else round(rotate_s * 1e9), compression,
                   background_compression, fsync,
                   {str(k): str(v) for k, v in (metadata or {}).items()}, backlog_bytes,
                   log_batch_samples)


@dataclass
class OpenPart:
    """The file being written (one part of a rotated recording) and what it registered."""

    file: IO[bytes]
    mcap: McapFile
    schema_ids: dict[str, int] = field(default_factory=dict)
    channel_ids: dict[str, int] = field(default_factory=dict)
    messages: int = 0
    start_ns: int = 0


@dataclass
class TopicBook:
    """Per topic, across parts: its schema, its next sequence number, its checked name, and
    each sensor's plot decimation phase."""

    specs: dict[str, SchemaSpec] = field(default_factory=dict)
    sequence: dict[str, int] = field(default_factory=dict)
    names: dict[tuple[str, str], str] = field(default_factory=dict)  # (sensor, suffix) ->
    plot_phase: dict[str, int] = field(default_factory=dict)


@dataclass
class Tally:
    """Messages written and flushed, flushes, and what finished parts hold and dropped."""

    written: int = 0
    flushed: int = 0
    flushes: int = 0
    parts_out: int = 0  # messages in the files of finished parts
    parts_dropped: tuple[int, int] = (0, 0)  # messages, samples dropped in finished parts


@dataclass
class Trouble:
    """What a refusing file (a full disk) or a failing fsync did so far (`WriteHealth`)."""

    failures: int = 0
    since_s: float | None = None
    last_error: str | None = None
    fsync_errors: int = 0
    unfinished: list[Path] = field(default_factory=list)

    def note(self, exc: OSError | None) -> None:
        """Keep the text of a write error (None: there was none)."""
        if exc is not None:
            self.last_error = describe(exc)

    def fsync_failed(self, exc: OSError) -> None:
        self.fsync_errors += 1
        self.last_error = describe(exc)

    def track(self, failure: OSError | None, now_s: float) -> None:
        """Note when the file began or stopped refusing writes (``failure``: the open part's
        refusal now, or None)."""
        if failure is None:
            self.since_s = None
            return
        if self.since_s is None:
            self.failures += 1
            self.since_s = now_s
        self.last_error = describe(failure)

    def background(self, exc: Exception) -> None:
        """An error on the flush thread, counted (with a backlog budget: nothing raises)."""
        if isinstance(exc, OSError):
            self.fsync_failed(exc)
        else:
            self.last_error = repr(exc)

    def health(self, tally: Tally, mcap: McapFile, closed: bool) -> WriteHealth:
        """What :meth:`recal.io.recording_writer.RecordingWriter.health` says."""
        # a finished part's drops are in tally.parts_dropped already
        open_dropped = (0, 0) if closed else (mcap.dropped_messages, mcap.dropped_samples)
        return WriteHealth(
            failing=mcap.failure is not None, error=self.last_error,
            failing_since_s=self.since_s, failures=self.failures,
            waiting_bytes=mcap.waiting_bytes,
            dropped_messages=tally.parts_dropped[0] + open_dropped[0],
            dropped_samples=tally.parts_dropped[1] + open_dropped[1],
            fsync_errors=self.fsync_errors, unfinished=tuple(self.unfinished))


def describe(exc: OSError) -> str:
    """An OS error as the text the health report shows."""
    return exc.strerror or str(exc)


def fsync_and_close(fd: int | None) -> None:
    """fsync a duplicated descriptor (see ``RecordingWriter._take_fsync``) and close it."""
    if fd is None:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
