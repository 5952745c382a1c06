"""ActiGraph .gt3x (a zip: info.txt and log.bin of log records), read by actfast; the kinds it
cannot read are recognised here and read by recal's own decoder (`actigraph_own`,
`recal.io.gt3x`): log.bin of ACTIVITY2 records (ActiGraph Link, CentrePoint; actfast 1.3
returns no samples for them) and the NHANES-era zip with activity.bin and no log.bin
(actigraph/GT3X-File-Format and NHANES-GT3X-File-Format describe both).

Each ACTIVITY record holds one second of samples at the sample rate, stamped with its whole
second: the seconds are the blocks. In idle sleep mode the device writes no ACTIVITY record for
the seconds it sleeps (EVENT records 0x08 and 0x09 mark entering and leaving it); actfast adds
no samples for them, so they stay a gap. Some readers fill them with the last sample repeated,
which would look like a perfectly still sensor; nothing here does.
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

__all__ = ["read", "sniff_activity2", "sniff_gt3x", "sniff_nhanes"]

ACTIVITY, ACTIVITY2 = 0x00, 0x1A


def sniff_gt3x(p: Probe) -> bool:
    return "log.bin" in p.zip_names


def sniff_activity2(p: Probe) -> bool:
    types = p.log_record_types
    return sniff_gt3x(p) and ACTIVITY2 in types and ACTIVITY not in types


def sniff_nhanes(p: Probe) -> bool:
    return "activity.bin" in p.zip_names and "log.bin" not in p.zip_names


def read(path: Path, shown: Path, lenient: bool, threads: int = 1) -> Parsed:
    guard.check_zip(path, ("log.bin", "info.txt"))
    r = actfast_read(path, shown, lenient, "ActiGraph .gt3x")
    ts = r.get("timeseries", {})
    acc = ts.get("acceleration", {})
    info = r.get("metadata", {}).get("info", {})
    rate = number(info.get("Sample Rate")) or 30.0
    zone = info.get("TimeZone")
    serial = info.get("Serial Number")
    features = r.get("metadata", {}).get("device_feature_enabled", {})
    meta = {"device_type": f"ActiGraph {info.get('Device Type', '')}".strip(),
            "device_id": serial, "serial": serial, "firmware": info.get("Firmware"),
            "nominal_rate_hz": rate, "range_g": f"{info.get('Acceleration Min')} to "
                                                f"{info.get('Acceleration Max')}",
            "acceleration_scale": info.get("Acceleration Scale"), "time_zone": zone,
            "idle_sleep_mode": features.get("sleep_mode"),
            "values": "acceleration in g: the counts divided by the file's acceleration scale"}
    notes = []
    notes += warning_notes(r)
    if str(serial).startswith("MOS") and str(info.get("Firmware")) == "1.6.0":
        notes.append("firmware 1.6.0 of a wGT3X-BT swaps x and y (ActiGraph's note on "
                     "ACTIVITY records): the values are as written")
    if str(features.get("sleep_mode")).lower() == "true":
        notes.append("idle sleep mode was on: the seconds the device slept are gaps, not "
                     "repeated samples")
    low = [t for n, k in (("light", "light"), ("battery_voltage", "battery_voltage"))
           if (t := table(ts.get(n, {}), k, "ActiGraph"))]
    t = np.asarray(acc.get("datetime", np.zeros(0, np.int64)), np.int64)
    whole_s = t[t % 1_000_000_000 == 0]  # each record's first sample: its whole second
    return Parsed("actigraph_gt3x", t, np.asarray(acc.get("acceleration", np.zeros((0, 3))),
                                                   np.float32).reshape(-1, 3),
                  rate, whole_s, low, {}, meta, str(serial) if serial else None,
                  utc_offset_s(zone), notes, {"reader_warnings": len(r.get("warnings", []))})
