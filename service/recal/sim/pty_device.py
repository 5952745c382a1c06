"""A simulated accelerometer on a real pseudo-terminal, for tests and ``recal demo``.

:class:`PtyDevice` opens a pty pair, puts the slave in raw mode (no echo, no newline
translation) and points a stable symlink at the slave, so a consumer opens ``link_path`` exactly
as it would open ``/dev/ttyACM0``. The device writes encoded samples on the master side.

Writes never hang: the master is non-blocking, and a write gives up at its deadline when nobody
reads the slave (a real UART drops bytes then too). :meth:`PtyDevice.unplug` closes both ends and
removes the link: the reader's next read fails with EIO and the path is gone, as when a USB
device is pulled. :meth:`PtyDevice.replug` makes a new pty behind the same link ("boots" again:
the ASCII header is sent again with the next samples).

The device's clock (``clock``): "us" writes the batch's ``t_us`` as they are; "us32" a 32-bit
``micros()`` (``t_us mod 2**32``: it wraps every 71.6 min); "ms" a ``millis()`` count
(``t_us // 1000``, still under a ``t_us`` header, as firmware often does); "none" no time
column (``x,y,z[,aux]`` lines). A device talks before anyone opens the port when it is
written to first: the pty keeps the bytes (up to its buffer) for the reader.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import threading
import time
import tty
from types import TracebackType

import numpy as np

from recal.errors import ConfigError, UsageError
from recal.io.frames import DeviceStyle
from recal.io.wire_formats import DEFAULT_FORMAT, wire_format
from recal.samples import RawBatch

__all__ = ["PtyDevice"]

_WRITE_SLICE_BYTES = 65536  # one os.write at most; bounds time spent holding the lock
_SELECT_SLICE_S = 0.01  # re-check unplug this often while waiting for room to write
_tmp_names = itertools.count()


class PtyDevice:
    """A device that writes a wire format on a pseudo-terminal behind a symlink.

    Args:
        link_path: where the symlink to the slave tty goes (replaced if it is a symlink).
        fmt: a name in :mod:`recal.io.wire_formats` ("ascii", "cobs", ...).
        header: for a format with a header (ASCII), print it (``#t_us,x,y,z,<aux>``) before
            the first samples after each (re)plug, as a device does at boot.
        write_timeout_s: how long one write waits for the reader to make room.
        line_ending: "\\n" or "\\r\\n" for ASCII.
        xyz: COBS x, y, z encoding, "auto" | "int32" | "float32".
        clock: the device's time stamps: "us", "us32", "ms" or "none" (only a format that
            takes records without time, ASCII; see the module docstring).
        header_prefix: "#" or "" (a header line without the comment mark).
    """

    CLOCKS = ("us", "us32", "ms", "none")

    def __init__(self, link_path: str, fmt: str = DEFAULT_FORMAT, header: bool = True, *,
                 write_timeout_s: float = 1.0, line_ending: str = "\n",
                 xyz: str = "auto", clock: str = "us", header_prefix: str = "#") -> None:
        try:
            self._wire = wire_format(fmt)
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
        if clock not in self.CLOCKS or (clock == "none" and not self._wire.untimed_by_rate):
            raise UsageError(f"clock must be one of {self.CLOCKS} ('none' not for {fmt!r}: "
                             f"its records carry their time)")
        if os.path.exists(link_path) and not os.path.islink(link_path):
            raise FileExistsError(f"{link_path} exists and is not a symlink")
        self.link_path = link_path
        self.fmt = fmt
        self.header = header
        self.write_timeout_s = write_timeout_s
        self.clock = clock
        # what the encoders read; a clock "none" writes no time column
        self.style = DeviceStyle(line_ending=line_ending, xyz=xyz,
                                 time_column=clock != "none", header_prefix=header_prefix)
        self._lock = threading.Lock()
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_name = ""
        self._header_due = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.samples_streamed = 0
        self.bytes_dropped = 0
        self._plug()

    # -- plugging

    @property
    def slave_name(self) -> str:
        """The pty's own device name, e.g. ``/dev/pts/3`` (changes on every replug)."""
        return self._slave_name

    @property
    def is_plugged(self) -> bool:
        return self._master is not None

    def _plug(self) -> None:
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no echo, no CR/LF translation: bytes pass through unchanged
            os.set_blocking(master, False)
            name = os.ttyname(slave)
            tmp = f"{self.link_path}.{os.getpid()}.{next(_tmp_names)}.tmp"
            os.symlink(name, tmp)
            os.replace(tmp, self.link_path)  # atomic: a reader never sees a half-made link
        except OSError:
            os.close(master)
            os.close(slave)
            raise
        with self._lock:
            self._master, self._slave, self._slave_name = master, slave, name
            self._header_due = self.header and self._wire.header is not None

    def unplug(self) -> None:
        """Close both ends and remove the link: readers get EIO, the path vanishes."""
        with self._lock:
            master, slave, name = self._master, self._slave, self._slave_name
            self._master = self._slave = None
        for fd in (master, slave):
            if fd is not None:
                os.close(fd)
        # Remove the link only if it is still ours (someone may have re-pointed it).
        with contextlib.suppress(OSError):
            if os.readlink(self.link_path) == name:
                os.unlink(self.link_path)

    def replug(self) -> None:
        """Unplug if plugged, then come back on a new pty behind the same link."""
        if self.is_plugged:
            self.unplug()
        self._plug()

    def close(self) -> None:
        """Stop streaming and unplug. Safe to call twice."""
        self.stop()
        self.join(timeout_s=2.0)
        if self.is_plugged:
            self.unplug()

    def __enter__(self) -> PtyDevice:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- writing

    def write_bytes(self, data: bytes, timeout_s: float | None = None) -> int:
        """Write raw bytes; return how many went out before the deadline (0 if unplugged)."""
        view = memoryview(bytes(data))
        deadline_s = time.monotonic() + (self.write_timeout_s if timeout_s is None
                                         else timeout_s)
        done = 0
        while done < len(view):
            with self._lock:
                fd = self._master
                if fd is None:
                    break  # unplugged: nobody hears it
                try:
                    done += os.write(fd, view[done:done + _WRITE_SLICE_BYTES])
                    continue
                except BlockingIOError:
                    pass  # the pty buffer is full: wait for the reader below
                except OSError:
                    break
            remaining_s = deadline_s - time.monotonic()
            if remaining_s <= 0:
                break
            # Short slices so an unplug from another thread is seen promptly; the fd may
            # be closed meanwhile, which select reports as an error we just retry past.
            with contextlib.suppress(OSError, ValueError):
                select.select([], [fd], [], min(remaining_s, _SELECT_SLICE_S))
        self.bytes_dropped += len(view) - done
        return done

    def write_nowait(self, data: bytes | memoryview) -> int:
        """One non-blocking write attempt; bytes written (0 if the pty is full or unplugged).

        For a caller that drives many devices from one thread (``bench/pty_fleet.py``): it
        keeps what did not fit and retries later, instead of waiting on one device.
        """
        with self._lock:
            fd = self._master
            if fd is None:
                return 0
            try:
                return os.write(fd, data)
            except OSError:  # BlockingIOError (full) or the reader side is gone
                return 0

    def write_batch(self, batch: RawBatch) -> int:
        """Write samples in the device's format (after the boot header if due); bytes written."""
        with self._lock:  # the streaming thread and the caller may both write
            header_due, self._header_due = self._header_due, False
        data = b""
        if header_due and self._wire.header is not None:
            data = self._wire.header(batch.aux_names, self.style)
        return self.write_bytes(data + self._wire.encode(self.on_wire(batch), self.style))

    def on_wire(self, batch: RawBatch) -> RawBatch:
        """The batch with the time stamps this device's clock writes."""
        if self.clock == "us32":
            return RawBatch(batch.t_us % 2**32, batch.v, batch.aux, batch.aux_names)
        if self.clock == "ms":
            return RawBatch(batch.t_us // 1000, batch.v, batch.aux, batch.aux_names)
        return batch

    def write_header(self, aux_names: tuple[str, ...]) -> int:
        """Send the format's header line now (devices may repeat it); UsageError for a
        format without one (COBS frames)."""
        if self._wire.header is None:
            raise UsageError(f"the {self.fmt!r} wire format has no header line")
        return self.write_bytes(self._wire.header(tuple(aux_names), self.style))

    def write_garbage(self, data: bytes) -> int:
        """Write arbitrary bytes (line noise, a reset banner, half a frame)."""
        return self.write_bytes(data)

    # -- streaming in real time

    def start_streaming(self, batch: RawBatch, rate_hz: float | None = None,
                        speedup: float = 1.0, chunk_samples: int | None = None) -> None:
        """Write ``batch`` in a background thread at its own pace, chunk by chunk.

        A chunk goes out when its last sample is due: at ``(t_us - t_us[0]) / speedup`` or, with
        ``rate_hz``, at ``i / (rate_hz * speedup)``. ``chunk_samples`` defaults to about 10 ms
        of samples. Unplugged periods drop their chunks, like a real device. Stops at the end,
        or at :meth:`stop`.
        """
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("already streaming")
        if rate_hz is not None:
            due_s = np.arange(len(batch)) / float(rate_hz)
        else:
            due_s = (batch.t_us - (batch.t_us[0] if len(batch) else 0)) / 1e6
        due_s = due_s / float(speedup)
        if chunk_samples is None:
            span_s = float(due_s[-1]) if len(batch) > 1 else 0.0
            per_s = (len(batch) - 1) / span_s if span_s > 0 else len(batch)
            chunk_samples = max(1, int(per_s * 0.01))
        self._stop.clear()
        self.samples_streamed = 0
        self._thread = threading.Thread(target=self._stream, args=(batch, due_s, chunk_samples),
                                        name=f"pty-device {self.link_path}", daemon=True)
        self._thread.start()

    def _stream(self, batch: RawBatch, due_s: np.ndarray, chunk_samples: int) -> None:
        start_s = time.monotonic()
        for i in range(0, len(batch), chunk_samples):
            chunk = batch[i:i + chunk_samples]
            wait_s = start_s + float(due_s[i + len(chunk) - 1]) - time.monotonic()
            if self._stop.wait(max(0.0, wait_s)):
                return
            self.write_batch(chunk)
            self.samples_streamed = i + len(chunk)

    def stop(self) -> None:
        """Ask the streaming thread to stop (returns at once; see :meth:`join`)."""
        self._stop.set()

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait for the streaming thread; True if it has finished (or never ran)."""
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    @property
    def streaming(self) -> bool:
        return self._thread is not None and self._thread.is_alive()
