"""`recal demo` as a user runs it: a real process, piped output, run twice in one directory.

Each run must start fresh (from the prior, with updates of its own), in a new folder of its
own, write nothing into the current directory but what --out names (or, without --out, a new
temporary folder), keep its checkpoint inside that folder (not a doubled path), and print
plain lines when its output is not a terminal.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from recal.io import recording as rec

SECONDS = "5"


def demo(cwd: Path, *args: str, env: dict[str, str] | None = None) -> tuple[str, Path]:
    """Run `recal demo` to its end; its piped stdout and the run folder it reports."""
    proc = subprocess.run([sys.executable, "-m", "recal", "demo", "--seconds", SECONDS, *args],
                          cwd=cwd, capture_output=True, timeout=120, check=False,
                          env=None if env is None else os.environ | env)
    out = proc.stdout.decode()
    assert proc.returncode == 0, out + proc.stderr.decode()
    files = [ln for ln in out.splitlines() if ln.startswith("files: ")]
    assert len(files) == 1, out
    return out, Path(files[0].removeprefix("files: "))


def check_fresh_run(out: str, run_dir: Path) -> dict[str, Any]:
    """What every run must show: plain lines, a fresh start, its checkpoint where it belongs."""
    assert "\r" not in out and "\x1b" not in out  # no redrawn progress line, no escapes
    assert sum("samples" in ln and "updates" in ln for ln in out.splitlines()) >= 1, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["started_from"] == "prior"
    assert summary["final_state"]["update_count"] > 0
    assert "calibration: started from prior" in out
    mcap = Path(summary["mcap"])
    assert mcap.parent == run_dir
    states = [obj for _, obj, _ in rec.iter_json(mcap, "/demo/calibration")]
    assert states[0]["reason"] == "start" and states[0]["update_count"] == 0
    assert states[-1]["update_count"] == summary["final_state"]["update_count"]
    # the daemon's checkpoint sits in the run's folder, not in <folder>/<folder>/checkpoints
    assert (run_dir / "checkpoints" / "demo.json").is_file()
    nested = [p for p in run_dir.rglob("*") if p.is_dir() and p.name in (run_dir.name,
                                                                           run_dir.parent.name)]
    assert nested == []
    return summary


def test_demo_runs_twice_in_one_out_folder_each_fresh_and_leaves_the_cwd_alone(
        tmp_path: Path) -> None:
    cwd = tmp_path / "checkout"
    cwd.mkdir()
    out1, run1 = demo(cwd, "--out", "runs")
    out2, run2 = demo(cwd, "--out", "runs")
    assert run1 != run2 and run1.parent == run2.parent == (cwd / "runs").resolve()
    s1, s2 = check_fresh_run(out1, run1), check_fresh_run(out2, run2)
    # the same seed: the second run repeats the first, it does not continue it
    assert s2["calibration_states"] > 1 and s1["calibration_states"] > 1
    assert [p.name for p in cwd.iterdir()] == ["runs"]
    assert sorted(p.name for p in (cwd / "runs").iterdir()) == sorted([run1.name, run2.name])


def test_demo_without_out_writes_only_a_new_temporary_folder(tmp_path: Path) -> None:
    cwd, tmp = tmp_path / "checkout", tmp_path / "tmp"
    cwd.mkdir()
    tmp.mkdir()
    out, run_dir = demo(cwd, env={"TMPDIR": str(tmp)})
    check_fresh_run(out, run_dir)
    assert list(cwd.iterdir()) == []
    assert run_dir.parent == tmp.resolve() and run_dir.name.startswith("recal-demo-")


def test_demo_help_says_where_files_go_and_that_runs_start_fresh() -> None:
    proc = subprocess.run([sys.executable, "-m", "recal", "demo", "--help"],
                          capture_output=True, timeout=60, check=True)
    text = " ".join(proc.stdout.decode().split())
    for words in ("--out DIR", "fresh", "temporary folder", "never resumes", "terminal"):
        assert words in text, words
