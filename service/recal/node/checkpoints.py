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

A checkpoint is trusted only after it has been checked (:func:`load_checkpoint` for the file,
:func:`restore_pipeline` for the state): size and nesting depth, strict JSON (no NaN, no
infinity, no integer beyond 2^53), the format, then the pipeline rebuilt with
``Pipeline.from_state_dict`` inside a guard and its result checked: the estimate and prior
shaped like the model, finite, inside the model's own ``bounds()`` (the offsets' centred on
the configured zero-g, `param_bounds`), a symmetric covariance with positive variances, device
times no later than the checkpoint's last sample (plus a day) and that one not after tomorrow
in Unix time, and one probe step on a copy that must run and give finite output. New state
fields are covered by the strict-JSON rule and the probe without edits here. The same checks
(without the probe) run before each save: a state that would not load is never written over a
good one.

Saving: every ``interval_s`` (spread over sensors, :class:`CheckpointSchedule`) and, after an
accepted update, within ``after_update_s`` (so a crash loses seconds of progress, not a
minute). :class:`Checkpoints` is what the gateway and the remote node use: locks, loading with
the fallback, saving, and the operator's console lines (a failed load is one line; failed saves
are one line, then a sum at most once a minute).
"""

from __future__ import annotations

import contextlib
import copy
import errno
import fcntl
import json
import logging
import os
import re
import secrets
import shutil
import stat
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.samples import RawBatch

__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "CheckpointSchedule",
    "Checkpoints",
    "SensorLock",
    "SensorLockedError",
    "StateFileRefused",
    "checkpoint_path",
    "estimate_problem",
    "finite_document",
    "json_depth",
    "load_checkpoint",
    "lock_path",
    "lock_sensor",
    "param_bounds",
    "pipeline_problem",
    "previous_path",
    "restore_pipeline",
    "save_checkpoint",
    "state_files",
    "unsafe_state_file",
]

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = 1
# A checkpoint is ~100 kB with the default buffer, ~1 MB with 8x its cells; 8 MiB of numbers
# parse into at most ~150 MB of Python objects.
MAX_BYTES = 8 << 20
MAX_DEPTH = 32  # a pipeline state nests 5 deep; JSON parsers recurse per level
MAX_INT = 2**53  # larger integers are no device time or count (and overflow int64 near 2^63)
FUTURE_US = 86_400 * 10**6  # a day: how far any time in a state may lie past its last sample
FAIL_NOTE_S = 60.0  # failed saves are summed up for the operator at most this often
PROBE_SAMPLES = 4

# the files of a sensor in the state folder, by suffix after its id (see the module docstring)
STATE_SUFFIXES = (".lock", ".json", ".json.prev", ".json.rejected", ".json.prev.rejected")
FOLDER_MODE = 0o700
_NOFOLLOW = os.O_NOFOLLOW | os.O_CLOEXEC

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


class CheckpointError(ValueError):
    """A checkpoint file that exists but cannot be trusted (the message says why)."""


class SensorLockedError(RuntimeError):
    """Another process calibrates this sensor id from the same state folder."""

    def __init__(self, sensor_id: str, path: Path, pid: int | None) -> None:
        self.sensor_id, self.path, self.pid = sensor_id, path, pid
        holder = f"process {pid}" if pid else "another process"
        super().__init__(f"sensor {sensor_id!r} is already calibrated by {holder} "
                         f"(lock {path}); one process per sensor id and state folder")


class StateFileRefused(OSError):
    """A symlink (or another non-file) where a state file should be: never opened through."""


# ---------------------------------------------------------------------------------------------
# Paths
# ---------------------------------------------------------------------------------------------

def state_files(directory: str | Path, sensor_id: str) -> list[Path]:
    """Every file the daemon may write for this sensor in ``directory``."""
    return [Path(directory) / f"{sensor_id}{suffix}" for suffix in STATE_SUFFIXES]


def unsafe_state_file(directory: str | Path, sensor_id: str) -> Path | None:
    """The first of the sensor's state files that is a symlink, or None."""
    for path in state_files(directory, sensor_id):
        with contextlib.suppress(OSError):
            if stat.S_ISLNK(path.lstat().st_mode):
                return path
    return None


def prepare_folder(directory: str | Path) -> str | None:
    """Make the state folder (0700: checkpoints and locks are the daemon's alone); a warning
    when it exists and others may write it (they could plant links or files), else None."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True, mode=FOLDER_MODE)
    mode = d.stat().st_mode
    if mode & (stat.S_IWGRP | stat.S_IWOTH):
        return (f"the state folder {d} is writable by others (mode {stat.S_IMODE(mode):o}); "
                f"make it {FOLDER_MODE:o} (chmod {FOLDER_MODE:o} {d}), or use a folder of "
                "its own")
    return None


def _refused(path: Path, err: OSError) -> StateFileRefused:
    what = "a symlink" if err.errno == errno.ELOOP else "not a regular file"
    return StateFileRefused(err.errno or errno.EINVAL, f"{path} is {what}; left alone",
                            str(path))


def _open_new(path_like: Path) -> tuple[int, Path]:
    """A new file next to ``path_like`` with a random name (O_CREAT | O_EXCL: never an
    existing file or link), mode 0600: (descriptor, path)."""
    for _ in range(100):  # a clash of 64 random bits is as good as impossible
        tmp = path_like.with_name(f".{path_like.name}.{secrets.token_hex(8)}.tmp")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o600)
        except FileExistsError:
            continue
        return fd, tmp
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(path_like))


def _is_regular(path: Path) -> bool:
    try:
        return stat.S_ISREG(path.lstat().st_mode)
    except OSError:
        return False

def checkpoint_path(directory: str | Path, sensor_id: str) -> Path:
    return Path(directory) / f"{sensor_id}.json"


def previous_path(directory: str | Path, sensor_id: str) -> Path:
    return Path(directory) / f"{sensor_id}.json.prev"


def lock_path(directory: str | Path, sensor_id: str) -> Path:
    return Path(directory) / f"{sensor_id}.lock"


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------

def save_checkpoint(path: str | Path, state: dict[str, Any], keep_previous: bool = True
                    ) -> None:
    """Write ``state`` as strict JSON atomically: a temporary file in the same directory,
    fsync, the old file kept as ``<name>.prev`` (``keep_previous``), os.replace, fsync of
    the directory. ValueError (nothing written) if the state holds NaN or infinity."""
    p = Path(path)
    text = json.dumps(state, separators=(",", ":"), allow_nan=False)
    p.parent.mkdir(parents=True, exist_ok=True, mode=FOLDER_MODE)
    fd, tmp = _open_new(p)
    try:
        with open(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if keep_previous and _is_regular(p):  # a link there is replaced, never followed
            _replace_with_copy(p, p.with_name(f"{p.name}.prev"))
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(p.parent)


def _replace_with_copy(src: Path, dst: Path) -> None:
    """``dst`` becomes ``src``'s content (a hard link, or a copy where the filesystem has
    none), replaced atomically: a crash leaves the old ``dst`` or the new one. Neither
    ``src`` nor the temporary is opened through a link."""
    # a random name; link() and the copy's O_EXCL fail on any existing name, link or not
    tmp = dst.with_name(f".{dst.name}.{secrets.token_hex(8)}.tmp")
    try:
        os.link(src, tmp, follow_symlinks=False)
    except FileExistsError:
        raise  # not ours: left alone
    except OSError:  # a filesystem without hard links
        _copy_nofollow(src, tmp)  # cleans up after itself; O_EXCL fails on any existing name
    try:
        os.replace(tmp, dst)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _copy_nofollow(src: Path, dst: Path) -> None:
    """Copy a regular file ``src`` to a new file ``dst`` (O_EXCL), through no link."""
    fd_in = os.open(src, os.O_RDONLY | os.O_NONBLOCK | _NOFOLLOW)
    try:
        if not stat.S_ISREG(os.fstat(fd_in).st_mode):
            raise StateFileRefused(errno.EINVAL, f"{src} is not a regular file", str(src))
        fd_out = os.open(dst, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o600)
        try:
            with open(fd_in, "rb", closefd=False) as fin, open(fd_out, "wb") as fout:
                shutil.copyfileobj(fin, fout)
                fout.flush()
                os.fsync(fout.fileno())
        except BaseException:
            with contextlib.suppress(OSError):
                dst.unlink()
            raise
    finally:
        os.close(fd_in)


def _fsync_dir(directory: Path) -> None:
    try:  # make the renames durable
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass  # some filesystems cannot fsync a directory; the data file is synced


def load_checkpoint(path: str | Path) -> dict[str, Any] | None:
    """A checkpoint written by :func:`save_checkpoint`; None if there is no file.

    Raises CheckpointError (a ValueError) for anything else that is not a checkpoint: a
    symlink (never followed), not a regular file, unreadable, larger than MAX_BYTES, nested
    deeper than MAX_DEPTH, not strict JSON (NaN, infinity, integers beyond 2^53), not a
    format-1 object.
    """
    p = Path(path)
    try:  # O_NONBLOCK: a FIFO would block the start
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | _NOFOLLOW)
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise CheckpointError(f"{p}: a symlink, not followed") from None
        raise CheckpointError(f"{p}: cannot read ({exc.strerror or exc})") from None
    try:
        with open(fd, "rb") as f:
            mode = os.fstat(fd).st_mode
            if stat.S_ISDIR(mode):
                raise CheckpointError(f"{p}: a directory, not a checkpoint file")
            if not stat.S_ISREG(mode):
                raise CheckpointError(f"{p}: not a regular file")
            data = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise CheckpointError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if len(data) > MAX_BYTES:
        raise CheckpointError(f"{p}: larger than {MAX_BYTES >> 20} MiB")
    depth = json_depth(data)
    if depth > MAX_DEPTH:
        raise CheckpointError(f"{p}: JSON nested {depth} deep (at most {MAX_DEPTH})")
    try:
        doc = json.loads(data, parse_constant=_no_constant, parse_float=_finite_float,
                         parse_int=_bounded_int)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise CheckpointError(f"{p}: not a strict JSON checkpoint ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{p}: unknown checkpoint format")
    return doc


def json_depth(data: bytes) -> int:
    """How deep the arrays and objects of a JSON text nest (strings skipped), vectorized: the
    parser itself recurses per level, so a deep file must be refused before parsing."""
    bare = np.frombuffer(_STRING.sub(b'""', data), np.uint8)
    step = (np.isin(bare, (ord("["), ord("{"))).astype(np.int64)
            - np.isin(bare, (ord("]"), ord("}"))))
    return int(np.cumsum(step).max(initial=0))


def _no_constant(name: str) -> float:
    raise ValueError(f"{name}: not a finite number")


def _finite_float(text: str) -> float:
    x = float(text)
    if not np.isfinite(x):
        raise ValueError(f"number {text[:20]} out of range")
    return x


def _bounded_int(text: str) -> int:
    if len(text) > 17:  # quick refusal before int() parses a megabyte of digits
        raise ValueError(f"integer {text[:20]}... out of range")
    x = int(text)
    if abs(x) >= MAX_INT:
        raise ValueError(f"integer {x} out of range")
    return x


def finite_document(doc: dict[str, Any]) -> tuple[dict[str, Any], list[str], int]:
    """``doc`` as strict JSON can hold it: (the document, where values were not finite, how
    many). A NaN or infinity (a window mean of a channel the stream lacked) is saved as null,
    which the state restores as NaN, so one such value never costs the whole save; whether
    the state may be trusted is still checked (`restore_pipeline`). The usual document is
    returned as it is after one strict encode; only a failing one is walked (arrays of numbers
    checked in numpy)."""
    try:
        json.dumps(doc, allow_nan=False)
    except ValueError:
        pass
    else:
        return doc, [], 0
    where: list[str] = []
    counted = [0]

    def clean(obj: Any, path: str) -> Any:
        if isinstance(obj, float):
            if np.isfinite(obj):
                return obj
            counted[0] += 1
            where.append(path)
            return None
        if isinstance(obj, dict):
            return {k: clean(v, f"{path}.{k}" if path else str(k)) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            try:
                arr = np.asarray(obj, np.float64)
            except (TypeError, ValueError):  # mixed content: item by item
                return [clean(v, f"{path}[{i}]") for i, v in enumerate(obj)]
            bad = ~np.isfinite(arr)
            if not bad.any():
                return obj
            counted[0] += int(bad.sum())
            where.append(path)
            return np.where(bad, None, arr.astype(object)).tolist()
        return obj

    out = clean(doc, "")
    return out, where, counted[0]


# ---------------------------------------------------------------------------------------------
# The state inside
# ---------------------------------------------------------------------------------------------

def restore_pipeline(state: Any, *, reference: tuple[SensorModel, Prior | None] | None = None,
                     probe: bool = True, now_unix_s: float | None = None) -> Pipeline:
    """A pipeline rebuilt from a checkpoint's ``pipeline`` state, checked (CheckpointError
    saying why if it cannot be trusted). ``reference``: the configured model and prior, whose
    zero-g centres the offsets' bounds (else the checkpoint's own prior does). Any exception
    while rebuilding is caught: a checkpoint never crashes a start."""
    if not isinstance(state, dict):
        raise CheckpointError("no pipeline state")
    try:
        pipe = Pipeline.from_state_dict(state)
    except Exception as exc:  # any shape or type a poisoned file gives
        raise CheckpointError(f"does not restore: {type(exc).__name__}: {exc}") from None
    why = pipeline_problem(pipe, now_unix_s, state, reference)
    if why is None and probe:
        why = _probe_problem(pipe)
    if why is not None:
        raise CheckpointError(why)
    return pipe


def pipeline_problem(pipe: Pipeline, now_unix_s: float | None = None,
                     state: Mapping[str, Any] | None = None,
                     reference: tuple[SensorModel, Prior | None] | None = None) -> str | None:
    """Why this pipeline's state cannot be trusted, or None. Checks what every update and every
    sample depends on: the estimate and prior (shapes, finite, inside the bounds, covariance;
    see `param_bounds`), the detector, and the device times (in ``state``, the pipeline's
    ``state_dict()`` if it is at hand, else made here)."""
    try:
        return (_estimate_problem(pipe, reference) or _detector_problem(pipe)
                or _times_problem(pipe, time.time() if now_unix_s is None else now_unix_s,
                                  state))
    except Exception as exc:  # a field of the wrong type
        return f"unreadable state: {type(exc).__name__}: {exc}"


def param_bounds(pipe: Pipeline, reference: tuple[SensorModel, Prior | None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Where a restored estimate and prior mean must lie: the model's own bounds
    (`SensorModel.bounds`), the offsets' centred on the configured zero-g (``reference``'s
    prior) or else the checkpoint's prior's, as the estimator's gate holds updates around the
    prior's zero-g (`recal.core.estimator.bounds_around`; an unsigned ADC reads ~2048 counts
    at 0 g). The configured zero-g, when known, also bounds the checkpoint's own prior: a
    poisoned prior cannot move its bounds."""
    model = pipe.model
    lo, hi = model.bounds()
    key = ("offset", None)
    if not model.has(*key):
        return lo, hi
    centre: np.ndarray | None = None
    if reference is not None and reference[1] is not None and reference[0].has(*key):
        centre = np.asarray(reference[1].mean)[reference[0].slice(key)]
    elif pipe.prior is not None:
        centre = np.asarray(pipe.prior.mean)[model.slice(key)]
    if centre is not None and centre.shape == (3,) and np.isfinite(centre).all():
        sl = model.slice(key)
        lo[sl] += centre
        hi[sl] += centre
    return lo, hi


def estimate_problem(pipe: Pipeline,
                     reference: tuple[SensorModel, Prior | None] | None = None) -> str | None:
    """Why the pipeline's model, estimate or prior would make its checkpoint refused at the
    next start (`restore_pipeline` with the same ``reference``), or None: the check a node runs
    on what it is about to adopt, so that it never holds a state it could not save."""
    try:
        return _estimate_problem(pipe, reference)
    except Exception as exc:  # a field of the wrong type
        return f"unreadable state: {type(exc).__name__}: {exc}"


def _estimate_problem(pipe: Pipeline, reference: tuple[SensorModel, Prior | None] | None
                      ) -> str | None:
    model = pipe.model
    n = len(model.names)
    if not (np.isfinite(model.s0) and model.s0 > 0):
        return f"model s0 {model.s0!r} is not a positive number"
    lo, hi = param_bounds(pipe, reference)
    parts = []
    if pipe.estimate is not None:
        parts.append(("estimate", pipe.estimate.p, pipe.estimate.cov))
    elif pipe.bootstrapped:
        return "no estimate although bootstrapped"
    if pipe.prior is not None:
        parts.append(("prior", pipe.prior.mean, pipe.prior.info))
    for what, p, m in parts:
        p, m = np.asarray(p), np.asarray(m)
        if p.shape != (n,) or m.shape != (n, n):
            return (f"{what} has {p.shape} parameters and a {m.shape} matrix, the model "
                    f"{n} ({', '.join(model.names)})")
        if not (np.isfinite(p).all() and np.isfinite(m).all()):
            return f"{what} is not finite"
        out = [nm for nm, x, a, b in zip(model.names, p, lo, hi, strict=True)
               if not a <= x <= b]
        if out:
            return f"{what} out of the model's bounds: " + ", ".join(
                f"{nm} = {x:.6g}" for nm, x in zip(model.names, p, strict=True) if nm in out)
        if not np.allclose(m, m.T, rtol=1e-6, atol=0) or not (np.diag(m) > 0).all():
            return f"{what} matrix is not symmetric with a positive diagonal"
    if pipe.estimate is not None:
        e = pipe.estimate
        if np.shape(e.rate) != (3,) or np.shape(e.step) != (3,):
            return "estimate offset rate or step is not 3 values"
    return None


def _detector_problem(pipe: Pipeline) -> str | None:
    if pipe.det_cfg is None:
        return None
    s0 = pipe.det_cfg.s0
    if not (np.isfinite(s0) and s0 > 0):
        return f"detector s0 {s0!r} is not a positive number"
    return None


def _times_problem(pipe: Pipeline, now_unix_s: float, state: Mapping[str, Any] | None
                   ) -> str | None:
    """Device times: the last sample's, not after tomorrow read as Unix time (a device clock
    since boot is far below), and every other time in the state not more than a day after it
    (a window about to be committed lies a little ahead; years ahead stall every update)."""
    last = pipe.last_t_us
    if last is None:
        return None
    if not isinstance(last, (int, np.integer)) or not 0 <= last <= (now_unix_s * 1e6
                                                                   + FUTURE_US):
        return f"last_t_us {last!r} is not a plausible device time"
    for key, t in _times(pipe.state_dict() if state is None else state):
        if not 0 <= t <= last + FUTURE_US:
            return f"{key} = {t} is not between 0 and a day after last_t_us = {last}"
    return None


def _times(obj: Any, path: str = "") -> Iterator[tuple[str, int]]:
    """Every number under a key ending in ``_us`` (device times by the project's naming),
    with where it is (``estimate.t_us``); of a list, its least and greatest."""
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            yield from _times(v, f"{path}.{k}" if path else str(k))
    elif path.endswith("_us"):
        if isinstance(obj, list):
            flat = np.asarray(obj, float).ravel() if obj else np.zeros(0)
            if flat.size:
                yield path, int(flat.min())
                yield path, int(flat.max())
        elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
            yield path, int(obj)
    elif isinstance(obj, list) and obj and isinstance(obj[0], (Mapping, list)):
        for v in obj:
            yield from _times(v, path)


def _probe_problem(pipe: Pipeline) -> str | None:
    """Step a copy of the pipeline with a few samples of 1 g along z right after its last
    sample: a state that fails or gives non-finite output there fails on every batch."""
    try:
        trial = copy.deepcopy(pipe)
        dt_us = max(1, round(1e6 / trial.cfg.rate_hz))
        t0 = (trial.last_t_us if trial.last_t_us is not None else 0) + dt_us
        t_us = t0 + dt_us * np.arange(PROBE_SAMPLES, dtype=np.int64)
        v = np.tile([0.0, 0.0, float(trial.model.s0)], (PROBE_SAMPLES, 1))
        aux = np.zeros((PROBE_SAMPLES, len(trial.aux_names)))
        out = trial.step(RawBatch(t_us, v, aux, trial.aux_names))
    except Exception as exc:
        return f"fails on data: {type(exc).__name__}: {exc}"
    if not trial.model.covariates and not np.isfinite(out.calibrated.a_g).all():
        return "calibrates to non-finite values"
    if not np.isfinite(trial.params).all():
        return "parameters not finite after a step"
    return None


# ---------------------------------------------------------------------------------------------
# Ownership
# ---------------------------------------------------------------------------------------------

@dataclass
class SensorLock:
    """An flock held on ``<dir>/<sensor>.lock`` until :meth:`release` (or the process ends:
    the kernel drops it, so a killed daemon never leaves a sensor locked)."""

    sensor_id: str
    path: Path
    fd: int | None

    def release(self) -> None:
        if self.fd is not None:
            with contextlib.suppress(OSError):
                os.close(self.fd)  # the file stays: unlinking it would let two holders race
            self.fd = None


def lock_sensor(directory: str | Path, sensor_id: str) -> SensorLock:
    """Take the sensor's lock in ``directory`` without waiting; SensorLockedError (with the
    holder's PID) if another process holds it, StateFileRefused (an OSError) for a symlink or
    non-file in its place (left alone), OSError if the folder cannot be used."""
    path = lock_path(directory, sensor_id)
    path.parent.mkdir(parents=True, exist_ok=True, mode=FOLDER_MODE)
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NONBLOCK | _NOFOLLOW, 0o600)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise _refused(path, exc) from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise _refused(path, OSError(errno.EINVAL, "not a regular file"))
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        pid = _read_pid(fd)
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise SensorLockedError(sensor_id, path, pid) from None
        raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return SensorLock(sensor_id, path, fd)


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None


# ---------------------------------------------------------------------------------------------
# When to save
# ---------------------------------------------------------------------------------------------

class CheckpointSchedule:
    """When each sensor's checkpoint is next due: every ``interval_s``, the sensors spread over
    the interval (the k-th added at phase k * 0.618... of it, evenly for any count).

    Why: every sensor's checkpoint written at once holds the GIL long enough to stall the I/O
    loop (figures: docs/performance.md); spread out, each turn is short, shared with the loop.
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
                        raise _refused(bad, OSError(errno.ELOOP, "symlink"))
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
                    _replace_with_copy(prev, cur)
                    _fsync_dir(cur.parent)
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
