"""Run a study's jobs: local worker processes (`run_local`, concurrent.futures) or the workers of
an existing Dask cluster (`run_dask`, dask.distributed's Client). The same function per file
(`job.run_job`) either way, so the rows are the same; recal schedules nothing of its own.

A worker that dies (killed, out of memory, a crash in a library) is a row of its own, never a
stop: locally, the files that were running when a process died are run once more, each alone
in a fresh process, and a file that kills that one too gets the row ``worker died``; on Dask,
the scheduler tries a task on another worker up to its ``allowed-failures`` and then gives up
on it (KilledWorker): that row.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from recal.commands.study.job import Job, run_job
from recal.commands.study.plan import WORKER_DIED
from recal.errors import UsageError

__all__ = ["THREAD_VARS", "check_cluster", "default_workers", "run_dask", "run_local"]

#: each numeric library's thread count, pinned to 1 in the workers: N files on N cores, not
#: N files each starting a thread per core
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
#: a worker's memory: the interpreter and recal, plus a device file's samples as its reader
#: decodes them (t, x, y, z, aux as float64: about 16x a packed .cwa file's size)
BASE_BYTES = 300 * 2**20
BYTES_PER_FILE_BYTE = 16

Row = dict[str, Any]
JobFn = Callable[[Job], Row]


def _available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def default_workers(jobs: list[Job]) -> int:
    """As many workers as cores (this process's CPU affinity), fewer where the available memory
    cannot hold that many of the largest file being calibrated at once (`BYTES_PER_FILE_BYTE`),
    never more than the files."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    n = max(1, cores or 1)
    available = _available_bytes()
    if available is not None and jobs:
        largest = max(_size(j.path) for j in jobs)
        n = min(n, max(1, available // (BASE_BYTES + BYTES_PER_FILE_BYTE * largest)))
    return max(1, min(n, len(jobs)))


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


@contextmanager
def _one_thread_each() -> Any:
    """THREAD_VARS set to 1 while worker processes start (they inherit the environment)."""
    before = {k: os.environ.get(k) for k in THREAD_VARS}
    os.environ.update({k: "1" for k in THREAD_VARS})
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _died(job: Job, said: str) -> Row:
    return {"path": job.rel, "status": "failed", "failure": WORKER_DIED,
            "reason": f"the worker process calibrating it ended: {said}"}


_started: Any = None  # in a worker: the queue it tells the jobs it starts on


def _worker_init(queue: Any) -> None:
    global _started
    _started = queue


def _call(fn: JobFn, job: Job) -> Row:
    """In a worker: say the job started (the parent learns which jobs a dead worker had),
    then run it."""
    _started.put(job.rel)
    return fn(job)


def run_local(jobs: list[Job], workers: int, on_row: Callable[[Row], None],
              fn: JobFn = run_job) -> None:
    """Run every job in ``workers`` local processes; ``on_row`` gets each row as it ends.
    When a process dies, the jobs that had not started run on in a fresh pool; those that had
    (the one that killed it among them) each once more alone, and a second death is that
    file's row: rounds end, since each death sets at least one job aside."""
    with _one_thread_each():
        while jobs:
            not_started, suspects = _run_pool(jobs, workers, on_row, fn)
            for job in suspects:
                if any(_run_pool([job], 1, on_row, fn)):
                    on_row(_died(job, "twice, the second time running this file alone"))
            jobs = not_started


def _run_pool(jobs: list[Job], workers: int, on_row: Callable[[Row], None],
              fn: JobFn) -> tuple[list[Job], list[Job]]:
    """The jobs' rows through on_row; of the jobs whose pool broke (not yet rows), those that
    had not started and those that had."""
    import multiprocessing

    # spawn: each worker a fresh interpreter that reads THREAD_VARS when numpy loads (a fork
    # would inherit this process's numeric libraries as already started)
    ctx = multiprocessing.get_context("spawn")
    started = ctx.SimpleQueue()
    broken: list[Job] = []
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init,
                             initargs=(started,)) as pool:
        pending: dict[Future[Row], Job] = {pool.submit(_call, fn, j): j for j in jobs}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                job = pending.pop(fut)
                try:
                    on_row(fut.result())
                except BrokenProcessPool:
                    broken.append(job)
    began = set()
    while broken and not started.empty():
        began.add(started.get())
    started.close()
    return ([j for j in broken if j.rel not in began], [j for j in broken if j.rel in began])


# --- Dask ------------------------------------------------------------------------------------
def _worker_facts(paths: list[str], out_dir: str) -> dict[str, Any]:
    """Run on each Dask worker: its recal version, which of the paths it cannot see, whether
    it can write under OUTDIR."""
    from recal import __version__

    return {"recal": __version__, "missing": [p for p in paths if not os.path.exists(p)],
            "out_writable": os.access(out_dir, os.W_OK)}


def check_cluster(client: Any, paths: list[str], out_dir: Path) -> int:
    """Every worker runs this recal and sees the paths (the inputs this process sees) and
    OUTDIR (a shared file system); else a UsageError that says which worker lacks what. The
    number of workers."""
    from recal import __version__

    facts = client.run(_worker_facts, sorted(paths)[:1000], str(out_dir.resolve()))
    if not facts:
        raise UsageError("the Dask cluster has no worker")
    problems = []
    for worker, f in sorted(facts.items()):
        if f["recal"] != __version__:
            problems.append(f"{worker} runs recal {f['recal']}, this is {__version__}")
        if f["missing"]:
            problems.append(f"{worker} cannot see {len(f['missing'])} input files "
                            f"(first: {f['missing'][0]})")
        if not f["out_writable"]:
            problems.append(f"{worker} cannot write to {out_dir}")
    if problems:
        raise UsageError("the Dask workers cannot run this study: " + "; ".join(problems))
    return len(facts)


def connect(address: str) -> Any:
    """A dask.distributed Client to the scheduler at address (recal[cluster] installed),
    waiting for it as long as Dask's ``distributed.comm.timeouts.connect`` says."""
    try:
        from distributed import Client
    except ImportError:
        raise UsageError("--scheduler needs dask.distributed: pip install 'recal[cluster]'"
                         ) from None
    try:
        return Client(address, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise UsageError(f"cannot reach the Dask scheduler at {address}: "
                         f"{' '.join(str(exc).split())}") from None


def run_dask(client: Any, jobs: list[Job], on_row: Callable[[Row], None],
             fn: JobFn = run_job) -> None:
    """Run every job on the client's cluster; ``on_row`` gets each row as it ends."""
    from distributed import as_completed

    # keys of one task group (the function's name and a unique token): the scheduler queues
    # them and hands a worker one per thread, so a worker's death takes no waiting file with it
    futures = {client.submit(fn, j, pure=False): j for j in jobs}
    for fut in as_completed(list(futures), loop=client.loop):
        job = futures[fut]
        try:
            on_row(fut.result())
        except Exception as exc:  # KilledWorker (died on it too often), a lost connection
            on_row(_died(job, f"{type(exc).__name__}: {' '.join(str(exc).split())}"))
        fut.release()


def run_jobs(jobs: Iterable[Job], on_row: Callable[[Row], None], *, workers: int | None,
             client: Any | None) -> None:
    """Dask when a client is given, else local processes."""
    jobs = list(jobs)
    if client is not None:
        run_dask(client, jobs, on_row)
    else:
        run_local(jobs, workers or default_workers(jobs), on_row)
