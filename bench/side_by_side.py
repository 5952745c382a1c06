"""Old vs new speed in the same run: the acceptance that a restructuring made nothing slower.

    python bench/side_by_side.py                     # old /work/wt/base, new: this checkout
    python bench/side_by_side.py --repeats 5 --old A --new B
    python bench/side_by_side.py --quick             # smaller inputs, to try the tool

Why: a machine shared with other work drifts by more than the changes measured, so old and new
take turns (A B A B ..., --repeats times) on the same input files, each timing in a fresh
subprocess of the same interpreter with ``PYTHONPATH=<tree>/service``; see docs/performance.md.
Timed:
  core        `Pipeline.step` over a 24 h 50 Hz simulation in 100 000-sample batches, readings
              in g, datasheet prior (the recal core row of bench/compare_tools.py, same case)
  replay      `recal replay` end to end of a 2 h 100 Hz simulation logged in messages of 100
              samples (bench/replay_throughput.py's recording): replay's own time (its --json
              "seconds") and the command's wall time (interpreter start and imports included)
  windowing   `recal.core.window_means` over the 24 h 50 Hz recording (1000-sample
              messages, as `recal simulate` logs them)
  hindsight   `recal hindsight` of that recording (wall time of the command)
  discover    `recal discover` of that recording (wall time of the command)
Reported per tree: median and min of the wall time over the repeats, the median CPU time
(user + system of the timed process, all threads: less inflated by other work than the wall
time), and new/old of each; a markdown table
ready for docs/performance.md with the date, both commits, the machine and the command line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve()
NEW_DEFAULT = HERE.parents[1]
OLD_DEFAULT = Path("/work/wt/base")
CASES = ("core", "replay", "windowing", "hindsight", "discover")


@dataclass(frozen=True)
class Tree:
    label: str
    root: Path

    def env(self) -> dict[str, str]:
        return {**os.environ, "PYTHONPATH": str(self.root / "service")}

    def run(self, argv: list[str], cwd: Path, timeout_s: float = 3600
            ) -> tuple[float, float, str]:
        """(wall seconds, CPU seconds of the process and its threads, stdout) of
        ``python <argv>``; fails loudly on a non-zero exit."""
        cpu0 = _children_cpu()
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, *argv], cwd=cwd, env=self.env(), text=True,
                           capture_output=True, timeout=timeout_s, check=False)
        wall = time.perf_counter() - t0
        cpu = _children_cpu() - cpu0
        if r.returncode:
            raise SystemExit(f"{self.label} ({self.root}): {' '.join(argv[:4])} failed, exit "
                             f"{r.returncode}:\n{r.stderr[-2000:]}")
        return wall, cpu, r.stdout

    def child(self, name: str, args: dict[str, Any], cwd: Path) -> dict[str, Any]:
        out = self.run([str(HERE), "--child", name, json.dumps(args)], cwd)[2]
        return json.loads(out.strip().splitlines()[-1])

    def commit(self) -> str:
        r = subprocess.run(["git", "-C", str(self.root), "rev-parse", "HEAD"],
                           capture_output=True, text=True, check=False)
        dirty = subprocess.run(["git", "-C", str(self.root), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               check=False).stdout.strip()
        return (r.stdout.strip()[:12] or "?") + (" (uncommitted changes)" if dirty else "")


def _children_cpu() -> float:
    """User + system CPU seconds of this process's finished children (subprocesses run one
    at a time here, so a difference is one child's)."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


# --- children: run inside one tree ---------------------------------------------------------------
def _bench_module(bench: str, name: str) -> Any:
    """A module of the new tree's bench/, or None if it will not import with its recal."""
    sys.path.insert(0, bench)
    try:
        return __import__(name)
    except ImportError:
        return None
    finally:
        sys.path.pop(0)


def child_make_inputs(a: dict[str, Any]) -> dict[str, Any]:
    """The shared inputs (run once, with the new tree): arrays of the core case, the replay
    recording, and the 24 h recording's raw samples as arrays for the windowing."""
    from recal.sim import wearer as sim
    out = Path(a["dir"])
    ct = _bench_module(a["bench"], "compare_tools")
    if ct is not None:  # its speed case exactly: "plain", in g
        res = ct.simulate_case(ct.CASES[0], float(a["core_hours"]))
        counts, case_from = ct.COUNTS_PER_G, "bench/compare_tools.py simulate_case('plain')"
    else:  # the same settings by hand
        from dataclasses import replace
        spec = sim.SensorSpec.random(np.random.default_rng(1), offset_mg=50.0, gain_pct=3.0)
        spec = replace(spec, counts_per_g=1024.0)
        res = sim.simulate(float(a["core_hours"]), 50.0, 1, spec,
                           start_us=1_704_067_200_000_000)
        counts, case_from = 1024.0, "recal.sim.wearer, compare_tools' settings"
    raw = res.raw
    np.savez(out / "core.npz", t_us=raw.t_us, v=raw.v / counts, aux=raw.aux,
             aux_names=np.array(raw.aux_names, dtype=str))
    rt = _bench_module(a["bench"], "replay_throughput")
    spec = sim.SensorSpec.random(np.random.default_rng(3), offset_mg=40.0, gain_pct=3.0)
    rraw = sim.simulate(float(a["replay_hours"]), 100.0, 3, spec).raw
    if rt is not None:
        rt.write_recording(out / "replay.mcap", rraw, 100)
        replay_from = "bench/replay_throughput.py write_recording"
    else:
        writer = _find("RecordingWriter", "recal.io.recording_writer", "recal.io.recording")
        with writer(out / "replay.mcap", overwrite=True) as w:
            for i in range(0, len(rraw), 100):
                b = rraw[i:i + 100]
                w.write_raw("s1", b, 1_700_000_000_000_000_000 + int(b.t_us[0]) * 1000)
        replay_from = f"{writer.__module__}.RecordingWriter"
    wraw = _read_raw(out / "day.mcap")
    np.savez(out / "day.npz", t_us=wraw.t_us, v=wraw.v, aux=wraw.aux,
             aux_names=np.array(wraw.aux_names, dtype=str))
    return {"core_samples": len(raw), "core_from": case_from, "replay_samples": len(rraw),
            "replay_from": replay_from, "day_samples": len(wraw)}


def _find(name: str, *modules: str) -> Any:
    """``name`` from the first of ``modules`` that has it (io/ may be split differently)."""
    import importlib
    for m in modules:
        try:
            return getattr(importlib.import_module(m), name)
        except (ImportError, AttributeError):
            continue
    raise ImportError(f"{name} in none of {modules}")


def _read_raw(path: Path) -> Any:
    """Every raw sample of a one-sensor recording, with the tree's reader wherever it is."""
    from recal.samples import RawBatch
    iter_raw = _find("iter_raw", "recal.io.recording_reader", "recal.io.reader",
                     "recal.io.recording")
    return RawBatch.concat([b for _, b, _ in iter_raw(path)])


def _load(path: str) -> Any:
    from recal.samples import RawBatch
    z = np.load(path)
    return RawBatch(z["t_us"], z["v"], z["aux"], tuple(str(s) for s in z["aux_names"]))


def _core_names() -> tuple[Any, Any, Any, Any]:
    try:
        from recal.core import Pipeline, PipelineConfig, Prior, SensorModel
    except ImportError:
        from recal.core.estimator import Prior
        from recal.core.model import SensorModel
        from recal.core.pipeline import Pipeline, PipelineConfig
    return Pipeline, PipelineConfig, Prior, SensorModel


def child_core(a: dict[str, Any]) -> dict[str, Any]:
    """compare_tools' run_recal: the pipeline built and stepped, the stepping timed."""
    Pipeline, PipelineConfig, Prior, SensorModel = _core_names()
    raw = _load(a["npz"])
    size = int(a["batch"])
    batches = [raw[i:i + size] for i in range(0, len(raw), size)]
    model = SensorModel.diagonal(1.0)
    t0, c0 = time.perf_counter(), time.process_time()
    pipe = Pipeline(PipelineConfig(rate_hz=50.0), model, Prior.default(model), raw.aux_names)
    out = np.concatenate([pipe.step(b).calibrated.a_g for b in batches])
    return {"seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0,
            "samples": len(out)}


def child_windowing(a: dict[str, Any]) -> dict[str, Any]:
    from recal.core import window_means
    _, PipelineConfig, _, _ = _core_names()
    raw = _load(a["npz"])
    batches = [raw[i:i + 1000] for i in range(0, len(raw), 1000)]
    t0, c0 = time.perf_counter(), time.process_time()
    w = window_means(iter(batches), PipelineConfig(rate_hz=50.0), 1024.0)[0]
    return {"seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0,
            "windows": len(w.t_us)}


CHILDREN: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    "make_inputs": child_make_inputs, "core": child_core, "windowing": child_windowing}


# --- timing --------------------------------------------------------------------------------------
@dataclass
class Timing:
    case: str
    what: str
    seconds: dict[str, list[float]] = field(default_factory=lambda: {"old": [], "new": []})
    cpu: dict[str, list[float]] = field(default_factory=lambda: {"old": [], "new": []})


def time_case(case: str, tree: Tree, inputs: Path, work: Path, batch: int
               ) -> dict[str, tuple[float, float | None]]:
    """{what: (wall s, CPU s or None)} of one run of ``case`` with ``tree``, in a fresh
    subprocess."""
    if case in ("core", "windowing"):
        what = ("Pipeline.step, 100 000-sample batches (in-process)" if case == "core"
                else "window_means (in-process)")
        args = ({"npz": str(inputs / "core.npz"), "batch": batch} if case == "core"
                else {"npz": str(inputs / "day.npz")})
        got = tree.child(case, args, work)
        return {what: (got["seconds"], got["cpu"])}
    if case == "replay":
        wall, cpu, _ = tree.run(["-m", "recal", "replay", str(inputs / "replay.mcap"), "--out",
                                 "replay-out.mcap", "--quiet", "--overwrite", "--json",
                                 "replay.json"], work)
        own = json.loads((work / "replay.json").read_text())["seconds"]
        return {"replay() (its --json seconds)": (own, None),
                "recal replay command": (wall, cpu)}
    out = ["--out", "hindsight-out.mcap", "--quiet", "--overwrite"] if case == "hindsight" else [
        "--json", "discover.json"]
    wall, cpu, _ = tree.run(["-m", "recal", case, str(inputs / "day.mcap"), *out], work)
    return {f"recal {case} command": (wall, cpu)}


def load_avg() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def markdown(timings: list[Timing], head: dict[str, str], sizes: dict[str, Any]) -> str:
    lines = [f"Old vs new, {head['date']}: {head['command']}", "",
             f"- old: {head['old']}", f"- new: {head['new']}",
             f"- machine: {head['machine']}; load average (1, 5, 15 min) before "
             f"{head['load_before']}, after {head['load_after']}",
             f"- inputs: core {sizes['core']}; replay {sizes['replay']}; windowing, hindsight, "
             f"discover {sizes['day']}",
             f"- {head['repeats']} repeats, old and new taking turns; wall seconds, and CPU "
             "seconds (all threads; a shared machine inflates them much less than wall); "
             "ratio new/old (above 1: new slower)", "",
             "| case | timed | old median | old min | new median | new min | new/old median "
             "| new/old min | CPU old median | CPU new median | CPU new/old |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for t in timings:
        o, n = t.seconds["old"], t.seconds["new"]
        if not o or not n:
            continue
        mo, mn = statistics.median(o), statistics.median(n)
        co, cn = t.cpu["old"], t.cpu["new"]
        cpu = (f"{statistics.median(co):.3f} | {statistics.median(cn):.3f} | "
               f"{statistics.median(cn) / statistics.median(co):.3f}" if co and cn else
               "- | - | -")
        lines.append(f"| {t.case} | {t.what} | {mo:.3f} | {min(o):.3f} | {mn:.3f} | "
                     f"{min(n):.3f} | {mn / mo:.3f} | {min(n) / min(o):.3f} | {cpu} |")
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", type=Path, default=OLD_DEFAULT, help="old tree (default %(default)s)")
    ap.add_argument("--new", type=Path, default=NEW_DEFAULT, help="new tree (default: this one)")
    ap.add_argument("--repeats", type=int, default=3, help="runs per tree and case (default 3)")
    ap.add_argument("--cases", default=",".join(CASES), help="comma list of: %(default)s")
    ap.add_argument("--core-hours", type=float,
                    help="hours of the core case (default 24)")
    ap.add_argument("--replay-hours", type=float,
                    help="hours of the replay case at 100 Hz (default 2)")
    ap.add_argument("--day-hours", type=float,
                    help="hours of the recording windowed, hindsighted, discovered (default 24)")
    ap.add_argument("--batch", type=int, default=100_000, help="core batch (default 100000)")
    ap.add_argument("--quick", action="store_true",
                    help="defaults of 2 h for the core and the recording, 0.5 h for replay")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("child_args", nargs="?", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    defaults = (2.0, 0.5, 2.0) if a.quick else (24.0, 2.0, 24.0)
    a.core_hours, a.replay_hours, a.day_hours = (
        x if x is not None else d for x, d in
        zip((a.core_hours, a.replay_hours, a.day_hours), defaults, strict=True))
    return a


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    if a.child:
        print(json.dumps(CHILDREN[a.child](json.loads(a.child_args))))
        return 0
    old, new = Tree("old", a.old.resolve()), Tree("new", a.new.resolve())
    cases = [c for c in a.cases.split(",") if c]
    if set(cases) - set(CASES):
        raise SystemExit(f"unknown case(s) {set(cases) - set(CASES)}; of {', '.join(CASES)}")
    head = {"date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "command": " ".join(["python", *sys.argv]),
            "old": f"{old.root} at {old.commit()}", "new": f"{new.root} at {new.commit()}",
            "machine": f"{os.cpu_count()} CPUs (nproc {len(os.sched_getaffinity(0))}), "
                       f"{platform.machine()}, Python {platform.python_version()}",
            "repeats": str(a.repeats)}
    work = Path(tempfile.mkdtemp(prefix="recal-side-by-side-"))
    try:
        inputs = work / "inputs"
        inputs.mkdir()
        print(f"inputs into {inputs} ...", flush=True)
        new.run(["-m", "recal", "simulate", "--out", str(inputs / "day.mcap"), "--hours",
                 str(a.day_hours), "--rate", "50", "--seed", "2"], work)
        made = new.child("make_inputs", {"dir": str(inputs), "bench": str(new.root / "bench"),
                                         "core_hours": a.core_hours,
                                         "replay_hours": a.replay_hours}, work)
        sizes = {"core": f"{made['core_samples']:,} samples ({a.core_hours:g} h at 50 Hz, "
                         f"{made['core_from']})",
                 "replay": f"{made['replay_samples']:,} samples ({a.replay_hours:g} h at 100 "
                           f"Hz, 100 per message, {made['replay_from']})",
                 "day": f"{made['day_samples']:,} samples ({a.day_hours:g} h at 50 Hz, recal "
                        "simulate --seed 2)"}
        head["load_before"] = load_avg()
        timings: dict[tuple[str, str], Timing] = {}
        for r in range(a.repeats):
            for case in cases:
                for tree in (old, new):
                    d = work / tree.label
                    d.mkdir(exist_ok=True)
                    for what, (sec, cpu) in time_case(case, tree, inputs, d,
                                                      a.batch).items():
                        t = timings.setdefault((case, what), Timing(case, what))
                        t.seconds[tree.label].append(sec)
                        if cpu is not None:
                            t.cpu[tree.label].append(cpu)
                    print(f"  repeat {r + 1}/{a.repeats} {case} {tree.label}: "
                          + ", ".join(f"{s[tree.label][-1]:.3f} s" for s in
                                      (t.seconds for (c, _), t in timings.items() if c == case)),
                          flush=True)
        head["load_after"] = load_avg()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print()
    print(markdown(list(timings.values()), head, sizes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
