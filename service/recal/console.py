"""Rate-limited console lines: a device that misbehaves on every sample must not write a line
per sample into the operator's journal.

Every line a long-running recal process prints for the operator goes through one
:class:`LineLimiter` (`recal.daemon.runtime.console` wraps the process's output with it; the CLI
puts :class:`RateLimitFilter` on the logging handler it installs). Lines are grouped by their
template, the text with its numbers blanked out ("device time restarted (41 -> 40 ms)" and
"(40 -> 39 ms)" are one kind): each kind passes ``burst`` lines per ``interval_s``, the rest of
that interval are counted, and one line then says how many were left out and shows the last.
Only console lines are limited: the events in the recording and on the bus stay complete.
Memory is bounded by ``max_kinds``.
"""

from __future__ import annotations

import logging
import re
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["BURST", "INTERVAL_S", "LineLimiter", "RateLimitFilter", "template"]

BURST = 10  # lines of one kind passed per interval before they are counted instead
INTERVAL_S = 60.0
MAX_KINDS = 512

_NUMBER = re.compile(r"[-+]?(?:0x[0-9a-fA-F]+|\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)")


def template(line: str) -> str:
    """The kind of a line: its text with every number replaced by ``#``."""
    return _NUMBER.sub("#", line)


@dataclass
class _Kind:
    since_s: float  # start of the current interval
    passed: int = 0  # lines passed in it
    suppressed: int = 0  # lines counted instead
    last: str = ""  # the last line left out


class _Limit:
    """The bookkeeping shared by :class:`LineLimiter` and :class:`RateLimitFilter`."""

    def __init__(self, burst: int, interval_s: float, clock: Callable[[], float],
                 max_kinds: int) -> None:
        self.burst, self.interval_s, self.clock = int(burst), float(interval_s), clock
        self.max_kinds = int(max_kinds)
        self.kinds: dict[str, _Kind] = {}
        self.lock = threading.Lock()

    def admit(self, key: str, line: str) -> tuple[bool, list[str]]:
        """(pass this line?, summaries now due), under the lock."""
        with self.lock:
            now = self.clock()
            notes = self._due(now)
            kind = self.kinds.get(key)
            if kind is None:
                if len(self.kinds) >= self.max_kinds:  # forget the oldest quiet kind
                    quiet = [k for k, v in self.kinds.items() if not v.suppressed]
                    for k in quiet[: max(1, len(quiet) // 2)]:
                        del self.kinds[k]
                kind = self.kinds[key] = _Kind(now)
            if kind.passed < self.burst:
                kind.passed += 1
                return True, notes
            kind.suppressed += 1
            kind.last = line
            return False, notes

    def _due(self, now: float, final: bool = False) -> list[str]:
        notes = []
        for kind in self.kinds.values():
            if final or now >= kind.since_s + self.interval_s:
                if kind.suppressed:
                    notes.append(f"recal: {kind.suppressed} similar line"
                                 f"{'s' if kind.suppressed > 1 else ''} left out in "
                                 f"{now - kind.since_s:.0f} s, the last: {kind.last}")
                kind.since_s, kind.passed, kind.suppressed = now, 0, 0
        return notes

    def flush(self) -> list[str]:
        with self.lock:
            return self._due(self.clock(), final=True)


class LineLimiter:
    """A console output (``out(line)``) that passes at most ``burst`` lines of a kind per
    ``interval_s`` and sums up the rest (see the module docstring). Thread-safe. Call
    :meth:`flush` at the end for the counts not said yet."""

    def __init__(self, out: Callable[[str], None], burst: int = BURST,
                 interval_s: float = INTERVAL_S, clock: Callable[[], float] = time.monotonic,
                 max_kinds: int = MAX_KINDS) -> None:
        self.out = out
        self._limit = _Limit(burst, interval_s, clock, max_kinds)

    def __call__(self, line: str) -> None:
        ok, notes = self._limit.admit(template(line), line)
        for note in notes:
            self.out(note)
        if ok:
            self.out(line)

    def flush(self) -> None:
        for note in self._limit.flush():
            self.out(note)


class RateLimitFilter(logging.Filter):
    """The same limit for log records, by logger and message template (``record.msg``, before
    its arguments are filled in). A summary goes out as a record of its own."""

    def __init__(self, burst: int = BURST, interval_s: float = INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic,
                 max_kinds: int = MAX_KINDS) -> None:
        super().__init__()
        self._limit = _Limit(burst, interval_s, clock, max_kinds)

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "recal_summary", False):
            return True
        key = f"{record.name}\0{template(str(record.msg))}"
        ok, notes = self._limit.admit(key, record.getMessage())
        for note in notes:
            logging.getLogger(record.name).warning(note, extra={"recal_summary": True})
        return ok


class _Stderr(logging.StreamHandler):  # type: ignore[type-arg]
    """To whatever ``sys.stderr`` is when a record comes (as Python's own last-resort handler:
    a stream bound at install time would outlive a redirection)."""

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        pass


def install_logging(level: int = logging.WARNING) -> logging.Handler:
    """Warnings and errors of every recal logger to stderr as bare lines (as Python prints
    them with no logging set up), rate-limited; returns the handler (installed once)."""
    root = logging.getLogger()
    for h in root.handlers:
        if getattr(h, "recal_console", False):
            return h
    handler = _Stderr()
    handler.setLevel(level)
    handler.addFilter(RateLimitFilter())
    handler.recal_console = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    return handler
