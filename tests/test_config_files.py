"""A config file that cannot be used, for every command that takes ``--config``: one line
``recal: error: ...`` naming the file, exit status 2, no traceback, nothing started.

Real files of each kind (binary, text in another encoding, a directory, missing, unreadable,
not valid TOML or JSON5) given to ``recal.cli.main``; one case end to end through the installed
command as a user types it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from recal.cli import main

#: every command with a --config, and the rest of a command line it would otherwise accept
COMMANDS = {
    "run": ["run", "--port", "/dev/null-nothing-here"],
    "node": ["node", "--sensor-id", "wrist"],
    "replay": ["replay", "in.mcap", "--out", "out.mcap"],
    "router": ["router", "--listen", "tcp/127.0.0.1:0"],
}

KINDS = ("binary", "not_utf8", "directory", "missing", "unreadable", "invalid")


def _bad_config(tmp: Path, kind: str, command: str) -> Path:
    """A config path of the given kind of unusable."""
    if kind == "binary":  # what `--config /bin/ls` gives: an ELF header, bytes not UTF-8
        p = tmp / "ls"
        p.write_bytes(b"\x7fELF\x02\x01\x01\x00" + bytes(range(128, 256)) * 4)
    elif kind == "not_utf8":  # text saved in Latin-1
        p = tmp / "latin1.toml"
        p.write_bytes("[mcap]\npath = 'café.mcap'\n".encode("latin-1"))
    elif kind == "directory":
        p = tmp / "configs"
        p.mkdir()
    elif kind == "missing":
        p = tmp / "no-such.toml"
    elif kind == "unreadable":
        p = tmp / "secret.toml"
        p.write_text("[mcap]\n")
        p.chmod(0)
        if os.access(p, os.R_OK):  # root reads anything: a file whose read fails (EIO) instead
            p = Path("/proc/self/mem")
    else:  # valid UTF-8, not valid in the config's language
        p = tmp / ("broken.json5" if command == "router" else "broken.toml")
        p.write_text("{ listen: [\n" if command == "router" else "[mcap\npath = 1\n")
    return p


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_unusable_config_is_one_error_line_and_exit_2(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        command: str, kind: str) -> None:
    monkeypatch.chdir(tmp_path)
    path = _bad_config(tmp_path, kind, command)
    try:
        rc = main([*COMMANDS[command], "--config", str(path)])
    finally:
        if path.is_relative_to(tmp_path) and path.exists():
            path.chmod(0o700)
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert rc == 2, (rc, out, err)
    assert len(lines) == 1 and lines[0].startswith("recal: error: "), err
    assert path.name in lines[0], lines[0]
    assert "Traceback" not in err and out == ""


def test_recal_run_config_bin_ls_end_to_end(tmp_path: Path) -> None:
    """The command as typed: an executable given as the config."""
    proc = subprocess.run([sys.executable, "-m", "recal", "run", "--config", sys.executable],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2, proc
    assert proc.stderr.splitlines() == [proc.stderr.strip()], proc.stderr
    assert proc.stderr.startswith("recal: error: ") and "UTF-8" in proc.stderr, proc.stderr
