"""Codecs of the bus and the log: the bus carries each batch in the float64 fields, the log
joins batches into compact messages of the same protobuf types.

The parts, by idea: the schemas (`recal.io.schemas`), the protobuf wire primitives
(`recal.io.protobuf_wire`), the batch codecs (`recal.io.batch_codecs`); this module keeps the
JSON messages and the plot samples, and names the codecs of all of them in one place.

Low-rate messages are JSON (schema encoding ``jsonschema``, message encoding ``json``):
calibration state and service events. The per-sample plot message is protobuf (Foxglove's Plot
panel draws one value per message, so the log carries a decimated stream of single samples).
 A ``PlotSample`` is written with every field present, so each one is the same 43
bytes and a whole batch of them is one numpy structured array (formatting floats as JSON text
cost more than the calibration).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

# Besides its own (JSON, plot), every codec's and schema's name as callers always used them
# (``messages.encode_raw``, ``messages.RAW_SCHEMA``): they are imported here for that.
from recal.io.batch_codecs import (
    SIGMA_STEP,
    Arrivals,
    batch_extent,
    decode_body_rotation,
    decode_calibrated,
    decode_raw,
    decode_raw_arrivals,
    encode_body_rotation,
    encode_calibrated,
    encode_calibrated_compact,
    encode_raw,
    encode_raw_compact,
    sigma_steps,
)
from recal.io.protobuf_wire import (
    _WT_I32,
    _WT_I64,
    _WT_VARINT,
    _as_bytes,
    _bools,
    _fixed64,
    _last_real,
    _scan,
    _small_varints,
    unzigzag_varints,
    zigzag_varints_many,
)
from recal.io.schemas import (
    _PLOT_FIELDS,
    CALIBRATED_MESSAGE_NAME,
    CALIBRATED_SCHEMA,
    CALIBRATION_STATE_SCHEMA,
    EVENT_SCHEMA,
    GENERIC_JSON_SCHEMA,
    PLOT_MESSAGE_NAME,
    PLOT_SCHEMA,
    RAW_MESSAGE_NAME,
    RAW_SCHEMA,
    SchemaSpec,
    file_descriptor_set,
    protobuf_message_class,
)
from recal.samples import CalibratedBatch

__all__ = [
    "CALIBRATED_MESSAGE_NAME",
    "CALIBRATED_SCHEMA",
    "CALIBRATION_STATE_SCHEMA",
    "EVENT_SCHEMA",
    "GENERIC_JSON_SCHEMA",
    "PLOT_DTYPE",
    "PLOT_MESSAGE_NAME",
    "PLOT_SCHEMA",
    "RAW_MESSAGE_NAME",
    "RAW_SCHEMA",
    "SIGMA_STEP",
    "Arrivals",
    "SchemaSpec",
    "batch_extent",
    "decode_body_rotation",
    "decode_calibrated",
    "decode_json",
    "decode_plot",
    "decode_raw",
    "decode_raw_arrivals",
    "encode_body_rotation",
    "encode_calibrated",
    "encode_calibrated_compact",
    "encode_event",
    "encode_json",
    "encode_plot",
    "encode_raw",
    "encode_raw_compact",
    "file_descriptor_set",
    "plot_payloads",
    "protobuf_message_class",
    "sigma_steps",
    "unzigzag_varints",
    "zigzag_varints_many",
]


# ---------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------

def _jsonable(obj: Any) -> Any:
    """Plain JSON types from numpy scalars/arrays, tuples and dataclass-free containers.

    Non-finite floats become null: JSON has no NaN, and Foxglove rejects the bare token.
    """
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.generic,)):
        return _jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {_json_key(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _json_key(key: Any) -> str:
    """A key as ``json.dumps`` writes the ones it accepts (so both paths of `encode_json`
    agree), and str() of any other."""
    if key is None or isinstance(key, bool):
        return json.dumps(key)
    return str(key)


def _json_default(obj: Any) -> Any:
    """numpy values and other mappings for ``json.dumps``; anything else is not JSON."""
    if isinstance(obj, (np.ndarray, np.generic)):
        return obj.tolist()
    if isinstance(obj, Mapping):
        return dict(obj)
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def encode_json(obj: Any) -> bytes:
    """Compact UTF-8 JSON of ``obj`` (numpy values converted, NaN/inf written as null)."""
    try:  # the C encoder, when nothing needs replacing (much faster for a state message)
        text = json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_json_default)
    except (ValueError, TypeError):  # non-finite numbers (or not JSON at all): walk it
        text = json.dumps(_jsonable(obj), separators=(",", ":"), allow_nan=False)
    return text.encode()


def decode_json(data: bytes | bytearray | memoryview) -> Any:
    """Parse a JSON message; ValueError (json.JSONDecodeError) if it is not JSON."""
    try:
        return json.loads(_as_bytes(data))
    except UnicodeDecodeError as exc:
        raise ValueError(f"JSON message is not UTF-8: {exc}") from exc


def encode_event(kind: str, *, t_us: int | None = None, sensor_id: str | None = None,
                 detail: Any = None) -> bytes:
    """A service event ``{"t_us", "kind", "sensor_id", "detail"}`` as JSON bytes."""
    return encode_json({"t_us": None if t_us is None else int(t_us), "kind": kind,
                        "sensor_id": sensor_id, "detail": detail})


# One PlotSample with every field present: a tag byte before each value (field << 3 | wire
# type), so numpy lays out a batch of them in one structured array.
# The values are float32 (fields of type float): a plot needs no more, float32 keeps a value
# below 16 g within 1 micro-g, and a message of doubles cost 24 bytes more (about 2.4 bytes
# a logged sample at 100 Hz and 10 plot messages a second). Older recordings' doubles decode
# as well.
PLOT_DTYPE = np.dtype([
    ("k_t", "u1"), ("t_us", "<i8"), ("k_x", "u1"), ("x_g", "<f4"), ("k_y", "u1"),
    ("y_g", "<f4"), ("k_z", "u1"), ("z_g", "<f4"), ("k_n", "u1"), ("norm_g", "<f4"),
    ("k_q", "u1"), ("quasi_static", "u1"), ("k_d", "u1"), ("detector_g", "<f4"),
    ("k_s", "u1"), ("status", "u1"), ("k_e", "u1"), ("sigma_mg", "<f4")])
_PLOT_TAGS = {"k_t": 1 << 3 | _WT_I64, "k_x": 2 << 3 | _WT_I32, "k_y": 3 << 3 | _WT_I32,
              "k_z": 4 << 3 | _WT_I32, "k_n": 5 << 3 | _WT_I32, "k_q": 6 << 3 | _WT_VARINT,
              "k_d": 7 << 3 | _WT_I32, "k_s": 8 << 3 | _WT_VARINT, "k_e": 9 << 3 | _WT_I32}
_PLOT_FIELD_NUMBERS = {name: number for name, number, _ in _PLOT_FIELDS}


_PLOT_STRUCT = struct.Struct("<BqBfBfBfBfBBBfBBBf")  # one PlotSample, the layout of PLOT_DTYPE
_PLOT_TAG_VALUES = tuple(_PLOT_TAGS.values())


def _selection(indices: np.ndarray | Iterable[int] | slice | None) -> slice | np.ndarray:
    if indices is None or isinstance(indices, slice):
        return slice(None) if indices is None else indices
    return np.asarray(indices if isinstance(indices, np.ndarray) else list(indices), np.intp)


def plot_payloads(batch: CalibratedBatch,
                  indices: np.ndarray | Iterable[int] | slice | None = None) -> np.ndarray:
    """The selected samples (all when ``indices`` is None) as ``recal.PlotSample`` messages:
    a structured array of PLOT_DTYPE, one 43-byte message per row (``.tobytes()`` of a row is
    the message). Values are the float32 nearest each double (the norm from the doubles), NaN
    and inf included."""
    sel = _selection(indices)
    a_g = batch.a_g[sel]
    out = np.empty(len(a_g), PLOT_DTYPE)
    for name, tag in _PLOT_TAGS.items():
        out[name] = tag
    out["t_us"] = batch.t_us[sel]
    out["x_g"], out["y_g"], out["z_g"] = a_g[:, 0], a_g[:, 1], a_g[:, 2]
    out["norm_g"] = np.sqrt(np.einsum("ij,ij->i", a_g, a_g))
    out["quasi_static"] = batch.quasi_static[sel]
    out["detector_g"] = batch.detector_g[sel]
    out["status"] = batch.status[sel]
    out["sigma_mg"] = batch.sigma_mg[sel]
    return out


def encode_plot(batch: CalibratedBatch, indices: np.ndarray | Iterable[int] | None = None
                ) -> list[bytes]:
    """One ``recal.PlotSample`` message per selected sample (see `plot_payloads`; the same
    bytes, packed one by one, which is cheaper for a few samples)."""
    sel = _selection(indices)
    a_g = batch.a_g[sel]
    if len(a_g) > 16:
        blob = plot_payloads(batch, sel).tobytes()
        size = PLOT_DTYPE.itemsize
        return [blob[i:i + size] for i in range(0, len(blob), size)]
    norm = np.sqrt(np.einsum("ij,ij->i", a_g, a_g))  # as plot_payloads computes it
    kt, kx, ky, kz, kn, kq, kd, ks, ke = _PLOT_TAG_VALUES
    pack = _PLOT_STRUCT.pack
    return [pack(kt, t, kx, x, ky, y, kz, z, kn, n, kq, q, kd, d, ks, s, ke, e)
            for t, (x, y, z), n, q, d, s, e in zip(
                batch.t_us[sel].tolist(), a_g.tolist(), norm.tolist(),
                batch.quasi_static[sel].astype(np.uint8).tolist(),
                batch.detector_g[sel].tolist(), batch.status[sel].tolist(),
                batch.sigma_mg[sel].tolist(), strict=True)]


def decode_plot(data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Parse a ``recal.PlotSample`` (any valid protobuf encoding of it) into a dict with every
    field (proto3 defaults for absent ones); ValueError if malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, frozenset(_PLOT_FIELD_NUMBERS.values()))
    out: dict[str, Any] = {}
    for name, number in _PLOT_FIELD_NUMBERS.items():
        if name == "quasi_static":
            values = _bools(buf, fields.get(number), name)
            out[name] = bool(values[-1]) if len(values) else False
            continue
        if name == "status":
            values = _small_varints(buf, fields.get(number), name)
            out[name] = int(values[-1]) if len(values) else 0
            continue
        if name == "t_us":
            values = _fixed64(buf, fields.get(number), "<i8", name)
            out[name] = values[-1].item() if len(values) else 0
            continue
        out[name] = _last_real(buf, fields.get(number), name)
    return out
