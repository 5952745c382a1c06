"""The wire path per arrival, old tree beside new: one sample read from a real pty and parsed.

    python bench/wire_arrival.py --old A --new B          # 7 rounds of 4000 arrivals each
    python bench/wire_arrival.py --old A --rounds 3 --arrivals 2000

Why: a sensor handled as it sends costs one `SerialSource.poll` per sample (docs/design.md,
"One sample per arrival"); a restructuring of the wire formats must not make that slower. Per
format ("ascii" lines, "cobs" frames) and tree, a child process (``PYTHONPATH=<tree>/service``,
this interpreter) opens a pty, reads it with `SerialSource` and the format's parser from
`make_parser`, and times two things over --arrivals samples, one sample a time:

    poll   write one encoded sample to the pty's master, `SerialSource.poll(readable=True)`
           (the read, the parse, the error bookkeeping: what the gateway does per arrival)
    feed   `SerialSource._feed` of one encoded sample (the parse and the time-anchor check:
           the part without system calls)

Old and new take turns (A B A B ...) for --rounds rounds; reported: each round's median CPU ns
per arrival (the thread's CPU time), their median and their minimum over the rounds (the
minimum is the least disturbed by other work on a shared machine), and new/old of each.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import tty
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()
NEW_DEFAULT = HERE.parents[1]
FORMATS = ("ascii", "cobs")
AUX = ("temp_c",)


def _encoded(fmt: str, n: int) -> list[bytes]:
    """``n`` samples of ``fmt``, one record each, with the encoders of the tree on the path."""
    import numpy as np

    from recal.samples import RawBatch

    rng = np.random.default_rng(1)
    t_us = 1_000_000 + 10_000 * np.arange(n, dtype=np.int64)
    batch = RawBatch(t_us, rng.integers(-2048, 2048, (n, 3)).astype(float),
                     np.round(rng.normal(25, 1, (n, 1)), 2), AUX)
    if fmt == "ascii":
        from recal.io.ascii_lines import encode_ascii
        return encode_ascii(batch).splitlines(keepends=True)
    from recal.io.cobs_frames import encode_cobs
    frames = encode_cobs(batch).split(b"\x00")[:-1]
    return [f + b"\x00" for f in frames]


def child(fmt: str, arrivals: int) -> dict[str, float]:
    """Time poll and feed per arrival in this process (the tree is on PYTHONPATH)."""
    from recal.io.serial_source import SerialSource
    from recal.io.wire_formats import make_parser

    records = _encoded(fmt, 2 * arrivals + 10)
    master, slave = os.openpty()
    tty.setraw(slave)
    src = SerialSource(os.ttyname(slave), make_parser(fmt, AUX))
    try:
        src.open_now()
        for rec in records[:10]:  # warm up and settle the layout
            os.write(master, rec)
            src.poll(readable=True)
        poll_ns = []
        for rec in records[10:10 + arrivals]:
            os.write(master, rec)
            t0 = time.thread_time_ns()
            batch, _events = src.poll(readable=True)
            poll_ns.append(time.thread_time_ns() - t0)
            assert len(batch) == 1, "one sample per arrival"
        feed_ns = []
        for rec in records[10 + arrivals:]:
            t0 = time.thread_time_ns()
            src._feed(rec)  # the parse step alone (our own code)
            feed_ns.append(time.thread_time_ns() - t0)
    finally:
        src.close()
        os.close(master)
        os.close(slave)
    return {"poll": statistics.median(poll_ns), "feed": statistics.median(feed_ns)}


def _run_child(tree: Path, fmt: str, arrivals: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree / "service")}
    out = subprocess.run([sys.executable, str(HERE), "--child", fmt, "--arrivals",
                          str(arrivals)], env=env, capture_output=True, text=True, check=True,
                         timeout=600)
    return json.loads(out.stdout)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", type=Path, required=False, help="old tree (a checkout)")
    ap.add_argument("--new", type=Path, default=NEW_DEFAULT, help="new tree (default: this one)")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--arrivals", type=int, default=4000)
    ap.add_argument("--child", choices=FORMATS, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child, a.arrivals)))
        return 0
    if a.old is None:
        ap.error("--old is required")
    trees = {"old": a.old, "new": a.new}
    res: dict[tuple[str, str], list[dict[str, float]]] = {}
    for _ in range(a.rounds):
        for fmt in FORMATS:
            for label, tree in trees.items():
                res.setdefault((fmt, label), []).append(_run_child(tree, fmt, a.arrivals))
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}; {a.rounds} rounds "
          f"of {a.arrivals} arrivals; each round's median CPU ns per arrival, then the median "
          f"and the min over rounds\n")
    print("| format | step | old median | new median | new/old | old min | new min | new/old |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for fmt in FORMATS:
        for step in ("poll", "feed"):
            runs = {label: [r[step] for r in res[(fmt, label)]] for label in trees}
            med: dict[str, Any] = {k: statistics.median(v) for k, v in runs.items()}
            low: dict[str, Any] = {k: min(v) for k, v in runs.items()}
            print(f"| {fmt} | {step} | {med['old']:.0f} | {med['new']:.0f} | "
                  f"{med['new'] / med['old']:.3f} | {low['old']:.0f} | {low['new']:.0f} | "
                  f"{low['new'] / low['old']:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
