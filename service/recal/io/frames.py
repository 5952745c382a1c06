"""Wire formats of accelerometer devices: streaming parsers (bytes in, samples out) and encoders.

Pure: no I/O, no clocks. A parser keeps the partial line or frame left at the end of one
``feed()`` and completes it with the next, so feeding a byte stream in one call or split at any
points gives the same samples and the same error counts. Nothing a device sends raises: bad input
is counted in ``parser.errors`` (a :class:`ParseErrors`) and skipped, and every valid sample
after it is kept, exactly once, in order.

ASCII lines (``fmt="ascii"``)
-----------------------------
One sample a line, ``t_us,x,y,z[,aux...]``, ended by ``\\n`` or ``\\r\\n``. ``t_us`` is a
non-negative integer (an integral float literal below 2**53 is accepted too); x, y, z and aux are
decimal numbers (integer ADC counts or floats). A header line names the columns,
``t_us,x,y,z,temp_c,vdd_v`` or ``#t_us,x,y,z,temp_c,vdd_v``: every field a name (a letter or
``_`` first, no spaces), at least four fields. The first four names are ignored (their meaning
is fixed by position); the rest name the auxiliary channels. Other ``#`` lines are comments.
Lines without a time column, ``x,y,z[,aux...]`` (a header whose first name is an x axis:
``x``, ``ax``, ``acc_x``...; or, without a header, three fields), are accepted when the parser
knows the rate (``rate_hz``): sample i since the last anchor is stamped
``anchor + round(i * 1e6 / rate_hz)`` (:meth:`AsciiLineParser.anchor_time`: the shell's clock
at the first arrival).

Which auxiliary channels a stream carries (its layout) comes from, in this order of authority:
  1. the constructor's ``aux_names`` (configuration): fixed for the parser's life; a header that
     disagrees is counted in ``header_mismatch`` and ignored;
  2. the first header: fixed until :meth:`reset`; a later different header is a mismatch;
  3. the first valid data line, when neither is known: positional names ``aux0, aux1, ...``;
     a later header with the same number of channels renames them.
After :meth:`reset` (a reconnect) a layout learnt from the stream becomes provisional: the next
header replaces it, and the next valid data line keeps it if its column count agrees, else
re-learns it positionally (another device may have been plugged in).

COBS frames (``fmt="cobs"``)
----------------------------
Each frame is ``cobs.encode(payload) + b"\\x00"``; the zero byte is the delimiter and the sync
(COBS guarantees no zero inside an encoded frame). Payload, all little-endian, 25 + 4*K bytes::

    offset  size  field
    0       1     version, 1
    1       1     flags: bit 0 set = x, y, z are float32; clear = int32 counts (exact);
                  other bits reserved, must be 0
    2       1     K, number of auxiliary channels (0..32); fixes the payload length
    3       8     t_us, int64
    11      12    x, y, z: 3 x int32 or 3 x float32 (see flags)
    23      4*K   aux channels, float32 each
    23+4K   2     CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 0 .. 22+4K,
                  i.e. ``binascii.crc_hqx(payload[:-2], 0xFFFF)``, as uint16

A payload is at most 153 bytes, so an encoded frame is 1 byte longer than its payload (one
COBS block, no 0xFF code). Binary frames carry no channel names: they come from the
constructor, else positionally as for ASCII.

Error counts (names in :class:`ParseErrors`) for what is skipped: ``garbage`` (undecodable
COBS, control characters in a line), ``non_utf8``, ``too_long``, ``non_numeric``,
``wrong_columns``, ``non_finite`` (NaN/inf in any column), ``out_of_range`` (|x|,|y|,|z| above
``max_abs_xyz``; t_us negative or beyond int64), ``bad_crc``, ``bad_length``, ``bad_version``,
``header_mismatch``, ``truncated`` (a partial line/frame dropped by :meth:`reset`),
``resync_dropped`` (the first line after a reset, when nothing shows it is whole: see
:meth:`AsciiLineParser.reset`). ``header_lines``,
``comment_lines`` and ``empty_lines`` are informational and not in ``total``.

Speed: clean input takes a vectorized path (numpy over the whole chunk; ``np.fromstring`` for
ASCII numbers; a vectorized COBS decode and CRC for frames); only suspect lines or frames go
through the per-item path, which is the reference the fast path must agree with. So do chunks
of a few lines or frames (a sensor read as it sends), where setting up the vectorized path
would cost more than it saves.
"""

from __future__ import annotations

import binascii
import math
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import ClassVar, Protocol

import numpy as np
from cobs import cobs

from recal.samples import RawBatch

__all__ = [
    "COBS_FLAG_XYZ_FLOAT32",
    "COBS_MAX_AUX",
    "COBS_VERSION",
    "AsciiLineParser",
    "CobsFrameParser",
    "FrameParser",
    "ParseErrors",
    "cobs_payload_bytes",
    "crc16_ccitt_false",
    "encode_ascii",
    "encode_cobs",
    "make_parser",
]

COBS_VERSION = 1
COBS_FLAG_XYZ_FLOAT32 = 0x01
COBS_MAX_AUX = 32
_COBS_FIXED_BYTES = 25  # version, flags, K, t_us, x, y, z, CRC

_T_EXACT_LIMIT = 2**53  # a float t_us below this is an exact integer
_INT64_MAX = 2**63 - 1

DEFAULT_MAX_ABS_XYZ = 1e9
DEFAULT_MAX_LINE_BYTES = 4096
DEFAULT_MAX_FRAME_BYTES = 512


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
    """What a byte source needs from a parser (both parsers here implement it)."""

    errors: ParseErrors

    @property
    def aux_names(self) -> tuple[str, ...]: ...

    def feed(self, data: bytes) -> RawBatch: ...

    def flush(self) -> RawBatch: ...

    def reset(self, resync: bool = True) -> None: ...


# --------------------------------------------------------------------------- layout


class _Layout:
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


class _Rows:
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
        self._settle()
        if not self.t:
            return RawBatch.empty(aux_names)
        vals = self.vals[0] if len(self.vals) == 1 else np.concatenate(self.vals)
        t = self.t[0] if len(self.t) == 1 else np.concatenate(self.t)
        return RawBatch(t, vals[:, :3], vals[:, 3:], aux_names)


def _check_values(t_us: int, vals: list[float], max_abs_xyz: float) -> str | None:
    """Validate one sample; return the error name or None (reference for the vectorized path)."""
    if t_us < 0 or t_us > _INT64_MAX:
        return "out_of_range"
    if not all(map(math.isfinite, vals)):
        return "non_finite"
    if max(abs(vals[0]), abs(vals[1]), abs(vals[2])) > max_abs_xyz:
        return "out_of_range"
    return None


def _keep_valid(vals: np.ndarray, max_abs_xyz: float, errors: ParseErrors) -> np.ndarray:
    """Vectorized twin of the value part of :func:`_check_values`: mask of rows to keep."""
    finite = np.isfinite(vals).all(axis=1)
    in_range = (np.abs(vals[:, :3]) <= max_abs_xyz).all(axis=1)
    errors.non_finite += int(np.count_nonzero(~finite))
    errors.out_of_range += int(np.count_nonzero(finite & ~in_range))
    return finite & in_range


# --------------------------------------------------------------------------- ASCII

_FLOAT_RE = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf|infinity)",
                       re.IGNORECASE)
_INT_RE = re.compile(r"[+-]?\d+")
_NAME_RE = re.compile(r"[^\W\d][^\s,]*")
# a header's first name: a time column, or the x axis (lines without time: x,y,z[,aux])
_TIME_NAME_RE = re.compile(r"t|ts|time|timestamp|(t|time)_?(us|ms|s)|micros|millis",
                           re.IGNORECASE)
_X_NAME_RE = re.compile(r"(a|acc|accel)?_?x(_\w+)?", re.IGNORECASE)
_CONTROL_RE = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")
# Bytes the vectorized ASCII path lets through to np.fromstring; a line with any other byte
# (letters, spaces, '#', non-ASCII, control characters) takes the per-line path.
_FAST_BYTES = b"0123456789.+-eE,\r\n"
_FAST_TABLE = np.ones(256, bool)
_FAST_TABLE[list(_FAST_BYTES)] = False  # True marks a byte the fast path does not take


def _is_header(fields_: list[str]) -> bool:
    """Every field a name, at least four (``t,x,y,z``), or three from an x axis (``x,y,z``)."""
    return (len(fields_) >= 4 or (len(fields_) == 3 and _X_NAME_RE.fullmatch(fields_[0])
                                  is not None)) and all(
        _NAME_RE.fullmatch(f) and not _FLOAT_RE.fullmatch(f) for f in fields_)


def _header_layout(fields_: list[str]) -> tuple[tuple[str, ...], bool]:
    """(aux names, timeless) of a header: a first name like ``x`` or ``ax`` means no time."""
    timeless = (_X_NAME_RE.fullmatch(fields_[0]) is not None
                and _TIME_NAME_RE.fullmatch(fields_[0]) is None)
    return tuple(fields_[3 if timeless else 4:]), timeless




def _parse_t_us(token: str) -> int | str:
    """t_us from one field: an int, or the error name."""
    if _INT_RE.fullmatch(token):
        return int(token)
    if not _FLOAT_RE.fullmatch(token):
        return "non_numeric"
    value = float(token)
    if not math.isfinite(value):
        return "non_finite"
    # An integral float literal is a time stamp only where float64 is still exact.
    if value != math.floor(value) or abs(value) >= _T_EXACT_LIMIT:
        return "non_numeric"
    return int(value)


class AsciiLineParser:
    """Streaming parser of ``t_us,x,y,z[,aux...]`` lines (see the module docstring).

    Args:
        aux_names: auxiliary channel names from configuration; None to learn them from a header.
        max_line_bytes: longer lines are counted ``too_long`` and skipped; also bounds the
            partial line kept between calls.
        max_abs_xyz: samples with a larger |x|, |y| or |z| are ``out_of_range``.
        vectorized: False parses every line on the per-line path (for tests and debugging).
        vectorize_min_lines: a chunk with fewer complete lines than this goes line by line,
            which is cheaper at the read sizes of a sensor handled as it sends (one line per
            read: 10 us against 35 us warm, 90 us against 170 us right after a wake-up).
        rate_hz: the device's sample rate, if known; then lines without a time column
            (``x,y,z[,aux]``: a header starting with ``x``, or 3 fields with no header) are
            accepted and stamped ``origin + round(i * 1e6 / rate_hz)`` (see
            :meth:`anchor_time`).
    """

    def __init__(self, aux_names: Sequence[str] | None = None, *,
                 max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
                 max_abs_xyz: float = DEFAULT_MAX_ABS_XYZ, vectorized: bool = True,
                 vectorize_min_lines: int = 7, rate_hz: float | None = None) -> None:
        self.errors = ParseErrors()
        self.max_line_bytes = int(max_line_bytes)
        self.max_abs_xyz = float(max_abs_xyz)
        self.vectorized = vectorized
        self.vectorize_min_lines = int(vectorize_min_lines)
        self._layout = _Layout(aux_names)
        self._pending = b""
        self._discarding = False  # inside a too-long line: drop bytes until its end
        self._resync = False  # the next line may be the tail of a line cut by a reconnect
        self._candidate: bytes | None = None  # that line, until the next one says if whole
        self.rate_hz = None if rate_hz is None else float(rate_hz)
        self._origin_us = 0  # time of the first line without time since the last anchor
        self._since_origin = 0  # such lines since then
        self._next_timeless_us: int | None = None  # the time the next one would get
        self._anchor_due = True

    @property
    def needs_time_anchor(self) -> bool:
        """Whether lines without time may come and no arrival time anchors them yet."""
        return self._anchor_due and self.rate_hz is not None

    def anchor_time(self, t_us: int) -> None:
        """Lines without time from now on count from ``t_us`` (the shell's clock at their
        arrival; never before a time already given out)."""
        nxt = self._next_timeless_us
        self._origin_us = int(t_us) if nxt is None else max(int(t_us), nxt)
        self._since_origin = 0
        self._anchor_due = False

    @property
    def aux_names(self) -> tuple[str, ...]:
        """Names of the auxiliary channels as currently known (empty until learnt)."""
        return self._layout.names or ()

    @property
    def partial(self) -> bool:
        """Whether part of a line is waiting for its end."""
        return bool(self._pending)

    def feed(self, data: bytes) -> RawBatch:
        """Parse the complete lines in ``pending + data``; keep the unfinished tail."""
        data = bytes(data)
        if self._discarding:
            end = data.find(b"\n")
            if end < 0:
                return RawBatch.empty(self.aux_names)
            data, self._discarding = data[end + 1:], False
        buf = self._pending + data
        last = buf.rfind(b"\n")
        rows = _Rows()
        if last >= 0:
            self._parse_lines(buf[:last + 1], rows)
        tail = buf[last + 1:]
        if len(tail) > self.max_line_bytes:
            self.errors.too_long += 1
            self._resync, self._discarding, tail = False, True, b""
        self._pending = tail
        return rows.batch(self.aux_names)

    def flush(self) -> RawBatch:
        """Parse the unfinished last line as if it were ended (end of a file or recording)."""
        tail, self._pending = self._pending, b""
        self._discarding = False
        out = self.feed(tail + b"\n") if tail else RawBatch.empty(self.aux_names)
        self._drop_candidate()  # nothing came after it to vouch for it
        return out

    def reset(self, resync: bool = True) -> None:
        """Forget the partial line (counted ``truncated``) after the byte stream broke.

        With ``resync`` the first line after the break may be the tail of a line, which can
        look like a valid sample or header. It is held until the next line, and kept when that
        line vouches for it: a header (or a ``#`` line, taken at once) when the next line has
        as many fields; a sample when the next one has as many fields and, with a time column,
        ``0 < t1 - t0 <= t1 / 2`` (a tail cut in the time field lost its leading digits, so it
        is at least half of t1 behind; cut anywhere else it has fewer fields). Else it is
        dropped (``resync_dropped``). A line without time cannot be vouched for. Lines
        without time are anchored again at the next arrival.
        """
        if self._pending.strip():  # (a too-long line being skipped was counted already)
            self.errors.truncated += 1
        self._drop_candidate()
        self._pending, self._discarding, self._resync = b"", False, resync
        self._anchor_due = True
        self._layout.reset()

    def _drop_candidate(self) -> None:
        if self._candidate is not None:
            self._candidate = None
            self._resync = False
            self.errors.resync_dropped += 1

    # -- per-line path (the reference)

    def _parse_lines(self, chunk: bytes, rows: _Rows) -> None:
        """Parse complete lines (``chunk`` ends with a newline)."""
        if not self.vectorized or chunk.count(b"\n") < self.vectorize_min_lines:
            # Also for a sensor handled as its samples arrive (one line per call): setting up
            # the vectorized path (a dozen numpy calls) costs more than the per-line path,
            # which is the reference the vectorized one agrees with, so the result is the same.
            for line in chunk.split(b"\n")[:-1]:
                self._one_line(line, rows)
            return
        arr = np.frombuffer(chunk, np.uint8)
        ends = np.flatnonzero(arr == 10)
        starts = np.concatenate(([0], ends[:-1] + 1))
        first = 0
        # Until the layout is known (and while a resync is due) each line may change how the
        # next ones read, so go line by line; that is a handful of lines per connection.
        # Lines without time (a slow sensor's few per read) always go line by line.
        while first < len(ends) and (self._resync or not self._layout.settled
                                     or self._layout.timeless is not False):
            self._one_line(chunk[starts[first]:ends[first]], rows)
            first += 1
        if first < len(ends):
            self._fast_lines(chunk, arr, starts[first:], ends[first:], rows)

    def _one_line(self, line: bytes, rows: _Rows) -> None:
        if self._resync and len(line) <= self.max_line_bytes and line.strip():
            if self._candidate is None:
                if not self._resync_first(line):
                    return  # held: the next line decides
            else:
                candidate, self._candidate, self._resync = self._candidate, None, False
                if self._whole(candidate, line):
                    self._one_line(candidate, rows)
                else:
                    self.errors.resync_dropped += 1
        result = self._line_result(line)
        if isinstance(result, tuple):
            rows.add_one(*result)
        elif result is not None:
            self.errors.add(result)

    def _resync_first(self, line: bytes) -> bool:
        """The first line after a break: True to parse it now (a ``#`` header or comment:
        a tail does not start with ``#``), False when it is held for the next line."""
        if line.lstrip().startswith(b"#"):
            self._resync = False
            return True
        self._candidate = bytes(line)
        return False

    def _whole(self, candidate: bytes, nxt: bytes) -> bool:
        """Whether the line after ``candidate`` shows it whole: a header by the same number
        of fields (the tail ``x,y,z,vdd`` of ``t_us,x,y,z,vdd`` has one field less than the
        lines after it; a tail cut inside the first name keeps the channel names right), a
        sample by :func:`_vouches`; a line without time never."""
        try:
            names = [f.strip() for f in candidate.decode("ascii").split(",")]
        except UnicodeDecodeError:
            return False
        if _is_header(names):
            return len(names) == nxt.count(b",") + 1
        return self._layout.timeless is not True and _vouches(candidate, nxt)

    def _line_result(self, line: bytes) -> tuple[int, list[float]] | str | None:
        """One line (without its newline): a sample, an error name, or None (nothing to count)."""
        if len(line) > self.max_line_bytes:
            self._drop_candidate()
            self._resync = False
            return "too_long"
        try:
            text = line.decode("utf-8")
        except UnicodeDecodeError:
            return "non_utf8"
        if _CONTROL_RE.search(text):
            return "garbage"
        text = text.strip()
        if not text:
            return "empty_lines"
        if text.startswith("#"):
            names = [f.strip() for f in text[1:].split(",")]
            if not _is_header(names):
                return "comment_lines"
            self._layout.on_header(*_header_layout(names), errors=self.errors)
            return None
        tokens = [f.strip() for f in text.split(",")]
        if _is_header(tokens):
            self._layout.on_header(*_header_layout(tokens), errors=self.errors)
            return None
        return self._data_tokens(tokens)

    def _timeless(self, n_tokens: int) -> bool:
        """Whether a data line of ``n_tokens`` fields is read as ``x,y,z[,aux]``."""
        layout = self._layout
        if layout.timeless is not None and (layout.settled or layout.provisional):
            return layout.timeless
        if self.rate_hz is None:
            return False
        if layout.n_aux is not None:  # configured names: their count says
            return n_tokens == 3 + layout.n_aux
        return n_tokens == 3  # t,x,y,z or x,y,z,aux? time first, as always

    def _data_tokens(self, tokens: list[str]) -> tuple[int, list[float]] | str:
        layout = self._layout
        timeless = self._timeless(len(tokens))
        if timeless and self.rate_hz is None:
            return "wrong_columns"  # a header said x,y,z but nothing gives the rate
        first = 0 if timeless else 1
        if len(tokens) < 3 + first or (layout.settled and len(tokens) != 3 + first
                                       + (layout.n_aux or 0)):
            return "wrong_columns"
        if timeless:
            t_us: int | str = self._timeless_t_us()
        else:
            t_us = _parse_t_us(tokens[0])
        if isinstance(t_us, str):
            return t_us
        if not all(_FLOAT_RE.fullmatch(tok) for tok in tokens[first:]):
            return "non_numeric"
        vals = [float(tok) for tok in tokens[first:]]
        error = _check_values(t_us, vals, self.max_abs_xyz)
        if error is not None:
            return error
        if not layout.accept(len(tokens) - 3 - first, timeless):
            return "wrong_columns"
        if timeless:
            self._since_origin += 1
            self._next_timeless_us = self._timeless_t_us()
        return t_us, vals

    def _timeless_t_us(self) -> int:
        """The time of the next line without time: origin + i / rate (no drift over days)."""
        assert self.rate_hz is not None
        return self._origin_us + round(self._since_origin * 1e6 / self.rate_hz)

    # -- vectorized path

    def _fast_lines(self, chunk: bytes, arr: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                    rows: _Rows) -> None:
        """Parse lines with a settled layout: numpy over clean runs, per-line for suspects."""
        n_cols = 4 + (self._layout.n_aux or 0)
        suspect = (ends - starts) > self.max_line_bytes
        if chunk.translate(None, _FAST_BYTES):  # rare: some byte np.fromstring must not see
            bad_pos = np.flatnonzero(_FAST_TABLE[arr[starts[0]:]]) + starts[0]
            suspect[np.searchsorted(ends, bad_pos)] = True
        commas = np.flatnonzero(arr[starts[0]:] == 44) + starts[0]
        if not _commas_fit(commas, starts, ends, n_cols - 1):
            per_line = np.bincount(np.searchsorted(ends, commas), minlength=len(ends))
            suspect |= per_line != n_cols - 1
        t_us = np.zeros(len(ends), np.int64)
        parsed = np.zeros((len(ends), n_cols))  # t_us (as float) first, then x, y, z, aux
        keep = np.zeros(len(ends), bool)
        fast = np.zeros(len(ends), bool)
        begin = 0
        for bad in [*np.flatnonzero(suspect).tolist(), len(ends)]:
            if begin < bad:
                _fast_run(chunk, starts, ends, begin, bad, parsed, fast)
            begin = bad + 1
        # Time stamps the float path cannot vouch for (negative, fractional, >= 2**53)
        # go back to the per-line path together with the suspects.
        t_f = parsed[:, 0]
        fast &= (t_f >= 0) & (t_f < _T_EXACT_LIMIT) & (t_f == np.floor(t_f))
        t_us[fast] = t_f[fast].astype(np.int64)
        out = parsed[:, 1:]
        keep[fast] = _keep_valid(out[fast], self.max_abs_xyz, self.errors)
        for i in np.flatnonzero(~fast).tolist():
            result = self._line_result(chunk[starts[i]:ends[i]])
            if isinstance(result, tuple):
                t_us[i], out[i, :] = result[0], result[1]
                keep[i] = True
            elif result is not None:
                self.errors.add(result)
        rows.add_many(t_us[keep], out[keep])

def _vouches(candidate: bytes, nxt: bytes) -> bool:
    """Whether ``nxt`` shows that the first line after a break, ``candidate``, is whole (see
    :meth:`AsciiLineParser.reset`)."""
    try:
        a = [f.strip() for f in candidate.decode("ascii").split(",")]
        b = [f.strip() for f in nxt.decode("ascii").split(",")]
    except UnicodeDecodeError:
        return False
    if len(a) != len(b) or len(a) < 4:
        return False
    if not all(_FLOAT_RE.fullmatch(f) for f in a + b):
        return False
    t0, t1 = _parse_t_us(a[0]), _parse_t_us(b[0])
    return isinstance(t0, int) and isinstance(t1, int) and 0 < t1 - t0 <= t1 / 2


def _fast_run(chunk: bytes, starts: np.ndarray, ends: np.ndarray, begin: int, end: int,
              parsed: np.ndarray, fast: np.ndarray) -> None:
    """np.fromstring over lines [begin, end); on failure halve the run to isolate bad lines.

    Writes each line's values into ``parsed[i]`` and sets ``fast[i]``; lines left unset go
    per-line. np.fromstring rounds correctly (like float()) and raises on malformed numbers and
    empty fields; the caller has already proven every line has the right number of commas.
    """
    n_cols = parsed.shape[1]
    segment = chunk[starts[begin]:ends[end - 1]].replace(b"\n", b",")
    try:
        values = np.fromstring(segment, sep=",")
    except (ValueError, DeprecationWarning):  # numpy < 2 warns where numpy 2 raises
        values = None
    if values is not None and values.size == (end - begin) * n_cols:
        parsed[begin:end] = values.reshape(-1, n_cols)
        fast[begin:end] = True
    elif end - begin > 8:
        middle = (begin + end) // 2
        _fast_run(chunk, starts, ends, begin, middle, parsed, fast)
        _fast_run(chunk, starts, ends, middle, end, parsed, fast)


def _commas_fit(commas: np.ndarray, starts: np.ndarray, ends: np.ndarray, per_line: int) -> bool:
    """Cheap proof that every line has exactly ``per_line`` commas (the usual case)."""
    if len(commas) != len(starts) * per_line:
        return False
    grid = commas.reshape(len(starts), per_line)
    return bool(((grid[:, 0] >= starts) & (grid[:, -1] < ends)).all())


# --------------------------------------------------------------------------- COBS


def cobs_payload_bytes(n_aux: int) -> int:
    """Length of a decoded binary payload with ``n_aux`` auxiliary channels."""
    return _COBS_FIXED_BYTES + 4 * n_aux


def _crc_tables() -> tuple[np.ndarray, np.ndarray]:
    """Byte-at-a-time and 16-bit-at-a-time tables of CRC-16/CCITT-FALSE (poly 0x1021)."""
    table8 = np.zeros(256, np.uint16)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table8[byte] = crc & 0xFFFF
    # For a 16-bit CRC, two byte steps depend only on crc ^ (b0 << 8 | b1): after 16 shifts
    # no bit of the old register is left, so one lookup per 2 bytes does the work of two.
    x = np.arange(65536, dtype=np.uint32)
    once = ((x << 8) & 0xFFFF) ^ table8[x >> 8]  # step with data byte 0 (b0 already mixed in)
    table16 = (((once << 8) & 0xFFFF) ^ table8[once >> 8]).astype(np.uint16)
    return table8, table16


_CRC_TABLE8, _CRC_TABLE16 = _crc_tables()


def crc16_ccitt_false(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of each row of a (F, n) uint8 array; equals ``crc_hqx(row, 0xFFFF)``.

    The loop runs over the bytes of one frame (two at a time), vectorized over frames.
    """
    rows = np.asarray(rows, np.uint8)
    n_pairs = rows.shape[1] // 2
    words = np.ascontiguousarray(rows[:, :2 * n_pairs]).view(">u2").astype(np.uint16)
    crc = np.full(len(rows), 0xFFFF, np.uint16)
    for j in range(n_pairs):
        crc = _CRC_TABLE16[crc ^ words[:, j]]
    if rows.shape[1] % 2:
        crc = ((crc << 8) & 0xFFFF).astype(np.uint16) ^ _CRC_TABLE8[(crc >> 8) ^ rows[:, -1]]
    return crc


def _payload_dtype(n_aux: int, xyz: str) -> np.dtype:
    return np.dtype([("version", "u1"), ("flags", "u1"), ("n_aux", "u1"), ("t_us", "<i8"),
                     ("xyz", xyz, (3,)), ("aux", "<f4", (n_aux,)), ("crc", "<u2")])


def _cobs_decode_rows(enc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorized COBS decode of (F, E) encoded frames whose payload is shorter than 254 bytes.

    Returns (decoded (F, E-1), ok (F,)): ok is False where the code-byte chain does not end
    exactly at the frame end (those frames need ``cobs.decode`` to say what is wrong).
    """
    width = enc.shape[1]
    decoded = enc[:, 1:].copy()
    code_pos = enc[:, 0].astype(np.int64)  # each code byte says where the next zero was
    for _ in range(width):
        active = np.flatnonzero(code_pos < width)
        if not len(active):
            break
        decoded[active, code_pos[active] - 1] = 0
        code_pos[active] += enc[active, code_pos[active]]
    return decoded, code_pos == width


class CobsFrameParser:
    """Streaming parser of COBS binary frames (layout in the module docstring).

    Args:
        aux_names: names of the K auxiliary channels (frames carry no names); None learns K
            from the first valid frame and names the channels ``aux0, aux1, ...``.
        max_frame_bytes: longer encoded frames are ``too_long``; bounds the kept partial frame.
        max_abs_xyz: samples with a larger |x|, |y| or |z| are ``out_of_range``.
        vectorized: False decodes frame by frame with ``cobs.decode`` (tests, debugging).
        vectorize_min_frames: a chunk with fewer well-sized frames than this goes frame by
            frame, which is cheaper at serial-port read sizes (the vectorized decode has a
            fixed cost of about 30 frames' worth).
    """

    def __init__(self, aux_names: Sequence[str] | None = None, *,
                 max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
                 max_abs_xyz: float = DEFAULT_MAX_ABS_XYZ, vectorized: bool = True,
                 vectorize_min_frames: int = 32) -> None:
        self.errors = ParseErrors()
        self.max_frame_bytes = int(max_frame_bytes)
        self.max_abs_xyz = float(max_abs_xyz)
        self.vectorized = vectorized
        self.vectorize_min_frames = int(vectorize_min_frames)
        self._layout = _Layout(aux_names)
        self._pending = b""
        self._discarding = False
        self._resync = False

    @property
    def aux_names(self) -> tuple[str, ...]:
        return self._layout.names or ()

    @property
    def partial(self) -> bool:
        """Whether part of a frame is waiting for its delimiter."""
        return bool(self._pending)

    def feed(self, data: bytes) -> RawBatch:
        """Parse the complete frames in ``pending + data``; keep the unfinished tail."""
        data = bytes(data)
        if self._discarding:
            end = data.find(b"\x00")
            if end < 0:
                return RawBatch.empty(self.aux_names)
            data, self._discarding = data[end + 1:], False
        buf = self._pending + data
        last = buf.rfind(b"\x00")
        rows = _Rows()
        if last >= 0:
            self._parse_frames(buf[:last], rows)
        tail = buf[last + 1:]
        if len(tail) > self.max_frame_bytes:
            self.errors.too_long += 1
            self._resync, self._discarding, tail = False, True, b""
        self._pending = tail
        return rows.batch(self.aux_names)

    def flush(self) -> RawBatch:
        """Parse an unterminated last frame (end of a file)."""
        tail, self._pending = self._pending, b""
        self._discarding = False
        return self.feed(tail + b"\x00") if tail else RawBatch.empty(self.aux_names)

    def reset(self, resync: bool = True) -> None:
        """Forget the partial frame (counted ``truncated``) after the byte stream broke.

        With ``resync`` the bytes before the first delimiter are kept only if they form a
        valid frame, else counted ``resync_dropped`` (not as a CRC or COBS error).
        """
        if self._pending:  # (a too-long frame being skipped was counted already)
            self.errors.truncated += 1
        self._pending, self._discarding, self._resync = b"", False, resync
        self._layout.reset()

    def _parse_frames(self, chunk: bytes, rows: _Rows) -> None:
        """Parse the frames of ``chunk`` (zero-separated, the last delimiter stripped)."""
        arr = np.frombuffer(chunk, np.uint8)
        ends = np.concatenate((np.flatnonzero(arr == 0), [len(arr)]))
        starts = np.concatenate(([0], ends[:-1] + 1))
        first = 0
        while first < len(ends) and (self._resync or not self._layout.settled
                                     or not self.vectorized):
            self._one_frame(chunk[starts[first]:ends[first]], rows)
            first += 1
        if first < len(ends):
            self._fast_frames(chunk, arr, starts[first:], ends[first:], rows)

    def _one_frame(self, frame: bytes, rows: _Rows) -> None:
        resync, self._resync = self._resync, False
        if not frame:
            return  # back-to-back delimiters: idle line or a sync byte, not an error
        result = self._frame_result(frame)
        if isinstance(result, tuple):
            rows.add_one(*result)
        elif resync and result != "too_long":  # too_long must not depend on where we split
            self.errors.resync_dropped += 1
        else:
            self.errors.add(result)

    def _frame_result(self, frame: bytes) -> tuple[int, list[float]] | str:
        """One encoded frame (no delimiter): a sample or the error name (the reference path)."""
        if len(frame) > self.max_frame_bytes:
            return "too_long"
        try:
            payload = cobs.decode(frame)
        except cobs.DecodeError:
            return "garbage"
        if len(payload) < _COBS_FIXED_BYTES:
            return "bad_length"
        if binascii.crc_hqx(payload[:-2], 0xFFFF) != int.from_bytes(payload[-2:], "little"):
            return "bad_crc"
        version, flags, n_aux = payload[0], payload[1], payload[2]
        if version != COBS_VERSION or flags & ~COBS_FLAG_XYZ_FLOAT32:
            return "bad_version"
        if n_aux > COBS_MAX_AUX or len(payload) != cobs_payload_bytes(n_aux):
            return "bad_length"
        if self._layout.settled and n_aux != self._layout.n_aux:
            return "wrong_columns"
        xyz = "f" if flags & COBS_FLAG_XYZ_FLOAT32 else "i"
        t_us, *values = struct.unpack_from(f"<q3{xyz}{n_aux}f", payload, 3)
        vals = [float(x) for x in values]
        error = _check_values(t_us, vals, self.max_abs_xyz)
        if error is not None:
            return error
        self._layout.accept(n_aux)
        return t_us, vals

    def _fast_frames(self, chunk: bytes, arr: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                     rows: _Rows) -> None:
        """Decode all frames of the expected length at once; others go frame by frame."""
        n_aux = self._layout.n_aux or 0
        payload_bytes = cobs_payload_bytes(n_aux)
        lengths = ends - starts
        t_us = np.zeros(len(ends), np.int64)
        vals = np.zeros((len(ends), 3 + n_aux))
        keep = np.zeros(len(ends), bool)
        fast = np.zeros(len(ends), bool)
        cand = np.flatnonzero(lengths == payload_bytes + 1)
        if len(cand) >= max(1, self.vectorize_min_frames):
            width = payload_bytes + 1
            if len(cand) == len(ends) and len(arr) == len(ends) * (width + 1) - 1:
                # Clean stream: frames are back to back, so the chunk is a matrix already.
                enc = np.frombuffer(chunk + b"\x00", np.uint8).reshape(-1, width + 1)[:, :width]
            else:
                enc = arr[starts[cand, None] + np.arange(width)]
            decoded, ok = _cobs_decode_rows(enc)
            crc = decoded[:, -2].astype(np.uint32) | (decoded[:, -1].astype(np.uint32) << 8)
            ok &= crc16_ccitt_false(decoded[:, :-2]) == crc
            ok &= (decoded[:, 0] == COBS_VERSION) & (decoded[:, 2] == n_aux)
            ok &= (decoded[:, 1] & ~np.uint8(COBS_FLAG_XYZ_FLOAT32)) == 0
            as_int = decoded.view(_payload_dtype(n_aux, "<i4")).reshape(-1)
            as_float = decoded.view(_payload_dtype(n_aux, "<f4")).reshape(-1)
            is_float = (decoded[:, 1] & COBS_FLAG_XYZ_FLOAT32).astype(bool)
            xyz = np.where(is_float[:, None], as_float["xyz"], as_int["xyz"])
            t_cand = as_int["t_us"]
            ok &= t_cand >= 0  # negative t_us: let the reference path count it
            good = cand[ok]
            fast[good] = True
            t_us[good] = t_cand[ok]
            vals[good, :3] = xyz[ok]
            vals[good, 3:] = as_int["aux"][ok]
            keep[good] = _keep_valid(vals[good], self.max_abs_xyz, self.errors)
        for i in np.flatnonzero(~fast & (lengths > 0)).tolist():
            result = self._frame_result(chunk[starts[i]:ends[i]])
            if isinstance(result, tuple):
                t_us[i], vals[i] = result
                keep[i] = True
            else:
                self.errors.add(result)
        rows.add_many(t_us[keep], vals[keep])


# --------------------------------------------------------------------------- factory


def make_parser(fmt: str, aux_names: Sequence[str] | None = None,
                **kwargs: float | int | bool) -> AsciiLineParser | CobsFrameParser:
    """A streaming parser for ``fmt`` "ascii" or "cobs"; kwargs go to its constructor."""
    if fmt == "ascii":
        return AsciiLineParser(aux_names, **kwargs)  # type: ignore[arg-type]
    if fmt == "cobs":
        return CobsFrameParser(aux_names, **kwargs)  # type: ignore[arg-type]
    raise ValueError(f"unknown wire format {fmt!r}; expected 'ascii' or 'cobs'")


# --------------------------------------------------------------------------- encoders


def _format_number(x: float) -> str:
    """Shortest text that parses back to exactly ``x``; integral values without '.0'."""
    if x.is_integer() and abs(x) < _T_EXACT_LIMIT and not (x == 0 and math.copysign(1, x) < 0):
        return str(int(x))
    return repr(x)


def encode_ascii(batch: RawBatch, header: bool = False, line_ending: str = "\n", *,
                 time_column: bool = True, header_prefix: str = "#") -> bytes:
    """Device side of the ASCII format: optional ``#t_us,x,y,z,<aux names>`` header, then lines.

    Numbers are written with ``repr`` quality, so parsing gives back exactly the same floats.
    ``time_column=False`` writes ``x,y,z[,aux]`` lines (and header) as simple firmware does;
    ``header_prefix=""`` a header without ``#``.
    """
    if line_ending not in ("\n", "\r\n"):
        raise ValueError("line_ending must be '\\n' or '\\r\\n'")
    out: list[str] = []
    if header:
        bad = [n for n in batch.aux_names if not _NAME_RE.fullmatch(n) or _FLOAT_RE.fullmatch(n)]
        if bad:
            raise ValueError(f"auxiliary names {bad} cannot be written in an ASCII header")
        names = ("t_us", "x", "y", "z") if time_column else ("x", "y", "z")
        out.append(header_prefix + ",".join((*names, *batch.aux_names)) + line_ending)
    values = np.hstack((batch.v, batch.aux)).tolist()
    fmt = _format_number
    if time_column:
        out.extend(f"{t},{','.join(map(fmt, row))}{line_ending}"
                   for t, row in zip(batch.t_us.tolist(), values, strict=True))
    else:
        out.extend(f"{','.join(map(fmt, row))}{line_ending}" for row in values)
    return "".join(out).encode("ascii")


def encode_cobs(batch: RawBatch, xyz: str = "auto") -> bytes:
    """Device side of the binary format: one COBS frame + ``b"\\x00"`` per sample.

    Args:
        xyz: "int32" (exact for integer counts), "float32", or "auto": int32 when every x, y, z
            is an integer that fits, else float32. Aux channels are always float32.
    """
    n_aux = batch.aux.shape[1]
    if n_aux > COBS_MAX_AUX:
        raise ValueError(f"at most {COBS_MAX_AUX} auxiliary channels fit a frame")
    if xyz == "auto":
        v = batch.v
        fits = np.isfinite(v).all() and (v == np.round(v)).all() and (np.abs(v) < 2**31).all()
        xyz = "int32" if fits else "float32"
    if xyz not in ("int32", "float32"):
        raise ValueError("xyz must be 'auto', 'int32' or 'float32'")
    is_float = xyz == "float32"
    records = np.zeros(len(batch), _payload_dtype(n_aux, "<f4" if is_float else "<i4"))
    records["version"] = COBS_VERSION
    records["flags"] = COBS_FLAG_XYZ_FLOAT32 if is_float else 0
    records["n_aux"] = n_aux
    records["t_us"] = batch.t_us
    records["xyz"] = batch.v if is_float else np.round(batch.v).astype(np.int32)
    records["aux"] = batch.aux
    payloads = records.view(np.uint8).reshape(len(batch), records.dtype.itemsize)
    records["crc"] = crc16_ccitt_false(payloads[:, :-2])
    raw = records.tobytes()
    size = records.dtype.itemsize
    return b"".join(cobs.encode(raw[i:i + size]) + b"\x00" for i in range(0, len(raw), size))
