"""CSV import and export of recordings.

What ``read_csv`` accepts:

- Comma-separated, UTF-8 (a byte-order mark is fine). Blank lines and lines starting with
  ``#`` before the header and between rows are ignored.
- A header row is required. Names are matched case-insensitively after trimming spaces.
- Time: a column ``t_us`` (integer microseconds; parsed as float64, so exact up to 2**53 us,
  285 years), ``t_ms`` or ``t_s`` (decimal, rounded to the microsecond); if several are
  present the first of that list is the time and the others are kept as auxiliary channels.
  Without a time column ``rate_hz`` is required and times are
  ``t0_us + round(i * 1e6 / rate_hz)``.
- Axes: ``x,y,z``, or ``x_<unit>,y_<unit>,z_<unit>`` with one unit among ``counts``, ``g``,
  ``ms2``. The unit in the header is the default for ``units`` and must agree with it when both
  are given. Values are kept as they are: the raw unit is whatever the sensor gives, and it is
  returned so the caller knows (no conversion here).
- Every other column is an auxiliary channel named by its header, as written.
- A row with the wrong number of fields, a field that is not a number (an empty auxiliary
  field is NaN), or a time that is not finite or beyond an int64 of microseconds is skipped
  and counted; a missing header or axis column, or duplicate column names, are errors.

``iter_csv`` reads the same a chunk of lines at a time, in bounded memory; ``read_csv`` joins
its chunks. ``write_raw_csv`` writes ``t_us,x,y,z,<aux...>`` and ``write_calibrated_csv`` writes
``t_us,x_g,y_g,z_g``, then ``status,sigma_mg`` when the samples carry statuses (the number of
`recal.core.status.Status`: 1 uncalibrated, 2 bootstrapping, 3 calibrated, 4 held, 5 suspect;
the predicted 1-sigma error of the vector in mg), optionally ``quasi_static,detector_g``, with
Python's shortest
round-trip float text, so reading a written file gives back exactly the same numbers.
"""

from __future__ import annotations

import codecs
import csv
import io
import itertools
import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import IO, Any, Literal

import numpy as np

from recal.errors import InputError, UsageError
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["CsvTable", "iter_csv", "read_csv", "write_calibrated_csv", "write_raw_csv"]

Units = Literal["counts", "g", "ms2"]
UNITS: tuple[str, ...] = ("counts", "g", "ms2")
TIME_COLUMNS: dict[str, float] = {"t_us": 1.0, "t_ms": 1e3, "t_s": 1e6}  # name -> us per unit
_AXES = ("x", "y", "z")
_MAX_REPORTED_BAD_LINES = 20
_WRITE_CHUNK_ROWS = 65536
_READ_CHUNK_LINES = 200_000  # ~ 10 MB of text, ~ 40 MB while parsed
_FORBIDDEN_IN_NAMES = (",", "\n", "\r", '"')


@dataclass(frozen=True)
class CsvTable:
    """What ``read_csv`` found.

    Attributes:
        batch: the samples, in file order.
        units: unit of ``batch.v`` as declared (argument or header suffix).
        time_column: the column the times came from, or "synthesized".
        skipped_rows: bad rows skipped.
        skipped_lines: 1-based line numbers of the first skipped rows (at most 20).
    """

    batch: RawBatch
    units: str
    time_column: str
    skipped_rows: int = 0
    skipped_lines: tuple[int, ...] = ()


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Layout:
    """Column positions decided from the header."""

    names: tuple[str, ...]
    time: int | None
    time_name: str
    axes: tuple[int, int, int]
    aux: tuple[int, ...]
    header_units: str | None


def _split_header(line: str) -> tuple[str, ...]:
    return tuple(name.strip() for name in _split_row(line))


def _split_row(line: str) -> list[str]:
    # skipinitialspace: spreadsheets write `a, "b"`; the quote after the space still quotes.
    return next(csv.reader([line], skipinitialspace=True), [])


def _find_axes(lowered: Sequence[str]) -> tuple[tuple[int, int, int], str | None]:
    if all(a in lowered for a in _AXES):
        return (lowered.index("x"), lowered.index("y"), lowered.index("z")), None
    for unit in UNITS:
        wanted = [f"{a}_{unit}" for a in _AXES]
        if all(w in lowered for w in wanted):
            return (lowered.index(wanted[0]), lowered.index(wanted[1]),
                    lowered.index(wanted[2])), unit
    raise InputError(f"no axis columns: expected x,y,z or x_<unit>,y_<unit>,z_<unit> with unit "
                     f"in {list(UNITS)}; header is {list(lowered)}")


def _layout(names: tuple[str, ...]) -> _Layout:
    lowered = [n.lower() for n in names]
    if any(not n for n in names):
        raise InputError(f"empty column name in header {list(names)}")
    duplicates = sorted({n for n in lowered if lowered.count(n) > 1})
    if duplicates:
        raise InputError(f"duplicate column names {duplicates}")
    time_name = next((t for t in TIME_COLUMNS if t in lowered), "synthesized")
    time = lowered.index(time_name) if time_name in lowered else None
    axes, header_units = _find_axes(lowered)
    used = {*axes, time}
    aux = tuple(i for i in range(len(names)) if i not in used)
    return _Layout(names, time, time_name, axes, aux, header_units)


def _resolve_units(declared: str | None, header_units: str | None) -> str:
    if declared is not None and declared not in UNITS:
        raise UsageError(f"units must be one of {list(UNITS)}, got {declared!r}")
    if declared and header_units and declared != header_units:
        raise InputError(f"units={declared!r} but the header says {header_units!r}")
    return declared or header_units or "counts"


def _data_lines(lines: Sequence[str], first_number: int) -> Iterator[tuple[int, str]]:
    """(1-based line number, line) of every non-blank, non-comment line."""
    for number, line in enumerate(lines, start=first_number):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            yield number, line


def _parse_fast(body: str, n_columns: int) -> np.ndarray | None:
    """numpy's C parser for clean files; None if any row is not clean (then parse slowly)."""
    try:
        table = np.loadtxt(io.StringIO(body), delimiter=",", comments="#", dtype=np.float64,
                           ndmin=2)
    except ValueError:
        return None
    return table if table.shape[1] == n_columns else None


def _parse_row(fields: list[str], layout: _Layout) -> list[float] | None:
    """One row as floats in column order; None if it is bad."""
    if len(fields) != len(layout.names):
        return None
    values = []
    for i, text in enumerate(fields):
        text = text.strip()
        if not text and i in layout.aux:
            values.append(math.nan)  # an auxiliary channel may be missing in some rows
            continue
        try:
            values.append(float(text))
        except ValueError:
            return None
    return values


def _parse_slow(lines: Iterable[tuple[int, str]], layout: _Layout
                ) -> tuple[np.ndarray, list[int], int]:
    """Row-by-row parse that skips bad rows; returns (table, first bad lines, bad count)."""
    rows: list[list[float]] = []
    bad_lines: list[int] = []
    bad = 0
    for number, line in lines:
        row = _parse_row(_split_row(line), layout)
        if row is None or (layout.time is not None and not _times_ok(
                np.array([row[layout.time]]), layout.time_name)[0]):
            bad += 1
            if len(bad_lines) < _MAX_REPORTED_BAD_LINES:
                bad_lines.append(number)
            continue
        rows.append(row)
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(layout.names))
    return table, bad_lines, bad


def _times_ok(t: np.ndarray, time_name: str) -> np.ndarray:
    """Times that are finite and fit an int64 of microseconds (NaN compares False)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.abs(t * TIME_COLUMNS[time_name]) < 2.0**63


def _times_us(table: np.ndarray, layout: _Layout, rate_hz: float | None, t0_us: int,
              first: int = 0) -> np.ndarray:
    """Each row's time: its column, else synthesized (rows ``first`` on, at ``rate_hz``)."""
    if layout.time is None:
        if rate_hz is None or not rate_hz > 0:
            raise InputError("the file has no time column (t_us, t_ms or t_s): pass rate_hz")
        i = np.arange(first, first + len(table))
        return t0_us + np.round(i * (1e6 / rate_hz)).astype(np.int64)
    return np.round(table[:, layout.time] * TIME_COLUMNS[layout.time_name]).astype(np.int64)


def _text_lines(f: IO[bytes], path: str | os.PathLike[str], chunk_lines: int,
                on_bytes: Callable[[int], None] | None = None) -> Iterator[list[str]]:
    """The file's lines (str.splitlines, ends kept) in lists of about ``chunk_lines``, decoded
    a chunk at a time; a byte-order mark is dropped. Chunks end after a newline byte, so a line
    never straddles two."""
    start = 0
    first = True
    while True:
        raw = b"".join(itertools.islice(f, chunk_lines))
        if not raw:
            return
        if first and raw.startswith(codecs.BOM_UTF8):
            raw, start = raw[len(codecs.BOM_UTF8):], len(codecs.BOM_UTF8)
        first = False
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise InputError(f"{path}: not UTF-8 text (byte {start + exc.start})") from None
        start += len(raw)
        if on_bytes is not None:
            on_bytes(len(raw))
        yield text.splitlines(keepends=True)


def iter_csv(path: str | os.PathLike[str], units: Units | None = None,
             rate_hz: float | None = None, *, t0_us: int = 0,
             chunk_lines: int | None = None,
             on_bytes: Callable[[int], None] | None = None) -> Iterator[CsvTable]:
    """`read_csv` a chunk of about ``chunk_lines`` lines at a time, in bounded memory (a week
    at 100 Hz is 60 M rows): one CsvTable per chunk, with that chunk's samples and skipped rows
    (line numbers are the file's; at most 20 reported over the whole file). Header errors are
    raised at the first chunk. ``on_bytes(n)``: called with each chunk's size in bytes (a
    progress bar)."""
    with open(path, "rb") as f:
        chunks = _text_lines(f, path, chunk_lines or _READ_CHUNK_LINES, on_bytes)
        number = 0  # lines before the current chunk
        header: tuple[int, str] | None = None
        rows: list[str] = []
        for lines in chunks:
            header = next(_data_lines(lines, number + 1), None)
            if header is not None:
                rows = lines[header[0] - number:]  # the lines after the header
                break
            number += len(lines)
        if header is None:
            raise InputError(f"{path}: no header row")
        try:  # name the file in the one-line error
            layout = _layout(_split_header(header[1]))
            resolved_units = _resolve_units(units, layout.header_units)
        except (InputError, UsageError) as exc:  # the same kind of error, with the file
            raise type(exc)(f"{path}: {exc}") from None
        if layout.time is None and (rate_hz is None or not rate_hz > 0):
            raise InputError("the file has no time column (t_us, t_ms or t_s): pass rate_hz")
        done, reported = 0, 0  # rows kept, bad lines reported
        first_number = header[0] + 1
        for body in itertools.chain([rows], chunks):
            table, bad_lines, bad = _parse_chunk(body, first_number, layout)
            first_number += len(body)
            bad_lines = bad_lines[:max(_MAX_REPORTED_BAD_LINES - reported, 0)]
            reported += len(bad_lines)
            t_us = _times_us(table, layout, rate_hz, t0_us, done)
            done += len(table)
            batch = RawBatch(t_us, table[:, list(layout.axes)], table[:, list(layout.aux)],
                             tuple(layout.names[i] for i in layout.aux))
            yield CsvTable(batch, resolved_units, layout.time_name, bad, tuple(bad_lines))


def _parse_chunk(body: list[str], first_number: int, layout: _Layout
                 ) -> tuple[np.ndarray, list[int], int]:
    """Rows of lines (numbered from first_number): numpy's parser when they are clean, else
    row by row, skipping bad ones. Returns (table, first bad line numbers, bad count)."""
    table: np.ndarray | None = np.zeros((0, len(layout.names)))
    if any(True for _ in _data_lines(body, 0)):  # loadtxt warns on empty input
        table = _parse_fast("".join(body), len(layout.names))
    if table is None or (layout.time is not None
                         and not _times_ok(table[:, layout.time], layout.time_name).all()):
        return _parse_slow(_data_lines(body, first_number), layout)
    return table, [], 0


def read_csv(path: str | os.PathLike[str], units: Units | None = None,
             rate_hz: float | None = None, *, t0_us: int = 0) -> CsvTable:
    """Read a CSV of triaxial samples (see the module docstring for the accepted layout).

    Args:
        path: the file.
        units: the unit of x, y, z; None takes it from the header suffix, else "counts".
        rate_hz: sample rate, required (only) when there is no time column.
        t0_us: time of the first sample when times are synthesized.
    """
    parts = list(iter_csv(path, units, rate_hz, t0_us=t0_us))
    return CsvTable(RawBatch.concat([c.batch for c in parts]), parts[0].units,
                    parts[0].time_column, sum(c.skipped_rows for c in parts),
                    tuple(n for c in parts for n in c.skipped_lines))


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------

def _check_names(names: Sequence[str], reserved: Sequence[str]) -> None:
    lowered = [n.lower() for n in names]
    for name in names:
        if not name or any(c in name for c in _FORBIDDEN_IN_NAMES):
            raise InputError(f"column name {name!r} cannot be written to CSV as is")
    clash = sorted(set(lowered) & {r.lower() for r in reserved})
    if clash or len(set(lowered)) != len(lowered):
        raise InputError(f"auxiliary channel names {list(names)} clash with each other or "
                         f"with {list(reserved)}")


def _float_texts(values: np.ndarray) -> list[str]:
    # repr is the shortest text that parses back to the same double (nan/inf included).
    return list(map(float.__repr__, values.tolist()))


def _write_table(path: str | os.PathLike[str], header: Sequence[str],
                 batches: Iterable[Sequence[np.ndarray]], integer_columns: Sequence[bool]
                 ) -> int:
    """Write every batch's columns under one header, in chunks of rows, each chunk formatted
    column-wise in bulk; returns the rows written."""
    rows = 0
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(header) + "\n")
        for columns in batches:
            n = len(columns[0]) if columns else 0
            for start in range(0, n, _WRITE_CHUNK_ROWS):
                stop = min(start + _WRITE_CHUNK_ROWS, n)
                texts = [list(map(str, col[start:stop].tolist())) if is_int
                         else _float_texts(col[start:stop])
                         for col, is_int in zip(columns, integer_columns, strict=True)]
                f.write("\n".join(map(",".join, zip(*texts, strict=True))))
                f.write("\n")
            rows += n
    return rows


def _batches(data: RawBatch | CalibratedBatch | Iterable) -> tuple[Any, Iterator]:
    """(first batch or None, every batch): one batch or an iterable of them, read lazily."""
    if isinstance(data, RawBatch | CalibratedBatch):
        return data, iter([data])
    it = iter(data)
    first = next(it, None)
    return first, itertools.chain([] if first is None else [first], it)


def write_raw_csv(path: str | os.PathLike[str], batch: RawBatch | Iterable[RawBatch],
                  units: Units | None = None, time_column: str = "t_us") -> int:
    """Write ``t_us,x,y,z,<aux...>`` (axes named ``x_<units>`` ... when units are given) of one
    batch or of several with the same channels, read one at a time; returns the rows.
    ``time_column``: the time's name by its unit (``t_ms`` for a device that counts
    milliseconds: the values are the device's, written as they are)."""
    axes = list(_AXES) if units is None else [f"{a}_{units}" for a in _AXES]
    if units is not None and units not in UNITS:
        raise UsageError(f"units must be one of {list(UNITS)}, got {units!r}")
    if time_column not in TIME_COLUMNS:
        raise UsageError(f"time column must be one of {list(TIME_COLUMNS)}, got {time_column!r}")
    first, batches = _batches(batch)
    aux_names = first.aux_names if first is not None else ()
    _check_names(aux_names, ["t_us", *TIME_COLUMNS, *axes])

    def columns(b: RawBatch) -> list[np.ndarray]:
        if b.aux_names != aux_names:
            raise InputError(f"channels change from {list(aux_names)} to {list(b.aux_names)}: "
                             "one CSV has one set of columns")
        return [b.t_us, *b.v.T, *b.aux.T]

    return _write_table(path, [time_column, *axes, *aux_names], map(columns, batches),
                        [True] + [False] * (3 + len(aux_names)))


def write_calibrated_csv(path: str | os.PathLike[str],
                         batch: CalibratedBatch | Iterable[CalibratedBatch],
                         with_detector: bool = False, with_status: bool | None = None,
                         device_time: str | None = None) -> int:
    """Write ``t_us,x_g,y_g,z_g``, plus ``status,sigma_mg`` (``with_status``; None: when the
    first batch carries statuses, `CalibratedBatch.recorded`), ``quasi_static,detector_g``
    (if asked) and the device's own time stamps (`CalibratedBatch.t_dev`) in a column named
    ``device_time`` (if given; every batch must carry them), of one batch or of several, read
    one at a time; returns the rows.

    ``read_csv`` reads the file back as a batch in units "g" (the other columns as auxiliary
    channels, ``quasi_static`` as 0/1).
    """
    first, batches = _batches(batch)
    if with_status is None:
        with_status = first is not None and first.recorded
    header = ["t_us", "x_g", "y_g", "z_g"]
    is_int = [True, False, False, False]
    if with_status:
        header += ["status", "sigma_mg"]
        is_int += [True, False]
    if with_detector:
        header += ["quasi_static", "detector_g"]
        is_int += [True, False]
    if device_time is not None:
        header.append(device_time)
        is_int.append(True)

    def columns(b: CalibratedBatch) -> list[np.ndarray]:
        cols = [b.t_us, *b.a_g.T]
        if with_status:
            cols += [b.status.astype(np.int64), b.sigma_mg]
        if with_detector:
            cols += [b.quasi_static.astype(np.int64), b.detector_g]
        if device_time is not None:
            if b.t_dev is None:
                raise InputError("device time stamps stop partway (a recording joined from "
                                 "an older one): export without them")
            cols.append(b.t_dev)
        return cols

    return _write_table(path, header, map(columns, batches), is_int)
