"""Real worn recordings: recal beside actipy's calibrate_gravity on the same device files.

    python bench/device_tools.py FILE [FILE ...]           # .cwa, .bin, .gt3x, or a shared .npz

The files are public test data of the projects the field uses; they are not in this repository
and never fetched by it (tests use none of them). Measured with:

* ``stepcount_tiny-sample.cwa``: Axivity AX3, 100 Hz, +-8 g, 2.97 h worn, with temperature
  (27-35 deg C). OxWearables/stepcount, ``tests/data/tiny-sample.cwa.gz`` (gunzip it).
* ``pygt3x_small.gt3x``: ActiGraph GT9X Link, wrist, 30 Hz, 256 counts/g, 13.6 h from first to
  last sample with 7.5 h of samples (idle sleep mode leaves the still rest out), no temperature.
  actigraph/pygt3x, ``tests/resources/small.gt3x`` (its data only: pygt3x is GPL and is neither
  imported nor copied). Its records are ACTIVITY2, which actfast 1.3.0 skips; recal's own
  decoder (`recal.io.gt3x`) reads them.

Get them with ``git clone`` of those repositories (or ``git show HEAD:<path>``). Every other file
actfast reads works the same way; ``../shared/data/real/*.npz`` (`_npz`) too.

Per file, every tool is judged on the same still 10 s windows: non-overlapping, on a grid from the
first sample, at least 90 % of their samples present, every axis's SD under 13 mg in the file's
own readings (GGIR's sdCriter). The metric is GGIR's: mean over those windows of
| |window mean| - 1 g | (mg).

* in-sample: each tool fits on the whole file and is judged on it (as the tools report).
* held out: the file is cut into 30 min blocks from its first sample; each tool fits on the even
  blocks and corrects the odd ones, and the other way round; every still window is judged by the
  fit that did not see it.

Tools, each in a process of its own (bench/device_tools_runner.py; time is the fit and the
correction of every sample, peak memory the process's VmHWM):
  raw                       the file's readings in g, as given (its factory scaling)
  actipy calibrate_gravity  van Hees et al. 2014 with the device temperature when the file has
                            one (in bench/.venvs/actipy, built by bench/compare_tools.py); it
                            refuses (keeps the input) unless its still windows reach beyond
                            +-0.3 g on every axis
  actipy, sphere criterion off   the same with calib_cube=0: the fit it would make anyway
  recal offsets and gains   `recal hindsight --model` of offsets and gains alone
  recal hindsight           `recal hindsight` as it runs without --model: the effects
                            discover's rule selects on the windows, then one fit
  recal discover+hindsight  `recal discover` then `recal hindsight --model` of the model it
                            writes; "calibrated" is the share of samples hindsight marks
                            calibrated (status CALIBRATED, in-sample fit).
Device files are read by `recal.io.device_files` (each sample stamped between its block's stamp
and the next's); actipy gets the temperature channel, recal every aux channel the file has (as
`recal hindsight FILE` and `recal discover FILE` do).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from compare_tools import VENV_SPECS, ensure_venv  # noqa: E402

# GGIR's (and actipy's) still 10 s windows, as `recal hindsight DIR` reports them
from recal.core.still_error import MIN_FILL, STILL_SD_G, WINDOW_US  # noqa: E402

RUNNER = HERE / "device_tools_runner.py"
BLOCK_US = 1_800_000_000  # held-out blocks: 30 min
TOOLS = ("actipy", "actipy-nocube", "recal-diagonal", "recal-hindsight", "recal-discover")
LABELS = {"raw": "raw (file's scaling)", "actipy": "actipy calibrate_gravity",
          "actipy-nocube": "actipy, sphere criterion off",
          "recal-diagonal": "recal offsets and gains", "recal-hindsight": "recal hindsight",
          "recal-discover": "recal discover+hindsight"}
TIMEOUT_S = 900


@dataclass
class Recording:
    """One device file as arrays: times, readings in g, temperature per sample (or None)."""

    name: str
    device: str
    t_us: np.ndarray
    v_g: np.ndarray
    aux: np.ndarray  # (N, K) the file's other channels at each sample
    aux_names: tuple[str, ...]
    rate_hz: float
    notes: list[str] = field(default_factory=list)

    @property
    def temp_c(self) -> np.ndarray | None:
        """The device's temperature at each sample (what actipy is given), if it has one."""
        names = [n for n in self.aux_names if n.startswith("temp")]
        return self.aux[:, self.aux_names.index(names[0])] if names else None

    @property
    def hours(self) -> float:
        return len(self.t_us) / self.rate_hz / 3600.0

    @property
    def span_hours(self) -> float:
        return float(self.t_us[-1] - self.t_us[0]) / 3.6e9


# --- reading ---------------------------------------------------------------------------------
def load(path: Path) -> Recording:
    """A device file through `recal.io.device_files` (true per-sample times between the
    file's block stamps, every aux channel), or a shared .npz (`_npz`)."""
    if path.suffix.lower() == ".npz":
        return _npz(path)
    from recal.io.device_files import open_device

    dev = open_device(path)
    batches = list(dev.batches())
    rec = Recording(path.name, str(dev.metadata.get("device_type", dev.kind)),
                    np.concatenate([b.t_us for b in batches]),
                    np.concatenate([b.v for b in batches]),
                    np.concatenate([b.aux for b in batches]), dev.aux_names, dev.rate_hz,
                    [n for n in dev.notes if "gap" in n])
    return _sorted(rec)


def _sorted(rec: Recording) -> Recording:
    order = np.argsort(rec.t_us, kind="stable")
    if not np.array_equal(order, np.arange(len(order))):
        rec.notes.append("samples re-sorted by time")
        rec.t_us, rec.v_g, rec.aux = rec.t_us[order], rec.v_g[order], rec.aux[order]
    return rec


def _npz(path: Path) -> Recording:
    d = np.load(path)
    meta = json.loads(str(d["meta"])) if "meta" in d else {}
    t_us = np.round(np.asarray(d["t"], np.float64) * 1e6).astype(np.int64)
    rate = 1e6 / float(np.median(np.diff(t_us)))
    names = tuple(k for k in ("temp", "batt") if k in d)
    aux = np.column_stack([np.asarray(d[k], np.float64) for k in names]) if names else None
    return _sorted(Recording(path.name, str(meta.get("device", "?")), t_us,
                             np.asarray(d["acc"], np.float64),
                             aux if aux is not None else np.zeros((len(t_us), 0)),
                             tuple({"temp": "temperature", "batt": "battery_voltage"}[k]
                                   for k in names), rate))


# --- the still windows and the metric --------------------------------------------------------
@dataclass(frozen=True)
class Windows:
    """Every sample's 10 s window, which windows are still, and each window's 30 min block."""

    index: np.ndarray  # (N,) window of each sample
    still: np.ndarray  # (W,) bool
    block: np.ndarray  # (W,) 0 or 1: even or odd 30 min block
    sd_g: np.ndarray  # (S, 3) SD per axis of the still windows


def windows(rec: Recording) -> Windows:
    index = (rec.t_us - rec.t_us[0]) // WINDOW_US
    n = np.bincount(index).astype(np.float64)
    mean = (np.stack([np.bincount(index, rec.v_g[:, k]) for k in range(3)], 1)
            / np.maximum(n, 1)[:, None])
    centred = rec.v_g - mean[index]  # two passes: no cancellation in the SD
    var = np.stack([np.bincount(index, centred[:, k]**2) for k in range(3)], 1)
    sd = np.sqrt(var / np.maximum(n - 1, 1)[:, None])
    still = (n >= MIN_FILL * rec.rate_hz * WINDOW_US / 1e6) & np.all(sd < STILL_SD_G, axis=1)
    block = (np.arange(len(n)) * WINDOW_US // BLOCK_US) % 2
    return Windows(index, still, block, sd[still])


def still_error_mg(out: np.ndarray, w: Windows) -> float:
    """GGIR's metric: mean over the still windows of | |window mean| - 1 g |, in mg."""
    n = np.bincount(w.index, minlength=len(w.still)).astype(np.float64)
    mean = np.stack([np.bincount(w.index, out[:, k], minlength=len(n)) for k in range(3)], 1)
    mean = mean[w.still] / n[w.still, None]
    return 1e3 * float(np.mean(np.abs(np.linalg.norm(mean, axis=1) - 1.0)))


# --- running ---------------------------------------------------------------------------------
@dataclass
class Row:
    file: str
    tool: str
    in_mg: float = float("nan")
    held_mg: float = float("nan")
    seconds: float = float("nan")
    peak_mb: float = float("nan")
    before_mb: float = float("nan")
    calibrated: float | None = None
    status: str = ""
    detail: str = ""
    folds: list[str] = field(default_factory=list)


def run_child(python: Path, tool: str, case: Path, fold: str) -> tuple[dict, np.ndarray | None]:
    r = subprocess.run(["nice", "-n", "10", str(python), str(RUNNER), tool, str(case), fold],
                       capture_output=True, text=True, timeout=TIMEOUT_S, check=False)
    if r.returncode != 0:
        tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
        return {"status": "failed", "detail": tail[:300]}, None
    out_path = case / f"out_{tool}_{fold}.npy"
    out = np.load(out_path)
    out_path.unlink()
    return json.loads(r.stdout.strip().splitlines()[-1]), out


def run_file(rec: Recording, w: Windows, pythons: dict[str, Path], workdir: Path) -> list[Row]:
    case = workdir / rec.name
    case.mkdir(parents=True, exist_ok=True)
    np.save(case / "v_g.npy", rec.v_g)
    np.save(case / "t_us.npy", rec.t_us)
    np.save(case / "aux.npy", rec.aux)
    if rec.temp_c is not None:
        np.save(case / "temp_c.npy", rec.temp_c)
    (case / "meta.json").write_text(json.dumps({"rate_hz": rec.rate_hz,
                                                "aux_names": list(rec.aux_names)}))
    sample_block = w.block[w.index]
    np.save(case / "train_all.npy", np.ones(len(rec.t_us), bool))
    np.save(case / "train_even.npy", sample_block == 0)
    np.save(case / "train_odd.npy", sample_block == 1)

    raw = Row(rec.name, LABELS["raw"], status="-")
    raw.in_mg = raw.held_mg = still_error_mg(rec.v_g, w)
    rows = [raw]
    for tool in TOOLS:
        if tool not in pythons:
            continue
        row = Row(rec.name, LABELS[tool])
        held = np.empty_like(rec.v_g)
        for fold in ("all", "even", "odd"):
            _log(f"[{rec.name}] {tool} fit on {fold}")
            res, out = run_child(pythons[tool], tool, case, fold)
            row.folds.append(f"{fold}: {res['status']}")
            if out is None:  # the in-sample result stays; the folds column says why
                if fold == "all":
                    row.status, row.detail = res["status"], res["detail"]
                row.folds[-1] += f" ({res['detail']})"
                break
            if fold == "all":
                row.in_mg = still_error_mg(out, w)
                row.seconds, row.peak_mb = res["seconds"], res["peak_mb"]
                row.before_mb, row.calibrated = res["rss_before_mb"], res["calibrated_fraction"]
                row.status, row.detail = res["status"], res["detail"]
            else:  # judged on the blocks it did not see
                other = sample_block == (1 if fold == "even" else 0)
                held[other] = out[other]
        else:
            row.held_mg = still_error_mg(held, w)
        rows.append(row)
    shutil.rmtree(case, ignore_errors=True)
    return rows


# --- output ----------------------------------------------------------------------------------
def describe(rec: Recording, w: Windows) -> str:
    quantum = np.min(np.diff(np.unique(rec.v_g[:200_000, 0])))
    temp = (f"{rec.temp_c.min():.1f}-{rec.temp_c.max():.1f} deg C" if rec.temp_c is not None
            else "no temperature")
    sd = np.median(w.sd_g, axis=0) * 1e3 if len(w.sd_g) else np.full(3, np.nan)
    return (f"{rec.name}: {rec.device}, {rec.rate_hz:.4g} Hz, {len(rec.t_us)} samples "
            f"({rec.hours:.2f} h of samples over {rec.span_hours:.2f} h), {temp}; reading step "
            f"{1e3 * quantum:.2f} mg; {int(w.still.sum())} still 10 s windows of {len(w.still)} "
            f"(median SD x/y/z {sd[0]:.1f}/{sd[1]:.1f}/{sd[2]:.1f} mg)"
            + (f"; {'; '.join(rec.notes)}" if rec.notes else ""))


def still_means(rec: Recording, w: Windows) -> tuple[np.ndarray, np.ndarray]:
    """The still windows' means in g (S,3) and their share of each aux channel (S,K)."""
    n = np.maximum(np.bincount(w.index), 1).astype(np.float64)  # a gap's windows are empty
    mean = np.stack([np.bincount(w.index, rec.v_g[:, k]) for k in range(3)], 1) / n[:, None]
    aux = np.stack([np.bincount(w.index, rec.aux[:, k], minlength=len(n))
                    for k in range(rec.aux.shape[1])], 1) / n[:, None] if rec.aux.shape[1] \
        else np.zeros((len(n), 0))
    return mean[w.still], aux[w.still]


def diagonal_on_still(rec: Recording, w: Windows) -> str:
    """What offsets and gains fitted to the judged windows themselves reach, by least squares
    (as recal fits) and by mean absolute error (the metric's own loss, near actipy's
    weighted one): how much of a gap between tools is the loss, not the windows."""
    from scipy.optimize import least_squares, minimize

    m, _ = still_means(rec, w)

    def xi(p: np.ndarray) -> np.ndarray:
        return np.linalg.norm((m - p[:3]) * p[3:], axis=1) - 1.0

    l2 = least_squares(xi, np.r_[0.0, 0, 0, 1, 1, 1]).x
    l1 = minimize(lambda p: np.mean(np.abs(xi(p))), l2, method="Nelder-Mead",
                  options={"maxiter": 20_000, "xatol": 1e-7, "fatol": 1e-9}).x
    lo, hi = m.min(axis=0), m.max(axis=0)
    temp = rec.temp_c
    span = ""
    if temp is not None:
        t = still_means(rec, w)[1][:, rec.aux_names.index(
            next(n for n in rec.aux_names if n.startswith("temp")))]
        span = f"; their temperature {t.min():.1f}-{t.max():.1f} deg C"
    return (f"  still windows' means reach x {lo[0]:+.2f}..{hi[0]:+.2f}, y {lo[1]:+.2f}.."
            f"{hi[1]:+.2f}, z {lo[2]:+.2f}..{hi[2]:+.2f} g{span}; offsets and gains fitted "
            f"to them: {1e3 * np.mean(np.abs(xi(l2))):.2f} mg by least squares, "
            f"{1e3 * np.mean(np.abs(xi(l1))):.2f} mg by mean absolute error")


def _f(x: float | None, digits: int = 2) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def table(rows: list[Row]) -> str:
    lines = ["| file | tool | still err in-sample mg | held out mg | fit+correct s | peak MB "
             "(before call) | calibrated | fit |", "|" + "---|" * 8]
    for r in rows:
        cal = f"{100 * r.calibrated:.1f} %" if r.calibrated is not None else "-"
        mem = f"{_f(r.peak_mb, 0)} ({_f(r.before_mb, 0)})" if np.isfinite(r.peak_mb) else "-"
        folds = ("" if all(f.endswith(": calibrated") for f in r.folds[1:])
                 else f" (held-out fits: {', '.join(r.folds[1:])})")
        lines.append(f"| {r.file} | {r.tool} | {_f(r.in_mg)} | {_f(r.held_mg)} | "
                     f"{_f(r.seconds)} | {mem} | {cal} | {r.status}: {r.detail}{folds} |")
    return "\n".join(lines)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", type=Path)
    ap.add_argument("--tools", default=",".join(TOOLS), help="comma-separated subset")
    ap.add_argument("--hours", type=float, help="only the first HOURS of each file (development)")
    ap.add_argument("--workdir", type=Path, help="where the arrays go (default: a temp dir)")
    a = ap.parse_args(argv)
    wanted = a.tools.split(",")
    pythons: dict[str, Path] = {t: Path(sys.executable) for t in wanted if t.startswith("recal")}
    if any(t.startswith("actipy") for t in wanted):
        venv = next(v for v in VENV_SPECS if v.name == "actipy")
        ok, what = ensure_venv(venv)
        if ok:
            pythons.update({t: venv.python for t in wanted if t.startswith("actipy")})
        print(f"actipy: {what}")
    workdir = a.workdir or Path(tempfile.mkdtemp(prefix="recal-devices-"))
    rows: list[Row] = []
    try:
        for path in a.files:
            rec = load(path)
            if a.hours:
                keep = rec.t_us < rec.t_us[0] + int(a.hours * 3.6e9)
                rec.t_us, rec.v_g, rec.aux = rec.t_us[keep], rec.v_g[keep], rec.aux[keep]
            w = windows(rec)
            print(describe(rec, w), flush=True)
            print(diagonal_on_still(rec, w), flush=True)
            rows += run_file(rec, w, pythons, workdir)
    finally:
        if a.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    print()
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
