"""Old vs new, bit for bit: the same cases run with two source trees, their outputs compared.

    python bench/regression_check.py                    # old /work/wt/base, new: this checkout
    python bench/regression_check.py --old A --new B --sim-hours 1 --core-hours 1   # quicker

Why: the service is restructured with behaviour unchanged; this is the proof that a change in
module layout left every output as it was (docs/design.md). A tree is a checkout whose
`service/` holds the `recal` package; each tree's code runs in its own subprocesses with
``PYTHONPATH=<tree>/service`` under this interpreter, in its own work directory, on the same
input files. The command line (``python -m recal ...``) is used wherever it can be, so that
modules may move; the core case tries the new names first, then the old ones.

The log's batch topics (RawBatch, CalibratedBatch) are compared as their decoded samples joined
per topic (the message boundaries and the bytes are the log format's), integers and raw
readings exactly, calibrated values and the detector within half a micro-g and sigma within a
micro-g in mg plus half a percent (the compact form's fixed point, sigma's 1 % steps), the
protobuf schemas by name. A plot message's values (float32 in the log, double before) are
compared rounded to float32. Compared exactly otherwise (floats bit for bit): every other MCAP
message, topic by topic in its order, by log and publish time, schema and payload bytes (the
file's bytes may differ only in its metadata records, which are named); JSON key by key
(timings "seconds" and "samples_per_s" left out; when not identical the largest relative
difference is shown); CSV and stdout byte for byte; arrays bit for bit (else the largest
absolute difference). Exit status 0 only if every case is identical, or within the tolerance
`--tolerate NAME=ABS` grants the arrays and JSON numbers called NAME where a change is known to
move their last bits (say so with the result):

    python bench/regression_check.py --tolerate detector_g=1e-12 --tolerate zi_hp=1e-12 \
        --tolerate zi_lp=1e-12     # a new filter design: the detector's output may move


A body topic in the log's form (the samples' times and a rotation) is compared as the
calibrated samples at those times turned by it, within 1.37 micro-g of an older tree's body
(its values rounded to the micro-g, the new ones the calibrated micro-g turned).

The default plot rate went from 10 Hz to 2 Hz: against a tree from before, pass
``--plot-hz 2`` (each tree's replay then reads a config that sets it) so that the plot topics
can be compared message for message.

Cases (group names for --only): recordings: `recal replay` of recordings/wearer-10min.mcap and
wearer-temp-30min.mcap; sim: `recal simulate` (--sim-hours at 50 Hz) per sensor of --sensors,
each tree's file compared, then both replay the old tree's (which both can read); core:
`Pipeline.step` over a --core-hours simulation in batches of --batch, and --group batches per
call (`step_many`, or the old `step(marks=)`); discover: `recal discover --json --write-model`
and `recal hindsight` (MCAP, JSON, CSV) of wearer-temp-30min.mcap; static: `recal static` of a
phone table of the measured data (unknown and known orientations); real: the measured Xsens and
GENEActiv arrays as CSV through `recal import`, then `recal discover` of the import.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

HERE = Path(__file__).resolve()
NEW_DEFAULT = HERE.parents[1]
OLD_DEFAULT = Path("/work/wt/base")
SHARED_DATA = NEW_DEFAULT.parent / "shared" / "data"  # the measured data, beside the checkout
#: JSON keys that are wall-clock timings, not outputs
TIMING_KEYS = frozenset({"seconds", "samples_per_s"})
#: simulate arguments per sensor case: the default (ADC counts), floats, an unsigned analog part
SENSORS: dict[str, list[str]] = {
    "default": [],
    "phone-ms2": ["--sensor-type", "phone-ms2"],
    "g": ["--counts-per-g", "0"],
    "digital-2g": ["--sensor-type", "digital-2g"],
    "adxl335-adc12": ["--sensor-type", "adxl335-adc12"],
}
DEFAULT_SENSORS = "default,phone-ms2,g,adxl335-adc12"
#: core variants: (sensor case, with a datasheet prior?)
CORE_VARIANTS = ("default-bootstrap", "default-prior", "phone-ms2-bootstrap")


# --- running a tree ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Tree:
    """One source tree, run in subprocesses with its own `recal` package first on the path."""

    label: str
    root: Path
    python: str = sys.executable

    def env(self) -> dict[str, str]:
        return {**os.environ, "PYTHONPATH": str(self.root / "service"), "PYTHONHASHSEED": "0"}

    def run(self, argv: list[str], cwd: Path, timeout_s: float = 1800
            ) -> subprocess.CompletedProcess[str]:
        return subprocess.run([self.python, *argv], cwd=cwd, env=self.env(), text=True,
                              capture_output=True, timeout=timeout_s, check=False)

    def recal(self, args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
        return self.run(["-m", "recal", *args], cwd)

    def child(self, name: str, args: dict[str, Any], cwd: Path
              ) -> subprocess.CompletedProcess[str]:
        return self.run([str(HERE), "--child", name, json.dumps(args)], cwd)

    def check(self, cwd: Path) -> str:
        """The `recal` package this tree's subprocesses import (must be the tree's own)."""
        r = self.run(["-c", "import recal; print(recal.__file__)"], cwd)
        where = Path(r.stdout.strip()).resolve()
        if r.returncode or not where.is_relative_to((self.root / "service").resolve()):
            raise SystemExit(f"{self.label} tree {self.root}: imports recal from "
                             f"{where or r.stderr.strip()}, not from its own service/")
        return str(where)

    def commit(self) -> str:
        r = subprocess.run(["git", "-C", str(self.root), "rev-parse", "--short", "HEAD"],
                           capture_output=True, text=True, check=False)
        dirty = subprocess.run(["git", "-C", str(self.root), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               check=False).stdout.strip()
        return (r.stdout.strip() or "?") + ("+dirty" if dirty else "")


class CommandFailed(Exception):
    """A command failed in one of the trees: the case cannot be compared."""


def ok_or_raise(tree: Tree, r: subprocess.CompletedProcess[str], what: str) -> str:
    if r.returncode != 0:
        tail = " | ".join((r.stderr.strip() or r.stdout.strip()).splitlines()[-3:])
        raise CommandFailed(f"{tree.label}: {what} exit {r.returncode}: {tail[:400]}")
    return r.stdout


# --- comparing ---------------------------------------------------------------------------------
#: name of an array or JSON key -> the largest absolute difference accepted (--tolerate);
#: empty: everything bit for bit.
TOLERATE: dict[str, float] = {}
#: how a verdict within TOLERATE begins
WITHIN = "within tolerance"


@dataclass
class Row:
    case: str
    compared: str
    verdict: str = "identical"

    @property
    def ok(self) -> bool:
        return self.verdict == "identical" or self.verdict.startswith(WITHIN)


def _rel(a: float, b: float) -> float:
    if a == b or (math.isnan(a) and math.isnan(b)):
        return 0.0
    scale = max(abs(a), abs(b))
    return math.inf if not math.isfinite(scale) else abs(a - b) / scale if scale else 0.0


def _same_float(a: float, b: float) -> bool:
    return (a == b and math.copysign(1, a) == math.copysign(1, b)) or (
        math.isnan(a) and math.isnan(b))


def _tolerance(path: str) -> float | None:
    """The tolerance for the JSON number at ``path`` (any of its keys in TOLERATE)."""
    keys = [k for k in re.split(r"[/\[\]]", path) if k in TOLERATE]
    return TOLERATE[keys[-1]] if keys else None


def json_diff(a: Any, b: Any, path: str = "", within: list[str] | None = None
              ) -> tuple[list[str], float]:
    """(differences as "path: what", the largest relative difference of numbers) of two
    JSON values, key by key; floats must be equal bit for bit (NaN equals NaN), but for those
    under a key in TOLERATE, whose differences within it are noted in ``within``."""
    diffs: list[str] = []
    worst = 0.0

    def walk(x: Any, y: Any, p: str) -> None:
        nonlocal worst
        if isinstance(x, dict) and isinstance(y, dict):
            keys = [k for k in x if k not in TIMING_KEYS] + [
                k for k in y if k not in x and k not in TIMING_KEYS]
            for k in keys:
                if k not in x or k not in y:
                    diffs.append(f"{p}/{k}: only in {'new' if k in y else 'old'}")
                else:
                    walk(x[k], y[k], f"{p}/{k}")
            if not diffs and [k for k in x if k in y] != [k for k in y if k in x]:
                diffs.append(f"{p or '/'}: key order differs")
        elif isinstance(x, list) and isinstance(y, list):
            if len(x) != len(y):
                diffs.append(f"{p}: {len(x)} vs {len(y)} items")
            for i, (u, v) in enumerate(zip(x, y, strict=False)):
                walk(u, v, f"{p}[{i}]")
        elif (isinstance(x, (int, float)) and isinstance(y, (int, float))
              and not isinstance(x, bool) and not isinstance(y, bool)):
            if type(x) is not type(y) or not _same_float(float(x), float(y)):
                tol = _tolerance(p)
                if (within is not None and tol is not None and type(x) is type(y)
                        and abs(float(x) - float(y)) <= tol):
                    within.append(f"{p}: {x!r} vs {y!r}")
                    return
                worst = max(worst, _rel(float(x), float(y)))
                diffs.append(f"{p}: {x!r} vs {y!r}")
        elif x != y or type(x) is not type(y):
            diffs.append(f"{p}: {_short(x)} vs {_short(y)}")

    walk(a, b, path)
    return diffs, worst


def _short(x: Any) -> str:
    s = repr(x)
    return s if len(s) <= 60 else s[:57] + "..."


def json_verdict(a: Any, b: Any) -> str:
    within: list[str] = []
    diffs, worst = json_diff(a, b, within=within)
    if not diffs and within:
        return f"{WITHIN}: {len(within)} numbers, first {within[0]}"
    if not diffs:
        return "identical"
    rel = f"; max rel diff {worst:.3g}" if worst else ""
    return f"{len(diffs)} differences, first {diffs[0]}{rel}"


def array_verdict(name: str, a: np.ndarray, b: np.ndarray) -> str:
    """'identical' (same dtype, shape and bytes: NaN and -0.0 included) or the difference."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return f"{name}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
    if a.tobytes() == b.tobytes():
        return "identical"
    a, b = np.atleast_1d(a), np.atleast_1d(b)
    flat_a, flat_b = a.reshape(len(a), -1), b.reshape(len(b), -1)
    differ = ~((flat_a == flat_b) | (_isnan(flat_a) & _isnan(flat_b)))
    rows = np.flatnonzero(differ.any(axis=1))
    first = int(rows[0]) if len(rows) else 0
    text = f"{name}: {len(rows)} of {len(a)} rows differ, first at row {first}"
    if a.dtype.kind in "fiu" and len(rows):
        d = np.abs(flat_a.astype(np.float64) - flat_b.astype(np.float64))[differ]
        worst = float(np.nanmax(d) if np.isfinite(d).any() else d.max())
        text += f"; max abs diff {worst:.3g}"
        if name in TOLERATE and worst <= TOLERATE[name]:  # NaN where the other is not: > tol
            return f"{WITHIN}: {text}"
    return text


def first_verdict(verdicts: Iterable[str]) -> str:
    """The first verdict neither identical nor within tolerance; else the first within, else
    identical."""
    within = ""
    for v in verdicts:
        if v.startswith(WITHIN):
            within = within or v
        elif v != "identical":
            return v
    return within or "identical"


def _isnan(x: np.ndarray) -> np.ndarray:
    return np.isnan(x) if x.dtype.kind == "f" else np.zeros(x.shape, bool)


def npz_verdict(a: Path, b: Path) -> str:
    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        if sorted(za.files) != sorted(zb.files):
            return f"arrays {sorted(za.files)} vs {sorted(zb.files)}"
        return first_verdict(array_verdict(k, za[k], zb[k]) for k in za.files)


@dataclass(frozen=True)
class McapContent:
    library: str
    metadata: dict[str, dict[str, str]]
    #: topic, log time, publish time, schema name, message encoding, sequence, payload
    messages: list[tuple[str, int, int, str, str, int, bytes]]
    #: per topic: message encoding, channel metadata, schema name, encoding and data
    channels: dict[str, tuple]


def read_mcap(path: Path) -> McapContent:
    with open(path, "rb") as f:
        r = make_reader(f)
        library = r.get_header().library
        meta = {m.name: dict(m.metadata) for m in r.iter_metadata()}
        msgs, channels = [], {}
        for s, c, m in r.iter_messages(log_time_order=False):
            msgs.append((c.topic, m.log_time, m.publish_time, s.name if s else "",
                         c.message_encoding, m.sequence, bytes(m.data)))
            if c.topic not in channels:
                channels[c.topic] = (c.message_encoding, sorted(c.metadata.items()),
                                     *((s.name, s.encoding, bytes(s.data)) if s else ()))
    return McapContent(library, meta, msgs, channels)


#: The log's batch topics are compared as decoded samples, not as messages: the compact form
#: joins a flush interval's batches into one message and keeps calibrated values to the
#: micro-g (rounded: half a micro-g at most), the detector in 2 micro-g steps (one micro-g at
#: most) and sigma on 1 % steps; its body messages are the
#: calibrated samples turned (times and a rotation), compared as those samples. Everything
#: else stays exact.
BATCH_SCHEMAS = ("recal.RawBatch", "recal.CalibratedBatch")
FORMAT_TOL = {"a_g": 0.5e-6 + 1e-12, "detector_g": 1e-6 + 1e-12,  # (2 micro-g steps)
              "sigma_mg": 1e-3 + 1e-12}  # sigma is in mg (each tree rounds it to the micro-g)
#: The body's values: the calibrated micro-g turned (0.87 micro-g at most from the exact
#: body) against an older tree's body rounded to the micro-g (0.5).
FORMAT_TOL_BODY = {"a_g": 1.37e-6 + 1e-12}
#: ... plus this fraction of the larger value: the log keeps sigma in 1 % steps (half a step
#: off at most, `messages.sigma_steps`), where an older tree kept it to the micro-g.
FORMAT_REL = {"sigma_mg": 0.005 + 1e-12}
BATCH_COLUMNS = ("t_us", "v", "aux", "a_g", "quasi_static", "detector_g", "status",
                 "sigma_mg", "t_dev")


def _joined_batches(content: McapContent, topic: str) -> dict[str, np.ndarray]:
    """A batch topic's samples, decoded (by the new tree's decoder, which reads both forms)
    and joined across messages."""
    from recal.io import messages
    batches = []
    calibrated = None
    for m in content.messages:
        if m[0] != topic:
            continue
        rotated = (getattr(messages, "decode_body_rotation", lambda _: None)(m[6])
                   if "alibrated" in m[3] else None)
        if rotated is not None:  # the log's body: the calibrated topic's samples, turned
            if calibrated is None:
                calibrated = _joined_batches(content, topic.rsplit("/", 1)[0] + "/calibrated")
            batches.append(_rotated(calibrated, rotated[1], rotated[2]))
            continue
        decode = messages.decode_calibrated if "alibrated" in m[3] else messages.decode_raw
        batches.append(decode(m[6])[1])
    cols: dict[str, np.ndarray] = {}
    for name in BATCH_COLUMNS:
        parts = [getattr(b, name) for b in batches if getattr(b, name, None) is not None]
        if parts and len(parts) == len(batches):
            cols[name] = np.concatenate(parts)
    return cols


def _rotated(cal: dict[str, np.ndarray], t_us: np.ndarray, rotation: np.ndarray) -> Any:
    """A body message of the log's form as a batch: the calibrated columns at its times, the
    values turned by its rotation (R @ a)."""
    from types import SimpleNamespace
    i = np.searchsorted(cal["t_us"], t_us)
    if len(t_us) and (i[-1] >= len(cal["t_us"]) or not np.array_equal(cal["t_us"][i], t_us)):
        raise ValueError("a body message names samples the calibrated topic does not have")
    cols = {name: (v[i] if v is not None else None) for name, v in cal.items()}
    cols["a_g"] = cols["a_g"] @ np.asarray(rotation).T
    return SimpleNamespace(**{name: cols.get(name) for name in BATCH_COLUMNS})


def batch_topics_verdict(ca: McapContent, cb: McapContent) -> str:
    """The batch topics sample by sample: exact, or within the log format's fixed point."""
    topics = sorted({m[0] for m in ca.messages + cb.messages if m[3] in BATCH_SCHEMAS})
    notes = []
    for topic in topics:
        xa, xb = _joined_batches(ca, topic), _joined_batches(cb, topic)
        if sorted(xa) != sorted(xb):
            return f"{topic}: columns {sorted(xa)} vs {sorted(xb)}"
        for name in xa:
            if xa[name].shape != xb[name].shape:
                return f"{topic} {name}: shape {xa[name].shape} vs {xb[name].shape}"
            if np.array_equal(xa[name], xb[name], equal_nan=xa[name].dtype.kind == "f"):
                continue
            tol = (FORMAT_TOL_BODY if topic.endswith("/body") else FORMAT_TOL).get(
                name, FORMAT_TOL.get(name))
            a, b = xa[name].astype(float), xb[name].astype(float)
            diff = float(np.nanmax(np.abs(a - b)))
            same_nan = xa[name].dtype.kind != "f" or np.array_equal(np.isnan(xa[name]),
                                                                   np.isnan(xb[name]))
            finite = np.isfinite(a) & np.isfinite(b)
            within = tol is not None and bool(np.all(
                np.abs(a - b)[finite] <= tol + FORMAT_REL.get(name, 0.0) * np.maximum(
                    np.abs(a[finite]), np.abs(b[finite]))))
            same_inf = np.array_equal(a[~finite], b[~finite], equal_nan=True)
            if not same_nan or not same_inf or not within:
                return f"{topic} {name}: max |diff| {diff:.3g}"
            notes.append(f"{topic} {name} {diff:.2g}")
    if notes:
        return f"{WITHIN} (the log's micro-g): " + ", ".join(notes)
    return "identical"


def mcap_verdict(a: Path, b: Path) -> tuple[str, str]:
    """(verdict on the messages, a note on the file's bytes and metadata)."""
    if a.read_bytes() == b.read_bytes():
        return "identical", "file bytes identical"
    ca, cb = read_mcap(a), read_mcap(b)
    batch_verdict = batch_topics_verdict(ca, cb)
    # the other messages one by one, exactly, topic by topic (each topic in its order: how
    # the writer interleaves topics in the file is layout, as the chunking is)
    ca = McapContent(ca.library, ca.metadata,
                     sorted((m for m in ca.messages if m[3] not in BATCH_SCHEMAS),
                            key=lambda m: m[0]), ca.channels)
    cb = McapContent(cb.library, cb.metadata,
                     sorted((m for m in cb.messages if m[3] not in BATCH_SCHEMAS),
                            key=lambda m: m[0]), cb.channels)
    verdict, within, n_within = "identical", "", 0
    if len(ca.messages) != len(cb.messages):
        verdict = f"{len(ca.messages)} vs {len(cb.messages)} messages"
    for i, (x, y) in enumerate(zip(ca.messages, cb.messages, strict=False)):
        if x != y:
            what = f"message {i} ({x[0]} @ {x[1]}): {_message_diff(x, y)}"
            if f"payload {WITHIN}" not in what:
                verdict = what
                break
            within, n_within = within or what, n_within + 1
    if verdict == "identical" and within:
        verdict = f"{WITHIN}: {n_within} messages, first {within}"
    if (verdict == "identical" or verdict.startswith(WITHIN)) and batch_verdict != "identical":
        verdict = batch_verdict
    if (verdict == "identical" or verdict.startswith(WITHIN)) and _channels(ca) != _channels(cb):
        topic = next(t for t in {**ca.channels, **cb.channels}
                     if _channels(ca).get(t) != _channels(cb).get(t))
        verdict = f"channel or schema of {topic} differs"
    meta = [f"header library {ca.library!r} vs {cb.library!r}"] if ca.library != cb.library else []
    for name in sorted(set(ca.metadata) | set(cb.metadata)):
        x, y = ca.metadata.get(name, {}), cb.metadata.get(name, {})
        meta += [f"metadata {name}.{k} {x.get(k)!r} vs {y.get(k)!r}"
                 for k in sorted(set(x) | set(y)) if x.get(k) != y.get(k)]
    note = "file bytes differ" + (f" in: {'; '.join(meta)}" if meta else
                                  " (same messages and metadata: layout/chunking)"
                                  if verdict == "identical" else " (metadata the same)")
    if verdict == "identical" and meta and not all("version" in m or "library" in m
                                                    for m in meta):
        verdict = "metadata differs: " + "; ".join(meta)
    return verdict, note


def _channels(content: McapContent) -> dict[str, tuple]:
    """The channels, with the protobuf schemas' bytes left out (the compact form added fields
    to the batch messages; every schema is still checked by name and encoding)."""
    return {t: c[:4] if len(c) > 4 and c[3] == "protobuf" else c
            for t, c in content.channels.items()}


def _message_diff(x: tuple, y: tuple) -> str:
    fields = ("topic", "log time", "publish time", "schema", "encoding", "sequence")
    for name, u, v in zip(fields, x, y, strict=False):
        if u != v:
            return f"{name} {u!r} vs {v!r}"
    return payload_diff(x[3], x[6], y[6])


def payload_diff(schema: str, a: bytes, b: bytes) -> str:
    """What differs in two payloads: JSON key by key, recal's batches array by array (decoded
    with the new tree's decoder when it can be imported), else the first differing byte."""
    try:
        return "payload " + json_verdict(json.loads(a), json.loads(b))
    except (ValueError, UnicodeDecodeError):
        pass
    try:
        from recal.io import messages
        if schema == messages.PLOT_MESSAGE_NAME:  # one sample: its fields as 1-element arrays
            pa, pb = messages.decode_plot(a), messages.decode_plot(b)
            v = first_verdict(array_verdict(k, np.atleast_1d(pa[k]), np.atleast_1d(pb[k]))
                              for k in pa)
            if v != "identical" and _plot_float32_equal(pa, pb):
                v = f"{WITHIN} (the plot's float32)"
            if v != "identical":
                return f"payload {v}"
        decode = (messages.decode_calibrated if "alibrated" in schema else messages.decode_raw)
        ba, bb = decode(a)[1], decode(b)[1]
        v = first_verdict(
            array_verdict(name, np.asarray(getattr(ba, name)), np.asarray(getattr(bb, name)))
            for name in ("t_us", "v", "aux", "a_g", "quasi_static", "detector_g", "status",
                         "sigma_mg")
            if hasattr(ba, name) and getattr(ba, name) is not None)
        if v != "identical":
            return f"payload {v}"
    except Exception:  # a decoder that moved, or a schema it does not know: bytes below
        pass
    k = next((i for i, (u, v) in enumerate(zip(a, b, strict=False)) if u != v), min(len(a),
                                                                                       len(b)))
    return f"payload bytes differ ({len(a)} vs {len(b)} bytes, first at byte {k})"


def _plot_float32_equal(pa: dict, pb: dict) -> bool:
    """Two plot samples the same once their values are rounded to float32 (the plot's fields
    are floats; older recordings have doubles), everything else exactly."""
    def f32(value: float) -> np.ndarray:
        return np.atleast_1d(np.float32(value))
    return all(np.array_equal(f32(pa[k]), f32(pb[k]), equal_nan=True)
               if isinstance(pa[k], float) else pa[k] == pb[k] for k in pa)


def mask_stdout(text: str) -> str:
    """The commands' own wall-clock timings masked ("in 0.12 s", "(0.38 M samples/s)")."""
    text = re.sub(r"\bin \d+(?:\.\d+)? s\b", "in <t> s", text)
    return re.sub(r"\d+(?:\.\d+)? M samples/s", "<rate> M samples/s", text)


def text_verdict(a: str, b: str) -> str:
    if a == b:
        return "identical"
    la, lb = a.splitlines(), b.splitlines()
    for i, (u, v) in enumerate(zip(la, lb, strict=False)):
        if u != v:
            return f"line {i + 1}: {_short(u)} vs {_short(v)}"
    return f"{len(la)} vs {len(lb)} lines"


def file_verdict(a: Path, b: Path) -> tuple[str, str]:
    """Compare two output files by kind: (verdict, note)."""
    if not a.exists() or not b.exists():
        return f"missing: old {a.exists()}, new {b.exists()}", ""
    suffix = a.suffix.lower()
    if suffix == ".mcap":
        return mcap_verdict(a, b)
    if suffix == ".json":
        return json_verdict(json.loads(a.read_text()), json.loads(b.read_text())), ""
    if suffix == ".npz":
        return npz_verdict(a, b), ""
    return text_verdict(a.read_text(errors="replace"), b.read_text(errors="replace")), ""


# --- cases ---------------------------------------------------------------------------------------
@dataclass
class Context:
    old: Tree
    new: Tree
    work: Path
    inputs: Path
    args: argparse.Namespace

    def dirs(self, case: str) -> tuple[Path, Path]:
        out = []
        for t in (self.old, self.new):
            d = self.work / t.label / case
            d.mkdir(parents=True, exist_ok=True)
            out.append(d)
        return out[0], out[1]


def both(ctx: Context, case: str, argv: list[str], what: str) -> tuple[Path, Path, str, str]:
    """`recal <argv>` with each tree in its own directory (outputs named relative to it, so
    no path differs); (old dir, new dir, old stdout, new stdout) with the dirs masked."""
    dirs = ctx.dirs(case)
    outs = []
    for tree, d in zip((ctx.old, ctx.new), dirs, strict=True):
        out = ok_or_raise(tree, tree.recal(argv, d), what)
        outs.append(mask_stdout(out.replace(str(d), "<dir>")))
    return dirs[0], dirs[1], outs[0], outs[1]


def compare_files(case: str, old_dir: Path, new_dir: Path, names: list[str]) -> list[Row]:
    rows = []
    for name in names:
        verdict, note = file_verdict(old_dir / name, new_dir / name)
        rows.append(Row(case, name + (f" ({note})" if note else ""), verdict))
    return rows


def case_replay(ctx: Context, case: str, src: Path) -> list[Row]:
    config: list[str] = []
    if ctx.args.plot_hz is not None:  # both trees at one plot rate (their defaults differ)
        toml = ctx.inputs / "plot_hz.toml"
        toml.write_text(f"[pipeline]\nplot_hz = {ctx.args.plot_hz!r}\n")
        config = ["--config", str(toml)]
    od, nd, so, sn = both(ctx, case, ["replay", str(src), "--out", "replay.mcap", "--quiet",
                                      "--json", "replay.json", *config], "recal replay")
    rows = compare_files(case, od, nd, ["replay.mcap", "replay.json"])
    return [*rows, Row(case, "stdout (timings masked)", text_verdict(so, sn))]


def case_simulated(ctx: Context, sensor: str) -> list[Row]:
    """`recal simulate` with both trees (compared), then both replay the same (old) file."""
    case = f"sim {sensor}"
    argv = ["simulate", "--out", "sim.mcap", "--hours", str(ctx.args.sim_hours), "--rate", "50",
            "--seed", "11", *SENSORS[sensor]]
    od, nd, so, sn = both(ctx, case, argv, "recal simulate")
    rows = compare_files(case, od, nd, ["sim.mcap", "sim.truth.npz"])
    rows.append(Row(case, "simulate stdout", text_verdict(so, sn)))
    # both replay the old tree's file: the new tree reads the older log format, not the
    # other way round
    return rows + case_replay(ctx, f"replay sim {sensor}", od / "sim.mcap")


def case_core(ctx: Context, variant: str) -> list[Row]:
    sensor, start = variant.rsplit("-", 1)
    src = ctx.inputs / f"core-{sensor}.npz"
    if not src.exists():
        r = ctx.new.child("make_sim", {"out": str(src), "hours": ctx.args.core_hours,
                                       "sensor": sensor}, ctx.inputs)
        ok_or_raise(ctx.new, r, "core input simulation")
    rows = []
    for mode, group in (("step x100", 1), ("10 batches per call", ctx.args.group)):
        case = f"core {variant} {mode}"
        dirs = ctx.dirs(case.replace(" ", "_"))
        notes = []
        for tree, d in zip((ctx.old, ctx.new), dirs, strict=True):
            r = tree.child("core", {"npz": str(src), "out": str(d), "prior": start == "prior",
                                    "batch": ctx.args.batch, "group": group}, d)
            notes.append(ok_or_raise(tree, r, "core child").strip().splitlines()[-1])
        rows += compare_files(case, dirs[0], dirs[1], ["arrays.npz", "events.json"])
        old_sd, new_sd = ((d / "state_dict.json").read_text() for d in dirs)
        rows.append(Row(case, "final state_dict JSON (==)", "identical" if old_sd == new_sd
                        else json_verdict(json.loads(old_sd), json.loads(new_sd))))
        rows[-1].compared += f" [old: {notes[0]}; new: {notes[1]}]"
    return rows


def case_discover_hindsight(ctx: Context, src: Path) -> list[Row]:
    case = f"discover {src.name}"
    od, nd, so, sn = both(ctx, case, ["discover", str(src), "--json", "report.json",
                                      "--write-model", "model.json"], "recal discover")
    rows = compare_files(case, od, nd, ["report.json", "model.json"])
    rows.append(Row(case, "stdout", text_verdict(so, sn)))
    case = f"hindsight {src.name}"
    od, nd, so, sn = both(ctx, case, ["hindsight", str(src), "--out", "hind.mcap", "--json",
                                      "hind.json", "--quiet"], "recal hindsight")
    rows += compare_files(case, od, nd, ["hind.mcap", "hind.json"])
    rows.append(Row(case, "stdout", text_verdict(so, sn)))
    both(ctx, case, ["hindsight", str(src), "--out", "hind.csv", "--quiet"], "recal hindsight")
    return rows + compare_files(case, od, nd, ["hind.csv"])


def case_static(ctx: Context, table: Path) -> list[Row]:
    rows = []
    for label, extra in (("unknown orientations", ["--fit-rows", "1-20"]),
                         ("known orientations", ["--known-orientations", "--fit-rows", "1-6"])):
        case = f"static {table.name} {label}"
        od, nd, so, sn = both(ctx, case.replace(" ", "_"), ["static", str(table), "--json",
                                                           "static.json", *extra], "recal static")
        rows += compare_files(case, od, nd, ["static.json"])
        rows.append(Row(case, "stdout", text_verdict(so, sn)))
    return rows


def real_csv(npz: Path, out: Path) -> None:
    """A measured .npz (README of the data) as a CSV `recal import` reads: t_us, the raw
    counts (zero-g at mid-scale taken off a 16-bit unsigned part), and the channels."""
    with np.load(npz) as z:
        t_us = np.round(z["t"] * 1e6).astype(np.int64)
        v = z["acc_counts"].astype(np.int64)
        if v.min() >= 0:
            v = v - 32768
        aux = {k: z[k] for k in ("temp", "batt") if k in z.files}
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_us", "x", "y", "z", *aux])
        cols = [t_us, v[:, 0], v[:, 1], v[:, 2], *[a.astype(np.float64) for a in aux.values()]]
        for row in zip(*(c.tolist() for c in cols), strict=True):
            w.writerow([repr(x) if isinstance(x, float) else x for x in row])


def case_real(ctx: Context, npz: Path) -> list[Row]:
    src = ctx.inputs / f"{npz.stem}.csv"
    real_csv(npz, src)
    case = f"real {npz.stem}"
    od, nd, so, sn = both(ctx, case, ["import", str(src), "--out", "imported.mcap", "--units",
                                      "counts", "--quiet"], "recal import")
    rows = compare_files(case, od, nd, ["imported.mcap"])
    rows.append(Row(case, "import stdout", text_verdict(so, sn)))
    so, sn = (ok_or_raise(t, t.recal(["discover", "imported.mcap", "--json", "report.json"], d),
                          "recal discover") for t, d in ((ctx.old, od), (ctx.new, nd)))
    rows += compare_files(case, od, nd, ["report.json"])
    rows.append(Row(case, "discover stdout", text_verdict(so, sn)))
    return rows


# --- children: code run inside one tree ----------------------------------------------------------
def _core_names() -> dict[str, Any]:
    """The core's classes by their new names (recal.core exports) else the old modules."""
    try:
        from recal.core import Pipeline, PipelineConfig, Prior, SensorModel
    except ImportError:
        from recal.core.estimator import Prior
        from recal.core.model import SensorModel
        from recal.core.pipeline import Pipeline, PipelineConfig
    from recal.samples import RawBatch
    return {"Pipeline": Pipeline, "PipelineConfig": PipelineConfig, "Prior": Prior,
            "SensorModel": SensorModel, "RawBatch": RawBatch}


def child_make_sim(a: dict[str, Any]) -> None:
    """A simulated recording as arrays (the core case's shared input)."""
    from dataclasses import replace

    from recal.sim import wearer as sim
    rng = np.random.default_rng(5)
    spec = sim.SensorSpec.random(rng, offset_mg=50.0, gain_pct=3.0)
    if a["sensor"] != "default":
        spec = replace(spec, **sim.SENSOR_TYPES[a["sensor"]])
    raw = sim.simulate(float(a["hours"]), 50.0, 5, spec).raw
    np.savez(a["out"], t_us=raw.t_us, v=raw.v, aux=raw.aux,
             aux_names=np.array(raw.aux_names, dtype=str),
             counts_per_g=np.float64(spec.counts_per_g or 1.0))


def _jsonable(x: Any) -> Any:
    import dataclasses
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "to_dict"):
        return _jsonable(x.to_dict())
    return x


def _per_batch(pipe: Any, batches: list[Any], group: int, RawBatch: Any
               ) -> Iterator[tuple[Any, list, list, Any]]:
    """(calibrated, updates, watch events, (model, summary) or None) per batch, stepping
    one batch per call (group 1) or `group` batches per call: `step_many` where the tree
    has it, else one step over the joined batches with marks at their ends."""
    if group == 1:
        for b in batches:
            out = pipe.step(b)
            state = (pipe.model, pipe.summary()) if out.updates else None
            yield out.calibrated, list(out.updates), list(out.watch), state
        return
    for g in range(0, len(batches), group):
        part = batches[g:g + group]
        if hasattr(pipe, "step_many"):
            for out in pipe.step_many(part):
                yield out.calibrated, list(out.updates), list(out.watch), out.state
            continue
        ends = np.cumsum([len(b) for b in part]).tolist()
        out = pipe.step(RawBatch.concat(part), marks=ends)
        lo = 0
        for hi in ends:
            ups = [u for u in out.updates if lo <= u.index < hi]
            ws = [w for w in out.watch if lo <= w.index < hi]
            yield (out.calibrated[lo:hi], [_shift(u, lo) for u in ups],
                   [_shift(w, lo) for w in ws], out.states.get(hi))
            lo = hi


def _shift(event: Any, lo: int) -> Any:
    from dataclasses import replace
    return replace(event, index=event.index - lo)


def child_core(a: dict[str, Any]) -> None:
    """Pipeline.step over the arrays in batches, outputs written for the parent to compare:
    the calibrated columns, per batch its updates (index, time, report), watch events and the
    state (model and summary) after a batch with an update, and the final state_dict. An
    update event's own copy of the model and estimate is plumbing, not output: left out."""
    n = _core_names()
    z = np.load(a["npz"])
    raw = n["RawBatch"](z["t_us"], z["v"], z["aux"], tuple(str(s) for s in z["aux_names"]))
    if a["prior"]:
        model = n["SensorModel"].diagonal(float(z["counts_per_g"]))
        prior = n["Prior"].default(model)
    else:
        model, prior = n["SensorModel"].diagonal(1.0), None
    pipe = n["Pipeline"](n["PipelineConfig"](rate_hz=50.0), model, prior, raw.aux_names)
    size = int(a["batch"])
    batches = [raw[i:i + size] for i in range(0, len(raw), size)]
    cols: dict[str, list[np.ndarray]] = {}
    events: list[dict[str, Any]] = []
    t0, offset = time.perf_counter(), 0
    for i, (cal, ups, watch, state) in enumerate(_per_batch(pipe, batches, int(a["group"]),
                                                            n["RawBatch"])):
        for name in ("t_us", "a_g", "quasi_static", "detector_g", "status", "sigma_mg"):
            cols.setdefault(name, []).append(np.asarray(getattr(cal, name)))
        if ups or watch or state is not None:
            events.append({
                "batch": i,
                "updates": [{"index": offset + u.index, "t_us": u.t_us, "bootstrap": u.bootstrap,
                             "report": _jsonable(u.report)} for u in ups],
                "watch": [{"index": offset + w.index, "t_us": w.t_us, "kind": w.kind,
                           "detail": _jsonable(w.detail)} for w in watch],
                "state": None if state is None else {"model": _jsonable(state[0]),
                                                     "summary": _jsonable(state[1])}})
        offset += len(cal.t_us)
    seconds = time.perf_counter() - t0
    out = Path(a["out"])
    np.savez(out / "arrays.npz", **{k: np.concatenate(v) for k, v in cols.items()})
    (out / "events.json").write_text(json.dumps(events))
    (out / "state_dict.json").write_text(json.dumps(pipe.state_dict()))
    how = ("step" if a["group"] == 1 else "step_many" if hasattr(pipe, "step_many")
           else "step(marks=)")
    print(f"{len(raw)} samples, {len(events)} batches with events, {how}, "
          f"{seconds:.1f} s")


CHILDREN: dict[str, Callable[[dict[str, Any]], None]] = {"core": child_core,
                                                         "make_sim": child_make_sim}


# --- main ----------------------------------------------------------------------------------------
def table(rows: list[Row]) -> str:
    head = "| case | compared | result |\n|---|---|---|"
    return "\n".join([head, *(f"| {r.case} | {r.compared} | {r.verdict} |" for r in rows)])


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", type=Path, default=OLD_DEFAULT, help="old tree (default %(default)s)")
    ap.add_argument("--new", type=Path, default=NEW_DEFAULT, help="new tree (default: this one)")
    ap.add_argument("--recordings", type=Path, default=NEW_DEFAULT / "recordings",
                    help="where wearer-10min.mcap and wearer-temp-30min.mcap are (default: "
                    "this checkout's recordings/)")
    ap.add_argument("--data", type=Path, default=SHARED_DATA,
                    help="the measured data (static_positions/, real/; default %(default)s)")
    ap.add_argument("--sim-hours", type=float, default=6.0,
                    help="hours of each simulated recording (default 6)")
    ap.add_argument("--core-hours", type=float, default=6.0,
                    help="hours of the core case's simulation (default 6)")
    ap.add_argument("--batch", type=int, default=100, help="core batch size (default 100)")
    ap.add_argument("--group", type=int, default=10, help="core batches per call (default 10)")
    ap.add_argument("--sensors", default=DEFAULT_SENSORS,
                    help=f"simulated sensors, of {', '.join(SENSORS)} (default {DEFAULT_SENSORS})")
    ap.add_argument("--core", default=",".join(CORE_VARIANTS),
                    help="core variants, comma list (default all: %(default)s)")
    ap.add_argument("--only", help="run only cases whose group is in this comma list: "
                    "recordings,sim,core,discover,static,real")
    ap.add_argument("--keep", type=Path, help="keep every output under this directory")
    ap.add_argument("--plot-hz", type=float, help="replay with this plot rate in both trees "
                    "(a config file with [pipeline] plot_hz; for trees whose default differs)")
    ap.add_argument("--tolerate", action="append", default=[], metavar="NAME=ABS",
                    help="accept an absolute difference up to ABS in the arrays and JSON "
                    "numbers called NAME (repeatable); everything else stays bit for bit")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("child_args", nargs="?", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    if a.child:
        CHILDREN[a.child](json.loads(a.child_args))
        return 0
    for item in a.tolerate:
        name, _, limit = item.partition("=")
        TOLERATE[name] = float(limit)
    old, new = Tree("old", a.old.resolve()), Tree("new", a.new.resolve())
    recordings = a.recordings
    only = set(a.only.split(",")) if a.only else None
    groups: list[tuple[str, str, Callable[[], list[Row]]]] = []
    for name in ("wearer-10min.mcap", "wearer-temp-30min.mcap"):
        groups.append(("recordings", f"replay {name}",
                       lambda n=name: case_replay(ctx, f"replay {n}", recordings / n)))
    for s in filter(None, a.sensors.split(",")):
        groups.append(("sim", f"sim {s}", lambda s=s: case_simulated(ctx, s)))
    for v in filter(None, a.core.split(",")):
        groups.append(("core", f"core {v}", lambda v=v: case_core(ctx, v)))
    groups.append(("discover", "discover/hindsight", lambda: case_discover_hindsight(
        ctx, recordings / "wearer-temp-30min.mcap")))
    groups.append(("static", "static phone1", lambda: case_static(
        ctx, a.data / "static_positions" / "phone1.csv")))
    for npz in ("xsens_imutk_multipos.npz", "geneactiv_wristpy_cooling.npz"):
        groups.append(("real", f"real {npz}", lambda p=a.data / "real" / npz:
                       case_real(ctx, p)))
    work = Path(tempfile.mkdtemp(prefix="recal-regress-")) if a.keep is None else a.keep
    work.mkdir(parents=True, exist_ok=True)
    inputs = work / "inputs"
    inputs.mkdir(exist_ok=True)
    ctx = Context(old, new, work, inputs, a)
    print(f"old {old.root} ({old.commit()}): recal from {old.check(work)}")
    print(f"new {new.root} ({new.commit()}): recal from {new.check(work)}")
    print(f"command: {' '.join([Path(sys.executable).name, *sys.argv])}", flush=True)
    rows: list[Row] = []
    t_start = time.perf_counter()
    try:
        for group, label, run in groups:
            if only is not None and group not in only:
                continue
            t0 = time.perf_counter()
            try:
                got = run()
            except (CommandFailed, OSError) as e:  # OSError: an input file not there
                got = [Row(label, "command", f"FAILED: {e}")]
            rows += got
            bad = sum(not r.ok for r in got)
            print(f"  {label}: {len(got) - bad}/{len(got)} identical or within tolerance "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
    finally:
        if a.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    print()
    print(table(rows))
    bad = [r for r in rows if not r.ok]
    print(f"\n{len(rows) - len(bad)} of {len(rows)} comparisons identical"
          + (f" or within tolerance ({', '.join(f'{k} {v:g}' for k, v in TOLERATE.items())})"
             if TOLERATE else "") + " "
          f"({time.perf_counter() - t_start:.0f} s)" + (": NOT IDENTICAL: " + ", ".join(
              sorted({r.case for r in bad})) if bad else ""))
    return 0 if not bad and rows else 1


if __name__ == "__main__":
    sys.exit(main())
