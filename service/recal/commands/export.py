"""``recal export``: one sensor's raw or calibrated samples of a recording to CSV, message by
message (a week-long recording must not have to fit in memory), with the samples counted per
status (`recal.core.status.Status`).

Time columns say their unit: the raw export's time is the device's, as it came, named by the
unit its time base read (``t_us``, ``t_ms`` for a ``millis()`` device, ``t_s``); the calibrated
export has the service's ``t_us`` and, where the recording keeps it, the device's own stamp of
each sample in the same unit (``device_t_ms`` ...), so the two join on it exactly, across
device reboots too."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from recal.core import timebase as tb
from recal.core.status import Status, status_line
from recal.errors import UsageError
from recal.io import csv_table, recording

__all__ = ["StatusCounts", "export_csv"]


def export_csv(source: str, csv_out: str, sensor_id: str | None, topic: str
               ) -> tuple[dict[str, Any], list[str]]:
    """Write ``topic`` ("raw" or "calibrated") of one sensor (default: the first) to
    ``csv_out``: the report (rows, counts per status) and the lines that say it."""
    sensors = recording.sensors(source)
    if not sensors:
        raise UsageError(f"{source} holds no sensor topics")
    if sensor_id is not None and sensor_id not in sensors:
        raise UsageError(f"{source} has no sensor {sensor_id!r} (it has: "
                         f"{', '.join(sensors)})")
    sid = sensor_id or sensors[0]
    unit = _device_unit(source, sid)
    if topic == "raw":
        units = recording.metadata(source).get("units")  # set by `recal import`
        raws = (b for _, b, _ in recording.iter_raw(source, sid))
        first_raw = next(raws, None)
        if unit is None and first_raw is not None:  # no setup recorded: the time base's rule
            unit = tb.UNIT_NAMES[tb.decide_unit(first_raw.t_us, tb.TimebaseConfig())[0]]
        rows = csv_table.write_raw_csv(
            csv_out, itertools.chain([first_raw] if first_raw is not None else [], raws),
            units if units in csv_table.UNITS else None, f"t_{unit or 'us'}")
    else:
        counts = StatusCounts()
        batches = (counts.add(b) for _, b, _ in recording.iter_calibrated(source, sid))
        first = next(batches, None)
        if first is None:
            raise UsageError(f"{source} has no calibrated data for {sid!r}; run recal replay")
        device = None if first.t_dev is None else f"device_t_{unit or 'us'}"
        rows = csv_table.write_calibrated_csv(csv_out, itertools.chain([first], batches),
                                              device_time=device)
    lines = [f"wrote {rows} rows of {sid}/{topic} to {csv_out}"]
    report = {"in": source, "csv": csv_out, "sensor_id": sid, "topic": topic, "rows": rows}
    if topic != "raw":
        report.update(counts.to_dict())
        lines.append(f"  {counts.line()}")
    return report, lines


def _device_unit(source: str, sid: str) -> str | None:
    """The unit the sensor's device time was read in ("us", "ms", "s"), from the first setup
    its node recorded (`recal.node.node`); None without one."""
    for _, obj, _ in recording.iter_json(source, recording.sensor_topic(sid, "setup")):
        base = obj.get("timebase") if isinstance(obj, dict) else None
        unit_us = base.get("unit_us") if isinstance(base, dict) else None
        return tb.UNIT_NAMES.get(unit_us) if isinstance(unit_us, int) else None
    return None


class StatusCounts:
    """Samples per status (`recal.core.status.Status`) of the calibrated batches it sees."""

    def __init__(self) -> None:
        self.counts = np.zeros(256, np.int64)

    def add(self, batch: Any) -> Any:
        self.counts += np.bincount(batch.status, minlength=256)
        return batch

    def to_dict(self) -> dict:
        S = Status
        by = {S(i).label if i in S._value2member_map_ else str(i): int(n)
              for i, n in enumerate(self.counts.tolist()) if n}
        recorded = int(self.counts.sum() - self.counts[S.NOT_RECORDED])
        # each name counts what it says: uncalibrated and bootstrapping apart, and every
        # status but calibrated (held, suspect too) as not calibrated
        return {"samples_by_status": by,
                "samples_not_calibrated": recorded - int(self.counts[S.CALIBRATED]),
                "samples_uncalibrated": int(self.counts[S.UNCALIBRATED]),
                "samples_bootstrapping": int(self.counts[S.BOOTSTRAPPING]),
                "samples_status_not_recorded": int(self.counts[S.NOT_RECORDED])}

    def line(self) -> str:
        return status_line(self.to_dict())
