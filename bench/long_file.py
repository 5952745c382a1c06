"""A long device file through `recal hindsight`, beside the reader alone and actipy.

    python bench/long_file.py --cache /tmp/week.cwa            # a week at 100 Hz (60.7 M samples)
    python bench/long_file.py --hours 24 --cache /tmp/day.cwa  # a day, for development

The file: a synthetic Axivity AX3 ``.cwa`` at 100 Hz nominal (100.3 Hz real), written by the
tests' device writer (`tests/device_writers.py`) a day at a time (the simulator holds a day in
memory, about 2 GB, never the week) and joined into one file, its sectors numbered on; kept at
``--cache`` and reused when it is there (the same --hours and --seed are assumed).

Each measured in a process of its own, one after the other, under ``nice -n 10``:

* actfast: ``actfast.read`` of the file alone (what any tool reading it in Python pays);
  seconds without the imports, peak memory (VmHWM) with them;
* actipy: ``actipy.read_device`` (its own reader: Java; no low-pass, resampling, calibration or
  non-wear) and then ``actipy.processing.calibrate_gravity`` on what it read, timed apart; in
  its own environment (bench/.venvs/actipy, built by bench/compare_tools.py, or
  ``--actipy-python``);
* recal: ``recal hindsight FILE --json fit.json --quiet``, the calibration alone (no samples
  written), with its default threads (the cores). Timed as the others are, without the
  interpreter's start and the imports: ``recal.cli.main`` called in a process that has
  imported what the command imports (reading, windows, discovery, the fit; the JSON
  written). And, in a process of its own, the whole command (``python -m recal``): its wall
  time and its peak memory (the child's maximum resident set, as ``/usr/bin/time -v``).

Wall seconds, and CPU seconds (user + system of the timed part), which a machine shared with
other work inflates less, but which threads do not shorten.

The goal (a study's folder in bounded memory): recal's time at most actfast's read plus
actipy's calibrate_gravity, its peak at most twice actfast's read alone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from compare_tools import VENV_SPECS, ensure_venv  # noqa: E402

SECTOR_BYTES, HEADER_BYTES = 512, 1024
#: where the sequence counter and the checksum sit in a .cwa data sector (cwa.h)
_SECTOR = np.dtype({"names": ["sequence", "checksum"], "formats": ["<u4", "<u2"],
                    "offsets": [10, 510], "itemsize": SECTOR_BYTES})
DAY_H = 24.0
TIMEOUT_S = 1800

ACTFAST = """
import json, sys, time
import actfast, numpy  # imports are not the reading
t0, c0 = time.perf_counter(), time.process_time()
r = actfast.read(sys.argv[1], lenient=True)
n = len(r["timeseries"]["high_frequency"]["datetime"])
seconds, cpu_s = time.perf_counter() - t0, time.process_time() - c0
hwm = next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM"))
print(json.dumps({"samples": n, "seconds": seconds, "cpu_s": cpu_s, "peak_mib": hwm / 1024}))
"""

ACTIPY = """
import json, sys, time, warnings
import actipy, numpy, pandas
from actipy.processing import calibrate_gravity
warnings.simplefilter("ignore")
t0 = time.perf_counter()
data, _ = actipy.read_device(sys.argv[1], lowpass_hz=None, calibrate_gravity=False,
                             detect_nonwear=False, resample_hz=None, verbose=False)
t1, c1 = time.perf_counter(), time.process_time()
_, info = calibrate_gravity(data)
t2, c2 = time.perf_counter(), time.process_time()
hwm = next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM"))
print(json.dumps({"samples": len(data), "read_s": t1 - t0, "calibrate_s": t2 - t1,
                  "calibrate_cpu_s": c2 - c1,
                  "peak_mib": hwm / 1024, "calibrated": bool(info.get("CalibOK", 0)),
                  "version": actipy.__version__}))
"""

RECAL = """
import json, sys, time
import actfast, scipy.signal, tqdm  # what the command imports, here before the clock starts
import recal.commands.hindsight, recal.io.sources
from recal.cli import main
t0, c0 = time.perf_counter(), time.process_time()
code = main(["hindsight", sys.argv[1], "--json", sys.argv[2], "--quiet"])
print(json.dumps({"code": code, "seconds": time.perf_counter() - t0,
                  "cpu_s": time.process_time() - c0}))
"""


def make_file(path: Path, hours: float, seed: int) -> int:
    """The AX3 file of `hours`, simulated and written a day at a time (module doc); returns
    its samples."""
    sys.path.insert(0, str(ROOT / "tests"))
    from device_writers import _START, DeviceRun, device_signal, write_cwa

    samples, sequence = 0, 0
    tmp_path = path.with_name(path.name + ".part")
    with open(tmp_path, "wb") as out, tempfile.TemporaryDirectory() as tmp:
        day = 0
        while day * DAY_H < hours:
            run = DeviceRun(hours=min(DAY_H, hours - day * DAY_H), nominal_hz=100,
                            real_hz=100.3, seed=seed + day,
                            start=_START + np.timedelta64(int(day * DAY_H * 3600), "s"))
            written = write_cwa(Path(tmp) / "day.cwa", device_signal(run))
            raw = written.path.read_bytes()
            if day == 0:
                out.write(raw[:HEADER_BYTES])
            sectors = np.frombuffer(raw[HEADER_BYTES:], np.uint8).copy()
            table = sectors.view(_SECTOR)
            table["sequence"] = sequence + np.arange(len(table))
            words = sectors.reshape(-1, SECTOR_BYTES // 2, 2).view("<u2")[..., 0]
            table["checksum"] = (-words[:, :-1].sum(axis=1, dtype=np.uint64)) & 0xFFFF
            out.write(sectors.tobytes())
            sequence += len(table)
            samples += len(written.signal)
            day += 1
            print(f"  day {day}: {samples} samples", file=sys.stderr, flush=True)
    tmp_path.replace(path)
    return samples


def _child(argv: list[str]) -> tuple[str, float, float, float]:
    """Run argv under nice; its stdout, wall seconds, CPU seconds (user + system) and peak
    resident memory (MiB: the child's own ru_maxrss, from wait4, as /usr/bin/time -v
    reports it)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(["nice", "-n", "10", *argv], stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
        out.seek(0)
        err.seek(0)
        if proc.returncode != 0:
            tail = err.read().strip().splitlines()[-1:]
            raise RuntimeError(f"{' '.join(argv[:4])} failed ({proc.returncode}): {tail}")
        return out.read(), seconds, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def actipy_python(given: str | None) -> Path:
    """actipy's environment: the one given, else bench/.venvs/actipy (built once)."""
    if given:
        return Path(given)
    venv = next(v for v in VENV_SPECS if v.name == "actipy")
    ok, why = ensure_venv(venv)
    if not ok:
        raise SystemExit(f"actipy's environment could not be built: {why}")
    return venv.python


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=168.0, help="length (default: a week)")
    ap.add_argument("--cache", type=Path, help="the .cwa to make, or reuse when it exists "
                    "(default: a temporary file, removed after)")
    ap.add_argument("--seed", type=int, default=1, help="the simulator's seed of the first day")
    ap.add_argument("--actipy-python", help="python of an environment with actipy")
    ap.add_argument("--skip", nargs="*", default=(), choices=("actfast", "actipy", "recal"),
                    help="tools not measured")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each tool, in turn; the "
                    "median of each figure is reported (default: 3)")
    ap.add_argument("--make", type=Path, help=argparse.SUPPRESS)  # the child that writes it
    a = ap.parse_args()
    if a.make:
        print(f"{make_file(a.make, a.hours, a.seed)} samples", file=sys.stderr)
        return
    with tempfile.TemporaryDirectory(prefix="recal-long-") as tmp:
        path = a.cache or Path(tmp) / "long.cwa"
        if not path.exists():  # in a child: a parent's memory at fork counts in the
            t0 = time.perf_counter()  # children's peak (ru_maxrss), and the simulator's is GBs
            subprocess.run(["nice", "-n", "10", sys.executable, __file__, "--make", str(path),
                            "--hours", str(a.hours), "--seed", str(a.seed)], check=True,
                           timeout=TIMEOUT_S)
            print(f"made {path} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        print(f"{path} ({path.stat().st_size / 1e6:.0f} MB)")
        runs: list[dict[str, dict]] = []
        for r in range(a.repeat):  # the tools in turn, so a load that comes and goes hits all
            runs.append(measure(path, Path(tmp), a))
            print(f"  run {r + 1} of {a.repeat}: " + ", ".join(
                f"{k} {v.get('seconds', v.get('calibrate_s', 0)):.2f} s"
                for k, v in runs[-1].items()), file=sys.stderr)
        rows = median_rows(runs)
    report(rows)


def measure(path: Path, tmp: Path, a: argparse.Namespace) -> dict[str, dict]:
    """One run of each tool not skipped, each in a process of its own."""
    rows: dict[str, dict] = {}
    if "actfast" not in a.skip:
        out, *_ = _child([sys.executable, "-c", ACTFAST, str(path)])
        rows["actfast"] = json.loads(out)
    if "actipy" not in a.skip:
        out, *_ = _child([str(actipy_python(a.actipy_python)), "-c", ACTIPY, str(path)])
        rows["actipy"] = json.loads(out)
    if "recal" not in a.skip:
        fit = tmp / "fit.json"
        out, *_ = _child([sys.executable, "-c", RECAL, str(path), str(fit)])
        timed = json.loads(out.strip().splitlines()[-1])
        _, wall, cpu, peak = _child([sys.executable, "-m", "recal", "hindsight", str(path),
                                     "--json", str(fit), "--quiet"])
        s = json.loads(fit.read_text())
        rows["recal"] = {"samples": s["samples"], "seconds": timed["seconds"],
                         "cpu_s": timed["cpu_s"], "command_s": wall, "command_cpu_s": cpu,
                         "inside_s": s["seconds"], "peak_mib": peak, "windows": s["windows"],
                         "discovery_windows": (s.get("discovery") or {}).get("windows")}
    return rows


def median_rows(runs: list[dict[str, dict]]) -> dict[str, dict]:
    """Each tool's figures, the median over the runs (of each number apart)."""
    out: dict[str, dict] = {}
    for tool, first in runs[0].items():
        out[tool] = {k: (float(np.median([r[tool][k] for r in runs]))
                         if isinstance(v, float) else v) for k, v in first.items()}
    return out


def report(rows: dict[str, dict]) -> None:
    """The table and the goal's two tests, where the measurements allow them."""
    print(json.dumps(rows))
    print(f"{'tool':44} {'samples':>11} {'s':>8} {'CPU s':>8} {'peak MiB':>9}")
    af, ap_, rc = rows.get("actfast"), rows.get("actipy"), rows.get("recal")
    if af:
        print(f"{'actfast.read':44} {af['samples']:>11} {af['seconds']:8.2f} "
              f"{af['cpu_s']:8.2f} {af['peak_mib']:9.0f}")
    if ap_:
        print(f"{'actipy read_device (Java)':44} {ap_['samples']:>11} {ap_['read_s']:8.2f} "
              f"{'':>8} {ap_['peak_mib']:9.0f}")
        print(f"{'actipy calibrate_gravity':44} {'':>11} {ap_['calibrate_s']:8.2f} "
              f"{ap_['calibrate_cpu_s']:8.2f} {'':>9}")
    if rc:
        print(f"{'recal hindsight --json':44} {rc['samples']:>11} "
              f"{rc['seconds']:8.2f} {rc['cpu_s']:8.2f} {'':>9}")
        print(f"{'  the whole command (interpreter, imports)':44} {'':>11} "
              f"{rc['command_s']:8.2f} {rc['command_cpu_s']:8.2f} {rc['peak_mib']:9.0f}")
        print(f"  (after the reading: {rc['inside_s']:.2f} s; fit on {rc['windows']} windows, "
              f"discovery on {rc['discovery_windows']})")
    if af and ap_ and rc:
        budget = af["seconds"] + ap_["calibrate_s"]
        print(f"time: recal {rc['seconds']:.2f} s vs actfast read + actipy calibrate_gravity "
              f"{budget:.2f} s: {'met' if rc['seconds'] <= budget else 'NOT met'}")
        cpu_budget = af["cpu_s"] + ap_["calibrate_cpu_s"]
        print(f"CPU:  recal {rc['cpu_s']:.2f} s vs {cpu_budget:.2f} s (the same sum in CPU "
              f"seconds: a shared machine's load counts less): "
              f"{'met' if rc['cpu_s'] <= cpu_budget else 'NOT met'}")
    if af and rc:
        print(f"memory: recal {rc['peak_mib']:.0f} MiB vs 2 x actfast read "
              f"{2 * af['peak_mib']:.0f} MiB: "
              f"{'met' if rc['peak_mib'] <= 2 * af['peak_mib'] else 'NOT met'}")


if __name__ == "__main__":
    main()
