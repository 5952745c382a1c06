"""Samples from a serial port: chunked reads through a streaming parser, reconnect with backoff.

A :class:`SerialSource` owns one pyserial port (``serial.serial_for_url``, so ``/dev/ttyACM0``,
a pty symlink and ``loop://`` all work) and one parser from :mod:`recal.io.wire_formats`. It reads
in two ways: :meth:`SerialSource.read_batch` waits up to a deadline and reads whatever the
port has in ``read(max(1, in_waiting))`` chunks (never ``readline()``, which costs a system
call per byte); :meth:`SerialSource.poll` never waits, reads the non-blocking descriptor
directly and exposes it (:meth:`SerialSource.fileno`) so that one selector serves many ports
(the gateway). Both parse and return the valid samples plus what happened as
:class:`SourceEvent` s. Neither raises for a device that is missing, unplugged or talking
nonsense: the port is closed, ``port_lost`` is reported, and opening is retried with
exponential backoff until ``port_found``.

First contact: the port is opened without pyserial's input flush (its POSIX ``open()`` ends
with ``tcflush``, which threw away what the device had said before we looked: a header printed
at boot, the seconds of a daemon restart), so every byte the kernel holds is read; the parser's
resync decides whether the first line is whole. A device path is opened exclusively: an
advisory ``flock`` (pyserial's ``exclusive``; a second recal fails at once, and
:func:`port_holder` names the holder's PID from /proc/locks) and the kernel's ``TIOCEXCL``
(other non-root processes cannot open the tty at all), released at close. Who owns a port is
decided by that open alone (a check before opening would race with another process starting
at the same instant): a port that is busy is reported as ``port_busy`` (with ``holder_pid``),
which the gateway treats as fatal; the source itself retries it like a missing one.
:meth:`SerialSource.open_now` makes the first attempt at once, so that a daemon learns it
lost the port before it opens anything else.
:func:`port_problem` says at start why a ``--port`` can never be a serial port (a regular
file, a directory, a character device that is no terminal such as /dev/null, a URL scheme
pyserial does not know); a path that does not exist yet is no problem (it is waited for).

Memory is bounded: one partial line or frame in the parser, at most ``max_batch_bytes`` read
per call, a handful of events per call.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import serial

from recal.io.frames import FrameParser, ParseErrors
from recal.samples import RawBatch

__all__ = ["EVENT_KINDS", "SerialSource", "SourceEvent", "port_holder", "port_problem"]

EVENT_KINDS = frozenset({"port_opened", "port_lost", "port_found", "open_failed",
                         "port_busy", "parse_errors"})
_BUSY_ERRNOS = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EBUSY)

# What a vanished or broken device raises: pyserial wraps most OS errors in SerialException,
# but in_waiting's ioctl and the path checks raise OSError directly.
_PORT_ERRORS = (serial.SerialException, OSError)


@dataclass(frozen=True)
class SourceEvent:
    """Something that happened to a source, for logs and the status topic.

    Attributes:
        kind: one of :data:`EVENT_KINDS`.
        detail: ``port``, and by kind: ``error`` (port_lost, open_failed), ``attempt`` and
            ``retry_in_s`` (open_failed), ``down_s`` (port_found: time since it was lost);
            for parse_errors the error counts added since the previous read_batch, by name
            (see :class:`recal.io.frames.ParseErrors`; informational counts left out).
        t_s: ``time.monotonic()`` when it happened.
    """

    kind: str
    detail: dict[str, Any] = field(default_factory=dict)
    t_s: float = 0.0


def _descriptor(ser: Any) -> int | None:
    """A pyserial port's non-blocking file descriptor, or None (URL ports, other platforms).

    pyserial's POSIX ports open the device with O_NONBLOCK and read it directly, so reading
    the descriptor ourselves skips its per-call select and in_waiting ioctl without changing
    what is read."""
    try:
        fd = ser.fileno()
    except (AttributeError, OSError, serial.SerialException, NotImplementedError):
        return None
    if not isinstance(fd, int) or fd < 0 or os.get_blocking(fd):
        return None
    return fd


class _PortGone(Exception):
    """The device path vanished or now names another device."""


def port_holder(path: str) -> int | None:
    """PID of the process holding an flock on the device ``path`` (Linux /proc/locks), or
    None (no lock, not Linux, or the lock belongs to another PID namespace's view)."""
    try:
        st = os.stat(path)
        with open("/proc/locks") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    want = (os.major(st.st_dev), os.minor(st.st_dev), st.st_ino)
    for line in lines:  # "1: FLOCK  ADVISORY  WRITE 1234 00:19:5 0 EOF" (major:minor in hex)
        parts = line.split()
        if len(parts) < 6 or parts[1] != "FLOCK" or "->" in parts:
            continue
        try:
            major, minor, inode = parts[5].split(":")
            if (int(major, 16), int(minor, 16), int(inode)) == want:
                return int(parts[4])
        except ValueError:
            continue
    return None


def _busy_text(path: str) -> str:
    pid = port_holder(path)
    return (f"in use by process {pid}" if pid is not None
            else "in use by another process (opened exclusively)")


def port_problem(port: str) -> str | None:
    """Why ``port`` can never be read as a serial port, or None when it can (a terminal, a
    URL scheme pyserial knows, a path that does not exist yet), or is busy now (None too:
    the open decides who owns it, see :meth:`SerialSource.open_now`)."""
    if "://" in port:
        try:
            serial.serial_for_url(port, do_not_open=True)
        except (ValueError, serial.SerialException) as exc:
            return f"{port}: {exc}"
        return None
    try:
        st = os.stat(port)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"{port}: {exc.strerror}"
    if stat.S_ISDIR(st.st_mode):
        return f"{port} is a directory, not a serial port"
    if not stat.S_ISCHR(st.st_mode):
        return f"{port} is not a character device (a regular file?), not a serial port"
    if not _is_terminal(port, st):
        return f"{port} is a character device but not a terminal, not a serial port"
    return None


def _is_terminal(port: str, st: os.stat_result) -> bool:
    """Whether a character device is a terminal, if possible without opening it (opening a
    USB serial port raises DTR, which resets many boards): a pty slave by its major number,
    else the kernel's device class in sysfs; open it only where neither tells."""
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    if 136 <= major <= 143:  # Unix98 pty slaves (/dev/pts/N)
        return True
    sysfs = f"/sys/dev/char/{major}:{minor}/subsystem"
    if os.path.exists(sysfs):
        return os.path.basename(os.path.realpath(sysfs)) == "tty"
    try:  # O_NONBLOCK | O_NOCTTY: does not wait for carrier, does not become our terminal
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        return exc.errno in _BUSY_ERRNOS  # held exclusively: only a tty can be
    try:
        return os.isatty(fd)
    finally:
        os.close(fd)


def _open_unflushed(port: str, exclusive: bool, **kwargs: Any) -> Any:
    """``serial.serial_for_url(port, ...)``, opened without the input flush that pyserial
    3.5's POSIX ``open()`` ends with: bytes the device sent before the open stay readable."""
    if exclusive:
        kwargs["exclusive"] = True
    ser = serial.serial_for_url(port, do_not_open=True, **kwargs)
    # 3.5 calls _reset_input_buffer() at the end of open(), earlier releases the public one:
    # shadowed on the instance during open() only
    flushes = [n for n in ("_reset_input_buffer", "reset_input_buffer") if hasattr(ser, n)]
    for name in flushes:
        setattr(ser, name, lambda: None)
    try:
        ser.open()
    finally:
        for name in flushes:
            delattr(ser, name)
    fd = getattr(ser, "fd", None)
    if exclusive and isinstance(fd, int):
        try:  # the kernel's own exclusive open: other (non-root) opens get EBUSY
            fcntl.ioctl(fd, termios.TIOCEXCL)
        except OSError:
            pass  # not a tty that supports it; the flock still guards recal against recal
    return ser


@dataclass
class _Reopen:
    """When to try opening a closed port again, and how the tries went: the delay doubles
    from ``initial_s`` up to ``max_s`` with each failed open and starts again after a
    success."""

    initial_s: float
    max_s: float
    delay_s: float = field(init=False)  # the wait after the next failed open
    next_open_s: float = 0.0  # on the source's clock
    attempts: int = 0  # failed opens since the last success
    ever_opened: bool = False
    lost_at_s: float | None = None

    def __post_init__(self) -> None:
        self.delay_s = self.initial_s

    def failed(self, now_s: float) -> float:
        """Count a failed open at ``now_s``; the delay until the next one."""
        self.attempts += 1
        delay_s = self.delay_s
        self.next_open_s = now_s + delay_s
        self.delay_s = min(2.0 * delay_s, self.max_s)
        return delay_s

    def opened(self, now_s: float) -> float | None:
        """Count an open at ``now_s``; how long the port was down (None: its first open)."""
        down_s = None
        if self.ever_opened:
            down_s = now_s - (self.lost_at_s if self.lost_at_s is not None else now_s)
        self.delay_s, self.attempts, self.ever_opened = self.initial_s, 0, True
        return down_s

    def lost(self, now_s: float) -> None:
        """The open port failed at ``now_s``: the next open after the current delay."""
        self.lost_at_s = now_s
        self.next_open_s = now_s + self.delay_s


class SerialSource:
    """One serial device read through a streaming parser.

    Args:
        port: device path or pyserial URL (``loop://``, ``/tmp/recal-dev0``, ``/dev/ttyUSB0``).
        parser: a parser from :func:`recal.io.wire_formats.make_parser` (it keeps partial lines).
        baudrate: line rate (ignored by ptys and ``loop://``).
        read_timeout_s: longest a single read waits for a first byte; bounds the latency of
            noticing the deadline, and is the pyserial ``timeout``.
        backoff_initial_s, backoff_max_s: reopen delays double from initial up to max.
        max_read_bytes: largest single read.
        max_batch_bytes: stop reading in one read_batch call after this many bytes.
        path_check_interval_s: how often to check that a device path still exists and still
            names the opened device (catches an unplug that reads do not report).
        serial_kwargs: more keyword arguments for ``serial.serial_for_url``.
        clock: monotonic clock in seconds (tests may pass their own).
    """

    def __init__(self, port: str, parser: FrameParser, baudrate: int = 115200, *,
                 read_timeout_s: float = 0.01, backoff_initial_s: float = 0.05,
                 backoff_max_s: float = 2.0, max_read_bytes: int = 65536,
                 max_batch_bytes: int = 1 << 20, path_check_interval_s: float = 0.25,
                 serial_kwargs: dict[str, Any] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.port = port
        self.parser = parser
        self.baudrate = baudrate
        self.read_timeout_s = read_timeout_s
        self.max_read_bytes = max_read_bytes
        self.max_batch_bytes = max_batch_bytes
        self.path_check_interval_s = path_check_interval_s
        self._serial_kwargs = dict(serial_kwargs or {})
        self._clock = clock
        self._ser: Any = None
        self._fd: int | None = None
        self._closed = False
        self._reopen = _Reopen(backoff_initial_s, backoff_max_s)
        self._device_id: tuple[int, int] | None = None
        self._next_path_check_s = 0.0
        self._errors_seen = parser.errors.copy()
        self._carry: RawBatch | None = None

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def read_batch(self, max_wait_s: float = 0.1, *,
                   min_samples: int = 1) -> tuple[RawBatch, list[SourceEvent]]:
        """Read for at most ``max_wait_s`` and return (samples, events).

        Returns early once ``min_samples`` samples were parsed and the port had nothing more
        waiting, when the port is lost, or after ``max_batch_bytes``. Opens (or reopens, on
        the backoff schedule) the port as needed. Samples are in arrival order; the batch has
        the parser's auxiliary names. Never raises for port or data trouble.
        """
        deadline_s = self._clock() + max(0.0, max_wait_s)
        events: list[SourceEvent] = []
        batches: list[RawBatch] = [self._carry] if self._carry is not None else []
        self._carry = None
        n_samples = sum(len(b) for b in batches)
        n_bytes = 0
        while not self._closed:
            if self._ser is None:
                self._open_when_due(deadline_s, events)
                if self._ser is None:
                    if self._clock() >= deadline_s:
                        break
                    continue
            try:
                waiting = self._ser.in_waiting
                data = self._ser.read(max(1, min(waiting, self.max_read_bytes)))
                self._check_path()
            except (*_PORT_ERRORS, _PortGone) as exc:
                self._lose(exc, events)
                break
            if data:
                n_bytes += len(data)
                batch = self._feed(data)
                if len(batch) and batches and batch.aux.shape[1] != batches[-1].aux.shape[1]:
                    self._carry = batch  # new layout: starts the next call's batch
                    break
                if len(batch):
                    batches.append(batch)
                    n_samples += len(batch)
            drained = waiting < self.max_read_bytes
            if (n_samples >= min_samples and drained) or n_bytes >= self.max_batch_bytes:
                break
            if self._clock() >= deadline_s:
                break
        self._report_parse_errors(events)
        return self._join(batches), events

    def open_now(self) -> list[SourceEvent]:
        """Try to open the port now, whatever the back-off schedule says; what happened
        (``port_opened``, ``open_failed`` for a port that is not there yet, ``port_busy``
        for one another process holds). Nothing is read: the bytes wait in the kernel."""
        events: list[SourceEvent] = []
        if self._ser is None and not self._closed:
            self._try_open(events)
        return events

    def fileno(self) -> int | None:
        """The open port's file descriptor, for a selector; None if closed or not a file."""
        return self._fd

    @property
    def next_open_s(self) -> float:
        """When (on ``clock``) the next open attempt of a closed port is due."""
        return self._reopen.next_open_s

    def poll(self, readable: bool = False) -> tuple[RawBatch, list[SourceEvent]]:
        """Never wait: open the port if an attempt is due, read what is waiting, parse it.

        The non-blocking twin of :meth:`read_batch` for a caller that serves many ports from
        one selector loop (``recal.daemon.gateway``): call it when the selector reports the port
        readable (``readable=True``: no bytes then means the device hung up, as pyserial
        decides too), and now and then regardless, so that opening retries and the path check
        run. Reads at most ``max_batch_bytes``. Never raises for port or data trouble.
        """
        events: list[SourceEvent] = []
        batches: list[RawBatch] = [self._carry] if self._carry is not None else []
        self._carry = None
        if self._ser is None and not self._closed and self._clock() >= self._reopen.next_open_s:
            self._try_open(events)
        if self._ser is not None:
            try:
                data = self._read_waiting(readable)
                self._check_path()
            except (*_PORT_ERRORS, _PortGone) as exc:
                data = b""
                self._lose(exc, events)
            if data:
                batch = self._feed(data)
                if len(batch) and batches and batch.aux.shape[1] != batches[0].aux.shape[1]:
                    self._carry, batch = batch, RawBatch.empty(batch.aux_names)
                if len(batch):
                    batches.append(batch)
        self._report_parse_errors(events)
        return self._join(batches), events

    def _read_waiting(self, readable: bool) -> bytes:
        """Every byte the port has now, up to ``max_batch_bytes``, without waiting.

        A tty in pyserial's raw mode (VMIN = VTIME = 0) answers an empty read with 0 bytes,
        not EAGAIN, so 0 bytes means "hung up" only when the selector said readable."""
        if self._fd is None:  # a URL port without a descriptor (loop://): ask pyserial
            waiting = self._ser.in_waiting
            return bytes(self._ser.read(min(waiting, self.max_batch_bytes))) if waiting else b""
        parts: list[bytes] = []
        total = 0
        while total < self.max_batch_bytes:
            try:
                part = os.read(self._fd, min(self.max_read_bytes, self.max_batch_bytes - total))
            except BlockingIOError:
                break
            if not part:
                if readable and not parts:
                    raise _PortGone(f"{self.port} reports data but returns none (hung up)")
                break
            if len(part) < self.max_read_bytes:  # drained: a further read would say EAGAIN
                if not parts:
                    return part  # the usual case (a line or a few per wake-up): no join
                parts.append(part)
                break
            parts.append(part)
            total += len(part)
        return b"".join(parts)

    def _feed(self, data: bytes) -> RawBatch:
        """Parse bytes; lines without time are stamped from their first arrival (wall clock,
        microseconds since the epoch) on."""
        if self.parser.needs_time_anchor:
            self.parser.anchor_time(time.time_ns() // 1000)
        return self.parser.feed(data)

    def write(self, data: bytes) -> int:
        """Send bytes to the device (a command); bytes written, 0 if the port is not open.

        A failing write is not raised: the next read_batch notices a lost port.
        """
        if self._ser is None:
            return 0
        try:
            return int(self._ser.write(data) or 0)
        except _PORT_ERRORS:
            return 0

    def close(self) -> None:
        """Close the port; later read_batch calls return nothing."""
        self._closed = True
        self._close_port()

    def __enter__(self) -> SerialSource:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- opening and losing the port

    def _open_when_due(self, deadline_s: float, events: list[SourceEvent]) -> None:
        """Sleep until the next open attempt if it falls before the deadline, then try."""
        now_s, next_open_s = self._clock(), self._reopen.next_open_s
        if now_s < next_open_s:
            if next_open_s > deadline_s:
                time.sleep(max(0.0, deadline_s - now_s))
                return
            time.sleep(next_open_s - now_s)
        self._try_open(events)

    def _try_open(self, events: list[SourceEvent]) -> None:
        now_s = self._clock()
        try:
            ser = _open_unflushed(self.port, self._is_path(), baudrate=self.baudrate,
                                  timeout=self.read_timeout_s, **self._serial_kwargs)
        except (*_PORT_ERRORS, ValueError) as exc:
            if self._is_path() and getattr(exc, "errno", None) in _BUSY_ERRNOS:
                self._open_failed(exc, now_s, events, busy=True)
            else:
                self._open_failed(exc, now_s, events)
            return
        try:
            device_id = self._path_device_id()
        except OSError as exc:  # vanished between open and stat
            ser.close()
            self._open_failed(exc, now_s, events)
            return
        self._ser, self._device_id = ser, device_id
        self._fd = _descriptor(ser)
        self._next_path_check_s = now_s + self.path_check_interval_s
        # The first bytes may be the tail of a line the device was sending before we looked.
        self.parser.reset(resync=True)
        down_s = self._reopen.opened(now_s)
        if down_s is not None:
            events.append(SourceEvent("port_found", {"port": self.port, "down_s": down_s},
                                      now_s))
        else:
            events.append(SourceEvent("port_opened", {"port": self.port}, now_s))

    def _open_failed(self, exc: BaseException, now_s: float,
                     events: list[SourceEvent], busy: bool = False) -> None:
        delay_s = self._reopen.failed(now_s)
        detail: dict[str, Any] = {"port": self.port, "error": str(exc),
                                  "attempt": self._reopen.attempts, "retry_in_s": delay_s}
        if busy:
            holder = port_holder(self.port)
            detail.update(error=_busy_text(self.port), holder_pid=holder)
        events.append(SourceEvent("port_busy" if busy else "open_failed", detail, now_s))

    def _lose(self, exc: BaseException, events: list[SourceEvent]) -> None:
        now_s = self._clock()
        self._close_port()
        # A partial line from before the unplug must not be glued to the new device's bytes.
        self.parser.reset(resync=True)
        self._reopen.lost(now_s)
        events.append(SourceEvent("port_lost", {"port": self.port, "error": str(exc)}, now_s))

    def _close_port(self) -> None:
        ser, self._ser, self._fd = self._ser, None, None
        if ser is not None:
            fd = getattr(ser, "fd", None)
            if self._is_path() and isinstance(fd, int):
                try:  # TIOCEXCL outlives us while the tty stays open elsewhere (a pty's
                    fcntl.ioctl(fd, termios.TIOCNXCL)  # device side): clear it
                except OSError:
                    pass
            try:
                ser.close()
            except _PORT_ERRORS:
                pass  # closing a dead device may fail; it is closed as far as we care

    # -- noticing a device path that vanished

    def _is_path(self) -> bool:
        return "://" not in self.port

    def _path_device_id(self) -> tuple[int, int] | None:
        """(st_ino, st_rdev) of what the path names now (following symlinks), or None."""
        if not self._is_path():
            return None
        st = os.stat(self.port)
        return st.st_ino, st.st_rdev

    def _check_path(self) -> None:
        if self._device_id is None or self._clock() < self._next_path_check_s:
            return
        self._next_path_check_s = self._clock() + self.path_check_interval_s
        try:
            now_id = self._path_device_id()
        except FileNotFoundError:
            raise _PortGone(f"{self.port} vanished") from None
        if now_id != self._device_id:
            raise _PortGone(f"{self.port} now names another device")

    # -- results

    def _report_parse_errors(self, events: list[SourceEvent]) -> None:
        if self.parser.errors == self._errors_seen:
            return  # the usual case, checked without building the difference
        delta: ParseErrors = self.parser.errors - self._errors_seen
        self._errors_seen = self.parser.errors.copy()
        if delta.total > 0:
            counts = {k: v for k, v in delta.nonzero().items()
                      if k not in ParseErrors.INFORMATIONAL}
            events.append(SourceEvent("parse_errors", {"port": self.port, **counts},
                                      self._clock()))

    def _join(self, batches: list[RawBatch]) -> RawBatch:
        names = self.parser.aux_names
        if not batches:
            return RawBatch.empty(names)
        # Within one connection only a rename can happen (a header naming positional
        # channels); label the whole batch with the newest names.
        last = batches[-1].aux_names
        if len(batches) == 1:
            return batches[0]  # the usual case: no copy
        return RawBatch.concat([b if b.aux_names == last else
                                RawBatch(b.t_us, b.v, b.aux, last) for b in batches])
