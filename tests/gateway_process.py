"""The gateway daemon as a child process (`python -m recal run`), for the tests that kill it."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

from polling import wait_for
from recal.daemon.gateway import READY_PREFIX


def write_config(tmp: Path, link: str, zenoh: str, flush_s: float, sensor_id: str = "s1",
                 rate_hz: float = 100.0, aux_names: Sequence[str] | None = (),
                 after_update_s: float | None = None) -> Path:
    """``tmp/gateway.toml`` for one sensor on ``link``: the ``zenoh`` table as given, MCAP
    flushed every ``flush_s``, checkpoints every 0.25 s in ``tmp/ck`` (and ``after_update_s``
    after an update, if given), a 1024 counts/g prior; ``aux_names`` None: the channels are
    whatever the device's header says."""
    path = tmp / "gateway.toml"
    after = "" if after_update_s is None else f"after_update_s = {after_update_s}\n"
    names = "" if aux_names is None else f"aux_names = {json.dumps(list(aux_names))}\n"
    path.write_text(f"""{zenoh}
[mcap]
flush_interval_s = {flush_s}

[checkpoint]
dir = "{tmp / 'ck'}"
interval_s = 0.25
{after}
[[sensors]]
id = "{sensor_id}"
port = "{link}"
{names}rate_hz = {rate_hz}
prior = {{ counts_per_g = 1024.0, zero_g = 0 }}
""")
    return path


class GatewayProcess:
    """`python -m recal run` as a child process; its output is read by a thread."""

    def __init__(self, config: Path, mcap: Path, args: Sequence[str] = (),
                 wait_ready: bool = True) -> None:
        """Start it; unless ``wait_ready`` is False, wait for its ready line (AssertionError
        with its output if it exits or does not get ready in 30 s)."""
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "recal", "run", "--config", str(config), "--mcap", str(mcap),
             *args],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        if not wait_ready:
            return
        ready = wait_for(lambda: self.ready_line is not None or self.proc.poll() is not None,
                         30, 0.02)
        if not ready or self.ready_line is None or self.proc.poll() is not None:
            self.kill()
            raise AssertionError(f"gateway did not start: {self.lines}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if len(self.lines) < 1000:
                self.lines.append(line.rstrip("\n"))

    @property
    def ready_line(self) -> str | None:
        return next((ln for ln in self.lines if ln.startswith(READY_PREFIX)), None)

    @property
    def ready(self) -> bool:
        return self.ready_line is not None

    @property
    def mcap(self) -> Path:
        """The file it writes (a time-stamped sibling when --mcap already exists)."""
        assert self.ready_line is not None
        match = re.search(r"mcap=(\S+)", self.ready_line)
        assert match is not None
        return Path(match.group(1))

    def has_open(self, device_path: str) -> bool:
        """Whether the process holds ``device_path`` open (Linux: /proc/<pid>/fd)."""
        fd_dir = f"/proc/{self.proc.pid}/fd"
        try:
            names = os.listdir(fd_dir)
        except OSError:
            return False
        for name in names:
            try:
                if os.readlink(f"{fd_dir}/{name}") == device_path:
                    return True
            except OSError:
                continue  # closed meanwhile
        return False

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

