"""The one root of every error recal reports to a user as one line (`RecalError`).

The command line turns exactly these (and OSError: a file or port the system refused) into
"recal: error: ..." and exit code 2; anything else is a bug and shows its traceback. Each
subclass also derives from the built-in error it used to be, so callers that catch ValueError
keep working.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["CheckpointError", "ConfigError", "DeviceFileError", "InputError", "ModelError",
           "RecalError", "RecordingError", "SensorLockedError", "UsageError"]


class RecalError(Exception):
    """An error the user can act on: bad input, configuration or usage, said in one line."""


class UsageError(RecalError, ValueError):
    """A command line that cannot be carried out (a bad option value, an output that exists)."""


class ConfigError(RecalError, ValueError):
    """A configuration, prior or model file that is not valid."""


class InputError(RecalError, ValueError):
    """Input data that cannot be used (a table without the columns, a file of another format)."""


class RecordingError(RecalError, ValueError):
    """An MCAP recording that cannot be read or written as asked (not a recording, no such
    sensor, damaged beyond repair)."""


class DeviceFileError(RecalError, ValueError):
    """A device file (Axivity .cwa, GENEActiv .bin, ActiGraph .gt3x) that cannot be read: a
    kind recal recognises but cannot read yet, or a damaged or crafted file (the message says
    which kind of file it is and why)."""


class ModelError(RecalError, ValueError):
    """A sensor model that does not fit the data it is given (a channel the stream lacks)."""


class CheckpointError(RecalError, ValueError):
    """A checkpoint file that exists but cannot be trusted (the message says why)."""


class SensorLockedError(RecalError, RuntimeError):
    """Another process calibrates this sensor id from the same state folder."""

    def __init__(self, sensor_id: str, path: Path, pid: int | None) -> None:
        self.sensor_id, self.path, self.pid = sensor_id, path, pid
        holder = f"process {pid}" if pid else "another process"
        super().__init__(f"sensor {sensor_id!r} is already calibrated by {holder} "
                         f"(lock {path}); one process per sensor id and state folder")
