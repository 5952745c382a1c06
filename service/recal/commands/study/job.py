"""One file of a study: the single-file hindsight (`commands.hindsight.fit_recording`, and
`calibrate_file` when the calibrated samples are asked for), GGIR's still-window error before
and after (`core.still_error`), and the file's results written beside each other under OUTDIR
at the input's relative path, each atomically (a temporary name, then a rename; the result
JSON last: it is what marks the file done).

`run_job` never raises for a file: whatever goes wrong is its row (status ``failed``, a
``failure`` word and the reason) and a log of its own. It runs in a worker process (local or
Dask): everything it takes and gives is plain data.
"""

from __future__ import annotations

import json
import os
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from recal.core import still_error
from recal.errors import DeviceFileError, InputError, RecordingError

__all__ = ["TOO_SHORT_S", "Job", "Options", "log_path", "result_path", "run_job",
           "samples_path", "write_atomic"]

#: a recording without a single quasi-static window that lasts less than this is "too short";
#: longer, it has "no still period"
TOO_SHORT_S = 300.0


@dataclass(frozen=True)
class Options:
    """What a file's result depends on besides the file (a change recomputes every file)."""

    model: str | None = None  # the model file's path
    model_sha256: str | None = None  # ... and its content
    samples: str | None = None  # None, "mcap" or "csv": also write the calibrated samples
    sensor_id: str | None = None
    rate_hz: float | None = None
    units: str | None = None


@dataclass(frozen=True)
class Job:
    """A file to calibrate: its path, its path relative to the folder (its results' names
    under ``out_dir``) and ``key`` (what makes its result current: size, mtime, recal's
    version, the options, with --verify its hash; written into the result)."""

    path: str
    rel: str
    out_dir: str
    options: Options
    key: dict[str, Any]


def result_path(out_dir: str | Path, rel: str) -> Path:
    """The file's result (the row and its calibration, JSON)."""
    return Path(out_dir) / f"{rel}.json"


def log_path(out_dir: str | Path, rel: str) -> Path:
    """The log of a file that failed (its reason and where)."""
    return Path(out_dir) / f"{rel}.log"


def samples_path(out_dir: str | Path, rel: str, fmt: str) -> Path:
    """The file's calibrated samples (--samples mcap|csv)."""
    return Path(out_dir) / f"{rel}.calibrated.{fmt}"


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` under a temporary name in the same folder, then rename it: a reader
    sees the old file or the whole new one, never half of it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def run_job(job: Job) -> dict[str, Any]:
    """Calibrate one file and write its results; its row (`summary.COLUMNS`)."""
    t0 = time.perf_counter()
    row: dict[str, Any] = {"path": job.rel, "status": "ok"}
    doc: dict[str, Any] = {}
    try:
        doc = _calibrate(job, row)
    except Exception as exc:  # any failure of one file is its row, never the study's stop
        row["status"] = "failed"
        row["failure"], row["reason"] = _failure(exc, row)
        _write_log(job, row, traceback.format_exc())
    row["seconds"] = round(time.perf_counter() - t0, 3)
    if row["status"] == "ok":
        log_path(job.out_dir, job.rel).unlink(missing_ok=True)  # an earlier failure's
    write_atomic(result_path(job.out_dir, job.rel),
                 json.dumps({"row": row, "done": job.key, **doc}, indent=1, default=_plain))
    return row


def _calibrate(job: Job, row: dict[str, Any]) -> dict[str, Any]:
    from recal.commands import hindsight as hf
    from recal.io.sources import open_recording

    o = job.options
    src = open_recording(job.path, o.sensor_id, o.rate_hz, o.units)
    _describe(src, row)
    if src.device is not None:  # known before any pass (a failed fit still says how long)
        row["samples"] = len(src.device)
        row["hours"] = len(src.device) / src.device.rate_hz / 3600.0
    model = None
    if o.model is not None:
        from recal.config import load_model_file

        model = load_model_file(o.model)[0]
    try:
        fitted = hf.fit_recording(src, model)
    except InputError:
        if "samples" not in row:  # how long it is: "too short" or "no still period"
            _count(src, row)
        raise
    if o.samples is not None:
        out = samples_path(job.out_dir, job.rel, o.samples)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}.{o.samples}")
        calibration = hf.calibrate_file(src, tmp, model, overwrite=True, fitted=fitted)
        os.replace(tmp, out)
        calibration["out"] = str(out.relative_to(job.out_dir))
        row["samples_file"] = calibration["out"]
    else:  # the calibration alone, as `recal hindsight FILE --json` writes it
        calibration = hf.calibrate_file(src, None, model, fitted=fitted)
    _judge(src, fitted, row)
    _discovered(calibration.get("discovery"), row)
    row["fit_windows"] = fitted.fit.windows
    row["rate_hz"] = fitted.rate_hz
    return {"calibration": calibration}


def _count(src: Any, row: dict[str, Any]) -> None:
    """The samples of an MCAP or CSV recording and the hours they span (one pass)."""
    samples, first, last = 0, None, None
    for b in src.batches():
        if len(b):
            samples += len(b)
            first = int(b.t_us[0]) if first is None else first
            last = int(b.t_us[-1])
    row["samples"] = samples
    row["hours"] = (last - first) / 3.6e9 if first is not None else 0.0


def _describe(src: Any, row: dict[str, Any]) -> None:
    """What the file is: its kind, device type, id and serial (a device file's header), the
    sensor id, and what the reader had to say (skipped blocks, gaps...)."""
    m = src.metadata
    row.update(kind=src.kind, format=m.get("format", src.kind), device_type=m.get("device_type"),
               device_id=m.get("device_id"), serial=m.get("serial"), sensor_id=src.sensor_id)
    skipped = [f"{k} {m[k]}" for k in ("skipped_sectors", "skipped_partial_sector", "gaps")
               if m.get(k)]
    row["reader_notes"] = "; ".join(skipped) or None


def _judge(src: Any, fitted: Any, row: dict[str, Any]) -> None:
    """One more pass: every sample corrected with the fit, GGIR's still-window error before
    (the readings over the model's nominal scale) and after, and the samples by status."""
    from recal.commands.hindsight import Corrected
    from recal.core.status import Status

    fit = fitted.fit
    ref_g: np.ndarray | None = None
    parts: list[still_error.StillSums] = []
    samples = suspect = 0
    for b in src.batches():
        if not len(b):
            continue
        raw_g = b.v / fit.model.s0
        if ref_g is None:
            ref_g = np.nan_to_num(raw_g[0])
        parts.append(still_error.batch_sums(b.t_us, raw_g, fit.correct(b), fit.t0_us, ref_g))
        samples += len(b)
        suspect += int(np.count_nonzero(fit.suspect(b.t_us)))
    err = still_error.result(parts, ref_g if ref_g is not None else np.zeros(3),
                             fitted.rate_hz)
    # one fit for the recording: every sample has its status but the suspect ones
    status = Status(Corrected(fit, fitted.cfg).status).name.lower()
    row.update(samples=samples, hours=samples / fitted.rate_hz / 3600.0,
               still_windows=err.still, windows_10s=err.windows,
               ggir_error_before_mg=err.before_mg, ggir_error_after_mg=err.after_mg,
               samples_calibrated=samples - suspect if status == "calibrated" else 0,
               samples_held=samples - suspect if status == "held" else 0,
               samples_suspect=suspect)


def _discovered(d: dict[str, Any] | None, row: dict[str, Any]) -> None:
    """discover's held-out error before -> after (mg) and the effects it found."""
    if d is None:
        row["effects_found"] = "(model given)"
        return
    row["effects_found"] = " + ".join(e["label"] for e in d["effects_found"])
    if "skipped" in d:
        row["discovery_skipped"] = d["skipped"]
        return
    row["heldout_error_before_mg"] = d["heldout_error_mg"]["base"]
    row["heldout_error_after_mg"] = d["heldout_error_mg"]["final"]


def _failure(exc: BaseException, row: dict[str, Any]) -> tuple[str, str]:
    """A word for what went wrong (the summary's ``failure``) and the reason in a line."""
    said = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, InputError) and "no quasi-static window" in said:
        hours = row.get("hours")
        if hours is not None and hours * 3600.0 < TOO_SHORT_S:
            return "too short", f"{hours * 60:.1f} min of samples and no still window: {said}"
        return "no still period", said
    if isinstance(exc, InputError) and "neither an MCAP" in said:
        return "unknown format", said
    if isinstance(exc, DeviceFileError | RecordingError):
        return "corrupt", said
    if isinstance(exc, InputError):
        return "unusable", said
    if isinstance(exc, OSError):
        return "unreadable", said
    if isinstance(exc, MemoryError):
        return "out of memory", said
    return "error", f"{type(exc).__name__}: {said}"


def _write_log(job: Job, row: dict[str, Any], trace: str) -> None:
    try:
        write_atomic(log_path(job.out_dir, job.rel),
                     f"{job.path}\nfailed: {row['failure']}: {row['reason']}\n"
                     f"options: {json.dumps(asdict(job.options))}\n\n{trace}")
    except OSError:  # the row still says why; the log is extra
        pass


def _plain(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)
