"""GENEActiv .bin (a text file of hex pages), read by actfast; the older Genea .bin is
recognised and refused.

The header (59 lines, "Device Identity" first) holds the device, its calibration (gain and
offset per axis, which actfast applies: the values are in g), the time zone and the page
count; each page of 300 samples has its own time, temperature and battery (the blocks).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recal.io.device_files import guard
from recal.io.device_files.parsed import (
    Parsed,
    actfast_read,
    number,
    table,
    utc_offset_s,
    warning_notes,
)
from recal.io.device_files.probe import Probe

__all__ = ["read", "sniff_genea", "sniff_geneactiv"]


def sniff_geneactiv(p: Probe) -> bool:
    return p.head.startswith(b"Device Identity")


def sniff_genea(p: Probe) -> bool:
    """The older Genea's header (actfast recognises it by these bytes and refuses it)."""
    return p.head.startswith(b"GENE")


def read(path: Path, shown: Path, lenient: bool, threads: int = 1) -> Parsed:
    claimed = guard.check_geneactiv_pages(path, guard.read_head(path, 8192))
    r = actfast_read(path, shown, lenient, "GENEActiv .bin")
    ts = r.get("timeseries", {})
    hf, lf = ts.get("high_frequency", {}), ts.get("low_frequency", {})
    m = r.get("metadata", {})
    ident, caps = m.get("Device Identity", {}), m.get("Device Capabilities", {})
    conf = m.get("Configuration Info", {})
    rate = number(conf.get("Measurement Frequency")) or 100.0
    zone = conf.get("Time Zone")
    serial = ident.get("Device Unique Serial Code")
    meta = {"device_type": f"{ident.get('Device Type', 'GENEActiv')} "
                           f"{ident.get('Device Model', '')}".strip(),
            "device_id": serial, "serial": serial,
            "firmware": ident.get("Device Firmware Version"),
            "calibration_date": ident.get("Calibration Date"),
            "nominal_rate_hz": rate, "range_g": caps.get("Accelerometer Range"),
            "start_time": conf.get("Start Time"), "time_zone": zone,
            "values": "acceleration in g: the calibration from the header applied by the reader"}
    pages_read = len(lf.get("datetime", ()))
    notes = ["values in g with the header's calibration (gain and offset per axis) applied by "
             "the reader"]
    notes += warning_notes(r)
    skipped = {"reader_warnings": len(r.get("warnings", []))}
    if claimed is not None and claimed > pages_read:
        skipped["pages"] = claimed - pages_read
        notes.append(f"the header says {claimed} pages, {pages_read} were read (the file is "
                     "cut short or has damaged pages)")
    low = [t for n in ("temperature", "battery_voltage") if (t := table(lf, n, "GENEActiv"))]
    per = {"light": np.asarray(hf["light"], np.float64)} if "light" in hf else {}
    t = np.asarray(hf.get("datetime", np.zeros(0, np.int64)), np.int64)
    return Parsed("geneactiv_bin", t, np.asarray(hf.get("acceleration", np.zeros((0, 3))),
                                                  np.float32).reshape(-1, 3),
                  rate, np.asarray(lf.get("datetime", ()), np.int64), low, per, meta,
                  f"GENEActiv-{serial}" if serial else None, utc_offset_s(zone), notes, skipped)
