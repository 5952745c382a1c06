"""Axivity AX3 / AX6 .cwa (also gzip-compressed, .cwa.gz), decoded by `cwa_sectors` as actfast
reads it (the same values and stamps, on threads).

A .cwa starts with a 1024-byte header packet "MD" (length 0x03FC), then 512-byte data sectors
"AX", each with its own time and one row of light, temperature and battery (openmovement's
Docs/ax3/cwa.h). The reader gives the samples (``high_frequency``) and one row per sector
(``low_frequency``): the sector times mark the blocks.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recal.errors import DeviceFileError
from recal.io.device_files import guard
from recal.io.device_files.cwa_sectors import read_cwa
from recal.io.device_files.parsed import (
    LowRate,
    Parsed,
    number,
    table,
    warning_notes,
)
from recal.io.device_files.probe import Probe

__all__ = ["read", "sniff_cwa"]

HEADER_BYTES, SECTOR_BYTES = 1024, 512
#: header byte 4 (hardwareType) that actfast does not name, as cwa.h does
_HARDWARE = {b"\x17": "AX3"}


def sniff_cwa(p: Probe) -> bool:
    """The header packet: "MD" and its length 1020 (little-endian)."""
    return p.head[:2] == b"MD" and p.head[2:4] == b"\xfc\x03"


def _cwa_battery(t: LowRate) -> LowRate:
    """Battery volts as cwa.h and omapi convert the sector's byte b: (b + 512) · 6 / 1024 V
    (the AX3 and AX6 firmware store the 10-bit reading less 512). actfast 1.3 doubles b first
    (an older scaling): 5.2 V for a 4.1 V cell. Its byte back, then converted."""
    byte = np.rint((t.values / 3.0 - 1.0) * 256.0)
    return LowRate(t.name, t.t_ns, (byte + 512.0) * 6.0 / 1024.0)


def _decoded(path: Path, shown: Path, lenient: bool, threads: int) -> dict:
    """`read_cwa`, its failures as one line that says what the file is."""
    try:
        return read_cwa(path, lenient, threads)
    except (DeviceFileError, OSError, ValueError) as e:
        raise DeviceFileError(f"{shown}: Axivity .cwa that cannot be read ({e})") from None


def read(path: Path, shown: Path, lenient: bool, threads: int = 1) -> Parsed:
    r = _decoded(path, shown, lenient, threads)
    ts = r.get("timeseries", {})
    hf, lf = ts.get("high_frequency", {}), ts.get("low_frequency", {})
    meta_in = r.get("metadata", {})
    dev, conf = meta_in.get("device", {}), meta_in.get("configuration", {})
    hw = str(dev.get("hardware_type") or "")
    if not hw.startswith("AX"):  # actfast names 0x00, 0xFF (AX3) and 0x64 (AX6); cwa.h 0x17
        hw = _HARDWARE.get(guard.read_head(path, HEADER_BYTES)[4:5], hw)
    named = hw.startswith("AX")
    hw = hw if named else "AX"
    tz_min = number(dev.get("time_zone"))
    tz = None if tz_min is None or tz_min == -1 else 60.0 * tz_min
    rate = number(conf.get("sample_rate_hz")) or 100.0
    kind = f"Axivity {hw}" if named else "Axivity (a hardware code the reader does not name)"
    meta = {"device_type": kind, "device_id": dev.get("device_id"),
            "session_id": dev.get("session_id"), "firmware": dev.get("firmware_revision"),
            "nominal_rate_hz": rate, "range_g": number(conf.get("accelerometer_range_g")),
            "logging_start": conf.get("logging_start"), "logging_end": conf.get("logging_end"),
            "values": "acceleration in g as the reader scales the counts (AX3: 1/256 g a step)"}
    notes = []
    notes += warning_notes(r)
    if "gyroscope" in hf:
        meta["gyroscope"] = "ignored"
        notes.append(f"{hw}: the gyroscope's channels are not used (ignored)")
    sectors_read = len(lf.get("datetime", ()))
    data_bytes = max(0, path.stat().st_size - HEADER_BYTES)
    sectors_in_file = data_bytes // SECTOR_BYTES
    skipped = max(0, sectors_in_file - sectors_read)
    if skipped:
        notes.append(f"{skipped} of {sectors_in_file} sectors skipped (corrupt, cut short or "
                     "not samples)")
    if data_bytes % SECTOR_BYTES:
        notes.append(f"the file ends in a partial sector ({data_bytes % SECTOR_BYTES} bytes: "
                     "cut short), skipped")
    low = [_cwa_battery(t) if t.name == "battery_voltage" else t
           for n in ("temperature", "battery_voltage", "light") if (t := table(lf, n, hw))]
    t = np.asarray(hf.get("datetime", np.zeros(0, np.int64)), np.int64)
    return Parsed("axivity_cwa", t, np.asarray(hf.get("acceleration", np.zeros((0, 3))),
                                                np.float32).reshape(-1, 3),
                  rate, np.asarray(lf.get("datetime", ()), np.int64), low, {}, meta,
                  f"{hw}-{dev['device_id']}" if dev.get("device_id") else None, tz, notes,
                  {"sectors": skipped, "partial_sector": int(data_bytes % SECTOR_BYTES > 0),
                   "reader_warnings": len(r.get("warnings", []))})
