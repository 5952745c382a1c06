"""ASCII lines, one sample a line: the parser and the device-side encoder.

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

The stream part (carry-over, resync, error counts) is `recal.io.frames`; why a vectorized path
beside the per-line one: docs/design.md, "Figures behind choices".
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

import numpy as np

from recal.io.frames import (
    DEFAULT_MAX_ABS_XYZ,
    DelimitedParser,
    DeviceStyle,
    Rows,
    WireFormat,
    check_values,
    keep_valid,
)
from recal.samples import RawBatch

__all__ = ["DEFAULT_MAX_LINE_BYTES", "WIRE_FORMAT", "AsciiLineParser", "encode_ascii"]

_T_EXACT_LIMIT = 2**53  # a float t_us below this is an exact integer

DEFAULT_MAX_LINE_BYTES = 4096


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
# Bytes of a line `AsciiLineParser._one_settled` reads (a plain data line: no spaces, letters,
# control characters or '#'; a field float() takes is then one _FLOAT_RE matches)
_PLAIN_BYTES = b"0123456789.+-eE,"
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

class AsciiLineParser(DelimitedParser):
    """Streaming parser of ``t_us,x,y,z[,aux...]`` lines (see the module docstring).

    Args:
        aux_names: auxiliary channel names from configuration; None to learn them from a header.
        max_line_bytes: longer lines are counted ``too_long`` and skipped; also bounds the
            partial line kept between calls.
        max_abs_xyz: samples with a larger |x|, |y| or |z| are ``out_of_range``.
        vectorized: False parses every line on the per-line path (for tests and debugging).
        vectorize_min_lines: a chunk with fewer complete lines than this goes line by line,
            which is cheaper at the read sizes of a sensor handled as it sends (one line per
            read; docs/design.md, "Figures behind choices").
        rate_hz: the device's sample rate, if known; then lines without a time column
            (``x,y,z[,aux]``: a header starting with ``x``, or 3 fields with no header) are
            accepted and stamped ``origin + round(i * 1e6 / rate_hz)`` (see
            :meth:`anchor_time`).
    """

    _DELIMITER = b"\n"

    def __init__(self, aux_names: Sequence[str] | None = None, *,
                 max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
                 max_abs_xyz: float = DEFAULT_MAX_ABS_XYZ, vectorized: bool = True,
                 vectorize_min_lines: int = 7, rate_hz: float | None = None) -> None:
        super().__init__(aux_names, max_line_bytes, max_abs_xyz, vectorized)
        self.vectorize_min_lines = int(vectorize_min_lines)
        # the first line after a break, held until the next one says whether it is whole
        self._candidate: bytes | None = None
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
    def max_line_bytes(self) -> int:
        """Longest line taken (longer ones are ``too_long``); bounds the partial line kept."""
        return self.max_record_bytes

    def flush(self) -> RawBatch:
        """Parse the unfinished last line as if it were ended (end of a file or recording)."""
        out = super().flush()
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
        self._drop_candidate()
        super().reset(resync)
        self._anchor_due = True

    def _counts_as_truncated(self, pending: bytes) -> bool:
        return bool(pending.strip())  # blanks before a break are no lost sample

    def _drop_candidate(self) -> None:
        if self._candidate is not None:
            self._candidate = None
            self._resync = False
            self.errors.resync_dropped += 1

    # -- per-line path (the reference)

    def _parse_records(self, buf: bytes, last: int, rows: Rows) -> None:
        """Parse the complete lines of ``buf``, up to and with its newline at ``last``."""
        if last == len(buf) - 1 and buf.find(b"\n") == last and self._one_settled(buf, rows):
            return  # one whole line (a sensor handled as it sends), read the short way
        chunk = buf[:last + 1]
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

    def _one_settled(self, buf: bytes, rows: Rows) -> bool:
        """``buf``, one line and its newline, read as `_one_line` would read it, when that is
        plain: the layout settled with a time column, no resync, nothing but digits, signs,
        points, exponents and commas in it, the right number of fields, an unsigned integer
        time and numbers `float` takes (each such field is one `_FLOAT_RE` matches). Then
        the sample is added (or its error counted) and True returned; else nothing is done
        and False returned (the general path decides)."""
        layout = self._layout
        if (self._resync or layout.timeless is not False or not layout.settled
                or len(buf) > self.max_record_bytes):
            return False
        line = buf[:-2] if buf.endswith(b"\r\n") else buf[:-1]
        if line.translate(None, _PLAIN_BYTES):
            return False
        tokens = line.split(b",")
        if len(tokens) != 4 + (layout.n_aux or 0) or not tokens[0].isdigit():
            return False
        try:
            vals = [float(tok) for tok in tokens[1:]]
        except ValueError:
            return False
        t_us = int(tokens[0])
        error = check_values(t_us, vals, self.max_abs_xyz)
        if error is not None:
            self.errors.add(error)
        elif layout.accept(len(tokens) - 4, False):
            rows.add_one(t_us, vals)
        else:  # (cannot be: the field count fits the settled layout)
            self.errors.add("wrong_columns")
        return True

    def _one_line(self, line: bytes, rows: Rows) -> None:
        if self._resync and len(line) <= self.max_record_bytes and line.strip():
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
        if len(line) > self.max_record_bytes:
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
        if not any(_FLOAT_RE.fullmatch(tok) for tok in tokens):
            # text, not a sample short of columns: a banner ("booting..."), a message
            return "non_numeric"
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
        error = check_values(t_us, vals, self.max_abs_xyz)
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
                    rows: Rows) -> None:
        """Parse lines with a settled layout: numpy over clean runs, per-line for suspects."""
        n_cols = 4 + (self._layout.n_aux or 0)
        suspect = (ends - starts) > self.max_record_bytes
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
        keep[fast] = keep_valid(out[fast], self.max_abs_xyz, self.errors)
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


def _device_lines(batch: RawBatch, style: DeviceStyle) -> bytes:
    return encode_ascii(batch, header=False, line_ending=style.line_ending,
                        time_column=style.time_column)


def _device_header(aux_names: tuple[str, ...], style: DeviceStyle) -> bytes:
    return encode_ascii(RawBatch.empty(aux_names), header=True, line_ending=style.line_ending,
                        time_column=style.time_column, header_prefix=style.header_prefix)


WIRE_FORMAT = WireFormat("ascii", AsciiLineParser, _device_lines, _device_header,
                         untimed_by_rate=True)
