"""A study's summary: OUTDIR/summary.csv and summary.json, one row per file under the folder
(in path order), with the columns of `COLUMNS` (docs/study.md lists them too)."""

from __future__ import annotations

import csv
import io
import json
from collections import Counter
from pathlib import Path
from typing import Any

from recal.commands.study.job import write_atomic

__all__ = ["COLUMNS", "counts", "summary_lines", "write_summary"]

#: each column of the summary and what it holds (empty where it does not apply)
COLUMNS: dict[str, str] = {
    "path": "the file, relative to the folder",
    "status": "ok, failed or skipped (not a recording)",
    "failure": "what went wrong: unreadable, corrupt, unknown format, unusable, too short, "
               "no still period, worker died, out of memory, error",
    "reason": "why it failed or was skipped, in a line (the file's .log has the rest)",
    "kind": "device, mcap or csv (recognised by content)",
    "format": "the device file's format (Axivity AX3/AX6 .cwa, GENEActiv .bin, ActiGraph .gt3x)",
    "device_type": "the device's type from the file's header",
    "device_id": "the device's id from the file's header",
    "serial": "the device's serial number, where the header has one",
    "sensor_id": "the sensor id the calibration is written for",
    "samples": "samples in the file",
    "hours": "samples / rate, in hours",
    "rate_hz": "the sample rate",
    "windows_10s": "10 s windows that hold samples",
    "still_windows": "of those, still by GGIR's rule (90 % filled, every axis's SD under 13 mg)",
    "ggir_error_before_mg": "GGIR's calibration error: mean over the still windows of "
                            "| |window mean| - 1 g | in mg, the readings over the nominal scale",
    "ggir_error_after_mg": "the same, calibrated",
    "heldout_error_before_mg": "discover's held-out error (mg) with offsets and gains alone",
    "heldout_error_after_mg": "the same with the effects it found",
    "effects_found": "the effects discovery selected beyond offsets and gains (+ between)",
    "fit_windows": "quasi-static windows the fit used (the live detector's)",
    "samples_calibrated": "samples whose status is calibrated",
    "samples_held": "samples held (the recording's poses could not determine the model)",
    "samples_suspect": "samples marked suspect (the fit's misfit there far above the noise)",
    "reader_notes": "what the device file's reader skipped (sectors, gaps)",
    "samples_file": "the calibrated samples under OUTDIR (--samples)",
    "seconds": "the time the file took (its worker's)",
}


def write_summary(out_dir: Path, rows: list[dict[str, Any]]) -> None:
    """summary.csv and summary.json under out_dir, each written whole (`write_atomic`)."""
    rows = sorted(rows, key=lambda r: r["path"])
    text = io.StringIO()
    w = csv.DictWriter(text, fieldnames=list(COLUMNS), extrasaction="ignore",
                       lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: _cell(r.get(k)) for k in COLUMNS})
    write_atomic(out_dir / "summary.csv", text.getvalue())
    write_atomic(out_dir / "summary.json",
                 json.dumps({"columns": COLUMNS, "counts": counts(rows), "rows": rows},
                            indent=1))


def _cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    """Rows by status."""
    c = Counter(r["status"] for r in rows)
    return {s: c.get(s, 0) for s in ("ok", "failed", "skipped")}


def summary_lines(rows: list[dict[str, Any]], out_dir: Path, computed: int,
                  seconds: float) -> list[str]:
    """The run's report for a person: counts, then each failed file with its reason."""
    c = counts(rows)
    lines = [f"{len(rows)} files: {c['ok']} calibrated, {c['failed']} failed, {c['skipped']} "
             f"skipped (not recordings); {computed} run now, "
             f"{len(rows) - computed - c['skipped']} were done already; {seconds:.1f} s",
             f"  summary: {out_dir / 'summary.csv'} (and summary.json)"]
    for r in sorted(rows, key=lambda r: r["path"]):
        if r["status"] == "failed":
            lines.append(f"  failed {r['path']}: {r.get('failure')}: {r.get('reason')}")
    return lines
