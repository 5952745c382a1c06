"""Child processes for the daemon benchmarks: started with output to a file, waited on by a
ready line, measured from /proc (CPU seconds, resident memory), stopped by their own pid."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

__all__ = ["ChildProcess", "cpu_seconds", "rss_mb", "status_mb"]

_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (all its threads), from /proc/<pid>/stat."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICKS_PER_S  # utime, stime


def status_mb(pid: int | str, *keys: str) -> dict[str, float]:
    """Memory fields of /proc/<pid>/status in MB (VmRSS, VmHWM, ...; pid may be "self")."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in keys:
                out[key] = int(value.split()[0]) / 1024.0
    return out


def rss_mb(pid: int) -> float:
    """Resident set size of ``pid`` in MB (VmRSS)."""
    return status_mb(pid, "VmRSS").get("VmRSS", float("nan"))


class ChildProcess:
    """``python -m <module> args`` (or any argv) with stdout+stderr in ``log_path``."""

    def __init__(self, argv: Sequence[str], log_path: Path, *, stdin: bool = False) -> None:
        self.argv = list(argv)
        self.log_path = log_path
        self._log = open(log_path, "w")
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                                     text=True, env=env)

    @classmethod
    def python(cls, module: str, args: Sequence[str], log_path: Path) -> ChildProcess:
        return cls([sys.executable, "-m", module, *args], log_path)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_line(self, prefix: str, timeout_s: float) -> str:
        """The first output line starting with ``prefix``; RuntimeError on exit or timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in self.output().splitlines():
                if line.startswith(prefix):
                    return line
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"{self.argv[:4]} gave no '{prefix}' line:\n{self.output()[-3000:]}")

    def cpu_seconds(self) -> float:
        return cpu_seconds(self.pid)

    def rss_mb(self) -> float:
        return rss_mb(self.pid)

    def terminate(self, timeout_s: float) -> int | None:
        """SIGTERM, wait up to ``timeout_s``, then SIGKILL; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        return self.wait(10.0)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.wait(10.0)

    def wait(self, timeout_s: float) -> int | None:
        try:
            code = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None
        self._log.close()
        return code
