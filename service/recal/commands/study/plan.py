"""A study's plan: which files under the folder are recordings (by content, as
`io.sources.recording_kind` tells them), which of those are done (their result is current),
and the lock that keeps two runs off one OUTDIR.

A file's result is current when the result JSON under OUTDIR holds the same key: the file's
relative path, size and mtime, recal's version and the options (with --verify also the file's
SHA-256). A result is written only whole (`job.write_atomic`), so a run stopped anywhere leaves
each file done or not done, never half done. A file whose worker died is tried again by the
next run (the cause may have been the machine), once per run.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from recal.commands.study.job import Job, Options, result_path
from recal.daemon.state_files import SensorLock, lock_sensor
from recal.errors import InputError, SensorLockedError, UsageError

__all__ = ["LOCK_NAME", "Plan", "StudyLock", "file_key", "find_files", "make_plan",
           "options_for", "sha256"]

LOCK_NAME = ".recal-study.lock"
WORKER_DIED = "worker died"


@dataclass(frozen=True)
class Plan:
    """Rows known without calibrating (files skipped as not recordings, results current)
    and the jobs left to do."""

    skipped: list[dict[str, Any]]
    done: list[dict[str, Any]]
    todo: list[Job]


def sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def options_for(model: str | None, samples: str | None, sensor_id: str | None,
                rate_hz: float | None, units: str | None) -> Options:
    """The options with the model file's content (a model file edited in place counts)."""
    return Options(str(Path(model).resolve()) if model else None,
                   sha256(model) if model else None, samples, sensor_id, rate_hz, units)


def file_key(path: Path, rel: str, options: Options, verify: bool) -> dict[str, Any]:
    """What a result must have been made from to be current (module doc)."""
    from recal import __version__

    st = path.stat()
    key = {"path": rel, "size": st.st_size, "mtime_ns": st.st_mtime_ns, "recal": __version__,
           "options": asdict(options)}
    if verify:
        key["sha256"] = sha256(path)
    return key


def find_files(root: Path, out_dir: Path) -> Iterator[Path]:
    """Every file under root (recursively, in name order; symbolic links to folders not
    followed: no loop), outside out_dir and hidden names (.DS_Store, editors' files)."""
    out = out_dir.resolve()
    for here, dirs, files in os.walk(root):
        here_path = Path(here)
        dirs[:] = sorted(d for d in dirs if not d.startswith(".")
                         and (here_path / d).resolve() != out)
        for name in sorted(files):
            if not name.startswith("."):
                yield here_path / name


def _not_a_file(path: Path) -> str | None:
    """Why a name is not a regular file to read (a pipe, a socket, a device: opening one may
    wait forever); a link to nothing is left to its job (a row: unreadable)."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return None
    return None if stat.S_ISREG(mode) else "not a regular file (a pipe, socket or device)"


def not_a_recording(path: Path) -> str | None:
    """Why a file is not a recording (then it is listed as skipped), else None. A text file
    is one when its header names x, y, z columns (`io.csv_table`). An unreadable file is left
    to its job: it is a row that failed, not one skipped."""
    from recal.io.csv_table import iter_csv
    from recal.io.sources import recording_kind

    try:
        kind = recording_kind(path)
    except OSError:
        return None
    if kind == "unknown":
        return "not a recording: neither MCAP, a device file recal reads nor text"
    if kind == "csv":
        try:
            next(iter_csv(path, chunk_lines=64), None)
        except InputError as exc:
            said = str(exc)
            if "no axis columns" in said or "no header row" in said:
                return "not a recording: text without x, y, z columns"
        except (OSError, UsageError):
            return None
    return None


def make_plan(root: Path, out_dir: Path, options: Options, verify: bool) -> Plan:
    """The rows known now and the jobs to run (module doc)."""
    skipped: list[dict[str, Any]] = []
    done: list[dict[str, Any]] = []
    todo: list[Job] = []
    for path in find_files(root, out_dir):
        rel = path.relative_to(root).as_posix()
        why = _not_a_file(path) or not_a_recording(path)
        if why is not None:
            skipped.append({"path": rel, "status": "skipped", "reason": why})
            continue
        try:
            key = file_key(path, rel, options, verify=False)
        except OSError:
            key = {"path": rel}
        row = _current_row(result_path(out_dir, rel), key, path, verify)
        if row is not None:
            done.append(row)
            continue
        if verify and "size" in key:
            key["sha256"] = sha256(path)
        todo.append(Job(os.path.abspath(path), rel, str(out_dir.resolve()), options, key))
    return Plan(skipped, done, todo)


def _current_row(result: Path, key: dict[str, Any], path: Path,
                 verify: bool) -> dict[str, Any] | None:
    """The row of a current result (module doc), else None."""
    try:
        doc = json.loads(result.read_text())
        had, row = dict(doc["done"]), doc["row"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if row.get("failure") == WORKER_DIED:
        return None
    stored_hash = had.pop("sha256", None)
    if had != key:
        return None
    if verify and (stored_hash is None or stored_hash != sha256(path)):
        return None
    return row


class StudyLock:
    """An exclusive lock on OUTDIR for one run: the state folder's lock (`lock_sensor`, an
    flock on OUTDIR/.recal-study.lock holding the PID); the system releases it when the
    process ends, however it ends (no stale lock to clear)."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self._lock: SensorLock | None = None

    def __enter__(self) -> StudyLock:
        self.out_dir.mkdir(parents=True, exist_ok=True)  # the user's folder: its usual mode
        try:
            self._lock = lock_sensor(self.out_dir, LOCK_NAME.removesuffix(".lock"))
        except SensorLockedError as e:
            holder = f"process {e.pid}" if e.pid else "another process"
            raise UsageError(f"{self.out_dir} is in use by another recal hindsight run "
                             f"({holder}); wait for it to end or choose another --out") from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None


def clear_temporaries(out_dir: Path) -> int:
    """Remove what a stopped run left half-written (`job.write_atomic`'s temporary names);
    only under the lock, so no running job's."""
    n = 0
    for here, _, files in os.walk(out_dir):
        for name in files:
            if name.startswith(".") and ".tmp-" in name:
                (Path(here) / name).unlink(missing_ok=True)
                n += 1
    return n
