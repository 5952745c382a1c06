"""Checkpoint files: where a sensor's calibration survives a restart, and who owns it.

A sensor's state folder (``[checkpoint] dir``) holds, per sensor id:

* ``<sensor>.json``: the current checkpoint, written atomically (a temporary file, fsync,
  rename, directory fsync): a crash leaves the old one or the new one, never half of one.
* ``<sensor>.json.prev``: the generation before it (a hard link to the old file made before the
  rename, so ``<sensor>.json`` is never missing). It is the fallback when the current one does
  not load.
* ``<sensor>.lock``: ``flock``-ed by the one process that calibrates the sensor (it holds its
  PID): two daemons with the same sensor id and state folder would resume each other's
  calibration and overwrite each other's checkpoints.
* ``<sensor>.json.rejected`` (and ``<sensor>.json.prev.rejected``): a file that did not load,
  moved aside so that no later rotation makes it the fallback; kept for inspection.

Every name ends in its own suffix after the sensor id, so no two sensors' files can share a
name (sensor ids may contain dots: ``a.prev.json`` could be ``a``'s or ``a.prev``'s).

No file of the folder is a way to write or read elsewhere (a daemon often runs as root): the
folder is made 0700 (one that others may write is warned about), every file is opened with
``O_NOFOLLOW``, temporaries get random names and ``O_EXCL``, and renames replace a link, never
its target. A sensor with a symlink where one of its files should be is refused at the start
(:meth:`Checkpoints.acquire`): one console line, the link and its target left alone, and that
sensor is calibrated without checkpoints; the other sensors are not affected.

Saving: every ``interval_s`` (spread over sensors, :class:`CheckpointSchedule`) and, after an
accepted update, within ``after_update_s`` (so a crash loses seconds of progress, not a
minute). :class:`Checkpoints` is what the gateway and the remote node use: locks, loading with
the fallback, saving, and the operator's console lines (a failed load is one line; failed saves
are one line, then a sum at most once a minute). What is inside a file, and when it is
trusted: `recal.node.checkpoint_doc`.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from recal.daemon.state_files import (
    SensorLock,
    StateFileRefused,
    checkpoint_path,
    fsync_dir,
    load_checkpoint,
    lock_path,
    lock_sensor,
    prepare_folder,
    previous_path,
    refused,
    replace_with_copy,
    save_checkpoint,
    state_files,
    unsafe_state_file,
)
from recal.errors import CheckpointError, SensorLockedError
from recal.node.checkpoint_doc import finite_document, restore_pipeline

__all__ = [
    "CheckpointError",
    "CheckpointSchedule",
    "Checkpoints",
    "SensorLock",
    "SensorLockedError",
    "StateFileRefused",
    "checkpoint_path",
    "load_checkpoint",
    "lock_path",
    "lock_sensor",
    "previous_path",
    "save_checkpoint",
    "state_files",
    "unsafe_state_file",
]

log = logging.getLogger(__name__)

FAIL_NOTE_S = 60.0  # failed saves are summed up for the operator at most this often


# ---------------------------------------------------------------------------------------------
# When to save
# ---------------------------------------------------------------------------------------------

class CheckpointSchedule:
    """When each sensor's checkpoint is next due: every ``interval_s``, the sensors spread over
    the interval (the k-th added at phase k * 0.618... of it, evenly for any count).

    Why: every sensor's checkpoint written at once holds the GIL long enough to stall the I/O
    loop (figures: docs/design.md, "Figures behind choices"); spread out, each turn is short,
    shared with the loop.
    """

    _PHASE_STEP = (5 ** 0.5 - 1) / 2  # golden-ratio steps stay evenly spread as sensors come

    def __init__(self, interval_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.interval_s = float(interval_s)
        self._clock = clock
        self._due: dict[str, float] = {}

    def add(self, sensor_id: str) -> None:
        if sensor_id not in self._due:
            phase = (len(self._due) * self._PHASE_STEP) % 1.0
            self._due[sensor_id] = self._clock() + self.interval_s * (phase or 1.0)

    def take_due(self) -> list[str]:
        """The sensors due now, each rescheduled one interval on."""
        now = self._clock()
        due = [sid for sid, t in self._due.items() if t <= now]
        for sid in due:
            self._due[sid] = now + self.interval_s
        return due

    def next_due_s(self) -> float:
        """Seconds until the next sensor is due (inf with none)."""
        return max(0.0, min(self._due.values()) - self._clock()) if self._due else float("inf")


# ---------------------------------------------------------------------------------------------
# The daemon's side: locks, loading with the fallback, saving, console lines
# ---------------------------------------------------------------------------------------------

@dataclass
class _Failures:
    """Failed saves of one sensor since the last console line about them."""

    count: int = 0  # since the last console line
    total: int = 0  # since the last successful save
    last_error: str = ""
    failing: bool = False


class Checkpoints:
    """Checkpoints of the sensors one process calibrates, in one state folder.

    Args:
        directory: the state folder (None: no checkpoints, no locks).
        interval_s: save every sensor this often.
        after_update_s: after an accepted update, save within this many seconds (at most
            that often per sensor; 0: off).
        out: one console line for the operator (prefix included by the caller's ``prefix``).
        event: ``event(sensor_id, kind, detail)`` for the log and the bus.
        prefix: how console lines begin ("recal gateway:").
    """

    def __init__(self, directory: str | Path | None, interval_s: float,
                 after_update_s: float = 5.0, *, out: Callable[[str], None] = print,
                 event: Callable[[str, str, Any], None] | None = None,
                 prefix: str = "recal:", clock: Callable[[], float] = time.monotonic) -> None:
        self.directory = Path(directory) if directory is not None else None
        self.after_update_s = float(after_update_s)
        self.schedule = CheckpointSchedule(interval_s, clock)
        self.out, self.prefix = out, prefix
        self._event = event
        self._clock = clock
        self.locks: dict[str, SensorLock] = {}
        #: sensors whose state files were refused (a symlink): calibrated without checkpoints
        self.refused: dict[str, str] = {}
        self._folder_checked = False
        self._saved_updates: dict[str, int] = {}
        self._saved_at: dict[str, float] = {}
        self._failures: dict[str, _Failures] = {}
        self._dropping: set[str] = set()  # sensors whose saves drop values (said once)
        self._fail_noted_s = float("-inf")
        self.saves = 0
        self.failed_saves = 0

    @property
    def enabled(self) -> bool:
        return self.directory is not None

    def set_event(self, event: Callable[[str, str, Any], None] | None) -> None:
        """Where events go from now on (the gateway's log exists only after loading)."""
        self._event = event

    # -- ownership ----------------------------------------------------------------------------

    def acquire(self, sensor_ids: Iterable[str]) -> None:
        """Lock these sensors (all or none: SensorLockedError or OSError, nothing held). A
        sensor with a symlink among its state files is not locked but refused (one line; it is
        calibrated without checkpoints), never an error for the others."""
        if self.directory is None:
            return
        if not self._folder_checked:
            warning = prepare_folder(self.directory)
            self._folder_checked = True
            if warning is not None:
                self.out(f"{self.prefix} {warning}")
        taken = []
        try:
            for sid in sensor_ids:
                if sid in self.locks or sid in self.refused:
                    continue
                bad = unsafe_state_file(self.directory, sid)
                try:
                    if bad is not None:
                        raise refused(bad, OSError(errno.ELOOP, "symlink"))
                    self.locks[sid] = lock_sensor(self.directory, sid)
                except StateFileRefused as exc:
                    self._refuse(sid, exc)
                    continue
                taken.append(sid)
        except BaseException:
            for sid in taken:
                self.locks.pop(sid).release()
            raise

    def _refuse(self, sid: str, exc: StateFileRefused) -> None:
        why = exc.strerror or str(exc)
        self.refused[sid] = why
        self.out(f"{self.prefix} {sid}: {why}: calibrated without checkpoints (no resume, "
                 "no saves) until it is removed")
        if self._event is not None:
            self._event(sid, "checkpoint_refused", {"error": why})

    def release(self) -> None:
        for lock in self.locks.values():
            lock.release()
        self.locks.clear()

    # -- loading ------------------------------------------------------------------------------

    def load(self, sensor_id: str, restore: Callable[[dict[str, Any]], Any],
             on_problem: Callable[[str, dict[str, Any]], None] | None = None) -> Any:
        """``restore(doc)`` of the sensor's current checkpoint, else of the previous generation,
        else None (start from the prior). A file that does not load or ``restore`` refuses is
        moved aside (``.rejected``), reported as an event ``checkpoint_invalid`` and one
        console line (and ``on_problem(kind, detail)``); nothing here raises for a bad file."""
        if self.directory is None or sensor_id in self.refused:
            return None
        cur = checkpoint_path(self.directory, sensor_id)
        if not cur.exists() and not cur.is_symlink():
            return None  # never saved, or deleted to start again from the prior
        prev = previous_path(self.directory, sensor_id)
        for path, fallback in ((cur, prev), (prev, None)):
            try:
                doc = load_checkpoint(path)
                if doc is None:
                    continue
                if doc.get("sensor_id") != sensor_id:
                    raise CheckpointError(f"{path}: for sensor {doc.get('sensor_id')!r}")
                restored = restore(doc)
            except Exception as exc:  # CheckpointError, a restore refusal, anything
                self._reject(sensor_id, path, exc, fallback, on_problem)
                continue
            if path == prev:  # the previous generation is current again: a crash before the
                try:          # next save must not find no checkpoint at all
                    replace_with_copy(prev, cur)
                    fsync_dir(cur.parent)
                except OSError as exc:
                    log.warning("cannot copy %s to %s: %s", prev, cur, exc)
            return restored
        return None

    def _reject(self, sensor_id: str, path: Path, exc: Exception, fallback: Path | None,
                on_problem: Callable[[str, dict[str, Any]], None] | None) -> None:
        why = str(exc)
        if not why.startswith(str(path)):
            why = f"{path}: {why}"
        aside = path.with_name(path.name + ".rejected")
        try:
            if aside.is_dir() and not aside.is_symlink():
                shutil.rmtree(aside)
            os.replace(path, aside)
            moved: str | None = str(aside)
        except OSError as err:
            moved = None
            log.warning("cannot move %s aside: %s", path, err)
        usable = fallback is not None and fallback.exists()
        then = f"trying {fallback.name}" if usable else "starting from the prior"
        self.out(f"{self.prefix} {sensor_id}: checkpoint ignored: {why}; {then}")
        detail = {"path": str(path), "error": why, "moved_to": moved,
                  "fallback": str(fallback) if usable else "prior"}
        if self._event is not None:
            self._event(sensor_id, "checkpoint_invalid", detail)
        if on_problem is not None:
            on_problem("checkpoint_invalid", detail)

    # -- saving -------------------------------------------------------------------------------

    def add(self, sensor_id: str, accepted_updates: int = 0) -> None:
        """Schedule a sensor's saves (its count of accepted updates as of now)."""
        self.schedule.add(sensor_id)
        self._saved_updates.setdefault(sensor_id, accepted_updates)
        self._saved_at.setdefault(sensor_id, float("-inf"))

    def next_due_s(self) -> float:
        return self.schedule.next_due_s()

    def save_due(self, nodes: Mapping[str, Any]) -> None:
        """Save the sensors whose interval is up, and those with an accepted update since
        their last save once ``after_update_s`` has passed since it."""
        if self.directory is None:
            return
        due = set(self.schedule.take_due())
        if self.after_update_s > 0:
            now = self._clock()
            for sid, node in nodes.items():
                if (node is not None and sid not in due
                        and getattr(node, "accepted_updates", 0) != self._saved_updates.get(sid)
                        and now - self._saved_at.get(sid, float("-inf")) >= self.after_update_s):
                    due.add(sid)
        self.save(nodes, [sid for sid in nodes if sid in due])

    def save(self, nodes: Mapping[str, Any], sensor_ids: Iterable[str] | None = None) -> None:
        """Save these sensors (default: all) now; failures are reported, never raised."""
        if self.directory is None:
            return
        for sid in nodes if sensor_ids is None else sensor_ids:
            node = nodes.get(sid)
            if node is None or sid in self.refused:
                continue
            updates = getattr(node, "accepted_updates", 0)
            try:
                doc = node.checkpoint()
                if doc is None:
                    continue
                doc, where, dropped = finite_document(doc)
                self._check_before_save(doc)
                save_checkpoint(checkpoint_path(self.directory, sid), doc)
            except (OSError, ValueError) as exc:
                self._failed(sid, exc)
                continue
            self._note_dropped(sid, where, dropped)  # said of a save made, not one refused
            self._saved_updates[sid] = updates
            self._saved_at[sid] = self._clock()
            self.saves += 1
            self._succeeded(sid)
        self._note_failures()

    @staticmethod
    def _check_before_save(doc: dict[str, Any]) -> None:
        """The load checks (bar the probe): a state that would be refused at the next start is
        not written over the last good one (ValueError)."""
        restore_pipeline(doc.get("pipeline"), probe=False)

    def _note_dropped(self, sid: str, where: list[str], count: int) -> None:
        """An event and a line when a sensor's saves start holding values strict JSON cannot
        (saved as null), not on every save; said again only after a clean save."""
        if not count:
            self._dropping.discard(sid)
            return
        if sid in self._dropping:
            return
        self._dropping.add(sid)
        shown = where[:8]
        if self._event is not None:
            self._event(sid, "checkpoint_values_dropped", {
                "values": count, "where": shown, "saved_as": None})
        self.out(f"{self.prefix} {sid}: {count} value{'s' if count > 1 else ''} in the "
                 f"checkpoint not finite ({', '.join(shown)}): saved as null, the rest as is")

    def _failed(self, sid: str, exc: Exception) -> None:
        self.failed_saves += 1
        error = (f"{type(exc).__name__}: {exc}" if not isinstance(exc, OSError)
                 else f"{exc.strerror or exc}" + (f": {exc.filename}" if exc.filename else ""))
        f = self._failures.setdefault(sid, _Failures())
        f.total += 1
        if self._event is not None:
            self._event(sid, "checkpoint_failed", {"error": error})
        if not f.failing:  # the first failure of a run of them: a line at once
            f.failing = True
            self.out(f"{self.prefix} {sid}: checkpoint not saved: {error} (calibration goes "
                     f"on; failures are summed up at most every {FAIL_NOTE_S:g} s)")
            self._fail_noted_s = max(self._fail_noted_s, self._clock())
            return
        f.count += 1
        f.last_error = error

    def _succeeded(self, sid: str) -> None:
        f = self._failures.get(sid)
        if f is not None and f.failing:
            self.out(f"{self.prefix} {sid}: checkpoint saved again after {f.total} failed "
                     f"save{'s' if f.total > 1 else ''}")
            del self._failures[sid]

    def _note_failures(self) -> None:
        """At most one line a FAIL_NOTE_S: the failed saves since the last line."""
        pending = {sid: f for sid, f in self._failures.items() if f.count}
        now = self._clock()
        if not pending or now < self._fail_noted_s + FAIL_NOTE_S:
            return
        self._fail_noted_s = now
        what = ", ".join(f"{sid} {f.count}x ({f.last_error})" for sid, f in pending.items())
        self.out(f"{self.prefix} checkpoints not saved in the last {FAIL_NOTE_S:g} s: {what}")
        for f in pending.values():
            f.count = 0
