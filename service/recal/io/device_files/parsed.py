"""What a device family's reader hands to `DeviceRecording`, and the call into actfast.

A family module (axivity, geneactiv, actigraph) turns actfast's dict into a `Parsed`: the
samples with the file's own stamps, where its blocks start, the low-rate channels with their
own stamps, the device's metadata and what the user must be told. Time stamping, time zones
and batching are then the same for every family (`recording.DeviceRecording`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from recal.errors import DeviceFileError

__all__ = ["LowRate", "Parsed", "actfast_read", "utc_offset_s", "warning_notes"]


@dataclass(frozen=True)
class LowRate:
    """A channel the device records at its own low rate (per block, per minute), stamped on
    the same clock as the samples; interpolated to the samples."""

    name: str
    t_ns: np.ndarray
    values: np.ndarray


@dataclass
class Parsed:
    """A device file as read: samples (in g as the reader gives them), the file's stamp of
    each (ns, device wall-clock), and where the file's blocks start."""

    kind: str
    file_t_ns: np.ndarray          # (N,) int64
    v_g: np.ndarray                # (N, 3) float32
    nominal_rate_hz: float
    known_starts_ns: np.ndarray | None
    low_rate: list[LowRate]
    per_sample: dict[str, np.ndarray]
    metadata: dict[str, Any]
    device_id: str | None
    utc_offset_s: float | None
    notes: list[str] = field(default_factory=list)
    skipped: dict[str, int] = field(default_factory=dict)


def actfast_read(path: Path, shown: Path, lenient: bool, what: str) -> dict[str, Any]:
    """actfast.read, its failures turned into one line that says what the file is."""
    import actfast

    try:
        return actfast.read(str(path), lenient=lenient)
    except Exception as e:  # actfast raises ValueError/OSError/RuntimeError on bad input
        raise DeviceFileError(f"{shown}: {what} that cannot be read ({_one_line(e)})") from None
    except BaseException as e:  # a Rust panic (pyo3 PanicException) is a BaseException
        if type(e).__name__ != "PanicException":
            raise
        raise DeviceFileError(f"{shown}: {what} that the reader failed on "
                              f"({_one_line(e)})") from None


def warning_notes(r: dict[str, Any]) -> list[str]:
    """What the lenient reader skipped, for the user (its count and first warning)."""
    warnings = [str(w) for w in r.get("warnings", [])]
    if not warnings:
        return []
    first = " ".join(warnings[0].split())[:160]
    return [f"the reader skipped damaged data {len(warnings)} time(s) (first: {first})"]


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text[:200] + ("..." if len(text) > 200 else "")


# The sign is optional: .NET (ActiGraph's info.txt) writes a zone east of UTC unsigned,
# "01:00:00"; an unsigned zone must then have its minutes, so a bare number is no zone.
_OFFSET = re.compile(r"^(?:GMT|UTC)?\s*(?:([+-])\s*(\d{1,2})(?::?(\d{2}))?|(\d{1,2}):(\d{2}))"
                     r"(?::(\d{2}))?$")


def utc_offset_s(text: str | None) -> float | None:
    """'GMT +01:00', '-05:00:00', '+0100', '01:00:00' -> seconds east of UTC; None when
    unknown."""
    if text is None:
        return None
    m = _OFFSET.match(str(text).strip())
    if m is None:
        return None
    sign = -1 if m.group(1) == "-" else 1
    h = int(m.group(2) or m.group(4))
    mi, s = int(m.group(3) or m.group(5) or 0), int(m.group(6) or 0)
    if h > 14 or mi >= 60 or s >= 60:
        return None
    return float(sign * (3600 * h + 60 * mi + s))


def table(ts: dict[str, Any], name: str, kind: str) -> LowRate | None:
    """One channel of one of actfast's tables (None if absent or empty)."""
    if name not in ts or not len(ts[name]):
        return None
    return LowRate(name, np.asarray(ts["datetime"], np.int64),
                   np.asarray(ts[name], np.float64))


def number(text: Any) -> float | None:
    """The first number in a header value ('60 Hz' -> 60.0, '-8 to 8' -> -8.0)."""
    m = re.search(r"[-+]?\d+(?:\.\d+)?", str(text))
    return float(m.group(0)) if m else None
