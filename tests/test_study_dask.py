"""A study on Dask: a LocalCluster of two worker processes, and real `dask scheduler` and
`dask worker` processes on 127.0.0.1 driven by `recal hindsight DIR --scheduler` as a
subprocess, give the same rows as local processes."""

from __future__ import annotations

import csv
import math
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from distributed import Client, LocalCluster

from polling import wait_for
from recal.cli import main
from recal.commands.study import run_study
from recal.commands.study.job import Options
from recal.errors import UsageError
from study_folder import EXPECTED, counts, make_folder
from study_jobs import dies_on_some

pytestmark = pytest.mark.slow

DASK = Path(sys.executable).with_name("dask")


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_folder(tmp_path_factory.mktemp("study") / "in")


@pytest.fixture(scope="module")
def local_rows(folder: Path, tmp_path_factory: pytest.TempPathFactory
               ) -> dict[str, dict[str, str]]:
    out = tmp_path_factory.mktemp("local") / "out"
    assert main(["hindsight", str(folder), "--out", str(out), "--workers", "2", "--quiet"]) == 1
    return _rows(out)


def _rows(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv", newline="") as f:
        return {r["path"]: r for r in csv.DictReader(f)}


def _assert_same_rows(a: dict[str, dict[str, str]], b: dict[str, dict[str, str]]) -> None:
    """The same rows, figures within float tolerance, times aside."""
    assert set(a) == set(b) == set(EXPECTED)
    for path in a:
        for col, va in a[path].items():
            vb = b[path][col]
            if col == "seconds" or va == vb:
                continue
            assert math.isclose(float(va), float(vb), rel_tol=1e-6, abs_tol=1e-9), \
                (path, col, va, vb)


def test_a_local_cluster_gives_the_same_rows(folder: Path, tmp_path: Path,
                                             local_rows: dict[str, dict[str, str]]) -> None:
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        result = run_study(folder, tmp_path / "out", Options(),
                           scheduler=cluster.scheduler_address, quiet=True)
    assert result.exit_code == 1
    _assert_same_rows(_rows(tmp_path / "out"), local_rows)


def test_a_cluster_whose_workers_cannot_see_the_files_is_refused(tmp_path: Path) -> None:
    """Each worker reports what it cannot see (here a path that exists nowhere stands for one
    on a disk only this machine mounts) and the run stops before any job, saying so."""
    from recal.commands.study.runner import check_cluster

    here = tmp_path / "day.cwa"
    here.write_bytes(b"")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, \
            Client(cluster.scheduler_address) as client:
        assert check_cluster(client, [str(here)], tmp_path) == 1
        with pytest.raises(UsageError, match=r"cannot see 1 input files \(first: /nowhere/"):
            check_cluster(client, [str(here), "/nowhere/x.cwa"], tmp_path)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[str]:
    """A real `dask scheduler` and one `dask worker` (two processes) on 127.0.0.1; killed in
    teardown."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = [open(tmp_path / f"{n}.log", "w") for n in ("scheduler", "worker")]
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port",
                               str(port), "--no-dashboard"], stdout=logs[0],
                              stderr=subprocess.STDOUT)]
    try:
        procs.append(subprocess.Popen(
            [str(DASK), "worker", address, "--host", "127.0.0.1", "--nworkers", "2",
             "--nthreads", "1", "--no-dashboard"], stdout=logs[1], stderr=subprocess.STDOUT))
        with Client(address, timeout=60) as client:
            assert wait_for(lambda: len(client.scheduler_info()["workers"]) == 2, 90, 0.5), \
                (tmp_path / "worker.log").read_text()
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)
        for f in logs:
            f.close()


def test_real_dask_processes_give_the_same_rows(folder: Path, tmp_path: Path, dask_cluster: str,
                                                local_rows: dict[str, dict[str, str]]) -> None:
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "recal", "hindsight", str(folder), "--out",
                           str(out), "--scheduler", dask_cluster, "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stderr
    c = counts()
    assert f"{c['ok']} calibrated, {c['failed']} failed, {c['skipped']} skipped" in done.stdout
    _assert_same_rows(_rows(out), local_rows)


def test_an_unreachable_scheduler_is_one_line(folder: Path, tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "recal", "hindsight", str(folder), "--out",
                           str(tmp_path / "out"), "--scheduler",
                           f"tcp://127.0.0.1:{_free_port()}", "--quiet"],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "2s"})
    assert done.returncode == 2
    assert done.stderr.strip().startswith("recal: error: cannot reach the Dask scheduler")
    assert len(done.stderr.strip().splitlines()) == 1


def test_a_dask_worker_that_dies_is_a_row_and_the_others_finish(tmp_path: Path) -> None:
    import dask

    from recal.commands.study.job import Job
    from recal.commands.study.runner import run_dask

    names = ["a", "b", "die1", "c", "d", "e", "f", "g"]
    jobs = [Job(str(tmp_path / n), n, str(tmp_path), Options(), {}) for n in names]
    rows: list[dict[str, str]] = []
    # the scheduler gives up on a task after it killed two workers (default: four); a worker
    # is given one task per thread (saturation 1.0), so no other task dies with it
    with dask.config.set({"distributed.scheduler.allowed-failures": 1,
                          "distributed.scheduler.worker-saturation": 1.0}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address=None) as cluster, \
            Client(cluster.scheduler_address) as client:
        run_dask(client, jobs, rows.append, dies_on_some)
    by_path = {r["path"]: r for r in rows}
    assert sorted(by_path) == sorted(names) and len(rows) == len(names)
    assert by_path["die1"]["failure"] == "worker died"
    assert "KilledWorker" in by_path["die1"]["reason"]
    assert all(by_path[n]["status"] == "ok" for n in names if n != "die1"), rows
