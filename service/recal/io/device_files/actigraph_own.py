"""The ActiGraph .gt3x kinds actfast cannot read (log.bin of ACTIVITY2 records; the NHANES-era
activity.bin), read by recal's own decoder (`recal.io.gt3x`) into the shape every device
family hands to `DeviceRecording`.

Each log.bin record holds one second: its samples' first one is a block start (the whole
second), as in `actigraph`. An NHANES activity.bin is one continuous stream from info.txt's
start: no blocks. Idle sleep and missing seconds stay gaps; nothing is repeated.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recal.io.device_files.parsed import LowRate, Parsed, utc_offset_s
from recal.io.gt3x import read_gt3x

__all__ = ["read"]

#: the decoder's channels under the names (and units) the actfast-read .gt3x gives them
_CHANNELS = {"lux": ("light", 1.0), "battery_v": ("battery_voltage", 1000.0)}


def read(path: Path, shown: Path, lenient: bool, threads: int = 1) -> Parsed:
    d = read_gt3x(path, lenient=lenient)
    m = d.metadata
    nhanes = m["layout"] == "nhanes"
    t_ns = d.t_us * 1000
    low = [LowRate(name, d.aux[key][0] * 1000, d.aux[key][1] * factor)
           for key, (name, factor) in _CHANNELS.items() if key in d.aux]
    zone = "+00:00" if m.get("time_is_utc") else str(m.get("utc_offset") or "") or None
    serial = str(m.get("serial") or "") or None
    meta = {"device_type": f"ActiGraph {m.get('device_type') or ''}".strip(),
            "device_id": serial, "serial": serial, "firmware": m.get("firmware"),
            "nominal_rate_hz": d.rate_hz, "acceleration_scale": m["scale_lsb_per_g"],
            "acceleration_scale_from": m.get("scale_from", "the NHANES format (341 LSB/g)"),
            "time_zone": zone, "idle_sleep_mode": m.get("idle_sleep_mode"),
            "calibration_json_applied": m["calibration_json_applied"],
            "reader": "recal's .gt3x decoder (ActiGraph's published format)",
            "values": "acceleration in g: the counts divided by the file's acceleration scale"}
    # times and gaps are said by DeviceRecording, from the stamps it makes
    notes = [n for n in d.notes if not n.startswith("times are") and "left as gaps" not in n]
    skipped = {"bad_records": int(m.get("bad_records", 0)),
               "stray_bytes": int(m.get("stray_bytes", 0)),
               "truncated": int(bool(m.get("truncated", False)))}
    starts = None if nhanes else t_ns[d.t_us % 1_000_000 == 0]
    kind = "actigraph_gt3x_nhanes" if nhanes else "actigraph_gt3x_activity2"
    return Parsed(kind, t_ns, d.acc_g.astype(np.float32), d.rate_hz, starts, low, {}, meta,
                  serial, utc_offset_s(zone), notes, skipped)
