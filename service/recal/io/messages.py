"""Codecs shared by the bus and the log: the same bytes go on Zenoh and into MCAP.

Bulk sample batches are protobuf, so Foxglove decodes them from the schema we store in the
log (a serialized ``FileDescriptorSet``, schema encoding ``protobuf``):

```
syntax = "proto3";
package recal;
message RawBatch {
  string sensor_id = 1;
  repeated sfixed64 t_us = 2 [packed = true];   // device time, microseconds
  repeated double x = 3 [packed = true];        // raw reading, the sensor's own unit
  repeated double y = 4 [packed = true];
  repeated double z = 5 [packed = true];
  repeated string aux_names = 6;                // K auxiliary channel names
  repeated double aux = 7 [packed = true];      // N x K, row-major
}
message CalibratedBatch {
  string sensor_id = 1;
  repeated sfixed64 t_us = 2 [packed = true];
  repeated double x_g = 3 [packed = true];      // calibrated acceleration, g
  repeated double y_g = 4 [packed = true];
  repeated double z_g = 5 [packed = true];
  repeated bool quasi_static = 6 [packed = true];
  repeated double detector_g = 7 [packed = true];
}
```

The hot path does not use the protobuf runtime: a packed fixed-width field is a tag byte, a
varint byte length and the raw little-endian values, so numpy writes and reads the arrays
directly (``protobuf``'s Python runtime is slow for large repeated fields). The decoder follows
protobuf semantics (unknown fields and known fields with an unexpected wire type are skipped,
packed and unpacked repeated encodings are both accepted, the last singular string wins) and
raises ``ValueError`` with a reason on malformed input.

Low-rate messages are JSON (schema encoding ``jsonschema``, message encoding ``json``):
calibration state, service events, and the per-sample plot message (Foxglove's Plot panel draws
one value per message, so the log carries a decimated stream of single samples).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2

from recal.samples import CalibratedBatch, RawBatch

__all__ = [
    "CALIBRATED_SCHEMA",
    "CALIBRATION_STATE_SCHEMA",
    "EVENT_SCHEMA",
    "GENERIC_JSON_SCHEMA",
    "PLOT_SCHEMA",
    "RAW_SCHEMA",
    "SchemaSpec",
    "batch_extent",
    "decode_calibrated",
    "decode_json",
    "decode_raw",
    "encode_calibrated",
    "encode_event",
    "encode_json",
    "encode_plot",
    "encode_raw",
    "file_descriptor_set",
    "protobuf_message_class",
]

PROTO_PACKAGE = "recal"
RAW_MESSAGE_NAME = "recal.RawBatch"
CALIBRATED_MESSAGE_NAME = "recal.CalibratedBatch"

# Wire types of the protobuf encoding.
_WT_VARINT = 0
_WT_I64 = 1
_WT_LEN = 2
_WT_I32 = 5

# Field numbers (shared layout: 1 sensor id, 2 time, 3-5 the three axes).
_F_SENSOR = 1
_F_T_US = 2
_F_X, _F_Y, _F_Z = 3, 4, 5
_F_RAW_AUX_NAMES = 6
_F_RAW_AUX = 7
_F_CAL_QUASI_STATIC = 6
_F_CAL_DETECTOR = 7


# ---------------------------------------------------------------------------------------------
# Schemas
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SchemaSpec:
    """Everything an MCAP writer needs to register a schema and its channels.

    Attributes:
        name: schema name (for protobuf the fully qualified message name Foxglove looks up).
        encoding: MCAP schema encoding ("protobuf" or "jsonschema").
        data: schema bytes (serialized FileDescriptorSet, or a JSON Schema document).
        message_encoding: MCAP message encoding of the channels ("protobuf" or "json").
    """

    name: str
    encoding: str
    data: bytes
    message_encoding: str


def _add_field(msg: descriptor_pb2.DescriptorProto, name: str, number: int, ftype: int,
               repeated: bool) -> None:
    fd = descriptor_pb2.FieldDescriptorProto
    field = msg.field.add(name=name, number=number, type=ftype,
                          label=fd.LABEL_REPEATED if repeated else fd.LABEL_OPTIONAL)
    if repeated and ftype != fd.TYPE_STRING:
        # proto3 packs by default; saying so explicitly documents the wire layout we rely on.
        field.options.packed = True


def file_descriptor_set() -> descriptor_pb2.FileDescriptorSet:
    """``recal/batches.proto`` (RawBatch and CalibratedBatch) as a FileDescriptorSet."""
    fd = descriptor_pb2.FieldDescriptorProto
    fds = descriptor_pb2.FileDescriptorSet()
    f = fds.file.add(name="recal/batches.proto", package=PROTO_PACKAGE, syntax="proto3")
    raw = f.message_type.add(name="RawBatch")
    _add_field(raw, "sensor_id", _F_SENSOR, fd.TYPE_STRING, False)
    _add_field(raw, "t_us", _F_T_US, fd.TYPE_SFIXED64, True)
    for name, number in (("x", _F_X), ("y", _F_Y), ("z", _F_Z)):
        _add_field(raw, name, number, fd.TYPE_DOUBLE, True)
    _add_field(raw, "aux_names", _F_RAW_AUX_NAMES, fd.TYPE_STRING, True)
    _add_field(raw, "aux", _F_RAW_AUX, fd.TYPE_DOUBLE, True)
    cal = f.message_type.add(name="CalibratedBatch")
    _add_field(cal, "sensor_id", _F_SENSOR, fd.TYPE_STRING, False)
    _add_field(cal, "t_us", _F_T_US, fd.TYPE_SFIXED64, True)
    for name, number in (("x_g", _F_X), ("y_g", _F_Y), ("z_g", _F_Z)):
        _add_field(cal, name, number, fd.TYPE_DOUBLE, True)
    _add_field(cal, "quasi_static", _F_CAL_QUASI_STATIC, fd.TYPE_BOOL, True)
    _add_field(cal, "detector_g", _F_CAL_DETECTOR, fd.TYPE_DOUBLE, True)
    return fds


def protobuf_message_class(name: str) -> type:
    """The official protobuf runtime's message class for ``name`` ("recal.RawBatch", ...).

    For tools and tests that want the reference implementation; the hot path does not use it.
    """
    from google.protobuf import descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for file_proto in file_descriptor_set().file:
        pool.AddSerializedFile(file_proto.SerializeToString())
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


_FDS_BYTES = file_descriptor_set().SerializeToString()

RAW_SCHEMA = SchemaSpec(RAW_MESSAGE_NAME, "protobuf", _FDS_BYTES, "protobuf")
CALIBRATED_SCHEMA = SchemaSpec(CALIBRATED_MESSAGE_NAME, "protobuf", _FDS_BYTES, "protobuf")


def _json_schema(title: str, description: str, properties: Mapping[str, Any],
                 required: Sequence[str] = ()) -> bytes:
    doc: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema",
                           "title": title, "description": description, "type": "object",
                           "properties": dict(properties)}
    if required:
        doc["required"] = list(required)
    return json.dumps(doc, separators=(",", ":")).encode()


_NUM_OR_NULL = {"type": ["number", "null"]}

CALIBRATION_STATE_SCHEMA = SchemaSpec(
    "recal.CalibrationState", "jsonschema", _json_schema(
        "recal.CalibrationState",
        "Calibration state of one sensor after an update. Permissive: fields beyond these may "
        "appear, and non-finite numbers are written as null.",
        {
            "t_us": {"type": "integer", "description": "device time of the state, microseconds"},
            "sensor_id": {"type": "string"},
            "model": {"type": "string", "description": "name of the calibration model"},
            "param_names": {"type": "array", "items": {"type": "string"}},
            "params": {"description": "parameter values, in param_names order, or by name"},
            "covariance": {"description": "parameter covariance, row-major nested lists"},
            "residual_g": {"description": "fit residual, g"},
            "coverage": {"description": "orientation coverage of the quasi-static buffer"},
            "observable": {"description": "per-parameter observability flags"},
            "update_count": {"type": "integer"},
        }), "json")

EVENT_SCHEMA = SchemaSpec(
    "recal.Event", "jsonschema", _json_schema(
        "recal.Event", "A service event (sensor connected, model updated, frame errors, ...).",
        {
            "t_us": {"type": ["integer", "null"], "description": "device or service time, us"},
            "kind": {"type": "string"},
            "sensor_id": {"type": ["string", "null"]},
            "detail": {"description": "free-form: text or an object"},
        }, required=("kind",)), "json")

PLOT_SCHEMA = SchemaSpec(
    "recal.PlotSample", "jsonschema", _json_schema(
        "recal.PlotSample", "One calibrated sample, for Foxglove's Plot panel (decimated).",
        {
            "t_us": {"type": "integer", "description": "device time, microseconds"},
            "x_g": _NUM_OR_NULL, "y_g": _NUM_OR_NULL, "z_g": _NUM_OR_NULL,
            "norm_g": _NUM_OR_NULL,
            "quasi_static": {"type": "boolean"},
            "detector_g": _NUM_OR_NULL,
        }), "json")

GENERIC_JSON_SCHEMA = SchemaSpec(
    "recal.Json", "jsonschema",
    _json_schema("recal.Json", "Any JSON object.", {}), "json")


# ---------------------------------------------------------------------------------------------
# Protobuf encoding
# ---------------------------------------------------------------------------------------------

def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _key(field: int, wire_type: int) -> bytes:
    return _varint((field << 3) | wire_type)


def _len_prefixed(field: int, payload: bytes | memoryview) -> list[bytes | memoryview]:
    return [_key(field, _WT_LEN), _varint(len(payload)), payload]


def _packed(field: int, payload: bytes | memoryview) -> list[bytes | memoryview]:
    # proto3 omits empty repeated fields; the official serializer does the same.
    return _len_prefixed(field, payload) if len(payload) else []


def _string_fields(field: int, text: str) -> list[bytes | memoryview]:
    return _len_prefixed(field, text.encode()) if text else []


def _le_bytes(values: np.ndarray, dtype: str) -> memoryview:
    """The values as one C-ordered run of little-endian bytes (a copy only if needed)."""
    flat = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
    return memoryview(flat.view(np.uint8))


def _axes_bytes(v: np.ndarray) -> list[memoryview]:
    """x, y, z columns as three byte runs, from one transposing copy."""
    n = len(v)
    columns = _le_bytes(v.T, "<f8")
    return [columns[i * 8 * n:(i + 1) * 8 * n] for i in range(3)]


def encode_raw(sensor_id: str, batch: RawBatch) -> bytes:
    """Serialize a raw batch as a ``recal.RawBatch`` protobuf message."""
    x, y, z = _axes_bytes(batch.v)
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_packed(_F_T_US, _le_bytes(batch.t_us, "<i8")),
             *_packed(_F_X, x), *_packed(_F_Y, y), *_packed(_F_Z, z)]
    for name in batch.aux_names:
        # An empty name is still a list element, so it must be written (not omitted).
        parts += _len_prefixed(_F_RAW_AUX_NAMES, name.encode())
    parts += _packed(_F_RAW_AUX, _le_bytes(batch.aux, "<f8"))
    return b"".join(parts)


def encode_calibrated(sensor_id: str, batch: CalibratedBatch) -> bytes:
    """Serialize a calibrated batch as a ``recal.CalibratedBatch`` protobuf message."""
    x, y, z = _axes_bytes(batch.a_g)
    # Packed bools are varints; 0 and 1 are single bytes, so uint8 is the wire form.
    quasi = np.ascontiguousarray(batch.quasi_static, dtype=np.uint8).tobytes()
    detector = _le_bytes(batch.detector_g, "<f8")
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_packed(_F_T_US, _le_bytes(batch.t_us, "<i8")),
             *_packed(_F_X, x), *_packed(_F_Y, y), *_packed(_F_Z, z),
             *_packed(_F_CAL_QUASI_STATIC, quasi), *_packed(_F_CAL_DETECTOR, detector)]
    return b"".join(parts)


# ---------------------------------------------------------------------------------------------
# Protobuf decoding
# ---------------------------------------------------------------------------------------------

# One occurrence of a field: (wire type, payload start, payload end).
_Occurrence = tuple[int, int, int]


def _read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    """Decode the varint at ``pos``; return (value, position after it)."""
    end = len(buf)
    result = 0
    for shift in range(0, 70, 7):
        if pos >= end:
            raise ValueError(f"truncated varint at byte {pos}")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result, pos
    raise ValueError(f"varint longer than 10 bytes ending at byte {pos}")


def _scan(buf: bytes, wanted: frozenset[int]) -> dict[int, list[_Occurrence]]:
    """Walk the top-level fields of a message; keep the occurrences of ``wanted`` fields."""
    fields: dict[int, list[_Occurrence]] = {}
    end = len(buf)
    pos = 0
    # Every field consumes at least one byte, so len(buf) iterations always suffice.
    for _ in range(end):
        if pos >= end:
            break
        at = pos
        key, pos = _read_varint(buf, pos)
        field, wire_type = key >> 3, key & 7
        if field == 0:
            raise ValueError(f"field number 0 at byte {at}")
        start = pos
        if wire_type == _WT_VARINT:
            _, pos = _read_varint(buf, pos)
        elif wire_type == _WT_I64:
            pos += 8
        elif wire_type == _WT_LEN:
            length, start = _read_varint(buf, pos)
            pos = start + length
        elif wire_type == _WT_I32:
            pos += 4
        else:
            raise ValueError(f"unsupported wire type {wire_type} (field {field}, byte {at})")
        if pos > end:
            raise ValueError(f"field {field} at byte {at} runs past the end of the message "
                             f"({pos} > {end} bytes)")
        if field in wanted:
            fields.setdefault(field, []).append((wire_type, start, pos))
    return fields


def _last_string(buf: bytes, occurrences: list[_Occurrence] | None) -> str:
    strings = _strings(buf, occurrences)
    return strings[-1] if strings else ""


def _strings(buf: bytes, occurrences: list[_Occurrence] | None) -> list[str]:
    out = []
    for wire_type, start, end in occurrences or ():
        if wire_type != _WT_LEN:
            continue  # protobuf treats a mismatched wire type as an unknown field
        try:
            out.append(buf[start:end].decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise ValueError(f"string field at byte {start} is not valid UTF-8") from exc
    return out


def _fixed64(buf: bytes, occurrences: list[_Occurrence] | None, dtype: str,
             what: str) -> np.ndarray:
    """A repeated 8-byte field (packed runs and/or single values).

    Usually a read-only view into ``buf``; callers copy it into the batch's own arrays, so
    the batch is aligned, writable and does not pin the message buffer.
    """
    runs = []
    for wire_type, start, end in occurrences or ():
        if wire_type not in (_WT_LEN, _WT_I64):
            continue
        if (end - start) % 8:
            raise ValueError(f"packed field {what} has {end - start} bytes, not a multiple of 8")
        runs.append(np.frombuffer(buf, dtype=dtype, count=(end - start) // 8, offset=start))
    if not runs:
        return np.zeros(0, dtype)
    return runs[0] if len(runs) == 1 else np.concatenate(runs)


def _bools(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> np.ndarray:
    """A repeated bool field: packed varints and/or single varints."""
    runs = []
    for wire_type, start, end in occurrences or ():
        if wire_type not in (_WT_LEN, _WT_VARINT):
            continue
        run = np.frombuffer(buf, dtype=np.uint8, count=end - start, offset=start)
        if run.size and run.max() >= 0x80:
            run = _multibyte_varints_nonzero(run, what)
        runs.append(run != 0)
    if not runs:
        return np.zeros(0, bool)
    return runs[0] if len(runs) == 1 else np.concatenate(runs)


def _multibyte_varints_nonzero(run: np.ndarray, what: str) -> np.ndarray:
    """Whether each varint of a packed run is nonzero (the rare non-canonical encoding)."""
    last_byte = run < 0x80
    if not last_byte[-1]:
        raise ValueError(f"packed field {what} ends inside a varint")
    starts = np.concatenate(([0], np.flatnonzero(last_byte)[:-1] + 1))
    return np.maximum.reduceat(run & 0x7F, starts)


def _axes(buf: bytes, fields: dict[int, list[_Occurrence]], names: Sequence[str]
          ) -> tuple[np.ndarray, np.ndarray]:
    """Time stamps and the (N, 3) axis block, with the lengths checked against each other."""
    t_us = np.array(_fixed64(buf, fields.get(_F_T_US), "<i8", "t_us"), dtype=np.int64)
    columns = [_fixed64(buf, fields.get(f), "<f8", name)
               for f, name in zip((_F_X, _F_Y, _F_Z), names, strict=True)]
    for name, column in zip(names, columns, strict=True):
        if len(column) != len(t_us):
            raise ValueError(f"{name} has {len(column)} values but t_us has {len(t_us)}")
    v = np.empty((len(t_us), 3))
    for i, column in enumerate(columns):
        v[:, i] = column
    return t_us, v


_RAW_FIELDS = frozenset((_F_SENSOR, _F_T_US, _F_X, _F_Y, _F_Z, _F_RAW_AUX_NAMES, _F_RAW_AUX))
_CAL_FIELDS = frozenset((_F_SENSOR, _F_T_US, _F_X, _F_Y, _F_Z, _F_CAL_QUASI_STATIC,
                         _F_CAL_DETECTOR))


def _as_bytes(data: bytes | bytearray | memoryview) -> bytes:
    return data if isinstance(data, bytes) else bytes(data)


def decode_raw(data: bytes | bytearray | memoryview) -> tuple[str, RawBatch]:
    """Parse a ``recal.RawBatch`` message into (sensor_id, batch); ValueError if malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, _RAW_FIELDS)
    t_us, v = _axes(buf, fields, ("x", "y", "z"))
    names = tuple(_strings(buf, fields.get(_F_RAW_AUX_NAMES)))
    aux = np.array(_fixed64(buf, fields.get(_F_RAW_AUX), "<f8", "aux"), dtype=np.float64)
    if len(aux) != len(t_us) * len(names):
        raise ValueError(f"aux has {len(aux)} values, expected {len(t_us)} samples x "
                         f"{len(names)} channels")
    batch = RawBatch(t_us, v, aux.reshape(len(t_us), len(names)), names)
    return _last_string(buf, fields.get(_F_SENSOR)), batch


def decode_calibrated(data: bytes | bytearray | memoryview) -> tuple[str, CalibratedBatch]:
    """Parse a ``recal.CalibratedBatch`` into (sensor_id, batch); ValueError if malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, _CAL_FIELDS)
    t_us, a_g = _axes(buf, fields, ("x_g", "y_g", "z_g"))
    quasi = _bools(buf, fields.get(_F_CAL_QUASI_STATIC), "quasi_static")
    detector = np.array(_fixed64(buf, fields.get(_F_CAL_DETECTOR), "<f8", "detector_g"),
                        dtype=np.float64)
    for name, column in (("quasi_static", quasi), ("detector_g", detector)):
        if len(column) != len(t_us):
            raise ValueError(f"{name} has {len(column)} values but t_us has {len(t_us)}")
    return _last_string(buf, fields.get(_F_SENSOR)), CalibratedBatch(t_us, a_g, quasi, detector)


def batch_extent(data: bytes | bytearray | memoryview) -> tuple[int, int | None, int | None]:
    """(sample count, first t_us, last t_us) of a RawBatch or CalibratedBatch message.

    Reads only the time field (both messages keep it as field 2), so summaries of long
    recordings need not decode the samples. Times are None for an empty batch.
    """
    buf = _as_bytes(data)
    runs = [(s, e) for wt, s, e in _scan(buf, frozenset((_F_T_US,))).get(_F_T_US, ())
            if wt in (_WT_LEN, _WT_I64) and e > s]
    if any((e - s) % 8 for s, e in runs):
        raise ValueError("packed field t_us is not a multiple of 8 bytes")
    if not runs:
        return 0, None, None
    count = sum((e - s) // 8 for s, e in runs)
    first = int(np.frombuffer(buf, "<i8", 1, runs[0][0])[0])
    last = int(np.frombuffer(buf, "<i8", 1, runs[-1][1] - 8)[0])
    return count, first, last


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
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def encode_json(obj: Any) -> bytes:
    """Compact UTF-8 JSON of ``obj`` (numpy values converted, NaN/inf written as null)."""
    return json.dumps(_jsonable(obj), separators=(",", ":"), allow_nan=False).encode()


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


def _json_numbers(values: np.ndarray) -> list[str]:
    """Shortest round-trip text of each float (Python's repr), null where not finite."""
    texts = list(map(float.__repr__, values.tolist()))
    bad = np.flatnonzero(~np.isfinite(values))
    for i in bad.tolist():
        texts[i] = "null"
    return texts


def encode_plot(batch: CalibratedBatch, indices: np.ndarray | Iterable[int] | None = None
                ) -> list[bytes]:
    """One JSON plot message per selected sample (all samples when ``indices`` is None).

    Columns are formatted in bulk (one ``tolist``/``repr`` pass per column) instead of a
    ``json.dumps`` per sample, which is several times slower.
    """
    sel: slice | np.ndarray = slice(None)
    if indices is not None:
        sel = np.asarray(indices if isinstance(indices, np.ndarray) else list(indices), np.intp)
    a_g = batch.a_g[sel]
    norm_g = np.sqrt(np.einsum("ij,ij->i", a_g, a_g))
    t_us = batch.t_us[sel].tolist()
    x, y, z = (_json_numbers(a_g[:, i]) for i in range(3))
    norms = _json_numbers(norm_g)
    detector = _json_numbers(batch.detector_g[sel])
    quasi = ["true" if q else "false" for q in batch.quasi_static[sel].tolist()]
    return [(f'{{"t_us":{t},"x_g":{xi},"y_g":{yi},"z_g":{zi},"norm_g":{ni},'
             f'"quasi_static":{qi},"detector_g":{di}}}').encode()
            for t, xi, yi, zi, ni, qi, di in zip(t_us, x, y, z, norms, quasi, detector,
                                                   strict=True)]
