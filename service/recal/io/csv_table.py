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

``write_raw_csv`` writes ``t_us,x,y,z,<aux...>`` and ``write_calibrated_csv`` writes
``t_us,x_g,y_g,z_g`` (optionally ``quasi_static,detector_g``), with Python's shortest
round-trip float text, so reading a written file gives back exactly the same numbers.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from recal.samples import CalibratedBatch, RawBatch

__all__ = ["CsvTable", "read_csv", "write_calibrated_csv", "write_raw_csv"]

Units = Literal["counts", "g", "ms2"]
UNITS: tuple[str, ...] = ("counts", "g", "ms2")
TIME_COLUMNS: dict[str, float] = {"t_us": 1.0, "t_ms": 1e3, "t_s": 1e6}  # name -> us per unit
_AXES = ("x", "y", "z")
_MAX_REPORTED_BAD_LINES = 20
_WRITE_CHUNK_ROWS = 65536
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
    raise ValueError(f"no axis columns: expected x,y,z or x_<unit>,y_<unit>,z_<unit> with unit "
                     f"in {list(UNITS)}; header is {list(lowered)}")


def _layout(names: tuple[str, ...]) -> _Layout:
    lowered = [n.lower() for n in names]
    if any(not n for n in names):
        raise ValueError(f"empty column name in header {list(names)}")
    duplicates = sorted({n for n in lowered if lowered.count(n) > 1})
    if duplicates:
        raise ValueError(f"duplicate column names {duplicates}")
    time_name = next((t for t in TIME_COLUMNS if t in lowered), "synthesized")
    time = lowered.index(time_name) if time_name in lowered else None
    axes, header_units = _find_axes(lowered)
    used = {*axes, time}
    aux = tuple(i for i in range(len(names)) if i not in used)
    return _Layout(names, time, time_name, axes, aux, header_units)


def _resolve_units(declared: str | None, header_units: str | None) -> str:
    if declared is not None and declared not in UNITS:
        raise ValueError(f"units must be one of {list(UNITS)}, got {declared!r}")
    if declared and header_units and declared != header_units:
        raise ValueError(f"units={declared!r} but the header says {header_units!r}")
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


def _times_us(table: np.ndarray, layout: _Layout, rate_hz: float | None, t0_us: int
              ) -> np.ndarray:
    if layout.time is None:
        if rate_hz is None or not rate_hz > 0:
            raise ValueError("the file has no time column (t_us, t_ms or t_s): pass rate_hz")
        return t0_us + np.round(np.arange(len(table)) * (1e6 / rate_hz)).astype(np.int64)
    return np.round(table[:, layout.time] * TIME_COLUMNS[layout.time_name]).astype(np.int64)


def read_csv(path: str | os.PathLike[str], units: Units | None = None,
             rate_hz: float | None = None, *, t0_us: int = 0) -> CsvTable:
    """Read a CSV of triaxial samples (see the module docstring for the accepted layout).

    Args:
        path: the file.
        units: the unit of x, y, z; None takes it from the header suffix, else "counts".
        rate_hz: sample rate, required (only) when there is no time column.
        t0_us: time of the first sample when times are synthesized.
    """
    try:
        all_lines = Path(path).read_text(encoding="utf-8-sig").splitlines(keepends=True)
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    header = next(_data_lines(all_lines, 1), None)
    if header is None:
        raise ValueError(f"{path}: no header row")
    try:  # name the file in the one-line error
        layout = _layout(_split_header(header[1]))
        resolved_units = _resolve_units(units, layout.header_units)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    rows = all_lines[header[0]:]  # header[0] is 1-based, so this starts after the header
    table: np.ndarray | None = np.zeros((0, len(layout.names)))
    if any(True for _ in _data_lines(rows, 0)):  # loadtxt warns on empty input
        table = _parse_fast("".join(rows), len(layout.names))
    bad_lines: list[int] = []
    bad = 0
    if table is None or (layout.time is not None
                         and not _times_ok(table[:, layout.time], layout.time_name).all()):
        table, bad_lines, bad = _parse_slow(_data_lines(rows, header[0] + 1), layout)
    t_us = _times_us(table, layout, rate_hz, t0_us)
    batch = RawBatch(t_us, table[:, list(layout.axes)], table[:, list(layout.aux)],
                     tuple(layout.names[i] for i in layout.aux))
    return CsvTable(batch, resolved_units, layout.time_name, bad, tuple(bad_lines))


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------

def _check_names(names: Sequence[str], reserved: Sequence[str]) -> None:
    lowered = [n.lower() for n in names]
    for name in names:
        if not name or any(c in name for c in _FORBIDDEN_IN_NAMES):
            raise ValueError(f"column name {name!r} cannot be written to CSV as is")
    clash = sorted(set(lowered) & {r.lower() for r in reserved})
    if clash or len(set(lowered)) != len(lowered):
        raise ValueError(f"auxiliary channel names {list(names)} clash with each other or "
                         f"with {list(reserved)}")


def _float_texts(values: np.ndarray) -> list[str]:
    # repr is the shortest text that parses back to the same double (nan/inf included).
    return list(map(float.__repr__, values.tolist()))


def _write_table(path: str | os.PathLike[str], header: Sequence[str],
                 columns: Sequence[np.ndarray], integer_columns: Sequence[bool]) -> None:
    """Write columns in chunks of rows, each chunk formatted column-wise in bulk."""
    n = len(columns[0]) if columns else 0
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(header) + "\n")
        for start in range(0, n, _WRITE_CHUNK_ROWS):
            stop = min(start + _WRITE_CHUNK_ROWS, n)
            texts = [list(map(str, col[start:stop].tolist())) if is_int
                     else _float_texts(col[start:stop])
                     for col, is_int in zip(columns, integer_columns, strict=True)]
            f.write("\n".join(map(",".join, zip(*texts, strict=True))))
            f.write("\n")


def write_raw_csv(path: str | os.PathLike[str], batch: RawBatch,
                  units: Units | None = None) -> None:
    """Write ``t_us,x,y,z,<aux...>`` (axes named ``x_<units>`` ... when units are given)."""
    axes = list(_AXES) if units is None else [f"{a}_{units}" for a in _AXES]
    if units is not None and units not in UNITS:
        raise ValueError(f"units must be one of {list(UNITS)}, got {units!r}")
    _check_names(batch.aux_names, ["t_us", *TIME_COLUMNS, *axes])
    columns = [batch.t_us, *batch.v.T, *batch.aux.T]
    _write_table(path, ["t_us", *axes, *batch.aux_names], columns,
                 [True] + [False] * (len(columns) - 1))


def write_calibrated_csv(path: str | os.PathLike[str], batch: CalibratedBatch,
                         with_detector: bool = False) -> None:
    """Write ``t_us,x_g,y_g,z_g`` (plus ``quasi_static,detector_g`` if asked).

    ``read_csv`` reads the file back as a batch in units "g" (detector columns as auxiliary
    channels, ``quasi_static`` as 0/1).
    """
    header = ["t_us", "x_g", "y_g", "z_g"]
    columns = [batch.t_us, *batch.a_g.T]
    is_int = [True, False, False, False]
    if with_detector:
        header += ["quasi_static", "detector_g"]
        columns += [batch.quasi_static.astype(np.int64), batch.detector_g]
        is_int += [True, False]
    _write_table(path, header, columns, is_int)
