"""Real worn recordings through `recal replay` with the defaults (no model, discovery on).

    python bench/real_replay.py FILE [FILE ...]          # .cwa, .bin, .gt3x
    python bench/real_replay.py FILE --json out.json     # the figures as JSON too

The files are public test data (see bench/device_tools.py for where each comes from); they are
not in this repository. Per file, each command runs in a process of its own, as a user runs it:

* ``recal replay FILE --out X.mcap --json X.json`` (the defaults), then the output MCAP is read
  back (`recal.io.recording`): every calibrated sample with its status, the events;
* ``recal discover FILE --json D.json``: the held-out error of each model it tries.

After the first hour of device time (from the file's first sample) it reports:

* the share of samples per status (calibrated, held, suspect, ...);
* the error of calibrated still 10 s windows: | |window mean| - 1 g | (mg), the windows as in
  bench/device_tools.py (a grid from the first sample, >= 90 % of their samples present, every
  axis's SD under 13 mg in the file's own readings), counted when all their samples are marked
  calibrated; mean and median;
* the summary's "misses" figure (`misfit_mg`) beside discover's held-out error of the model the
  replay ended with (the same effects; offsets and gains alone: discover's base);
* the adopted effects (discovery events) and when;
* why samples are not calibrated: each such sample counted by its status and the latest status
  event before it (a suspect's reason, a change of status, the bootstrap, an adoption).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from device_tools import load, windows  # noqa: E402
from recal.core.status import Status  # noqa: E402
from recal.io import recording as rec  # noqa: E402

HOUR_US = 3_600_000_000
TIMEOUT_S = 900


def _recal(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "recal", *args], check=True, timeout=TIMEOUT_S,
                   stdout=subprocess.DEVNULL)


def _reasons(events: list[tuple[int, dict]], t_us: np.ndarray, status: np.ndarray,
             not_cal: np.ndarray) -> dict[str, int]:
    """Samples not calibrated, counted by their status and the latest status event before
    each (held without an event of its own: an offset or scale unobserved or converging, or
    the probation after an adoption)."""
    marks, why = [(0, "before any status event")], "?"
    for t, ev in events:
        kind, detail = ev.get("kind"), ev.get("detail") or {}
        if kind == "suspect":
            why = str(detail.get("reason"))
            marks.append((t, f"suspect: {why}"))
        elif kind == "status_changed":
            marks.append((t, f"{detail.get('status')} (was {detail.get('was')})"
                          + (f": {why}" if detail.get("status") == "suspect" else "")))
        elif kind in ("bootstrap", "reset", "agrees", "discovery") and (
                kind != "discovery" or detail.get("adopted")):
            marks.append((t, kind))
    times = np.array([m[0] for m in marks], np.int64)
    which = np.searchsorted(times, t_us[not_cal], side="right") - 1
    labels = [Status(x).label for x in status[not_cal].tolist()]
    return dict(Counter(f"{lab}, after: {marks[i][1]}"
                        for lab, i in zip(labels, which.tolist(), strict=True)).most_common())


def _discover_error(report: dict, effects: list[str]) -> float | None:
    """Discover's held-out error (mg) of the model with these effects beyond offset and scale
    (its base when none; else the step that selected exactly these)."""
    err = report.get("heldout_error_mg") or {}
    extra = sorted(e for e in effects if e not in ("offset", "scale"))
    if not extra:
        return err.get("base")
    chosen: list[str] = []
    for step in report.get("steps") or []:  # each adds or drops one effect
        if step.get("action") == "add":
            chosen.append(step["effect"])
        elif step.get("effect") in chosen:
            chosen.remove(step["effect"])
        if sorted(chosen) == extra:
            return step.get("heldout_after_mg")
    return None


def run_file(path: Path, work: Path) -> dict:
    out, summ, disc = work / f"{path.stem}.mcap", work / f"{path.stem}.json", \
        work / f"{path.stem}.discover.json"
    _recal("replay", str(path), "--out", str(out), "--json", str(summ), "--quiet",
           "--overwrite")
    if not disc.exists():  # discover's report of this file, kept in --keep's folder
        _recal("discover", str(path), "--json", str(disc), "--quiet")
    summary, report = json.loads(summ.read_text()), json.loads(disc.read_text())
    sid, info = next(iter(summary["sensors"].items()))
    cal = rec.read_all_calibrated(out, sid)
    recording = load(path)
    if len(cal) != len(recording.t_us):
        raise SystemExit(f"{path}: {len(cal)} calibrated samples, {len(recording.t_us)} read")
    t0 = int(recording.t_us[0])
    late = recording.t_us >= t0 + HOUR_US
    status = np.asarray(cal.status)
    shares = {s.label: float(np.mean(status[late] == s)) for s in Status if s}
    # still 10 s windows on the file's own readings, judged on the calibrated output
    w = windows(recording)
    n_win = len(w.still)
    is_cal = (status == Status.CALIBRATED).astype(np.float64)
    n = np.bincount(w.index, minlength=n_win).astype(np.float64)
    all_cal = np.bincount(w.index, is_cal, minlength=n_win) == n
    start = np.zeros(n_win, bool)
    start[np.unique(w.index[late])] = True
    use = w.still & all_cal & start
    mean = np.stack([np.bincount(w.index, cal.a_g[:, k], minlength=n_win) for k in range(3)], 1)
    err_mg = 1e3 * np.abs(np.linalg.norm(mean[use] / n[use, None], axis=1) - 1.0)
    events = sorted(((int(ev.get("t_us", ns // 1000)), ev)
                     for _, ev, ns in rec.iter_json(out, "/*/events")
                     if isinstance(ev, dict)), key=lambda x: x[0])
    adopted = [(round((t - t0) / 3.6e9, 2), ev["detail"].get("added"),
                ev["detail"].get("dropped")) for t, ev in events
               if ev.get("kind") == "discovery" and ev["detail"].get("adopted")]
    effects = [] if info["model"] == "diagonal" else info["model"].split("+")
    not_cal = late & (status != Status.CALIBRATED)
    return {
        "file": path.name, "samples_after_1h": int(late.sum()), "shares": shares,
        "still_windows": int(w.still[start].sum()), "calibrated_still_windows": int(use.sum()),
        "still_error_mg": float(np.mean(err_mg)) if len(err_mg) else None,
        "still_error_median_mg": float(np.median(err_mg)) if len(err_mg) else None,
        "misses_mg": info.get("misfit_mg"), "model": info["model"],
        "discover_heldout_mg": _discover_error(report, effects),
        "discover_base_mg": (report.get("heldout_error_mg") or {}).get("base"),
        "discover_selected": [e["label"] for e in report.get("effects_selected") or []],
        "adopted": adopted,
        "not_calibrated_by_reason": _reasons(events, recording.t_us, status, not_cal),
    }


def _lines(r: dict) -> list[str]:
    s = r["shares"]
    out = [f"{r['file']}: after the first hour ({r['samples_after_1h']} samples), model "
           f"{r['model']}",
           "  " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in s.items() if v),
           f"  calibrated still 10 s windows: {r['calibrated_still_windows']} of "
           f"{r['still_windows']}, error mean {_f(r['still_error_mg'])} mg, median "
           f"{_f(r['still_error_median_mg'])} mg",
           f"  misses {_f(r['misses_mg'])} mg; discover held-out of that model "
           f"{_f(r['discover_heldout_mg'])} mg (offsets+gains {_f(r['discover_base_mg'])} mg; "
           f"discover selects {r['discover_selected']})",
           f"  adopted: {r['adopted'] or 'nothing'}",
           "  not calibrated: status, after the latest status event before:"]
    out += [f"    {v:8d}  {k}" for k, v in r["not_calibrated_by_reason"].items()]
    return out


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, help="write the figures here too")
    ap.add_argument("--keep", type=Path, help="keep the outputs in this folder (a discover "
                    "report found there is used again)")
    args = ap.parse_args(argv)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for path in args.files:
            r = run_file(path, work)
            results.append(r)
            print("\n".join(_lines(r)), flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
