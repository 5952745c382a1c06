"""How long `recal run` takes to be ready, and its memory then and after a minute of data.

For each of --runs starts: a pseudo-terminal for one 100 Hz sensor, a config for it (MCAP in a
temporary folder, checkpoints there, Zenoh a peer on a free 127.0.0.1 port), and `recal run`
as a child process of this interpreter. Measured:

* ready: wall time from the start of the child to its "recal gateway ready" line (the imports,
  the bus, the recording, the port: everything before the first sample can be handled);
* RSS at ready, and after --seconds of samples written to the pty at 100 Hz (VmRSS from
  /proc/<pid>/status);
* the floor beside it: a bare `python -c "import numpy, zenoh, mcap, serial"`, started and timed
  the same way (the libraries the daemon cannot do without), and `python -c pass`.

Medians of --runs. Each start is its own process, so nothing is warm but the OS file cache.

    python bench/start_time.py                  # 5 runs, 10 s of samples each
    python bench/start_time.py --runs 3 --seconds 3
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

READY = "recal gateway ready"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def config(tmp: Path, port: str) -> Path:
    path = tmp / "gateway.toml"
    path.write_text(f"""[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{free_port()}"]

[mcap]
dir = "{tmp / 'rec'}"

[checkpoint]
dir = "{tmp / 'ck'}"

[[sensors]]
id = "s1"
port = "{port}"
aux_names = []
rate_hz = 100.0
prior = {{ counts_per_g = 1024.0, zero_g = 0 }}
""")
    return path


def read_line_until(proc: subprocess.Popen[str], prefix: str, timeout_s: float) -> bool:
    """Read the child's output until a line starts with ``prefix`` (False at EOF/timeout)."""
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            return False
        if line.startswith(prefix):
            return True
    return False


def one_daemon(seconds: float) -> tuple[float, float, float]:
    """(seconds to ready, RSS MB at ready, RSS MB after ``seconds`` of 100 Hz samples)."""
    with tempfile.TemporaryDirectory(prefix="recal-start-") as d:
        tmp = Path(d)
        master, slave = os.openpty()
        try:
            cfg = config(tmp, os.ttyname(slave))
            t0 = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-m", "recal", "run", "--config", str(cfg)],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
            try:
                if not read_line_until(proc, READY, 60.0):
                    raise SystemExit("recal run did not get ready")
                ready_s = time.perf_counter() - t0
                rss_ready = rss_mb(proc.pid)
                for i in range(round(seconds * 100)):
                    os.write(master, f"{i * 10000},3,-5,{1024 + i % 3}\n".encode())
                    time.sleep(0.01)
                rss_later = rss_mb(proc.pid)
            finally:
                proc.terminate()
                proc.wait(30)
        finally:
            os.close(master)
            os.close(slave)
    return ready_s, rss_ready, rss_later


def floor(code: str) -> tuple[float, float]:
    """(seconds, peak RSS MB) of ``python -c code``."""
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code + "\nimport resource\n"
                          "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"],
                         capture_output=True, text=True, check=True, timeout=120)
    return time.perf_counter() - t0, int(out.stdout.split()[-1]) / 1024


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=10.0, help="samples after ready, s")
    a = ap.parse_args()
    daemon = [one_daemon(a.seconds) for _ in range(a.runs)]
    libs = [floor("import numpy, zenoh, mcap, serial") for _ in range(a.runs)]
    bare = [floor("pass") for _ in range(a.runs)]
    med = statistics.median
    print(f"# start_time: {a.runs} runs, {a.seconds:g} s of 100 Hz samples; medians")
    print("| what | seconds to ready | RSS MB at ready | RSS MB after samples |")
    print("|---|---|---|---|")
    print(f"| recal run, one sensor | {med(r[0] for r in daemon):.2f} | "
          f"{med(r[1] for r in daemon):.0f} | {med(r[2] for r in daemon):.0f} |")
    print(f"| python + numpy, zenoh, mcap, serial | {med(r[0] for r in libs):.2f} | "
          f"{med(r[1] for r in libs):.0f} (peak) | |")
    print(f"| python -c pass | {med(r[0] for r in bare):.2f} | {med(r[1] for r in bare):.0f} "
          f"(peak) | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
