"""Run the quick benches one after the other, each in a process of its own, and say which failed.

    python bench/quick.py                 # every quick run below (8.5 min on 2 cores at load 10)
    python bench/quick.py sigma honesty   # only those whose command contains a word given

Each entry is a maintained bench with its shortest settings (bench/README.md lists them all,
with their full commands). The benches print their own tables; this prints one line per bench
with its wall time and exit status, and exits 1 if any failed. Figures from these short runs
are for trying a change, not for docs/performance.md.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
DEVICES = BENCH.parent.parent / "shared" / "data" / "devices"

#: (script, arguments): the quick settings of each bench that has them
QUICK: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("in_use_accuracy.py", ("--quick",)),
    ("sigma_honesty.py", ("--quick",)),
    ("hindsight_honesty.py", ("--hours", "1")),
    ("sigma_tightness.py", ("--minutes", "20", "--seeds", "1")),
    ("discovery_selection.py", ("--quick",)),
    ("sensor_types.py", ("--quick",)),
    ("device_clocks.py", ("--seeds", "1")),
    ("status_watch.py", ("--pairs", "2")),
    ("tilt_alarm.py", ("--seeds", "2", "--hours", "1")),
    ("core_speed.py", ("--case", "plain", "--hours", "1", "--runs", "1")),
    ("pending_cost.py", ("--samples", "2000", "--runs", "1")),
    ("node_arrival.py", ("--part", "node", "--samples", "2000", "--runs", "1")),
    ("checkpoint_cost.py", ("--runs", "5")),
    ("log_size.py", ("--minutes", "5", "--runs", "1")),
    ("start_time.py", ("--runs", "1", "--seconds", "3")),
    ("replay_throughput.py", ("--quick",)),
    ("gt3x_speed.py", ("--hours", "1", "--repeats", "1")),
    ("device_files_read.py", tuple(str(p) for p in sorted(DEVICES.glob("*.cwa"))[:1])),
    ("rogue_ids.py", ("--ids", "20")),
)


def main(words: list[str]) -> int:
    failed: list[str] = []
    for script, args in QUICK:
        line = " ".join(["python", f"bench/{script}", *args])
        if words and not any(w in line for w in words):
            continue
        if script == "device_files_read.py" and not args:
            print(f"--- {script}: skipped, no device file under {DEVICES}", flush=True)
            continue
        print(f"--- {line}", flush=True)
        t0 = time.perf_counter()
        cmd = [sys.executable, str(BENCH / script), *args]
        rc = subprocess.run(cmd, cwd=BENCH.parent).returncode
        print(f"--- {script}: exit {rc}, {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(script)
    print(f"quick benches failed: {failed}" if failed else "quick benches: all ran")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
