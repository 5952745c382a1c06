"""The checkpoint document: what a node's state looks like on disk, and when it is trusted.

:func:`checkpoint_document` builds a node's document, :func:`restore_document` takes one back
(the pipeline, the alignment, the time base, discovery's schedule and evidence). A document is
trusted only after it has been checked (:func:`parse_document` for the text,
:func:`restore_pipeline` for the state): nesting depth, strict JSON (no NaN, no infinity, no
integer beyond 2^53), the format, then the pipeline rebuilt with ``Pipeline.from_state_dict``
inside a guard and its result checked: the estimate and prior shaped like the model, finite,
inside the model's own ``bounds()`` (the offsets' centred on the configured zero-g,
`param_bounds`), a symmetric covariance with positive variances, device times no later than the
checkpoint's last sample (plus a day) and that one not after tomorrow in Unix time, and one
probe step on a copy that must run and give finite output. New state fields are covered by the
strict-JSON rule and the probe without edits here. The same checks (without the probe) run
before each save: a state that would not load is never written over a good one; a node runs
them on every state it takes on (`estimate_problem`, `recal.node.vetting`).

The files (atomic saves, ``.prev``, locks, owners) are the daemon's:
`recal.daemon.checkpoint_store`.
"""

from __future__ import annotations

import copy
import json
import re
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from recal.config.settings import RediscoveryConfig
from recal.core import alignment as al
from recal.core import timebase as tb
from recal.core.estimator import Prior
from recal.core.evidence import EvidenceStore
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.errors import CheckpointError
from recal.node.state_message import model_name
from recal.samples import RawBatch

__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "Restored",
    "checkpoint_document",
    "estimate_problem",
    "finite_document",
    "json_depth",
    "param_bounds",
    "parse_document",
    "pipeline_problem",
    "restore_document",
    "restore_pipeline",
]

CHECKPOINT_FORMAT = 1
MAX_DEPTH = 32  # a pipeline state nests 5 deep; JSON parsers recurse per level
MAX_INT = 2**53  # larger integers are no device time or count (and overflow int64 near 2^63)
FUTURE_US = 86_400 * 10**6  # a day: how far any time in a state may lie past its last sample
PROBE_SAMPLES = 4

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


# ---------------------------------------------------------------------------------------------
# A node's document
# ---------------------------------------------------------------------------------------------

def checkpoint_document(sensor_id: str, t_us: int | None, pipeline: Pipeline,
                        alignment: al.Alignment | None, next_discovery_us: int | None,
                        timebase: tb.TimebaseState | None,
                        discovery: dict[str, Any] | None = None) -> dict[str, Any]:
    """A node's JSON-able checkpoint (`recal.node.node.CalibrationNode.checkpoint`);
    ``discovery``: the schedule's gap (``gap_us``) and the evidence (``evidence``,
    `core.evidence.EvidenceStore.to_dict`)."""
    return {"format": CHECKPOINT_FORMAT, "sensor_id": sensor_id,
            "saved_unix_s": time.time(), "t_us": t_us,
            "pipeline": pipeline.state_dict(),
            "alignment": alignment.to_dict() if alignment else None,
            "next_discovery_us": next_discovery_us,
            "discovery": discovery,
            "timebase": timebase.to_dict() if timebase else None}


@dataclass(frozen=True)
class Restored:
    """What a checkpoint gives back to a node (:func:`restore_document`)."""

    pipeline: Pipeline
    alignment: al.Alignment | None
    timebase: tb.TimebaseState | None
    next_discovery_us: int | None
    discovery_gap_us: int | None = None
    evidence: EvidenceStore | None = None
    discovery_pending: tuple[str, ...] | None = None


def restore_document(doc: dict[str, Any], sensor_id: str,
                     reference: tuple[SensorModel, Prior | None],
                     rediscovery: RediscoveryConfig) -> Restored:
    """The parts of :func:`checkpoint_document` output, checked (ValueError if it is not
    ``sensor_id``'s, does not fit the configured model and prior ``reference`` or cannot be
    trusted: `restore_pipeline` checks the state). The pipeline is doubted: another device
    may be under this id now, its first windows must agree."""
    if doc.get("sensor_id") != sensor_id:
        raise ValueError(f"checkpoint is for sensor {doc.get('sensor_id')!r}, "
                         f"not {sensor_id!r}")
    model = reference[0]
    pipe = restore_pipeline(doc.get("pipeline"), reference=reference)
    kinds = [e.kind for e in pipe.model.effects]
    configured = [e.kind for e in model.effects]
    grown = rediscovery.active and {e.key for e in model.effects} <= {
        e.key for e in pipe.model.effects}  # rediscovery extended the configured model
    if kinds != configured and not grown:
        raise ValueError(f"checkpoint model {model_name(pipe.model)} differs from the "
                         f"configured {model_name(model)}")
    ali = doc.get("alignment")
    try:
        alignment = al.Alignment.from_dict(ali) if ali else None
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint alignment: {type(exc).__name__}: {exc}") from None
    tbd = doc.get("timebase")  # absent in checkpoints from before it was kept
    try:
        timebase = tb.TimebaseState.from_dict(tbd) if isinstance(tbd, dict) else None
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint time base: {type(exc).__name__}: {exc}") from None
    pipe.doubt()  # another device may be under this id now: its first windows must agree
    due = doc.get("next_discovery_us")  # absent in checkpoints from before it was kept
    every_us = round(rediscovery.every_h * 3.6e9)
    last = pipe.last_t_us or 0
    # one further ahead than a period never comes: scheduled again from the data
    next_us = (int(due) if isinstance(due, (int, float)) and 0 <= due <= last + every_us
               else None)
    gap_us, evidence = _discovery(doc.get("discovery"), pipe, every_us)
    d = doc.get("discovery")
    pending = d.get("pending") if isinstance(d, dict) else None
    return Restored(pipe, alignment, timebase, next_us, gap_us, evidence,
                    tuple(map(str, pending)) if isinstance(pending, list) else None)


def _discovery(d: Any, pipe: Pipeline, every_us: int) -> tuple[int | None, EvidenceStore | None]:
    """The schedule's gap and the evidence of a checkpoint's ``discovery`` (absent in
    checkpoints from before it was kept: none, the evidence starts anew). Evidence whose
    channels or times do not fit the pipeline's is refused (ValueError)."""
    if not isinstance(d, dict):
        return None, None
    gap = d.get("gap_us")
    gap_us = int(gap) if isinstance(gap, (int, float)) and 0 < gap <= every_us else None
    ev = d.get("evidence")
    if not isinstance(ev, dict):
        return gap_us, None
    try:
        store = EvidenceStore.from_dict(ev)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint evidence: {type(exc).__name__}: {exc}") from None
    last = pipe.last_t_us or 0
    if store.aux.shape[1] != len(pipe.aux_names) or (
            len(store) and not 0 <= store.t_us[0] <= store.t_us[-1] <= last + FUTURE_US):
        raise ValueError("checkpoint evidence does not fit the pipeline's channels or times")
    return gap_us, store


# ---------------------------------------------------------------------------------------------
# The text
# ---------------------------------------------------------------------------------------------

def parse_document(data: bytes, where: object) -> dict[str, Any]:
    """A checkpoint's text as a document (CheckpointError, naming ``where``, for anything
    else: nested deeper than MAX_DEPTH, not strict JSON (NaN, infinity, integers beyond
    2^53), not a format-1 object)."""
    depth = json_depth(data)
    if depth > MAX_DEPTH:
        raise CheckpointError(f"{where}: JSON nested {depth} deep (at most {MAX_DEPTH})")
    try:
        doc = json.loads(data, parse_constant=_no_constant, parse_float=_finite_float,
                         parse_int=_bounded_int)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise CheckpointError(f"{where}: not a strict JSON checkpoint ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{where}: unknown checkpoint format")
    return doc


def json_depth(data: bytes) -> int:
    """How deep the arrays and objects of a JSON text nest (strings skipped), vectorized: the
    parser itself recurses per level, so a deep file must be refused before parsing."""
    bare = np.frombuffer(_STRING.sub(b'""', data), np.uint8)
    step = (np.isin(bare, (ord("["), ord("{"))).astype(np.int64)
            - np.isin(bare, (ord("]"), ord("}"))))
    return int(np.cumsum(step).max(initial=0))


def _no_constant(name: str) -> float:
    raise ValueError(f"{name}: not a finite number")


def _finite_float(text: str) -> float:
    x = float(text)
    if not np.isfinite(x):
        raise ValueError(f"number {text[:20]} out of range")
    return x


def _bounded_int(text: str) -> int:
    if len(text) > 17:  # quick refusal before int() parses a megabyte of digits
        raise ValueError(f"integer {text[:20]}... out of range")
    x = int(text)
    if abs(x) >= MAX_INT:
        raise ValueError(f"integer {x} out of range")
    return x


def finite_document(doc: dict[str, Any]) -> tuple[dict[str, Any], list[str], int]:
    """``doc`` as strict JSON can hold it: (the document, where values were not finite, how
    many). A NaN or infinity (a window mean of a channel the stream lacked) is saved as null,
    which the state restores as NaN, so one such value never costs the whole save; whether
    the state may be trusted is still checked (`restore_pipeline`). The usual document is
    returned as it is after one strict encode; only a failing one is walked (arrays of numbers
    checked in numpy)."""
    try:
        json.dumps(doc, allow_nan=False)
    except ValueError:
        pass
    else:
        return doc, [], 0
    where: list[str] = []
    counted = [0]

    def clean(obj: Any, path: str) -> Any:
        if isinstance(obj, float):
            if np.isfinite(obj):
                return obj
            counted[0] += 1
            where.append(path)
            return None
        if isinstance(obj, dict):
            return {k: clean(v, f"{path}.{k}" if path else str(k)) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            try:
                arr = np.asarray(obj, np.float64)
            except (TypeError, ValueError):  # mixed content: item by item
                return [clean(v, f"{path}[{i}]") for i, v in enumerate(obj)]
            bad = ~np.isfinite(arr)
            if not bad.any():
                return obj
            counted[0] += int(bad.sum())
            where.append(path)
            return np.where(bad, None, arr.astype(object)).tolist()
        return obj

    out = clean(doc, "")
    return out, where, counted[0]


# ---------------------------------------------------------------------------------------------
# The state inside
# ---------------------------------------------------------------------------------------------

def restore_pipeline(state: Any, *, reference: tuple[SensorModel, Prior | None] | None = None,
                     probe: bool = True, now_unix_s: float | None = None) -> Pipeline:
    """A pipeline rebuilt from a checkpoint's ``pipeline`` state, checked (CheckpointError
    saying why if it cannot be trusted). ``reference``: the configured model and prior, whose
    zero-g centres the offsets' bounds (else the checkpoint's own prior does). Any exception
    while rebuilding is caught: a checkpoint never crashes a start."""
    if not isinstance(state, dict):
        raise CheckpointError("no pipeline state")
    try:
        pipe = Pipeline.from_state_dict(state)
    except Exception as exc:  # any shape or type a poisoned file gives
        raise CheckpointError(f"does not restore: {type(exc).__name__}: {exc}") from None
    why = pipeline_problem(pipe, now_unix_s, state, reference)
    if why is None and probe:
        why = _probe_problem(pipe)
    if why is not None:
        raise CheckpointError(why)
    return pipe


def pipeline_problem(pipe: Pipeline, now_unix_s: float | None = None,
                     state: Mapping[str, Any] | None = None,
                     reference: tuple[SensorModel, Prior | None] | None = None) -> str | None:
    """Why this pipeline's state cannot be trusted, or None. Checks what every update and every
    sample depends on: the estimate and prior (shapes, finite, inside the bounds, covariance;
    see `param_bounds`), the detector, and the device times (in ``state``, the pipeline's
    ``state_dict()`` if it is at hand, else made here)."""
    try:
        return (_estimate_problem(pipe, reference) or _detector_problem(pipe)
                or _times_problem(pipe, time.time() if now_unix_s is None else now_unix_s,
                                  state))
    except Exception as exc:  # a field of the wrong type
        return f"unreadable state: {type(exc).__name__}: {exc}"


def param_bounds(pipe: Pipeline, reference: tuple[SensorModel, Prior | None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Where a restored estimate and prior mean must lie: the model's own bounds
    (`SensorModel.bounds`), the offsets' centred on the configured zero-g (``reference``'s
    prior) or else the checkpoint's prior's, as the estimator's gate holds updates around the
    prior's zero-g (`recal.core.estimator.bounds_around`; an unsigned ADC reads ~2048 counts
    at 0 g). The configured zero-g, when known, also bounds the checkpoint's own prior: a
    poisoned prior cannot move its bounds."""
    model = pipe.model
    lo, hi = model.bounds()
    key = ("offset", None)
    if not model.has(*key):
        return lo, hi
    centre: np.ndarray | None = None
    if reference is not None and reference[1] is not None and reference[0].has(*key):
        centre = np.asarray(reference[1].mean)[reference[0].slice(key)]
    elif pipe.prior is not None:
        centre = np.asarray(pipe.prior.mean)[model.slice(key)]
    if centre is not None and centre.shape == (3,) and np.isfinite(centre).all():
        sl = model.slice(key)
        lo[sl] += centre
        hi[sl] += centre
    return lo, hi


def estimate_problem(pipe: Pipeline,
                     reference: tuple[SensorModel, Prior | None] | None = None) -> str | None:
    """Why the pipeline's model, estimate or prior would make its checkpoint refused at the
    next start (`restore_pipeline` with the same ``reference``), or None: the check a node runs
    on what it is about to adopt, so that it never holds a state it could not save."""
    try:
        return _estimate_problem(pipe, reference)
    except Exception as exc:  # a field of the wrong type
        return f"unreadable state: {type(exc).__name__}: {exc}"


def _estimate_problem(pipe: Pipeline, reference: tuple[SensorModel, Prior | None] | None
                      ) -> str | None:
    model = pipe.model
    n = len(model.names)
    if not (np.isfinite(model.s0) and model.s0 > 0):
        return f"model s0 {model.s0!r} is not a positive number"
    lo, hi = param_bounds(pipe, reference)
    parts = []
    if pipe.estimate is not None:
        parts.append(("estimate", pipe.estimate.p, pipe.estimate.cov))
    elif pipe.bootstrapped:
        return "no estimate although bootstrapped"
    if pipe.prior is not None:
        parts.append(("prior", pipe.prior.mean, pipe.prior.info))
    for what, p, m in parts:
        p, m = np.asarray(p), np.asarray(m)
        if p.shape != (n,) or m.shape != (n, n):
            return (f"{what} has {p.shape} parameters and a {m.shape} matrix, the model "
                    f"{n} ({', '.join(model.names)})")
        if not (np.isfinite(p).all() and np.isfinite(m).all()):
            return f"{what} is not finite"
        out = [nm for nm, x, a, b in zip(model.names, p, lo, hi, strict=True)
               if not a <= x <= b]
        if out:
            return f"{what} out of the model's bounds: " + ", ".join(
                f"{nm} = {x:.6g}" for nm, x in zip(model.names, p, strict=True) if nm in out)
        if not np.allclose(m, m.T, rtol=1e-6, atol=0) or not (np.diag(m) > 0).all():
            return f"{what} matrix is not symmetric with a positive diagonal"
    if pipe.estimate is not None:
        e = pipe.estimate
        if np.shape(e.rate) != (3,) or np.shape(e.step) != (3,):
            return "estimate offset rate or step is not 3 values"
    return None


def _detector_problem(pipe: Pipeline) -> str | None:
    if pipe.det_cfg is None:
        return None
    s0 = pipe.det_cfg.s0
    if not (np.isfinite(s0) and s0 > 0):
        return f"detector s0 {s0!r} is not a positive number"
    return None


def _times_problem(pipe: Pipeline, now_unix_s: float, state: Mapping[str, Any] | None
                   ) -> str | None:
    """Device times: the last sample's, not after tomorrow read as Unix time (a device clock
    since boot is far below), and every other time in the state not more than a day after it
    (a window about to be committed lies a little ahead; years ahead stall every update)."""
    last = pipe.last_t_us
    if last is None:
        return None
    if not isinstance(last, (int, np.integer)) or not 0 <= last <= (now_unix_s * 1e6
                                                                   + FUTURE_US):
        return f"last_t_us {last!r} is not a plausible device time"
    for key, t in _times(pipe.state_dict() if state is None else state):
        if not 0 <= t <= last + FUTURE_US:
            return f"{key} = {t} is not between 0 and a day after last_t_us = {last}"
    return None


def _times(obj: Any, path: str = "") -> Iterator[tuple[str, int]]:
    """Every number under a key ending in ``_us`` (device times by the project's naming),
    with where it is (``estimate.t_us``); of a list, its least and greatest."""
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            yield from _times(v, f"{path}.{k}" if path else str(k))
    elif path.endswith("_us"):
        if isinstance(obj, list):
            flat = np.asarray(obj, float).ravel() if obj else np.zeros(0)
            if flat.size:
                yield path, int(flat.min())
                yield path, int(flat.max())
        elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
            yield path, int(obj)
    elif isinstance(obj, list) and obj and isinstance(obj[0], (Mapping, list)):
        for v in obj:
            yield from _times(v, path)


def _probe_problem(pipe: Pipeline) -> str | None:
    """Step a copy of the pipeline with a few samples of 1 g along z right after its last
    sample: a state that fails or gives non-finite output there fails on every batch."""
    try:
        trial = copy.deepcopy(pipe)
        dt_us = max(1, round(1e6 / trial.cfg.rate_hz))
        t0 = (trial.last_t_us if trial.last_t_us is not None else 0) + dt_us
        t_us = t0 + dt_us * np.arange(PROBE_SAMPLES, dtype=np.int64)
        v = np.tile([0.0, 0.0, float(trial.model.s0)], (PROBE_SAMPLES, 1))
        aux = np.zeros((PROBE_SAMPLES, len(trial.aux_names)))
        out = trial.step(RawBatch(t_us, v, aux, trial.aux_names))
    except Exception as exc:
        return f"fails on data: {type(exc).__name__}: {exc}"
    if not trial.model.covariates and not np.isfinite(out.calibrated.a_g).all():
        return "calibrates to non-finite values"
    if not np.isfinite(trial.params).all():
        return "parameters not finite after a step"
    return None


# ---------------------------------------------------------------------------------------------
# Ownership
# ---------------------------------------------------------------------------------------------
