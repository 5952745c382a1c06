"""What every long-running recal process shares: stop signals, the bus, the recording and its
health, and the operator's console lines.

The gateway daemon (`recal.daemon.gateway`) and the remote calibration node
(`recal.daemon.remote_node`) open the same Zenoh session and MCAP writer from the same [zenoh]
and [mcap] settings and tell the operator the same things the same way; that lives here, once.
Why the recording never stops the reading: docs/design.md.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any

from recal.config.settings import ServiceConfig
from recal.console import LineLimiter
from recal.io.recording_writer import RecordingWriter, WriteHealth

__all__ = [
    "ERROR_PREFIX",
    "WRITE_NOTE_S",
    "RecordingWatch",
    "console",
    "flush_console",
    "install_stop_signals",
    "open_bus",
    "open_recording",
    "recording_path",
    "watch_recording",
]

ERROR_PREFIX = "recal: error:"  # the one line a start-up failure prints (as the CLI's errors)
WRITE_NOTE_S = 60.0  # while the recording cannot be written, a reminder at most this often


def console(out: Callable[[str], None] | None
            ) -> tuple[Callable[[str], None], Callable[[str], None]]:
    """``(emit, fail)``: where a process's lines go, ``out`` for both if given (tests, the
    demo), else stdout for the operator's lines and stderr for the errors, flushed at once
    (a journal under systemd sees them as they happen). The operator's lines are
    rate-limited per kind (`recal.console`: a device that misbehaves on every sample floods
    no journal; the recording keeps every event); call :func:`flush_console` at the end."""
    emit = LineLimiter(out or (lambda line: print(line, flush=True)))
    fail = out or (lambda line: print(line, file=sys.stderr, flush=True))
    return emit, fail


def flush_console(emit: Callable[[str], None]) -> None:
    """Say how many lines :func:`console`'s limit left out and has not said yet."""
    if isinstance(emit, LineLimiter):
        emit.flush()


def install_stop_signals(stop: threading.Event) -> Callable[[], None]:
    """SIGINT/SIGTERM set ``stop`` (main thread only); returns a function that undoes it."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}

    def restore() -> None:
        for s, old in previous.items():
            signal.signal(s, old)

    return restore


def open_bus(cfg: ServiceConfig) -> Any:
    """A recal.io.bus.Bus from the [zenoh] settings, or None when Zenoh is disabled."""
    if not cfg.zenoh.enabled:
        return None
    # imported here: zenoh is loaded only by a process that opens a bus (replay never does)
    from recal.io.bus import Bus
    from recal.io.bus_config import zenoh_config

    z = cfg.zenoh
    return Bus(zenoh_config(z.mode, z.listen, z.connect,
                            config_file=str(z.config_file) if z.config_file else None))


def recording_path(cfg: ServiceConfig, mcap_out: str | Path | None) -> Path:
    """Where to log: ``mcap_out`` (a file, or a directory for an auto-named file), else the
    config's path or dir. An existing file is never overwritten: a time-stamped sibling
    ``<stem>-<UTC>.mcap`` is used instead (e.g. after a crash, for the repair to read)."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    target = Path(mcap_out) if mcap_out is not None else cfg.mcap.path
    if target is None or target.is_dir() or str(target).endswith(("/", "\\")):
        directory = target if target is not None else cfg.mcap.dir
        return Path(directory) / f"recal-{stamp}.mcap"
    if not target.exists():
        return target
    for i in range(1000):
        alt = target.with_name(f"{target.stem}-{stamp}{'' if i == 0 else f'-{i}'}"
                               f"{target.suffix}")
        if not alt.exists():
            return alt
    raise FileExistsError(f"no free name next to {target}")


def open_recording(cfg: ServiceConfig, mcap_out: str | Path | None) -> RecordingWriter:
    """A RecordingWriter with the [mcap] settings at :func:`recording_path`."""
    m = cfg.mcap
    return RecordingWriter(
        recording_path(cfg, mcap_out), chunk_size=m.chunk_size,
        flush_interval_s=m.flush_interval_s,
        rotate_bytes=None if m.rotate_mb is None else int(m.rotate_mb * 1e6),
        rotate_s=None if m.rotate_hours is None else m.rotate_hours * 3600.0,
        compression=m.compression, fsync=m.fsync,  # type: ignore[arg-type]
        backlog_bytes=int(m.backlog_mb * 1e6))


class RecordingWatch:
    """Tells the operator when a RecordingWriter stops being written (a full disk) and when it
    resumes, with what was lost: one line each (and an event), a reminder every WRITE_NOTE_S
    between, fsync failures at most as often, and at the close each part left unfinished with
    its repair command. Call :meth:`check` now and then (the gateway: once a second) and
    :meth:`closed` after the writer's close. Reading, calibrating and publishing never wait
    for the recording: the writer keeps what the disk refuses within its budget.

    Args:
        writer: the RecordingWriter (its ``health()`` is read).
        out: where the lines go.
        budget_mb: the writer's ``backlog_bytes`` in MB, for the first line.
        prefix: what each line starts with (the gateway's or the node's note prefix).
    """

    def __init__(self, writer: RecordingWriter, out: Callable[[str], None],
                 budget_mb: float, prefix: str = "recal gateway:") -> None:
        self.writer, self.out, self.budget_mb, self.prefix = writer, out, budget_mb, prefix
        self.failing = False
        self.failures = 0  # the writer's refusal count as of the last line
        self.error = ""
        self.since_s = 0.0
        self.since_ns = 0
        self.dropped = (0, 0)  # messages, samples dropped as of the last resume line
        self.noted_s = float("-inf")
        self.fsync_errors = 0
        self.fsync_noted_s = float("-inf")

    def check(self, now: int, event: Callable[[str, dict[str, Any]], None]) -> None:
        """Lines and ``event(kind, detail)`` calls for what changed since the last check."""
        h = self.writer.health()
        now_s = time.monotonic()
        if self.failing and (not h.failing or h.failures > self.failures):
            lost = (h.dropped_samples - self.dropped[1], h.dropped_messages - self.dropped[0])
            self.out(f"{self.prefix} recording: writing again after "
                     f"{now_s - self.since_s:.1f} s ({self.error}); lost {lost[0]} raw "
                     f"samples ({lost[1]} messages)")
            event("write_resumed", {
                "error": self.error, "failed_s": now_s - self.since_s,
                "since_ns": self.since_ns, "lost_samples": lost[0], "lost_messages": lost[1]})
            # drops happen only while writing is refused: all since the last line are this one's
            self.failing, self.dropped = False, (h.dropped_messages, h.dropped_samples)
        if not self.failing and h.failures > self.failures:
            self._began(h, now, now_s, event)
            if not h.failing:  # over within one check: say so now
                self.check(now, event)
        elif self.failing and now_s >= self.noted_s + WRITE_NOTE_S:
            self.noted_s = now_s
            self.out(f"{self.prefix} recording: still cannot write ({h.error}) for "
                     f"{now_s - self.since_s:.0f} s; dropped so far "
                     f"{h.dropped_samples - self.dropped[1]} raw samples "
                     f"({h.dropped_messages - self.dropped[0]} messages)")
        if h.fsync_errors > self.fsync_errors and now_s >= self.fsync_noted_s + WRITE_NOTE_S:
            self.out(f"{self.prefix} recording: fsync failed "
                     f"{h.fsync_errors - self.fsync_errors} times ({h.error}); the last "
                     "second may not be on the disk")
            self.fsync_errors, self.fsync_noted_s = h.fsync_errors, now_s

    def _began(self, h: WriteHealth, now: int, now_s: float,
               event: Callable[[str, dict[str, Any]], None]) -> None:
        self.failing, self.failures, self.error = True, h.failures, h.error or "write refused"
        self.since_s = h.failing_since_s if h.failing_since_s is not None else now_s
        self.since_ns = now - int((now_s - self.since_s) * 1e9)
        self.noted_s = now_s
        path = self.writer.paths[-1]
        self.out(f"{self.prefix} recording: cannot write {path}: {self.error}; reading, "
                 f"calibrating and publishing go on, up to {self.budget_mb:g} MB of it wait "
                 "in memory, then the oldest is dropped")
        event("write_failed", {"error": self.error, "path": str(path),
                               "backlog_mb": self.budget_mb})

    def closed(self) -> None:
        """After the writer's close: each part the disk would not let it finish, with its
        repair (the file ends at its last whole record)."""
        h = self.writer.health()
        for path in h.unfinished:
            self.out(f"{self.prefix} recording: {path} not finished ({h.error}); "
                     f"{h.dropped_samples} raw samples ({h.dropped_messages} messages) lost "
                     f"in all; recover the rest with: recal repair {path} --out FIXED.mcap")


def watch_recording(writer: RecordingWriter, emit: Callable[[str], None], budget_mb: float,
                    stop: threading.Event, prefix: str) -> RecordingWatch:
    """A RecordingWatch checked once a second by a thread of its own until ``stop`` (the
    remote node's; the gateway checks from its main loop), its events in the recording."""
    watch = RecordingWatch(writer, emit, budget_mb, prefix=prefix)

    def event(kind: str, detail: dict[str, Any]) -> None:
        with contextlib.suppress(ValueError):  # the writer closed under us (the stop)
            writer.write_event(kind, time.time_ns(), detail=detail)

    def loop() -> None:
        while not stop.wait(1.0):
            watch.check(time.time_ns(), event)

    threading.Thread(target=loop, name="recal-recording-watch", daemon=True).start()
    return watch
