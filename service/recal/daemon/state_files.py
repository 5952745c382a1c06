"""The state folder's files: paths, atomic saves with ``.prev``, strict loads, locks.

The layout and the rules (``O_NOFOLLOW``, 0700, random temporaries, one owner per sensor):
`recal.daemon.checkpoint_store`, which is what the gateway and the remote node use.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import secrets
import shutil
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from recal.errors import CheckpointError, SensorLockedError
from recal.node.checkpoint_doc import parse_document

__all__ = [
    "FOLDER_MODE",
    "MAX_BYTES",
    "STATE_SUFFIXES",
    "SensorLock",
    "StateFileRefused",
    "checkpoint_path",
    "fsync_dir",
    "load_checkpoint",
    "lock_path",
    "lock_sensor",
    "prepare_folder",
    "previous_path",
    "refused",
    "replace_with_copy",
    "save_checkpoint",
    "state_files",
    "unsafe_state_file",
]

# A checkpoint is ~100 kB with the default buffer, ~1 MB with 8x its cells; 8 MiB of numbers
# parse into at most ~150 MB of Python objects.
MAX_BYTES = 8 << 20

# the files of a sensor in the state folder, by suffix after its id (see the module docstring)
STATE_SUFFIXES = (".lock", ".json", ".json.prev", ".json.rejected", ".json.prev.rejected")
FOLDER_MODE = 0o700
_NOFOLLOW = os.O_NOFOLLOW | os.O_CLOEXEC


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


def refused(path: Path, err: OSError) -> StateFileRefused:
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
            replace_with_copy(p, p.with_name(f"{p.name}.prev"))
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(p.parent)


def replace_with_copy(src: Path, dst: Path) -> None:
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


def fsync_dir(directory: Path) -> None:
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
    symlink (never followed), not a regular file, unreadable, larger than MAX_BYTES, or a
    text `recal.node.checkpoint_doc.parse_document` refuses (too deep, not strict JSON, not
    a format-1 object).
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
    return parse_document(data, p)


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
            raise refused(path, exc) from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise refused(path, OSError(errno.EINVAL, "not a regular file"))
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
