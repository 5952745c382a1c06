"""Bytes on disk per sample of a live log at 100 Hz, the first (float64, a message per arrival)
form beside the compact, joined one (as it was, and as it is); and what a sample's write costs
the caller in each.

    python bench/log_size.py                # 20 min of a simulated wearer, 5 timing runs
    python bench/log_size.py --minutes 5    # shorter
    python bench/log_size.py --aligned      # from 60 s after the alignment: every topic logged
    python bench/log_size.py --flush-s 2    # the writers flushed every 2 s
    python bench/log_size.py --aligned --old-src OLD_TREE   # + the compact form of another
                                            # tree (a `git archive` of it), same calls

How: a simulated wearer at 100 Hz (recal.sim.wearer defaults, 1024 counts/g, no prior: the node
bootstraps, then calibrates and aligns, so every topic is there) goes through the calibration
node the gateway runs, one sample per arrival; the node's output (raw, calibrated, body, plot,
calibration states, events, setup) is captured once and then written by two writers on the
same injected clock (10 ms per arrival, a flush every second, 32 KiB zstd chunks: the daemon's
settings):

    first form   each batch encoded alone in float64 (`messages.encode_raw`,
                 `encode_calibrated`, as the bus still carries it) and logged as one message
                 (what the writer did before it joined batches)
    compact 10 Hz `RecordingWriter` with batches joined per topic until the next flush, in
                 this tree's compact form with what the second pass changed undone: the plot
                 every 10th sample, sigma kept to the micro-g (`messages.sigma_steps`
                 bypassed), the body's values logged
    compact      as `recal.node.sinks.LoggedBusSink` logs now (the plot at the node's default
                 rate, sigma in 1 % steps, the body as times and a rotation)

Per topic: the same writes with only that topic's messages, each in a file of its own (the
per-topic bytes do not add up to the whole exactly: zstd shares nothing across files).
Timing: microseconds per arrival of write_raw + write_calibrated (calibrated and body) +
write_plot, the log part of what the daemon does per sample, medians of --runs runs.

--old-src: the same captured calls (this tree's node) also written by the writer of another
tree in its compact form, in a child process importing that tree's ``service`` (a column
"old tree" and the ratio compact / old tree); its timing runs alternate with this tree's.
"""

from __future__ import annotations

import argparse
import math
import os
import pickle
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from layout import module
from recal.io import messages
from recal.io.recording_writer import RecordingWriter
from recal.samples import CalibratedBatch, RawBatch

_settings = module("recal.config.settings", "recal.config")
_node = module("recal.node.node", "recal.node")
SensorConfig, ServiceConfig = _settings.SensorConfig, _settings.ServiceConfig
CalibrationNode, node_settings = _node.CalibrationNode, _node.node_settings
BodyRotations = module("recal.node.sinks", "recal.sinks").BodyRotations
simulate = module("recal.sim.wearer", "recal.sim").simulate

RATE_HZ = 100.0
SENSOR = "s1"
T0_NS = 1_700_000_000_000_000_000


class Capture:
    """A node sink that keeps every call: (kind, suffix, payload, log time)."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str, Any, int]] = []

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        self.calls.append(("raw", "raw", batch, log_time_ns))

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        self.calls.append(("calibrated", suffix, batch, log_time_ns))

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        self.calls.append(("plot", "plot", (batch, every_n), log_time_ns))

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        self.calls.append(("json", suffix, obj, log_time_ns))


def capture(minutes: float, seed: int) -> tuple[list[tuple[str, str, Any, int]], int]:
    """The node's output for a simulated wearer, one sample per arrival; (calls, samples)."""
    raw = simulate(minutes / 60.0, RATE_HZ, seed).raw
    sink = Capture()
    node = CalibrationNode(node_settings(SensorConfig(id=SENSOR, rate_hz=RATE_HZ),
                                         ServiceConfig()), sink)
    for i in range(len(raw)):
        b = raw[i:i + 1]
        log_ns = T0_NS + int(b.t_us[0]) * 1000
        sink.raw(SENSOR, b, log_ns)  # the gateway logs the raw batch before the node runs
        node.process(b, log_ns)
    node.flush(T0_NS + int(raw.t_us[-1]) * 1000)
    return sink.calls, len(raw)


class Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


# The plot message as it was before its values became float32: every value a double.
_PLOT_DOUBLES = struct.Struct("<BqBdBdBdBdBBBdBBBd")


def _write_plot_doubles(w: RecordingWriter, batch: CalibratedBatch, log_ns: int, every_n: int,
                        phase: int) -> int:
    """The first form's plot: every ``every_n``-th sample as a message of doubles (the same
    decimation, log and publish times as `RecordingWriter.write_plot`); returns the phase."""
    first = (-phase) % every_n
    last_us = int(batch.t_us[-1])
    for i in range(first, len(batch), every_n):
        x, y, z = (float(v) for v in batch.a_g[i])
        t_us = int(batch.t_us[i])
        data = _PLOT_DOUBLES.pack(1 << 3 | 1, t_us, 2 << 3 | 1, x, 3 << 3 | 1, y, 4 << 3 | 1, z,
                                  5 << 3 | 1, math.sqrt(x * x + y * y + z * z), 6 << 3,
                                  int(batch.quasi_static[i]), 7 << 3 | 1,
                                  float(batch.detector_g[i]), 8 << 3, int(batch.status[i]),
                                  9 << 3 | 1, float(batch.sigma_mg[i]))
        w.write_encoded(f"/{SENSOR}/plot", data, max(log_ns - (last_us - t_us) * 1000, 0),
                        t_us * 1000, schema=messages.PLOT_SCHEMA)
    return (phase + len(batch)) % every_n


FORMS = ("first form", "compact 10 Hz", "compact")
#: The writers' flush interval, s (the daemon's default: 1; --flush-s).
FLUSH_S = 1.0


def write(path: Path, calls: list[tuple[str, str, Any, int]], form: str,
          topics: frozenset[str] | None = None) -> float:
    """Write the captured calls in one of FORMS (only ``topics``' when given); returns
    seconds spent in the writer's calls for raw, calibrated, body and plot."""
    if form != "compact":  # the plot at 10 Hz, as it was
        calls = [(k, s, (p[0], round(RATE_HZ / 10.0)) if k == "plot" else p, t)
                 for k, s, p, t in calls]
    if form != "compact 10 Hz":
        return _write(path, calls, form == "first form", topics)
    steps, messages.sigma_steps = messages.sigma_steps, lambda s: s  # sigma to the micro-g
    try:
        return _write(path, calls, False, topics, body_rotation=False)
    finally:
        messages.sigma_steps = steps


def _write(path: Path, calls: list[tuple[str, str, Any, int]], first_form: bool,
           topics: frozenset[str] | None, body_rotation: bool = True) -> float:
    """`write`: the first form, or the compact one as `recal.node.sinks.LoggedBusSink` writes it
    (``body_rotation``: the body as times and a rotation when the calibrated batch and the
    alignment give it, else as its values)."""
    clock = Clock()
    w = RecordingWriter(path, clock=clock, background_flush=False, fsync=False,
                        overwrite=True, log_batch_samples=1 if first_form else 8192)
    rotations = BodyRotations() if body_rotation and not first_form else None
    spent = 0.0
    plot_phase = 0
    t_first = calls[0][3]
    for kind, suffix, payload, log_ns in calls:
        if rotations is not None and kind in ("json", "note"):  # (seen whatever is written)
            rotations.note_json(SENSOR, suffix, payload)
        if kind == "note":  # (`aligned`: what came before, seen but not written)
            continue
        elif rotations is not None and (kind, suffix) == ("calibrated", "calibrated"):
            rotations.note_calibrated(SENSOR, payload)
        if topics is not None and suffix not in topics:
            continue
        clock.now_s = (log_ns - t_first) / 1e9 / FLUSH_S
        t = time.perf_counter()
        if kind == "raw":
            if first_form:
                w.write_encoded(f"/{SENSOR}/raw", messages.encode_raw(SENSOR, payload), log_ns,
                                int(payload.t_us[0]) * 1000)
            else:
                w.write_raw(SENSOR, payload, log_ns)
        elif kind == "calibrated":
            found = (rotations.of(SENSOR, payload) if rotations is not None
                     and suffix == "body" else None)
            if first_form:
                w.write_encoded(f"/{SENSOR}/{suffix}",
                                messages.encode_calibrated(SENSOR, payload), log_ns,
                                int(payload.t_us[0]) * 1000, schema=messages.CALIBRATED_SCHEMA)
            elif found is not None:  # as LoggedBusSink: the log the rotation, the bus values
                w.log_body(SENSOR, found[0], found[1], log_ns)
                messages.encode_calibrated(SENSOR, payload)
            else:
                w.write_calibrated(SENSOR, payload, log_ns, suffix)
        elif kind == "plot":
            if first_form:
                plot_phase = _write_plot_doubles(w, payload[0], log_ns, payload[1], plot_phase)
            else:
                w.write_plot(SENSOR, payload[0], log_ns, payload[1])
        else:
            w.write_json(f"/{SENSOR}/{suffix}", payload, log_ns)
        if kind != "json":
            spent += time.perf_counter() - t
    w.close()
    return spent


GROUPS: list[tuple[str, frozenset[str] | None]] = [
    ("everything", None), ("raw", frozenset({"raw"})),
    ("calibrated", frozenset({"calibrated"})), ("body", frozenset({"body"})),
    ("plot", frozenset({"plot"})),
    ("states, events, setup", frozenset({"calibration", "events", "setup"}))]


def sizes(tmp: Path, calls: list, samples: int) -> list[tuple[Any, ...]]:
    rows: list[tuple[Any, ...]] = []
    for name, topics in GROUPS:
        per = []
        for form in FORMS:
            path = tmp / f"{name.split(',')[0]}-{form}.mcap"
            write(path, calls, form, topics)
            per.append(path.stat().st_size / samples)
        rows.append((name, *per))
    return rows


def timing(tmp: Path, calls: list, samples: int, runs: int,
           old: Callable[[], float] | None = None) -> list[float]:
    """Median microseconds per arrival in the writer, per form of FORMS (and of ``old``: the
    seconds of one write by another tree, run beside them in every run)."""
    times: dict[str, list[float]] = {form: [] for form in (*FORMS, "old tree")}
    for _ in range(runs):
        for form in FORMS:  # side by side in every run
            spent = write(tmp / "t.mcap", calls, form)
            times[form].append(spent / samples * 1e6)
        if old is not None:
            times["old tree"].append(old() / samples * 1e6)
    return [statistics.median(times[form]) for form in (*FORMS, "old tree")
            if times[form]]


def _old_tree(tree: Path, pickled: Path, tmp: Path, topics: frozenset[str] | None
              ) -> tuple[float, float]:
    """(bytes per sample, writer seconds) of the pickled calls written in the compact form by
    the tree at ``tree`` (its ``service`` first on the path, in a child process)."""
    out = tmp / "old.mcap"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tree / "service"), os.environ.get("PYTHONPATH", "")])}
    args = [sys.executable, __file__, "--child", str(pickled), str(out),
            ",".join(sorted(topics)) if topics is not None else "*"]
    done = subprocess.run(args, env=env, check=True, capture_output=True, text=True)
    spent, recal_file = done.stdout.split()
    if not Path(recal_file).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"the child imported {recal_file}, not the tree at {tree}")
    samples = pickle.loads(pickled.read_bytes())[1]
    return out.stat().st_size / samples, float(spent)


def _child(argv: list[str]) -> int:
    """--child PICKLE OUT TOPICS: write the pickled calls in the compact form; print the
    writer's seconds and the recal package written with."""
    import recal

    pickled, out, topics = argv
    calls, _ = pickle.loads(Path(pickled).read_bytes())
    spent = write(Path(out), calls, "compact",
                  None if topics == "*" else frozenset(topics.split(",")))
    print(spent, recal.__file__)
    return 0


def encode_one_us(calls: list, repeat: int = 20000) -> tuple[float, float]:
    """Microseconds to encode one 1-sample calibrated batch: float64 (the bus's) and compact."""
    one = next(p for k, s, p, _ in calls if k == "calibrated" and s == "calibrated"
               and len(p) == 1 and p.recorded)
    out = []
    fn: Callable[[str, CalibratedBatch], bytes]
    for fn in (messages.encode_calibrated, messages.encode_calibrated_compact):
        best = []
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(repeat):
                fn(SENSOR, one)
            best.append((time.perf_counter() - t) / repeat * 1e6)
        out.append(statistics.median(best))
    return out[0], out[1]


def aligned(calls: list[tuple[str, str, Any, int]]) -> tuple[list[tuple[str, str, Any, int]],
                                                               int]:
    """The calls from 60 s after the node's first body batch on, and their raw samples. The
    setup, states and events before are not written (a few bytes) but still seen, as
    "note" calls: the sink learns the alignment's rotation from them, as the daemon's did
    (without them every body batch of the steady state would be logged as its values)."""
    first = next(t for k, s, _, t in calls if (k, s) == ("calibrated", "body"))
    cut = first + 60 * 10**9
    kept = [c for c in calls if c[3] >= cut]
    if not kept:
        raise SystemExit("no body batch 60 s before the end: run longer (--minutes)")
    notes = [("note", s, p, kept[0][3]) for k, s, p, t in calls if k == "json" and t < cut]
    return notes + kept, sum(len(p) for k, _, p, _ in kept if k == "raw")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        return _child(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--aligned", action="store_true",
                    help="write only what the node gave from 60 s after its first body batch "
                         "on (every topic present: the steady state)")
    ap.add_argument("--flush-s", type=float, default=1.0,
                    help="the writers' flush interval, s (default 1, the daemon's)")
    ap.add_argument("--old-src", type=Path, default=None,
                    help="a tree (with service/) whose compact form is written beside")
    a = ap.parse_args(argv)
    global FLUSH_S
    FLUSH_S = a.flush_s
    print(f"load average before: {os.getloadavg()[0]:.2f}", file=sys.stderr)
    calls, samples = capture(a.minutes, a.seed)
    if a.aligned:
        calls, samples = aligned(calls)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = sizes(tmp, calls, samples)
        old: Callable[[], float] | None = None
        if a.old_src is not None:
            pickled = tmp / "calls.pkl"
            pickled.write_bytes(pickle.dumps((calls, samples)))
            old_rows = [_old_tree(a.old_src, pickled, tmp, topics)[0]
                        for _, topics in GROUPS]
            rows = [(*row, o) for row, o in zip(rows, old_rows, strict=True)]

            def old() -> float:
                return _old_tree(a.old_src, pickled, tmp, None)[1]
        first_us, before_us, compact_us, *old_us = timing(tmp, calls, samples, a.runs, old)
    enc_old, enc_new = encode_one_us(calls)
    part = " (from 60 s after the alignment)" if a.aligned else ""
    print(f"{a.minutes:g} min at {RATE_HZ:g} Hz{part}, one sample per arrival ({samples} "
          f"samples), zstd, 32 KiB chunks, flush every {a.flush_s:g} s\n")
    extra = " old tree, B/sample | compact / old tree |" if a.old_src is not None else ""
    print("| topics | first form, B/sample | compact 10 Hz, B/sample | compact, B/sample | "
          "compact / compact 10 Hz |" + extra)
    print("|---|---:|---:|---:|---:|" + ("---:|---:|" if extra else ""))
    for name, first, before, new, *tree in rows:
        cells = [f"{first:.2f}", f"{before:.2f}", f"{new:.2f}", f"{new / before:.3f}",
                 *(f"{v:.2f} | {new / v:.3f}" for v in tree)]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print(f"\nwriter per arrival (raw, calibrated, body, plot): first form {first_us:.1f} us, "
          f"compact 10 Hz {before_us:.1f} us, compact {compact_us:.1f} us (medians of "
          f"{a.runs})" + (f"; old tree {old_us[0]:.1f} us" if old_us else ""))
    print(f"encoding one 1-sample CalibratedBatch: float64 (the bus's) {enc_old:.2f} us, "
          f"compact {enc_new:.2f} us")
    print(f"load average after: {os.getloadavg()[0]:.2f}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
