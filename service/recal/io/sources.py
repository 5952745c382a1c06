"""One entry that opens any recording by its content: an MCAP recording (its magic bytes), a
device file (`device_files.sniff`: Axivity .cwa, GENEActiv .bin, ActiGraph .gt3x), else a CSV
time series. The commands ask this entry; none of them branches on a file's extension.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from recal.errors import InputError, RecordingError
from recal.io import device_files
from recal.samples import RawBatch

__all__ = ["MCAP_MAGIC", "Source", "open_recording", "recording_kind", "source_lines",
           "string_metadata"]

MCAP_MAGIC = b"\x89MCAP0\r\n"
Kind = Literal["mcap", "device", "csv", "unknown"]


@dataclass(frozen=True)
class Source:
    """Where the samples come from: ``batches()`` reads the input once more from its start;
    ``logged()`` (MCAP only) yields each raw batch with its message as logged; a device file
    also gives its ``metadata`` (device, id, rate, time zone, ...) and ``notes`` (what the
    user must be told) and ``device`` (the `DeviceRecording`)."""

    name: str
    sensor_id: str
    batches: Callable[[], Iterable[RawBatch]]
    logged: Callable[[], Iterator[tuple[RawBatch, Any]]] | None = None
    kind: Kind = "csv"
    metadata: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    device: device_files.DeviceRecording | None = None


def source_lines(src: Source) -> list[str]:
    """What a person must be told about a device file (nothing for another source): the
    device, its rate and what the reading did (times, time zone, skipped blocks, channels)."""
    if src.kind != "device":
        return []
    m = src.metadata
    head = (f"  {m.get('format')}: {m.get('device_type', '?')} {m.get('device_id', '')}, "
            f"{m.get('samples')} samples at {m.get('rate_hz', 0.0):.4f} Hz, channels "
            f"{m.get('aux_channels') or 'none'}")
    return [head, *(f"  {n}" for n in src.notes)]


def string_metadata(src: Source) -> dict[str, str]:
    """A device file's metadata and notes as the string pairs an MCAP metadata record holds
    (``device_<key>``, ``device_notes``); nothing for another source."""
    if src.kind != "device":
        return {}
    out = {f"device_{k}": str(v) for k, v in src.metadata.items()}
    out["device_notes"] = "; ".join(src.notes)
    return out


def recording_kind(path: str | Path) -> Kind:
    """'mcap' (the MCAP magic, or a file cut before it), 'device' (a device file recal
    recognises), 'csv' (text), else 'unknown'. OSError for a file that cannot be opened."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(512)
    if head and head[:len(MCAP_MAGIC)] == MCAP_MAGIC[:len(head)]:
        return "mcap"
    if device_files.sniff(path) is not None:
        return "device"
    return "csv" if _is_text(head) else "unknown"


def _is_text(head: bytes) -> bool:
    head = head.removeprefix(b"\xef\xbb\xbf")  # a byte order mark (Excel's UTF-8 CSV)
    if not head:
        return True
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:  # cut inside a character at the end: still text
        if exc.start <= len(head) - 4:
            return False
        text = head[:exc.start].decode("utf-8")
    return "".join(text.split()).isprintable()


def open_recording(path: str | Path, sensor_id: str | None = None, rate_hz: float | None = None,
                   units: str | None = None, *, lenient: bool = True, threads: int = 1
                   ) -> Source:
    """An MCAP recording (one sensor: the only one, or ``sensor_id``), a device file (read
    once, kept in memory as its reader gives it; a .cwa decoded on ``threads``) or a CSV time
    series, by content."""
    path = Path(path)
    kind = recording_kind(path)
    if kind == "unknown":
        raise InputError(f"{path} is neither an MCAP recording, a device file recal reads "
                         "(Axivity .cwa, GENEActiv .bin, ActiGraph .gt3x) nor a CSV")
    if kind == "device":
        rec = device_files.open_device(path, lenient=lenient, threads=threads)
        return Source(str(path), sensor_id or rec.sensor_id, rec.batches, kind="device",
                      metadata=rec.metadata, notes=rec.notes, device=rec)
    if kind == "csv":
        from recal.io.csv_table import iter_csv

        def rows() -> Iterator[RawBatch]:
            return (t.batch for t in iter_csv(path, units=units, rate_hz=rate_hz))  # type: ignore[arg-type]

        return Source(str(path), sensor_id or path.stem, rows)
    from recal.io import recording

    parts = recording.recording_parts(path)
    found = recording.sensors(parts)
    sid = recording.pick_sensor(path, found, sensor_id)
    if sid not in found:
        raise RecordingError(f"{path} has no sensor {sid!r} (it has: {', '.join(found) or 'none'})")

    def raw() -> Iterator[RawBatch]:
        return (b for _, b, _ in recording.iter_raw(parts, sid))

    def logged() -> Iterator[tuple[RawBatch, Any]]:
        return ((b, m) for _, b, m, _ in recording.iter_raw_logged(parts, sid))

    return Source(str(path), sid, raw, logged, kind="mcap")
