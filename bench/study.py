"""A study's folder through `recal hindsight DIR --out OUTDIR` (`recal.commands.study`).

Goals:
1. a folder of mixed files (Axivity .cwa, GENEActiv .bin, recal's MCAP and CSV; one unreadable,
   one cut short, one too short, one with no still period, two that are not recordings) gives
   one row per file, with a reason where one failed (tests/study_folder.py: EXPECTED);
2. the same rows on local processes and on Dask (a LocalCluster of 2 worker processes on
   127.0.0.1), figures within float tolerance, times aside;
3. a rerun (everything done) at most 20 % of the first run's time;
4. N hour-long device files (default 16 at 100 Hz): 2 workers at most 0.6x the time of 1.

    python bench/study.py                      # the goals as stated
    python bench/study.py --files 8 --hours 0.5 --repeats 1  # shorter

The files are synthetic (tests/device_writers.py: a simulated wearer, a sensor off by tens of
mg), written to a temporary folder first (not timed). Times are wall-clock of the whole
command's work (`run_study`), local workers' start included; the Dask LocalCluster is started
before its run (a cluster is there before a study is sent to it).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import math
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))  # the synthetic device files' writers
from recal.commands.study import StudyResult, run_study  # noqa: E402
from recal.commands.study.job import Options  # noqa: E402
from study_folder import EXPECTED, make_folder, write_device_files  # noqa: E402


def _cpu_s() -> float:
    """CPU seconds of this process and its ended children (the local workers)."""
    me, kids = (resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _run(folder: Path, out: Path, **kw: object) -> tuple[StudyResult, float]:
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        result = run_study(folder, out, Options(), quiet=True, **kw)  # type: ignore[arg-type]
    return result, time.perf_counter() - t0


def _load() -> str:
    return "load average " + " ".join(f"{x:.1f}" for x in os.getloadavg())


def _rows(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv", newline="") as f:
        return {r["path"]: r for r in csv.DictReader(f)}


def _differences(a: dict[str, dict[str, str]], b: dict[str, dict[str, str]]) -> list[str]:
    """Cells that differ beyond float tolerance (times aside)."""
    if set(a) != set(b):
        return [f"files {sorted(set(a) ^ set(b))}"]
    out = []
    for path, row in a.items():
        for col, va in row.items():
            vb = b[path][col]
            if col == "seconds" or va == vb:
                continue
            try:
                if math.isclose(float(va), float(vb), rel_tol=1e-6, abs_tol=1e-9):
                    continue
            except ValueError:
                pass
            out.append(f"{path} {col}: {va} != {vb}")
    return out


def mixed(tmp: Path) -> list[str]:
    folder = make_folder(tmp / "mixed")
    first, t_first = _run(folder, tmp / "out-local", workers=2)
    rows = _rows(tmp / "out-local")
    wrong = [p for p, (status, failure) in EXPECTED.items()
             if p not in rows or (rows[p]["status"], rows[p]["failure"] or None)
             != (status, failure)]
    _, t_rerun = _run(folder, tmp / "out-local", workers=2)
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        _, t_dask = _run(folder, tmp / "out-dask", scheduler=cluster.scheduler_address)
    diff = _differences(rows, _rows(tmp / "out-dask"))
    lines = ["| mixed folder | figure | goal | met |", "|---|---|---|---|",
             f"| rows (ok/failed/skipped) | {len(rows)} "
             f"({sum(r['status'] == 'ok' for r in rows.values())}/"
             f"{sum(r['status'] == 'failed' for r in rows.values())}/"
             f"{sum(r['status'] == 'skipped' for r in rows.values())}), exit {first.exit_code}"
             f" | one per file, reasons as expected | {'yes' if not wrong else wrong} |",
             f"| local 2 processes vs Dask LocalCluster 2 workers | {t_first:.1f} s vs "
             f"{t_dask:.1f} s, {len(diff)} cells differ | same rows | "
             f"{'yes' if not diff else diff[:3]} |",
             f"| rerun / first run | {t_rerun:.2f} s / {t_first:.1f} s = "
             f"{t_rerun / t_first:.2f} | <= 0.20 | {'yes' if t_rerun <= 0.2 * t_first else 'no'} |"]
    for r in rows.values():
        if r["status"] != "skipped":
            lines.append(f"|   {r['path']} | {r['status']} {r['failure']} | GGIR error "
                         f"{r['ggir_error_before_mg'] or '-'} -> {r['ggir_error_after_mg'] or '-'}"
                         f" mg | {r['still_windows'] or '-'} still windows |")
    return lines


def scaling(tmp: Path, files: int, hours: float, rate_hz: int, repeats: int) -> list[str]:
    folder = tmp / "hours"
    t0 = time.perf_counter()
    write_device_files(folder, files, hours, rate_hz=rate_hz)
    print(f"wrote {files} files of {hours} h at {rate_hz} Hz in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    load0 = _load()
    times: dict[int, list[float]] = {1: [], 2: []}
    cpu: dict[int, list[float]] = {1: [], 2: []}
    for rep in range(repeats):  # alternated: the machine's load moves under both alike
        for workers in ((1, 2) if rep % 2 == 0 else (2, 1)):
            c0 = _cpu_s()
            result, t = _run(folder, tmp / f"out-{workers}-{rep}", workers=workers)
            times[workers].append(t)
            cpu[workers].append(_cpu_s() - c0)
            if workers == 1:
                one = result
    load1 = _load()
    t1, t2 = statistics.median(times[1]), statistics.median(times[2])
    c1, c2 = statistics.median(cpu[1]), statistics.median(cpu[2])
    diff = _differences(_rows(tmp / "out-1-0"), _rows(tmp / "out-2-0"))
    ok = all(r["status"] == "ok" for r in one.rows)
    return ["| scaling | figure | goal | met |", "|---|---|---|---|",
            f"| {files} x {hours} h at {rate_hz} Hz (.cwa), 1 worker | {t1:.1f} s, "
            f"{c1:.1f} CPU s (all ok: {ok}) | | |",
            f"| the same, 2 workers | {t2:.1f} s = {t2 / t1:.2f}x, {c2:.1f} CPU s, "
            f"{len(diff)} cells differ | <= 0.6x | {'yes' if t2 <= 0.6 * t1 else 'no'} |",
            f"| machine | {os.cpu_count()} cores; {load0} before, {load1} after; medians of "
            f"{repeats} runs each, alternated | | |"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--files", type=int, default=16)
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--rate", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each worker count")
    ap.add_argument("--skip-scaling", action="store_true")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="recal-study-") as d:
        tmp = Path(d)
        print("\n".join(mixed(tmp)), flush=True)
        if not a.skip_scaling:
            print("\n".join(scaling(tmp, a.files, a.hours, a.rate, a.repeats)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
