"""Reading a device file: time and peak memory of ``actfast.read`` alone beside recal's
``open_device`` and a pass over every batch (true times, float64 values, aux columns), each in
a fresh process, so what recal adds to the reader is measured on the same file.

    python bench/device_files_read.py ../shared/data/devices/*.cwa FILE.cwa ...

Prints one line per file: samples, seconds (imports left out) and peak RSS (MiB, imports in)
of each, and the difference.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

CHILD = """
import json, resource, sys, time
path, what = sys.argv[1], sys.argv[2]
import actfast, numpy  # imports are not the reading
if what != "actfast":
    from recal.io.device_files import open_device
t0 = time.perf_counter()
if what == "actfast":
    r = actfast.read(path, lenient=True)
    ts = r["timeseries"]
    n = len((ts.get("high_frequency") or ts.get("acceleration"))["datetime"])
else:
    rec = open_device(path)
    n = sum(len(b) for b in rec.batches())
seconds = time.perf_counter() - t0
rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"samples": n, "seconds": seconds, "rss_mib": rss_mib}))
"""


def measure(path: Path, what: str) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, str(path), what], check=True,
                          capture_output=True, text=True, timeout=600)
    return json.loads(done.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", type=Path)
    a = ap.parse_args()
    print(f"{'file':36} {'samples':>10} {'actfast s':>9} {'MiB':>6} {'recal s':>8} {'MiB':>6} "
          f"{'+s':>6} {'+MiB':>6}")
    for path in a.files:
        af, rc = measure(path, "actfast"), measure(path, "recal")
        print(f"{path.name[:36]:36} {rc['samples']:>10} {af['seconds']:9.2f} "
              f"{af['rss_mib']:6.0f} {rc['seconds']:8.2f} {rc['rss_mib']:6.0f} "
              f"{rc['seconds'] - af['seconds']:6.2f} {rc['rss_mib'] - af['rss_mib']:6.0f}")


if __name__ == "__main__":
    main()
