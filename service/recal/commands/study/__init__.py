"""`recal hindsight DIR --out OUTDIR`: every recording under a folder calibrated with hindsight,
one row per file in OUTDIR/summary.csv (and .json), resumable, on local processes or a Dask
cluster. A plan (`plan`: what to do, what is done), a runner (`runner`: the same per-file
function, `job.run_job`, on local processes or Dask workers) and a summary writer (`summary`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from recal.commands.study.job import Options
from recal.commands.study.plan import StudyLock, clear_temporaries, make_plan
from recal.commands.study.summary import counts, summary_lines, write_summary
from recal.errors import UsageError

__all__ = ["StudyResult", "run_study"]


@dataclass(frozen=True)
class StudyResult:
    """Every row (skipped, done before, calibrated now), how many were calibrated in this run,
    and the exit code: 0 when no file failed, 1 when some did."""

    rows: list[dict[str, Any]]
    computed: int
    seconds: float

    @property
    def exit_code(self) -> int:
        return 1 if counts(self.rows)["failed"] else 0


def run_study(root: str | Path, out_dir: str | Path, options: Options, *,
              workers: int | None = None, scheduler: str | None = None, verify: bool = False,
              quiet: bool = False) -> StudyResult:
    """Calibrate every recording under root into out_dir (module doc); prints the report."""
    from tqdm import tqdm

    from recal.commands.study import runner

    t0 = time.perf_counter()
    root, out_dir = Path(root), Path(out_dir)
    if not root.is_dir():
        raise UsageError(f"{root} is not a folder")
    if workers is not None and workers < 1:
        raise UsageError(f"--workers must be at least 1, not {workers}")
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out {out_dir} exists and is not a folder")
    with StudyLock(out_dir):
        clear_temporaries(out_dir)
        plan = make_plan(root, out_dir, options, verify)
        rows = plan.skipped + plan.done
        client = runner.connect(scheduler) if scheduler else None
        try:
            if client is not None and plan.todo:
                # the files this process sees (one it cannot see is its job's row: unreadable)
                runner.check_cluster(client, [j.path for j in plan.todo
                                              if Path(j.path).exists()], out_dir)
            with tqdm(total=len(plan.todo), unit="file", desc="hindsight",
                      disable=quiet or None, leave=False) as bar:
                def on_row(row: dict[str, Any]) -> None:
                    rows.append(row)
                    bar.update(1)

                runner.run_jobs(plan.todo, on_row, workers=workers, client=client)
        finally:
            if client is not None:
                client.close()
        _record_deaths(out_dir, rows, plan)
        write_summary(out_dir, rows)
    result = StudyResult(sorted(rows, key=lambda r: r["path"]), len(plan.todo),
                         time.perf_counter() - t0)
    print("\n".join(summary_lines(result.rows, out_dir, result.computed, result.seconds)))
    return result


def _record_deaths(out_dir: Path, rows: list[dict[str, Any]], plan: Any) -> None:
    """A file whose worker died wrote no result: its row is written here (with its key, so the
    next run knows it and tries it again, `plan`)."""
    import json

    from recal.commands.study.job import log_path, result_path, write_atomic
    from recal.commands.study.plan import WORKER_DIED

    jobs = {j.rel: j for j in plan.todo}
    for row in rows:
        if row.get("failure") == WORKER_DIED and row["path"] in jobs:
            job = jobs[row["path"]]
            write_atomic(result_path(out_dir, job.rel),
                         json.dumps({"row": row, "done": job.key}, indent=1))
            write_atomic(log_path(out_dir, job.rel),
                         f"{job.path}\nfailed: {WORKER_DIED}: {row['reason']}\n")
