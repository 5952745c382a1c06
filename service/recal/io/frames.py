"""The shared half of the wire-format parsers: a delimited byte stream in, samples out.

Pure: no I/O, no clocks. A parser keeps the partial line or frame left at the end of one
``feed()`` and completes it with the next, so feeding a byte stream in one call or split at any
points gives the same samples and the same error counts. Nothing a device sends raises: bad input
is counted in ``parser.errors`` (a :class:`ParseErrors`) and skipped, and every valid sample
after it is kept, exactly once, in order. :class:`DelimitedParser` owns the byte stream
(buffering up to a delimiter, the bounded carry-over, skipping an over-long record, the reset
after a break); each format's module (`recal.io.ascii_lines`, `recal.io.cobs_frames`) decodes
the records and declares itself in a :class:`WireFormat`, and `recal.io.wire_formats` names
them.

Which auxiliary channels a stream carries (its layout) comes from, in this order of authority:
  1. the constructor's ``aux_names`` (configuration): fixed for the parser's life; a header that
     disagrees is counted in ``header_mismatch`` and ignored;
  2. the first header: fixed until :meth:`DelimitedParser.reset`; a later different header is
     a mismatch;
  3. the first valid data line, when neither is known: positional names ``aux0, aux1, ...``;
     a later header with the same number of channels renames them.
After a reset (a reconnect) a layout learnt from the stream becomes provisional: the next
header replaces it, and the next valid data line keeps it if its column count agrees, else
re-learns it positionally (another device may have been plugged in).

Error counts (names in :class:`ParseErrors`) for what is skipped: ``garbage`` (undecodable
COBS, control characters in a line), ``non_utf8``, ``too_long``, ``non_numeric``,
``wrong_columns``, ``non_finite`` (NaN/inf in any column), ``out_of_range`` (|x|,|y|,|z| above
``max_abs_xyz``; t_us negative or beyond int64), ``bad_crc``, ``bad_length``, ``bad_version``,
``header_mismatch``, ``truncated`` (a partial line/frame dropped by :meth:`reset`),
``resync_dropped`` (the first record after a reset, when nothing shows it is whole: see
:meth:`recal.io.ascii_lines.AsciiLineParser.reset`). ``header_lines``, ``comment_lines`` and
``empty_lines`` are informational and not in ``total``.

Speed: clean input takes a vectorized path (numpy over the whole chunk); only suspect lines or
frames go through the per-item path, which is the reference the fast path must agree with. So
do chunks of a few lines or frames (a sensor read as it sends), where setting up the vectorized
path would cost more than it saves. Measurements: docs/design.md, "Figures behind choices".
"""

from __future__ import annotations

import math
import types
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol

import numpy as np

from recal.samples import RawBatch

__all__ = [
    "DEFAULT_MAX_ABS_XYZ",
    "DelimitedParser",
    "DeviceStyle",
    "FrameParser",
    "Layout",
    "ParseErrors",
    "Rows",
    "WireFormat",
    "check_values",
    "keep_valid",
]

_INT64_MAX = 2**63 - 1

DEFAULT_MAX_ABS_XYZ = 1e9


@dataclass
class ParseErrors:
    """Counts of what a parser skipped (and a few informational counts), since it was made."""

    garbage: int = 0
    non_utf8: int = 0
    too_long: int = 0
    non_numeric: int = 0
    wrong_columns: int = 0
    non_finite: int = 0
    out_of_range: int = 0
    bad_crc: int = 0
    bad_length: int = 0
    bad_version: int = 0
    header_mismatch: int = 0
    truncated: int = 0
    resync_dropped: int = 0
    header_lines: int = 0
    comment_lines: int = 0
    empty_lines: int = 0

    INFORMATIONAL: ClassVar[frozenset[str]] = frozenset(
        {"header_lines", "comment_lines", "empty_lines"})

    @property
    def total(self) -> int:
        """Lines or frames rejected (informational counts excluded)."""
        return sum(v for k, v in self.as_dict().items() if k not in self.INFORMATIONAL)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def nonzero(self) -> dict[str, int]:
        return {k: v for k, v in self.as_dict().items() if v}

    def copy(self) -> ParseErrors:
        return ParseErrors(**self.as_dict())

    def __sub__(self, other: ParseErrors) -> ParseErrors:
        """Counts since ``other`` was copied: ``parser.errors - snapshot``."""
        return ParseErrors(**{k: v - getattr(other, k) for k, v in self.as_dict().items()})

    def add(self, name: str, n: int = 1) -> None:
        setattr(self, name, getattr(self, name) + n)


class FrameParser(Protocol):
    """What a byte source needs from a parser (:class:`DelimitedParser` implements it)."""

    errors: ParseErrors

    @property
    def aux_names(self) -> tuple[str, ...]: ...

    @property
    def partial(self) -> bool:
        """Whether part of a record is waiting for its delimiter."""

    @property
    def needs_time_anchor(self) -> bool:
        """Whether records without time may come and no arrival time anchors them yet: the
        shell then calls :meth:`anchor_time` with its clock before the next :meth:`feed`."""

    def anchor_time(self, t_us: int) -> None: ...

    def feed(self, data: bytes) -> RawBatch: ...

    def flush(self) -> RawBatch: ...

    def reset(self, resync: bool = True) -> None: ...


@dataclass(frozen=True)
class DeviceStyle:
    """How a (simulated) device writes its wire format; each encoder reads the fields it knows.

    Attributes:
        line_ending: "\\n" or "\\r\\n" (line formats).
        xyz: x, y, z as "int32", "float32" or "auto" (binary formats that offer both).
        time_column: False: records without time (only a format with ``untimed_by_rate``).
        header_prefix: "#" or "" before a header line.
    """

    line_ending: str = "\n"
    xyz: str = "auto"
    time_column: bool = True
    header_prefix: str = "#"


@dataclass(frozen=True)
class WireFormat:
    """One wire format as its own module declares it; `recal.io.wire_formats` lists them by
    name, and the config, the gateway and the pty device ask the record, not the name.

    Attributes:
        name: the ``format`` a sensor is configured with.
        parser: makes the streaming parser, ``parser(aux_names, **options)``.
        encode: the device side, samples to bytes: ``encode(batch, style)``.
        header: the line a device prints at boot naming its channels,
            ``header(aux_names, style)``; None when the format has none.
        untimed_by_rate: records may come without a time column when the sample rate is
            configured (the parser then takes ``rate_hz`` and stamps them from it); without
            the rate such records are counted ``wrong_columns``.
    """

    name: str
    parser: Callable[..., FrameParser]
    encode: Callable[[RawBatch, DeviceStyle], bytes]
    header: Callable[[tuple[str, ...], DeviceStyle], bytes] | None = None
    untimed_by_rate: bool = False


# --------------------------------------------------------------------------- layout


class Layout:
    """Which auxiliary channels the stream carries and how sure we are (see module docstring)."""

    def __init__(self, aux_names: Sequence[str] | None) -> None:
        self.names: tuple[str, ...] | None = None
        self.source: str | None = None  # "config" | "header" | "data" | None
        self.provisional = False
        # ASCII only: lines carry no time column (x,y,z[,aux]); None until a header or the
        # first data line says
        self.timeless: bool | None = None
        if aux_names is not None:
            self.names = tuple(str(n) for n in aux_names)
            self.source = "config"

    @property
    def settled(self) -> bool:
        """True when every further sample must have exactly ``len(names)`` channels."""
        return self.source is not None and not self.provisional

    @property
    def n_aux(self) -> int | None:
        return None if self.names is None else len(self.names)

    def reset(self) -> None:
        if self.source in ("header", "data"):
            self.provisional = True

    def on_header(self, names: tuple[str, ...], timeless: bool, errors: ParseErrors) -> None:
        if self.source is None or self.provisional:
            self.names, self.source, self.provisional = names, "header", False
            self.timeless = timeless
        elif (self.source == "data" and len(names) == len(self.names or ())
              and timeless == bool(self.timeless)):
            self.names, self.source = names, "header"  # names for positional channels
        elif self.source == "config" and names == self.names and self.timeless is None:
            self.timeless = timeless
        elif names != self.names or timeless != bool(self.timeless):
            errors.header_mismatch += 1
            return
        errors.header_lines += 1

    def accept(self, n_aux: int, timeless: bool = False) -> bool:
        """Whether a valid sample with ``n_aux`` channels (and a time column unless
        ``timeless``) fits, learning the layout if open."""
        if self.settled:
            if self.timeless is None:  # configured names: the first line says which
                self.timeless = timeless
            return n_aux == self.n_aux and timeless == self.timeless
        if not (self.provisional and n_aux == self.n_aux and timeless == bool(self.timeless)):
            self.names = tuple(f"aux{i}" for i in range(n_aux))
            self.source = "data"
        self.timeless = timeless
        self.provisional = False
        return True

    def columns(self) -> int | None:
        """Fields of an ASCII data line once the layout says (None: not yet)."""
        if not self.settled or self.timeless is None:
            return None
        return (3 if self.timeless else 4) + (self.n_aux or 0)


class Rows:
    """Samples of one feed() call collected in order, from both the fast and the slow path."""

    def __init__(self) -> None:
        self.t: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self._one_t: list[int] = []  # single samples from the per-item path, not yet arrays
        self._one_vals: list[list[float]] = []

    def add_one(self, t_us: int, vals: list[float]) -> None:
        self._one_t.append(t_us)
        self._one_vals.append(vals)

    def add_many(self, t_us: np.ndarray, vals: np.ndarray) -> None:
        self._settle()
        if len(t_us):
            self.t.append(t_us)
            self.vals.append(vals)

    def _settle(self) -> None:
        if self._one_t:
            self.t.append(np.array(self._one_t, np.int64))
            self.vals.append(np.array(self._one_vals, np.float64))
            self._one_t, self._one_vals = [], []

    def batch(self, aux_names: tuple[str, ...]) -> RawBatch:
        if not self.t and len(self._one_t) == 1 and len(self._one_vals[0]) == 3 + len(aux_names):
            # one sample (a sensor handled as it sends): its arrays made as the batch keeps them
            vals = self._one_vals[0]
            return RawBatch.of_checked(np.array(self._one_t, np.int64), np.array([vals[:3]]),
                                       np.array([vals[3:]]).reshape(1, -1), aux_names)
        self._settle()
        if not self.t:
            return RawBatch.empty(aux_names)
        vals = self.vals[0] if len(self.vals) == 1 else np.concatenate(self.vals)
        t = self.t[0] if len(self.t) == 1 else np.concatenate(self.t)
        return RawBatch(t, vals[:, :3], vals[:, 3:], aux_names)


def check_values(t_us: int, vals: list[float], max_abs_xyz: float) -> str | None:
    """Validate one sample; return the error name or None (reference for the vectorized path)."""
    if t_us < 0 or t_us > _INT64_MAX:
        return "out_of_range"
    if not all(map(math.isfinite, vals)):
        return "non_finite"
    if max(abs(vals[0]), abs(vals[1]), abs(vals[2])) > max_abs_xyz:
        return "out_of_range"
    return None


def keep_valid(vals: np.ndarray, max_abs_xyz: float, errors: ParseErrors) -> np.ndarray:
    """Vectorized twin of the value part of :func:`check_values`: mask of rows to keep."""
    finite = np.isfinite(vals).all(axis=1)
    in_range = (np.abs(vals[:, :3]) <= max_abs_xyz).all(axis=1)
    errors.non_finite += int(np.count_nonzero(~finite))
    errors.out_of_range += int(np.count_nonzero(finite & ~in_range))
    return finite & in_range


# --------------------------------------------------------------------------- the byte stream


class DelimitedParser:
    """Bytes up to a delimiter, the records between delimiters decoded by a subclass.

    Owns what both wire formats share: the tail after the last delimiter is carried to the
    next :meth:`feed` (at most ``max_record_bytes``; a longer record is counted ``too_long``
    and skipped to its delimiter), :meth:`flush` ends the stream, :meth:`reset` forgets a
    broken one. A subclass sets ``_DELIMITER`` and decodes complete records in
    :meth:`_parse_records`.
    """

    _DELIMITER: ClassVar[bytes]

    def __init__(self, aux_names: Sequence[str] | None, max_record_bytes: int,
                 max_abs_xyz: float, vectorized: bool) -> None:
        self.errors = ParseErrors()
        self.max_record_bytes = int(max_record_bytes)
        self.max_abs_xyz = float(max_abs_xyz)
        self.vectorized = vectorized
        self._layout = Layout(aux_names)
        self._pending = b""
        self._discarding = False  # inside a too-long record: drop bytes until its end
        self._resync = False  # the next record may be the tail of one cut by a reconnect
        self._delimiter = self._DELIMITER  # an instance attribute is the faster read

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Give each wire format its own copy of :meth:`feed`: CPython specializes attribute
        reads per code object, and one ``feed`` shared by an ASCII and a COBS parser in one
        process (a gateway with both kinds of sensor) would run unspecialized, slower."""
        super().__init_subclass__(**kwargs)
        shared = DelimitedParser.feed
        own = types.FunctionType(shared.__code__.replace(), shared.__globals__,
                                 shared.__name__, shared.__defaults__, shared.__closure__)
        own.__qualname__, own.__doc__ = f"{cls.__qualname__}.feed", shared.__doc__
        cls.feed = own  # type: ignore[method-assign]

    @property
    def aux_names(self) -> tuple[str, ...]:
        """Names of the auxiliary channels as currently known (empty until learnt)."""
        return self._layout.names or ()

    @property
    def partial(self) -> bool:
        """Whether part of a record is waiting for its delimiter."""
        return bool(self._pending)

    @property
    def needs_time_anchor(self) -> bool:
        """Whether records without time wait for :meth:`anchor_time` (never, unless a
        format that stamps them overrides this)."""
        return False

    def anchor_time(self, t_us: int) -> None:
        """Records without time from now on count from ``t_us`` (a format that has them
        overrides this)."""

    def feed(self, data: bytes) -> RawBatch:
        """Parse the complete records in ``pending + data``; keep the unfinished tail."""
        data = bytes(data)
        delimiter = self._delimiter
        if self._discarding:
            end = data.find(delimiter)
            if end < 0:
                return RawBatch.empty(self.aux_names)
            data, self._discarding = data[end + 1:], False
        buf = self._pending + data
        last = buf.rfind(delimiter)
        rows = Rows()
        if last >= 0:
            self._parse_records(buf, last, rows)
        tail = buf[last + 1:]
        if len(tail) > self.max_record_bytes:
            self.errors.too_long += 1
            self._resync, self._discarding, tail = False, True, b""
        self._pending = tail
        return rows.batch(self.aux_names)

    def flush(self) -> RawBatch:
        """Parse the unfinished last record as if it were ended (end of a file or recording)."""
        tail, self._pending = self._pending, b""
        self._discarding = False
        return self.feed(tail + self._delimiter) if tail else RawBatch.empty(self.aux_names)

    def reset(self, resync: bool = True) -> None:
        """Forget the partial record (counted ``truncated``) after the byte stream broke;
        with ``resync`` the first record after the break may be the tail of one."""
        if self._counts_as_truncated(self._pending):  # (a too-long one was counted already)
            self.errors.truncated += 1
        self._pending, self._discarding, self._resync = b"", False, resync
        self._layout.reset()

    def _counts_as_truncated(self, pending: bytes) -> bool:
        """Whether a partial record dropped by :meth:`reset` is counted ``truncated``."""
        return bool(pending)

    def _parse_records(self, buf: bytes, last: int, rows: Rows) -> None:
        """Decode the complete records of ``buf`` into ``rows``; ``buf[last]`` is the
        delimiter after the last of them (what follows it waits for the next feed)."""
        raise NotImplementedError
