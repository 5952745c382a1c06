"""Who owns a serial port: two `python -m recal run` processes started at the same instant on
one real pseudo-terminal; exactly one keeps it, the other exits at once with one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from polling import wait_for
from recal.gateway import READY_PREFIX
from recal.io.pty_device import PtyDevice

TRIES = 8
START_S = 30.0


def _config(tmp: Path, name: str) -> Path:
    """Zenoh off; a state folder of its own (the sensor locks must not decide)."""
    path = tmp / f"{name}.toml"
    path.write_text(f"""[zenoh]
enabled = false

[checkpoint]
dir = "{tmp / ('ck-' + name)}"
""")
    return path


class _Run:
    """`python -m recal run` with its output collected by a thread."""

    def __init__(self, tmp: Path, name: str, link: str) -> None:
        self.lines: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "recal", "run", "--config", str(_config(tmp, name)),
             "--mcap", str(tmp / f"{name}.mcap"), "--port", link, "--sensor-id", name,
             "--counts-per-g", "1024", "--zero-g", "0", "--rate", "100"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if len(self.lines) < 1000:
                self.lines.append(line.rstrip("\n"))

    @property
    def ready(self) -> bool:
        return any(ln.startswith(READY_PREFIX) for ln in list(self.lines))

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def _settled(runs: list[_Run]) -> bool:
    """One has exited and the other is ready."""
    return sum(r.proc.poll() is not None for r in runs) == 1 and any(r.ready for r in runs)


def test_two_daemons_started_at_once_on_one_port_leave_exactly_one(tmp_path: Path) -> None:
    link = str(tmp_path / "tty0")
    with PtyDevice(link, header=True):
        for attempt in range(TRIES):
            tmp = tmp_path / f"try{attempt}"
            tmp.mkdir()
            runs = [_Run(tmp, "a", link), _Run(tmp, "b", link)]
            try:
                assert wait_for(lambda runs=runs: _settled(runs), START_S, 0.05), \
                    [r.lines for r in runs]
                loser = next(r for r in runs if r.proc.poll() is not None)
                winner = next(r for r in runs if r is not loser)
                assert loser.proc.returncode != 0
                errors = [ln for ln in loser.lines if ln.startswith("recal: error:")]
                assert len(errors) == 1, loser.lines
                assert f"port {link} is in use by process {winner.proc.pid}" in errors[0]
                assert not any("Traceback" in ln for ln in loser.lines), loser.lines
                assert not loser.ready, loser.lines
                # the winner keeps running: no second exit while it is asked to stop
                assert winner.proc.poll() is None
                winner.proc.send_signal(signal.SIGTERM)
                assert winner.proc.wait(30) == 0, winner.lines
            finally:
                for r in runs:
                    r.kill()
