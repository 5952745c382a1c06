"""The calibration core alone: the recal core beside the calibrators people use instead.

    python bench/compare_tools.py            # full: 24 h at 50 Hz per case, 5 timed runs
    python bench/compare_tools.py --quick    # 13 h per case, 1 timed run (a few minutes)

Compared, on the same arrays (readings in g, Unix time stamps):

* recal core: `recal.core.pipeline.Pipeline.step` on big batches (numpy in, calibrated numpy
  out: detector, buffer, estimator, correction; no Zenoh, no MCAP), streaming: each sample is
  corrected with the parameters known when it arrived. Models: diagonal (Lötters' six
  parameters), full (with cross-axis terms) and diagonal + ratiometric supply scaling.
* actipy `actipy.processing.calibrate_gravity`, scikit-digital-health
  `skdh.preprocessing.CalibrateAccelerometer`, wristpy `wristpy.processing.calibration`
  (`ConstrainedMinimizationCalibration`, wristpy's default "gradient", and `GgirCalibration`):
  batch tools (van Hees et al. 2014 style: one offset and scale per axis fitted on the whole
  recording, then applied to all of it). Each runs in its own virtual environment under
  bench/.venvs/, built here once (pinned to the versions measured, the newest release as a
  fallback) and reused; `bench/compare_tools_runner.py` runs one tool there and times only its
  calibration call. skdh and wristpy's GGIR calibrator refuse recordings shorter than 72 h by
  default; they are given their smallest setting, 12 h.
* a floor row, timed only: the two passes over every sample the core cannot skip (the detector
  and the correction, `run_floor`), without windows, buffer or estimator. Whatever the core
  does on top costs more, so this row bounds how fast any core of this design in numpy can be.

Cases, simulated with `recal.sim.wearer` (truth included), offsets +-50 mg, gains +-3 %, 4 mg noise,
1024 counts/g, passed to everyone in g (counts / 1024):
  plain       offsets and gains only; also the speed case (24 h at 50 Hz = 4.32 M samples)
  cross-axis  plus cross-axis misalignment +-1.5 deg
  supply      plus a ratiometric supply effect (output scales 5 %/V with a 4.1 -> 3.6 V battery)
  upright     the wearer is never tilted more than 30 deg (-z and +-x, +-y beyond 0.3 g unseen)

Metrics, against the simulator's truth and on the same samples for every tool:
  samples/s       N / time of the calibration call (median of --runs runs on the speed case,
                  the tools and the core taking turns; one run on the other cases)
  still |n-1|     mean of | |1 s mean of the output| - 1 g | over 1 s windows inside true still
                  postures, from --warmup-s on (mg)
  1 s err         RMS over 1 s windows of |mean(output - truth)| after the best rotation
                  (a frame rotation is not observable from gravity), from --warmup-s on (mg)
                  and over the whole recording (mg)
The first --warmup-s (default 30 min) are left out of the first two metrics for every tool
because the streaming core starts uncalibrated; the batch tools have no warm-up, and the last
column shows the whole recording. Rows "uncalibrated" (the input as is) and "true parameters"
(the simulator's exact inverse: what is left is sensor noise) bracket the results.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from recal.core import hindsight
from recal.core.detector import detect
from recal.core.effects import Ratiometric
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec, SimResult, WearerSpec, error_1s_mg, inverse_model, simulate

HERE = Path(__file__).resolve().parent
VENVS = HERE / ".venvs"
RUNNER = HERE / "compare_tools_runner.py"
RATE_HZ = 50.0
FLOOR = "floor"  # the contender that times recal's per-sample passes alone (run_floor)
HINDSIGHT = "hindsight"  # the contender that runs recal's core in batch use (run_hindsight)
COUNTS_PER_G = 1024.0
START_US = 1_704_067_200_000_000  # 2024-01-01 00:00 UTC: the tools want calendar time stamps
RATIOMETRIC_PER_V = 0.05
SUPPLY_REF_V = 3.3
SUPPLY_SPREAD_V = 0.5  # the battery's range over a day: sets the ratiometric prior's width
TOOL_TIMEOUT_S = 1800  # one tool call on 24 h takes seconds; a hang must not stall the run


# --- the tools' virtual environments ---------------------------------------------------------
@dataclass(frozen=True)
class Venv:
    """One tool's environment: pip requirements to try in order, and the module to import."""

    name: str
    attempts: tuple[str, ...]
    module: str

    @property
    def path(self) -> Path:
        return VENVS / self.name

    @property
    def python(self) -> Path:
        return self.path / "bin" / "python"


VENV_SPECS = (
    Venv("actipy", ("actipy==3.8.3", "actipy"), "actipy.processing"),
    Venv("skdh", ("scikit-digital-health==0.17.18", "scikit-digital-health"),
         "skdh.preprocessing"),
    Venv("wristpy", ("wristpy==0.2.10", "wristpy"), "wristpy.processing.calibration"),
)
#: tool (runner name) -> environment it runs in
TOOLS = {"actipy": "actipy", "skdh": "skdh", "wristpy-gradient": "wristpy",
         "wristpy-ggir": "wristpy"}
TOOL_LABELS = {"actipy": "actipy calibrate_gravity",
               "skdh": "skdh CalibrateAccelerometer",
               "wristpy-gradient": "wristpy gradient (default)",
               "wristpy-ggir": "wristpy GgirCalibration"}


def _imports(v: Venv) -> bool:
    if not v.python.exists():
        return False
    r = subprocess.run([str(v.python), "-c", f"import {v.module}"], capture_output=True,
                       timeout=300, check=False)
    return r.returncode == 0


def _pip_error(output: str) -> str:
    """pip's own error line (its warnings about unreachable indexes are noise here)."""
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("ERROR")]
    return (errors or lines or ["no output"])[-1][:300]


def ensure_venv(v: Venv) -> tuple[bool, str]:
    """Build (once) the tool's environment. Returns (usable, what was installed or why not)."""
    marker = v.path / "recal-bench.json"
    if marker.exists() and _imports(v):
        return True, json.loads(marker.read_text())["installed"]
    if not v.python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(v.path)], check=True, timeout=600)
    log = v.path / "install.log"
    failures = []
    for req in v.attempts:
        _log(f"installing {req} into {v.path} (log: {log})")
        r = subprocess.run([str(v.python), "-m", "pip", "install", req], capture_output=True,
                           text=True, timeout=3600, check=False)
        with log.open("a") as fh:
            fh.write(r.stdout + r.stderr)
        if r.returncode == 0 and _imports(v):
            marker.write_text(json.dumps({"installed": req}))
            return True, req
        failures.append(f"{req}: pip exit {r.returncode}: {_pip_error(r.stdout + r.stderr)}"
                        if r.returncode else f"{req}: installed but `import {v.module}` failed")
    return False, "; ".join(failures) + f" (see {log})"


# --- cases -----------------------------------------------------------------------------------
ModelFactory = Callable[[], SensorModel]


def _diagonal() -> SensorModel:
    return SensorModel.diagonal(1.0)


def _full() -> SensorModel:
    return SensorModel.full(1.0)


def _ratiometric() -> SensorModel:
    return SensorModel.diagonal(1.0).with_effect(Ratiometric("vdd_v", SUPPLY_REF_V),
                                                 SUPPLY_SPREAD_V)


@dataclass(frozen=True)
class Case:
    name: str
    seed: int
    sensor: dict = field(default_factory=dict)  # SensorSpec.random overrides
    wearer: WearerSpec = field(default_factory=WearerSpec)
    cross_axis_deg: float = 0.0
    #: (label, model) the recal core runs with; the first is the model that fits the case
    models: tuple[tuple[str, ModelFactory], ...] = (("diagonal", _diagonal),)


CASES = (
    Case("plain", 1),
    Case("cross-axis", 2, cross_axis_deg=1.5,
         models=(("full", _full), ("diagonal", _diagonal))),
    Case("supply", 3, sensor={"ratiometric_per_v": RATIOMETRIC_PER_V},
         models=(("diagonal+ratiometric", _ratiometric), ("diagonal", _diagonal))),
    Case("upright", 4, wearer=WearerSpec(upright_only=True)),
)


def simulate_case(case: Case, hours: float) -> SimResult:
    rng = np.random.default_rng(case.seed)
    sensor = SensorSpec.random(rng, offset_mg=50.0, gain_pct=3.0,
                               cross_axis_deg=case.cross_axis_deg, **case.sensor)
    sensor = replace(sensor, counts_per_g=COUNTS_PER_G)
    return simulate(hours, RATE_HZ, case.seed, sensor, case.wearer, start_us=START_US)


def write_case(directory: Path, raw_g: RawBatch) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    np.save(directory / "v_g.npy", raw_g.v)
    np.save(directory / "t_us.npy", raw_g.t_us)
    (directory / "meta.json").write_text(json.dumps({"rate_hz": RATE_HZ}))


# --- running ---------------------------------------------------------------------------------
@dataclass
class Row:
    """One tool on one case."""

    case: str
    tool: str
    kind: str
    seconds: list[float] = field(default_factory=list)
    status: str = ""
    still_mg: float = float("nan")
    err_mg: float = float("nan")
    err_all_mg: float = float("nan")

    def rate(self, n: int) -> float:
        return n / statistics.median(self.seconds) if self.seconds else float("nan")


def run_tool(tool: str, case_dir: Path, out: Path | None) -> dict:
    venv = next(v for v in VENV_SPECS if v.name == TOOLS[tool])
    cmd = [str(venv.python), str(RUNNER), tool, str(case_dir)]
    if out is not None:
        cmd += ["--out", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=TOOL_TIMEOUT_S, check=False)
    if r.returncode != 0:
        tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
        return {"status": "failed", "reason": tail[:200], "seconds": None}
    return json.loads(r.stdout.strip().splitlines()[-1])


def run_recal(raw_g: RawBatch, model: SensorModel, batch: int,
              **settings: float) -> tuple[np.ndarray, float, Pipeline]:
    """The core alone: Pipeline.step over big batches, from a nominal prior (datasheet);
    settings: PipelineConfig fields other than the defaults."""
    batches = [raw_g[i:i + batch] for i in range(0, len(raw_g), batch)]
    t0 = time.perf_counter()
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ, **settings), model, Prior.default(model),
                    raw_g.aux_names)
    out = np.concatenate([pipe.step(b).calibrated.a_g for b in batches])
    return out, time.perf_counter() - t0, pipe


def run_hindsight(raw_g: RawBatch, model: SensorModel, batch: int
                  ) -> tuple[np.ndarray, float, hindsight.HindsightFit]:
    """The core in batch use, as the tools are (`core.hindsight`): the live detector and
    windows over the whole recording, one fit with hindsight, every sample corrected with it;
    in the same batches as `run_recal`."""
    batches = [raw_g[i:i + batch] for i in range(0, len(raw_g), batch)]
    t0 = time.perf_counter()
    fit = hindsight.calibrate(lambda: batches, model, PipelineConfig(rate_hz=RATE_HZ))
    out = np.empty_like(raw_g.v)  # one output array, as the tools return
    for i, b in zip(range(0, len(raw_g), batch), batches, strict=True):
        fit.correct(b, out[i:i + len(b)])
    return out, time.perf_counter() - t0, fit


def hindsight_status(fit: hindsight.HindsightFit) -> str:
    held = f"; held at nominal, unobservable: {', '.join(fit.held)}" if fit.held else ""
    return f"calibrated: {fit.windows} windows ({fit.dropped} dropped){held}"


def run_floor(raw_g: RawBatch, model: SensorModel, batch: int) -> float:
    """Seconds of the two passes over every sample the core cannot skip, alone: the detector
    (Lötters eq. 1-2) and the correction with fixed parameters, in the same batches as
    `run_recal`. No windows, buffer or estimator: a lower bound on the core's time, not a
    calibration."""
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model),
                    raw_g.aux_names)
    t0 = time.perf_counter()
    state = pipe.det_state
    for i in range(0, len(raw_g), batch):
        b = raw_g[i:i + batch]
        state, _ = detect(pipe.det_cfg, state, b.v)
        pipe.model.correct(pipe.params, b.v, pipe.covariates(b.t_us, b.aux))
    return time.perf_counter() - t0


def recal_status(pipe: Pipeline) -> str:
    c = pipe.counts
    held = [n for n, free in zip(pipe.model.names,
                                 pipe.model.observable_with(pipe.coverage().axes_covered),
                                 strict=True) if not free]
    text = f"{c['updates']} updates, {c['updates_rejected']} rejected"
    return text + (f"; held at prior, reported unobservable: {', '.join(held)}" if held else "")


# --- metrics ---------------------------------------------------------------------------------
def _window_means(x: np.ndarray, n: int) -> np.ndarray:
    k = len(x) // n
    return x[:k * n].reshape(k, n, *x.shape[1:]).mean(axis=1)


def still_norm_mg(cal: np.ndarray, still: np.ndarray, first: int) -> float:
    """Mean | |1 s mean| - 1 g | over 1 s windows that lie wholly inside true still postures."""
    n = int(RATE_HZ)
    means = _window_means(cal[first:], n)
    inside = _window_means(still[first:].astype(np.float64), n) == 1.0
    return 1e3 * float(np.mean(np.abs(np.linalg.norm(means[inside], axis=1) - 1.0)))


def vector_err_mg(cal: np.ndarray, truth: np.ndarray, first: int) -> float:
    """RMS over 1 s windows of |mean(cal - truth)| after the best rotation (as tests/test_core)."""
    return error_1s_mg(cal[first:], truth[first:], RATE_HZ, align=True)


def score(row: Row, cal: np.ndarray, sim: SimResult, first: int) -> None:
    if not np.all(np.isfinite(cal)):
        row.status += " (non-finite output)"
        return
    row.still_mg = still_norm_mg(cal, sim.truth.still, first)
    row.err_mg = vector_err_mg(cal, sim.truth.a_true_g, first)
    row.err_all_mg = vector_err_mg(cal, sim.truth.a_true_g, 0)


# --- one case --------------------------------------------------------------------------------
def run_case(case: Case, args: argparse.Namespace, tools: list[str], workdir: Path,
             runs: int) -> tuple[list[Row], int]:
    _log(f"[{case.name}] simulating {args.hours:g} h at {RATE_HZ:g} Hz")
    sim = simulate_case(case, args.hours)
    raw_g = RawBatch(sim.raw.t_us, sim.raw.v / COUNTS_PER_G, sim.raw.aux, sim.raw.aux_names)
    n = len(raw_g)
    first = int(args.warmup_s * RATE_HZ)
    case_dir = workdir / case.name
    write_case(case_dir, raw_g)

    rows: list[Row] = []
    base = Row(case.name, "uncalibrated (input as is)", "-", status="-")
    score(base, raw_g.v, sim, first)
    rows.append(base)
    ideal = Row(case.name, "true parameters (noise floor)", "-", status="-")
    aux = {name: raw_g.channel(name) for name in raw_g.aux_names}
    score(ideal, inverse_model(sim.raw.v, sim.truth.sensor,
                               vdd_v=aux.get(sim.truth.sensor.supply_channel)), sim, first)
    rows.append(ideal)

    tool_rows = {t: Row(case.name, TOOL_LABELS[t], "batch") for t in tools}
    ours = {label: Row(case.name, f"recal core ({label})", "streaming")
            for label, _ in case.models}
    best = case.models[0][0]  # the model that fits the case
    mine = Row(case.name, f"recal core with hindsight ({best})", "batch (recal)")
    models = dict(case.models)
    floor = Row(case.name, "recal's per-sample passes alone (detector + correction)", "floor",
                status="timed only: no estimator, not a calibration")
    contenders = [*tools, *ours, HINDSIGHT, FLOOR]
    for r in range(runs):
        # take turns, starting with a different contender each run: drift in machine load
        # then spreads over everyone instead of always hitting the same one
        order = contenders[r % len(contenders):] + contenders[:r % len(contenders)]
        for who in order:
            if who in tool_rows:
                _run_tool_once(tool_rows[who], who, case_dir, sim, first, score_it=r == 0)
            elif who == FLOOR:
                floor.seconds.append(run_floor(raw_g, models[best](), args.batch))
            elif who == HINDSIGHT:
                _log(f"[{case.name}] recal core with hindsight ({best}), run {r + 1}/{runs}")
                cal, sec, fit = run_hindsight(raw_g, models[best](), args.batch)
                mine.seconds.append(sec)
                if r == 0:
                    mine.status = hindsight_status(fit)
                    score(mine, cal, sim, first)
                del cal
            else:
                _log(f"[{case.name}] recal core ({who}), run {r + 1}/{runs}")
                cal, sec, pipe = run_recal(raw_g, models[who](), args.batch)
                ours[who].seconds.append(sec)
                if r == 0:
                    ours[who].status = recal_status(pipe)
                    score(ours[who], cal, sim, first)
                del cal, pipe
    rows += [tool_rows[t] for t in tools] + list(ours.values()) + [mine, floor]
    shutil.rmtree(case_dir, ignore_errors=True)
    return rows, n


def _run_tool_once(row: Row, tool: str, case_dir: Path, sim: SimResult, first: int,
                   score_it: bool) -> None:
    _log(f"[{row.case}] {tool}")
    out = case_dir / f"{tool}.npy" if score_it else None
    res = run_tool(tool, case_dir, out)
    if res["seconds"] is not None:
        row.seconds.append(float(res["seconds"]))
    if not score_it:
        return
    row.status = res["status"] + (f": {res['reason']}" if res.get("reason") else "")
    if res["status"] != "failed" and out is not None and out.exists():
        score(row, np.load(out), sim, first)
        out.unlink()


# --- output ----------------------------------------------------------------------------------
def _fmt(x: float, digits: int = 2) -> str:
    return "-" if not np.isfinite(x) else f"{x:.{digits}f}"


def _rate(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x / 1e6:.3f} M"


def table(rows: list[Row], sizes: dict[str, int], speed_case: str) -> str:
    fastest = {}
    for case, n in sizes.items():
        rates = [r.rate(n) for r in rows if r.case == case and r.kind == "batch"
                 and r.status.startswith("calibrated")]
        fastest[case] = max(rates) if rates else float("nan")
    head = ("| case | calibrator | batch or streaming | samples/s | vs fastest tool | "
            "still \\|n-1\\| mg | 1 s err mg | 1 s err mg (whole) | result |")
    lines = [head, "|" + "---|" * 9]
    for r in rows:
        n = sizes[r.case]
        rate = r.rate(n)
        runs = (f" (median of {len(r.seconds)}: {n / max(r.seconds) / 1e6:.3f}-"
                f"{n / min(r.seconds) / 1e6:.3f})" if len(r.seconds) > 1 else "")
        ratio = rate / fastest[r.case] if r.kind != "-" else float("nan")
        lines.append(
            f"| {r.case}{' (speed case)' if r.case == speed_case else ''} | {r.tool} | "
            f"{r.kind} | {_rate(rate)}{runs} | {_fmt(ratio, 3)}{'x' if np.isfinite(ratio) else ''}"
            f" | {_fmt(r.still_mg)} | {_fmt(r.err_mg)} | {_fmt(r.err_all_mg)} | {r.status} |")
    return "\n".join(lines)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="13 h per case and 1 timed run (the tools need at least 12 h)")
    ap.add_argument("--hours", type=float, help="hours per case (default 24, quick 13)")
    ap.add_argument("--runs", type=int, help="timed runs on the speed case (default 5, quick 1)")
    ap.add_argument("--runs-every-case", action="store_true",
                    help="time every case --runs times, not only the speed case")
    ap.add_argument("--cases", default=",".join(c.name for c in CASES),
                    help="comma-separated subset of: " + ", ".join(c.name for c in CASES))
    ap.add_argument("--tools", default=",".join(TOOLS), help="comma-separated subset of tools")
    ap.add_argument("--batch", type=int, default=100_000, help="samples per Pipeline.step")
    ap.add_argument("--warmup-s", type=float, default=1800.0,
                    help="left out of the still and 1 s error columns (the core converges)")
    ap.add_argument("--workdir", type=Path, help="where the case arrays go (default: a temp dir)")
    a = ap.parse_args(argv)
    a.hours = a.hours or (13.0 if a.quick else 24.0)
    a.runs = a.runs or (1 if a.quick else 5)
    return a


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    wanted_cases = args.cases.split(",")
    unknown = set(wanted_cases) - {c.name for c in CASES} | set(args.tools.split(",")) - set(TOOLS)
    if unknown:
        print(f"unknown case or tool: {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    installed = {}
    for v in VENV_SPECS:
        if any(TOOLS[t] == v.name for t in args.tools.split(",")):
            installed[v.name] = ensure_venv(v)
    tools = [t for t in args.tools.split(",") if installed[TOOLS[t]][0]]
    missing = {t: installed[TOOLS[t]][1] for t in args.tools.split(",") if t not in tools}

    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="recal-compare-"))
    rows: list[Row] = []
    sizes: dict[str, int] = {}
    cases = [c for c in CASES if c.name in wanted_cases]
    try:
        for i, case in enumerate(cases):
            case_rows, sizes[case.name] = run_case(case, args, tools, workdir,
                                                   args.runs if i == 0 or
                                                   args.runs_every_case else 1)
            rows += case_rows
    finally:
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)

    print(f"\nCalibration core alone vs batch tools: {args.hours:g} h at {RATE_HZ:g} Hz per case "
          f"({sizes[cases[0].name]} samples), warm-up {args.warmup_s:g} s left out of the still "
          f"and 1 s error columns; {args.runs} timed run(s) on "
          f"{'every case' if args.runs_every_case else 'the speed case'}.")
    print("Tools: " + "; ".join(f"{v}: {ok[1]}" for v, ok in installed.items() if ok[0]))
    for t, why in missing.items():
        print(f"NOT RUN {t}: {why}")
    print()
    print(table(rows, sizes, cases[0].name))
    return 0


if __name__ == "__main__":
    sys.exit(main())
