"""`recal hindsight DIR --out OUTDIR` on local processes: one row per file with its reason
where it failed, exit codes, a rerun that skips what is done, a run that resumes after a stop,
the lock on OUTDIR, and a worker that dies."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from recal.cli import main
from recal.commands.study.job import Job, Options
from recal.commands.study.runner import run_local
from recal.commands.study.summary import COLUMNS
from study_folder import EXPECTED, counts, make_folder
from study_jobs import dies_on_some


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_folder(tmp_path_factory.mktemp("study") / "in")


def _rows(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv", newline="") as f:
        return {r["path"]: r for r in csv.DictReader(f)}


def _results(out: Path) -> dict[str, int]:
    """Each result JSON under out and its mtime (ns)."""
    return {p.relative_to(out).as_posix(): p.stat().st_mtime_ns
            for p in out.rglob("*.json") if not p.name.startswith("summary")}


def _hindsight(folder: Path, out: Path, *extra: str) -> int:
    return main(["hindsight", str(folder), "--out", str(out), "--workers", "2", "--quiet",
                 *extra])


@pytest.mark.slow
def test_a_mixed_folder_gives_a_row_per_file_and_a_rerun_skips_what_is_done(
        folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert _hindsight(folder, out) == 1  # some failed
    rows = _rows(out)
    assert set(rows) == set(EXPECTED)
    for path, (status, failure) in EXPECTED.items():
        r = rows[path]
        assert (r["status"], r["failure"] or None) == (status, failure), (path, r)
        if status == "ok":
            assert int(r["still_windows"]) > 0 and int(r["samples"]) > 0
            # calibrated within 2 mg on the still windows; where the sensor was off by more
            # (not the .bin: its reader applies the header's factory calibration), better
            before, after = float(r["ggir_error_before_mg"]), float(r["ggir_error_after_mg"])
            assert after < 2.0 and (before < 2.0 or after < before)
            assert float(r["heldout_error_after_mg"]) <= float(r["heldout_error_before_mg"])
            assert int(r["samples_calibrated"]) + int(r["samples_held"]) + int(
                r["samples_suspect"]) == int(r["samples"])
            calibration = json.loads((out / f"{path}.json").read_text())["calibration"]
            assert calibration["windows"] == int(r["fit_windows"])
        elif status == "failed":
            assert r["reason"]
            assert "failed" in (out / f"{path}.log").read_text()
        else:
            assert r["reason"].startswith(("not a recording", "not a regular file"))
            assert not (out / f"{path}.json").exists()
    assert rows["wearer2/day.bin"]["device_type"].startswith("GENEActiv")
    assert rows["wearer2/day.bin"]["serial"]
    assert rows["wearer1/day.cwa"]["device_id"]
    assert rows["wearer1/cut.cwa"]["reader_notes"]  # the partial sector it skipped
    assert int(rows["wearer1/cut.cwa"]["samples"]) < int(rows["wearer1/day.cwa"]["samples"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"] == counts()
    capsys.readouterr()

    before = _results(out)
    assert _hindsight(folder, out) == 1
    assert _results(out) == before  # nothing recomputed, nothing rewritten
    recordings = counts()["ok"] + counts()["failed"]
    assert f"0 run now, {recordings} were done already" in capsys.readouterr().out
    assert _rows(out) == rows

    # a run stopped midway: one result never written, one cut mid-write (a temporary left)
    (out / "wearer1/day.cwa.json").unlink()
    (out / "lab/.sim.csv.json.tmp-999").write_text('{"row": {"path": "lab/sim.c')
    (out / "lab/sim.csv.json").unlink()
    # and a file that changed since
    os.utime(folder / "wearer2/day.bin", ns=(os.stat(folder / "wearer2/day.bin").st_atime_ns,
                                            os.stat(folder / "wearer2/day.bin").st_mtime_ns + 1))
    assert _hindsight(folder, out) == 1
    after = _results(out)
    redone = {k for k in after if after[k] != before.get(k)}
    assert redone == {"wearer1/day.cwa.json", "lab/sim.csv.json", "wearer2/day.bin.json"}
    assert not list(out.rglob(".*.tmp-*"))
    assert _same(_rows(out), rows)


def _same(a: dict[str, dict[str, str]], b: dict[str, dict[str, str]]) -> bool:
    """The same rows, times aside."""
    def strip(rows: dict[str, dict[str, str]]) -> dict[str, dict[str, str]]:
        return {p: {k: v for k, v in r.items() if k != "seconds"} for p, r in rows.items()}
    return strip(a) == strip(b)


@pytest.mark.slow
def test_verify_compares_the_content_too(tmp_path: Path) -> None:
    folder = tmp_path / "in"
    make_one = make_folder(tmp_path / "all")
    folder.mkdir()
    src = make_one / "lab/sim.csv"
    target = folder / "sim.csv"
    target.write_bytes(src.read_bytes())
    out = tmp_path / "out"
    assert _hindsight(folder, out, "--verify") == 0
    first = _results(out)
    # the same size and mtime, other content: only --verify sees it
    st = target.stat()
    text = target.read_bytes()
    target.write_bytes(text.replace(b"\n1", b"\n2", 1))
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert target.stat().st_size == st.st_size
    assert _hindsight(folder, out) == 0
    assert _results(out) == first
    assert _hindsight(folder, out, "--verify") == 0
    assert _results(out)["sim.csv.json"] != first["sim.csv.json"]


@pytest.mark.slow
def test_samples_are_written_beside_the_calibration(folder: Path, tmp_path: Path) -> None:
    one = tmp_path / "in"
    one.mkdir()
    (one / "day.cwa").write_bytes((folder / "wearer1/day.cwa").read_bytes())
    out = tmp_path / "out"
    assert _hindsight(one, out, "--samples", "csv") == 0
    row = _rows(out)["day.cwa"]
    assert row["samples_file"] == "day.cwa.calibrated.csv"
    with open(out / "day.cwa.calibrated.csv") as f:
        assert f.readline().startswith("t_us,x_g,y_g,z_g")
        assert sum(1 for _ in f) == int(row["samples"])


@pytest.mark.slow
def test_a_second_run_on_the_same_outdir_is_refused(
        folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from pathlib import Path; "
         "from recal.commands.study.plan import StudyLock\n"
         f"with StudyLock(Path({str(out)!r})):\n"
         "    print('locked', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        assert _hindsight(folder, out) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("recal: error:") and "in use by another" in err
        assert f"process {holder.pid}" in err and "\n" not in err
        assert not (out / "summary.csv").exists()
    finally:
        holder.communicate("", timeout=30)
    assert holder.returncode == 0


@pytest.mark.slow
@pytest.mark.parametrize("extra", [("--workers", "0"), ("--json", "x.json"),
                                   ("--overwrite",)])
def test_bad_arguments_exit_2(folder: Path, tmp_path: Path, extra: tuple[str, ...],
                              capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hindsight", str(folder), "--out", str(tmp_path / "o"), *extra]) == 2
    assert capsys.readouterr().err.startswith("recal: error:")


@pytest.mark.slow
def test_folder_options_are_refused_for_a_file(folder: Path, tmp_path: Path) -> None:
    assert main(["hindsight", str(folder / "lab/sim.csv"), "--out",
                 str(tmp_path / "o.mcap"), "--workers", "2"]) == 2


@pytest.mark.slow
def test_an_outdir_that_is_a_file_is_refused(folder: Path, tmp_path: Path) -> None:
    (tmp_path / "o").write_text("")
    assert main(["hindsight", str(folder), "--out", str(tmp_path / "o")]) == 2


@pytest.mark.slow
def test_a_worker_that_dies_is_a_row_and_the_others_finish(tmp_path: Path) -> None:
    names = ["a", "b", "die1", "c", "d", "e"]
    jobs = [Job(str(tmp_path / n), n, str(tmp_path), Options(), {}) for n in names]
    rows: list[dict[str, str]] = []
    run_local(jobs, 2, rows.append, dies_on_some)
    by_path = {r["path"]: r for r in rows}
    assert sorted(by_path) == sorted(names) and len(rows) == len(names)
    assert by_path["die1"]["failure"] == "worker died"
    assert all(by_path[n]["status"] == "ok" for n in names if n != "die1")


@pytest.mark.parametrize("column", sorted(COLUMNS))
def test_docs_study_lists_every_summary_column(column: str) -> None:
    doc = (Path(__file__).resolve().parents[1] / "docs" / "study.md").read_text()
    assert f"| `{column}` |" in doc
