"""Codecs of the bus and the log: the bus carries each batch in the float64 fields, the log
joins batches into compact messages of the same protobuf types.

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
  // the compact form (the log's), instead of fields 2-5:
  sfixed64 t0_us = 11;                          // first stamp
  repeated sint64 dt_us = 12 [packed = true];   // N - 1 differences
  repeated sint64 x_counts_delta = 13 [packed = true];  // integer readings: x[i] - x[i-1]
  repeated sint64 y_counts_delta = 14 [packed = true];  // (x[-1] = 0); readings that are not
  repeated sint64 z_counts_delta = 15 [packed = true];  // integers stay in fields 3-5
  repeated sint64 arrival_samples = 20 [packed = true];   // a joined batch's arrivals:
  repeated sint64 arrival_log_dt_us = 21 [packed = true]; // samples, log time deltas (us
                                                // after the message's log time, then apart)
  repeated sint64 arrival_lag_delta_us = 23 [packed = true];  // instead of 21: each log
}                                               // time's lag behind its last sample's device
                                                // time (both after the message's), deltas
message CalibratedBatch {
  string sensor_id = 1;
  repeated sfixed64 t_us = 2 [packed = true];
  repeated double x_g = 3 [packed = true];      // calibrated acceleration, g
  repeated double y_g = 4 [packed = true];
  repeated double z_g = 5 [packed = true];
  repeated bool quasi_static = 6 [packed = true];
  repeated double detector_g = 7 [packed = true];
  repeated Status status = 8 [packed = true];   // per sample; absent in older recordings
  repeated double sigma_mg = 9 [packed = true]; // predicted 1-sigma error of the vector, mg
  repeated sfixed64 t_dev = 10 [packed = true]; // the device's own stamp, as the raw batch had
  // the compact form (the log's), instead of fields 2-5, 7, 9, 10:
  sfixed64 t0_us = 11;
  repeated sint64 dt_us = 12 [packed = true];
  repeated sint64 x_ug_delta = 13 [packed = true];        // micro-g, differences
  repeated sint64 y_ug_delta = 14 [packed = true];
  repeated sint64 z_ug_delta = 15 [packed = true];
  repeated sint64 detector_ug_delta = 16 [packed = true];
  repeated sint64 sigma_ug_delta = 17 [packed = true];    // on 1 % steps (sigma_steps)
  sfixed64 t_dev0 = 18;
  repeated sint64 dt_dev = 19 [packed = true];
  // the log's body topic, instead of every field but 1, 11, 12: the rotation R (row-major)
  // that turns the calibrated topic's samples at these times into the body frame (R @ a)
  repeated double body_rotation = 22 [packed = true];
  // the compact form's second version, each instead of an older field (still read):
  repeated sint64 sigma_step_delta = 24 [packed = true];     // k of sigma = 1.01^k mg
  repeated sint64 detector_2ug_delta2 = 25 [packed = true];  // 2 micro-g steps, 2nd diffs
  repeated sint64 t_dev_offset_delta = 26 [packed = true];   // t_dev - t_us, differences
  repeated double body_quaternion = 27 [packed = true];      // R as (w, x, y, z), w >= 0
}
enum Status {                                   // recal.core.status.Status
  STATUS_NOT_RECORDED = 0;                      // a recording from before statuses
  STATUS_UNCALIBRATED = 1;
  STATUS_BOOTSTRAPPING = 2;
  STATUS_CALIBRATED = 3;
  STATUS_HELD = 4;
  STATUS_SUSPECT = 5;
}
message PlotSample {                            // one decimated sample, for a Plot panel
  sfixed64 t_us = 1;
  float x_g = 2;                                // float32 (double in older recordings)
  float y_g = 3;
  float z_g = 4;
  float norm_g = 5;
  bool quasi_static = 6;
  float detector_g = 7;
  Status status = 8;
  float sigma_mg = 9;
}
```

A CalibratedBatch whose samples all have status 0 (not recorded) is written without fields 8
and 9, byte for byte as before they existed; a decoded message without them has status 0 and
sigma_mg NaN for every sample. Field 10 (``t_dev``: each sample's device time stamp exactly
as its ``RawBatch`` carried it, in the device's unit, so raw and calibrated join on it after a
reboot too) is written when the batch has it; a message without it (an older recording)
decodes with ``t_dev`` None.

The compact form (`encode_raw_compact`, `encode_calibrated_compact`) is what the recording
writer logs: a column is written either in its float64 field or in its compact one. Times are
the first stamp and the differences; raw readings that are all integers (ADC counts) and
calibrated values in micro-g (rounded: within half a micro-g) are differences from the sample
before (the first from 0); the detector in 2 micro-g steps (within one) as second differences;
sigma on its ladder of 1 % steps (`sigma_steps`) as the differences of the steps' numbers; the
device stamps as their distance from ``t_us``, differences; a joined raw message's arrival log
times as the differences of their lag behind the device time; all as zigzag varints, which a
few numpy passes write and read (`zigzag_varints_many`, `unzigzag_varints`); a column with a
value that is not finite or beyond +-2147 g stays in float64 (sigma that is not all positive:
micro-g differences). The fields of the compact form's first version (micro-g differences of
the detector and sigma, ``t_dev0`` + ``dt_dev``, ``arrival_log_dt_us``, ``body_rotation`` as 9
values) are still read. Differences make most varints one or two bytes, and zstd, restarted at
every one-second chunk, finds little else to take. The log's body topic holds no values
(`encode_body_rotation`): its samples' times and the rotation (as its unit quaternion) that
turns the calibrated topic's samples at those times (``decode_calibrated`` refuses such a
message; `recal.io.recording` reads it back). The bus keeps the float64 form: one sample is
cheapest to encode that way, and subscribers read either. The decoders accept both forms (and
older recordings, which have only the float64 fields).

The hot path does not use the protobuf runtime: a packed fixed-width field is a tag byte, a
varint byte length and the raw little-endian values, so numpy writes and reads the arrays
directly (``protobuf``'s Python runtime is slow for large repeated fields). A ``PlotSample`` is
written with every field present, so each one is the same 43 bytes and a whole batch of them is
one numpy structured array (formatting floats as JSON text cost more than the calibration).
The decoder follows protobuf semantics (unknown fields and known fields with an unexpected
wire type are skipped, packed and unpacked repeated encodings are both accepted, the last
singular string wins) and raises ``ValueError`` with a reason on malformed input.

Low-rate messages are JSON (schema encoding ``jsonschema``, message encoding ``json``):
calibration state and service events. The per-sample plot message is protobuf (Foxglove's Plot
panel draws one value per message, so the log carries a decimated stream of single samples).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from google.protobuf import descriptor_pb2

from recal.core.status import Status
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
]

PROTO_PACKAGE = "recal"
RAW_MESSAGE_NAME = "recal.RawBatch"
CALIBRATED_MESSAGE_NAME = "recal.CalibratedBatch"
PLOT_MESSAGE_NAME = "recal.PlotSample"

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
_F_CAL_STATUS = 8
_F_CAL_SIGMA = 9
_F_CAL_T_DEV = 10
# The compact form (the log's): a first stamp and differences, values as integers (counts,
# micro-g) stored as differences from the sample before, as zigzag varints (sint64).
_F_T0_US = 11
_F_DT_US = 12
_F_X_FIX, _F_Y_FIX, _F_Z_FIX = 13, 14, 15
_F_CAL_DETECTOR_UG = 16
_F_CAL_SIGMA_UG = 17
_F_CAL_T_DEV0 = 18
_F_CAL_DT_DEV = 19
# The log's body topic: the samples' times and the rotation that turns the calibrated
# topic's samples at those times into the body frame (nothing the calibrated topic says).
_F_CAL_BODY_ROTATION = 22
# A joined raw message keeps its arrivals: samples per arrival and each one's log time (us
# after the message's), so a replay hands the node the batches the live node had.
_F_RAW_ARRIVAL_SAMPLES = 20
_F_RAW_ARRIVAL_LOG_US = 21
# The log's compact form, second version (each replaces an older field of the same column,
# which the decoders still read): arrival log times as the deltas of their lag behind the
# device time, sigma as its step on the 1 % ladder, the detector as second differences, the
# device stamps as their distance from t_us, the body's rotation as a unit quaternion.
_F_RAW_ARRIVAL_LAG_US = 23
_F_CAL_SIGMA_STEP = 24
_F_CAL_DETECTOR_UG_2 = 25
_F_CAL_T_DEV_OFFSET = 26
_F_CAL_BODY_QUATERNION = 27
STATUS_ENUM_NAME = "Status"


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
    if ftype == fd.TYPE_ENUM:
        field.type_name = f".{PROTO_PACKAGE}.{STATUS_ENUM_NAME}"
    if repeated and ftype != fd.TYPE_STRING:
        # proto3 packs by default; saying so explicitly documents the wire layout we rely on.
        field.options.packed = True


_PLOT_FIELDS = (("t_us", 1, descriptor_pb2.FieldDescriptorProto.TYPE_SFIXED64),
                ("x_g", 2, descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT),
                ("y_g", 3, descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT),
                ("z_g", 4, descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT),
                ("norm_g", 5, descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT),
                ("quasi_static", 6, descriptor_pb2.FieldDescriptorProto.TYPE_BOOL),
                ("detector_g", 7, descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT),
                ("status", 8, descriptor_pb2.FieldDescriptorProto.TYPE_ENUM),
                ("sigma_mg", 9, descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT))


def file_descriptor_set() -> descriptor_pb2.FileDescriptorSet:
    """``recal/batches.proto`` (RawBatch and CalibratedBatch) as a FileDescriptorSet."""
    fd = descriptor_pb2.FieldDescriptorProto
    fds = descriptor_pb2.FileDescriptorSet()
    f = fds.file.add(name="recal/batches.proto", package=PROTO_PACKAGE, syntax="proto3")
    status = f.enum_type.add(name=STATUS_ENUM_NAME)
    for st in Status:
        status.value.add(name=f"STATUS_{st.name}", number=int(st))
    raw = f.message_type.add(name="RawBatch")
    _add_field(raw, "sensor_id", _F_SENSOR, fd.TYPE_STRING, False)
    _add_field(raw, "t_us", _F_T_US, fd.TYPE_SFIXED64, True)
    for name, number in (("x", _F_X), ("y", _F_Y), ("z", _F_Z)):
        _add_field(raw, name, number, fd.TYPE_DOUBLE, True)
    _add_field(raw, "aux_names", _F_RAW_AUX_NAMES, fd.TYPE_STRING, True)
    _add_field(raw, "aux", _F_RAW_AUX, fd.TYPE_DOUBLE, True)
    _add_field(raw, "t0_us", _F_T0_US, fd.TYPE_SFIXED64, False)
    for name, number in (("dt_us", _F_DT_US), ("x_counts_delta", _F_X_FIX),
                         ("y_counts_delta", _F_Y_FIX), ("z_counts_delta", _F_Z_FIX),
                         ("arrival_samples", _F_RAW_ARRIVAL_SAMPLES),
                         ("arrival_log_dt_us", _F_RAW_ARRIVAL_LOG_US),
                         ("arrival_lag_delta_us", _F_RAW_ARRIVAL_LAG_US)):
        _add_field(raw, name, number, fd.TYPE_SINT64, True)
    cal = f.message_type.add(name="CalibratedBatch")
    _add_field(cal, "sensor_id", _F_SENSOR, fd.TYPE_STRING, False)
    _add_field(cal, "t_us", _F_T_US, fd.TYPE_SFIXED64, True)
    for name, number in (("x_g", _F_X), ("y_g", _F_Y), ("z_g", _F_Z)):
        _add_field(cal, name, number, fd.TYPE_DOUBLE, True)
    _add_field(cal, "quasi_static", _F_CAL_QUASI_STATIC, fd.TYPE_BOOL, True)
    _add_field(cal, "detector_g", _F_CAL_DETECTOR, fd.TYPE_DOUBLE, True)
    _add_field(cal, "status", _F_CAL_STATUS, fd.TYPE_ENUM, True)
    _add_field(cal, "sigma_mg", _F_CAL_SIGMA, fd.TYPE_DOUBLE, True)
    _add_field(cal, "t_dev", _F_CAL_T_DEV, fd.TYPE_SFIXED64, True)
    _add_field(cal, "t0_us", _F_T0_US, fd.TYPE_SFIXED64, False)
    _add_field(cal, "dt_us", _F_DT_US, fd.TYPE_SINT64, True)
    for name, number in (("x_ug_delta", _F_X_FIX), ("y_ug_delta", _F_Y_FIX),
                         ("z_ug_delta", _F_Z_FIX), ("detector_ug_delta", _F_CAL_DETECTOR_UG),
                         ("sigma_ug_delta", _F_CAL_SIGMA_UG)):
        _add_field(cal, name, number, fd.TYPE_SINT64, True)
    _add_field(cal, "t_dev0", _F_CAL_T_DEV0, fd.TYPE_SFIXED64, False)
    _add_field(cal, "dt_dev", _F_CAL_DT_DEV, fd.TYPE_SINT64, True)
    _add_field(cal, "body_rotation", _F_CAL_BODY_ROTATION, fd.TYPE_DOUBLE, True)
    for name, number in (("sigma_step_delta", _F_CAL_SIGMA_STEP),
                         ("detector_2ug_delta2", _F_CAL_DETECTOR_UG_2),
                         ("t_dev_offset_delta", _F_CAL_T_DEV_OFFSET)):
        _add_field(cal, name, number, fd.TYPE_SINT64, True)
    _add_field(cal, "body_quaternion", _F_CAL_BODY_QUATERNION, fd.TYPE_DOUBLE, True)
    plot = f.message_type.add(name="PlotSample")
    for name, number, ftype in _PLOT_FIELDS:
        _add_field(plot, name, number, ftype, False)
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
PLOT_SCHEMA = SchemaSpec(PLOT_MESSAGE_NAME, "protobuf", _FDS_BYTES, "protobuf")


def _json_schema(title: str, description: str, properties: Mapping[str, Any],
                 required: Sequence[str] = ()) -> bytes:
    doc: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema",
                           "title": title, "description": description, "type": "object",
                           "properties": dict(properties)}
    if required:
        doc["required"] = list(required)
    return json.dumps(doc, separators=(",", ":")).encode()


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
    """The values as one C-ordered run of little-endian bytes (a copy only if needed).

    Few numpy calls on purpose: a gateway encodes every sample as it arrives, and each call
    costs microseconds there, more than the bytes themselves."""
    if values.dtype.str != dtype or not values.flags.c_contiguous:
        values = np.ascontiguousarray(values, dtype=dtype)
    return memoryview(values).cast("B") if values.size else memoryview(b"")


def _axes_bytes(v: np.ndarray) -> list[memoryview]:
    """x, y, z columns as three byte runs, from one column-major copy."""
    n = len(v)
    columns = memoryview(v.astype("<f8", copy=False).tobytes(order="F"))
    return [columns[i * 8 * n:(i + 1) * 8 * n] for i in range(3)]


def encode_raw(sensor_id: str, batch: RawBatch) -> bytes:
    """Serialize a raw batch as a ``recal.RawBatch`` protobuf message (float64 form: the bus's,
    cheapest to make for a sample or two)."""
    x, y, z = _axes_bytes(batch.v)
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_packed(_F_T_US, _le_bytes(batch.t_us, "<i8")),
             *_packed(_F_X, x), *_packed(_F_Y, y), *_packed(_F_Z, z)]
    return b"".join(parts + _aux_fields(batch))


def _aux_fields(batch: RawBatch) -> list[bytes | memoryview]:
    parts: list[bytes | memoryview] = []
    for name in batch.aux_names:
        # An empty name is still a list element, so it must be written (not omitted).
        parts += _len_prefixed(_F_RAW_AUX_NAMES, name.encode())
    if batch.aux.size:  # (an empty packed field is omitted)
        parts += _packed(_F_RAW_AUX, _le_bytes(batch.aux, "<f8"))
    return parts


def encode_calibrated(sensor_id: str, batch: CalibratedBatch) -> bytes:
    """Serialize a calibrated batch as a ``recal.CalibratedBatch`` protobuf message (float64
    form: the bus's)."""
    x, y, z = _axes_bytes(batch.a_g)
    # Packed bools are varints; 0 and 1 are single bytes, so uint8 is the wire form.
    quasi = _le_bytes(batch.quasi_static, "|u1")
    detector = _le_bytes(batch.detector_g, "<f8")
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_packed(_F_T_US, _le_bytes(batch.t_us, "<i8")),
             *_packed(_F_X, x), *_packed(_F_Y, y), *_packed(_F_Z, z),
             *_packed(_F_CAL_QUASI_STATIC, quasi), *_packed(_F_CAL_DETECTOR, detector)]
    if batch.recorded:  # statuses 0-5 are one-byte varints, so uint8 is the wire form
        parts += [*_packed(_F_CAL_STATUS, _le_bytes(batch.status, "|u1")),
                  *_packed(_F_CAL_SIGMA, _le_bytes(batch.sigma_mg, "<f8"))]
    if batch.t_dev is not None:
        parts += _packed(_F_CAL_T_DEV, _le_bytes(batch.t_dev, "<i8"))
    return b"".join(parts)


# -- the compact form (the log's) -------------------------------------------------------------

_I32_MAX = 2**31 - 1
#: micro-g per g: calibrated values, the detector and sigma are logged as int32 micro-g
#: (rounded: within 0.5 micro-g of the float64 value, range +-2147 g).
UG_PER_G = 1e6


def _time_fields(t: np.ndarray, f_first: int, f_delta: int) -> list[bytes | memoryview]:
    """A stamp column as its first value (sfixed64) and the differences (sint64 varints: a
    few bytes each at any rate)."""
    if len(t) == 0:
        return []
    return [_key(f_first, _WT_I64), struct.pack("<q", int(t[0])),
            *_varint_field(f_delta, np.diff(t))]


def _fixed_point(values: np.ndarray, scale: float) -> np.ndarray | None:
    """``values * scale`` rounded to int32, or None if one is not finite or out of range
    (that column is then written as float64)."""
    scaled = np.rint(values * scale) if scale != 1.0 else values
    if scaled.size and not (np.abs(scaled).max() <= _I32_MAX):  # (NaN fails the test too)
        return None
    out = scaled.astype("<i4")
    if scale == 1.0 and not np.array_equal(out, values):  # raw values that are not integers
        return None
    return out


def zigzag_varints_many(columns: Sequence[np.ndarray]) -> list[bytes]:
    """Each column of signed integers as protobuf ``sint64`` packed varints (zigzag, 7 bits
    a byte): small magnitudes (deltas) take one or two bytes. All columns in one pass of a
    few numpy calls per byte of the widest value, whatever their number (a message's columns
    are encoded together)."""
    v = np.concatenate([np.asarray(c, np.int64) for c in columns])
    if len(v) == 0:
        return [b"" for _ in columns]
    z = ((v << 1) ^ (v >> 63)).view(np.uint64)
    if int(z.max()) < 1 << 32:  # (32-bit arithmetic is faster)
        z = z.astype(np.uint32)
    nbytes = np.ones(len(z), np.int64)
    rest = z >> 7
    for _ in range(9):  # a uint64 takes at most 10 bytes
        more = rest != 0
        if not more.any():
            break
        nbytes += more
        rest >>= 7
    ends = np.cumsum(nbytes)
    flat = np.empty(int(ends[-1]), np.uint8)
    # byte j of every value at once, then only the values that have a byte j + 1 (deltas:
    # most values end at the first or second byte, so the later passes are short)
    pos, zz = ends - nbytes, z
    for _ in range(10):
        more = zz >= 0x80
        flat[pos] = (zz & 0x7F).astype(np.uint8) | (more.view(np.uint8) << 7)
        if not more.any():
            break
        pos, zz = pos[more] + 1, zz[more] >> 7
    blob = flat.tobytes()
    out, start = [], 0
    for c, end in zip(columns, ends[np.cumsum([len(c) for c in columns]) - 1].tolist(),
                      strict=True):
        if len(c) == 0:
            out.append(b"")
            continue
        out.append(blob[start:end])
        start = end
    return out


def unzigzag_varints(run: np.ndarray, what: str) -> np.ndarray:
    """A column of `zigzag_varints_many` back (a packed run of bytes) as int64; ValueError
    if it ends inside a varint or a varint is longer than 10 bytes."""
    z = _unsigned_varints(run, what)
    return (z >> np.uint64(1)).view(np.int64) ^ -(z & np.uint64(1)).view(np.int64)


def _unsigned_varints(run: np.ndarray, what: str) -> np.ndarray:
    """A packed run of varints (bytes) as uint64, a few numpy calls per byte of the longest
    value; ValueError if it ends inside a varint or a varint is longer than 10 bytes (bits
    beyond 64 are dropped, as protobuf does)."""
    if run.size == 0:
        return np.zeros(0, np.uint64)
    last = run < 0x80
    if not last[-1]:
        raise ValueError(f"packed field {what} ends inside a varint")
    ends = np.flatnonzero(last)
    starts = np.concatenate(([0], ends[:-1] + 1))
    lengths = ends - starts + 1
    if lengths.max() > 10:
        raise ValueError(f"packed field {what} has a varint longer than 10 bytes")
    z = np.zeros(len(ends), np.uint64)
    for k in range(int(lengths.max())):
        sel = lengths > k
        z[sel] |= (run[starts[sel] + k] & 0x7F).astype(np.uint64) << np.uint64(7 * k)
    return z


class _Ints(NamedTuple):
    """A packed sint64 field waiting to be encoded with the message's others (`_join`)."""

    field: int
    values: np.ndarray


def _varint_field(field: int, values: np.ndarray) -> list[Any]:
    return [_Ints(field, values)] if len(values) else []


def _join(parts: list[Any]) -> bytes:
    """The message: its parts, with every sint64 field encoded in one pass."""
    ints = [p for p in parts if isinstance(p, _Ints)]
    if not ints:
        return b"".join(parts)
    encoded = iter(zigzag_varints_many([p.values for p in ints]))
    out: list[bytes | memoryview] = []
    for p in parts:
        if isinstance(p, _Ints):
            out += _len_prefixed(p.field, next(encoded))
        else:
            out.append(p)
    return b"".join(out)


def _deltas(values: np.ndarray) -> np.ndarray:
    """Each value minus the one before (the first as it is): what a delta field holds."""
    return np.diff(np.asarray(values, np.int64), prepend=0)


def _compact_axes(v: np.ndarray, scale: float, f_float: Sequence[int], f_fixed: Sequence[int]
                  ) -> list[bytes | memoryview]:
    """The three axes as sint64 varint deltas of their fixed-point values, or as float64
    columns if the fixed point cannot hold them."""
    fixed = _fixed_point(v, scale)
    if fixed is None:
        return [p for f, col in zip(f_float, _axes_bytes(v), strict=True) for p in _packed(f, col)]
    return [p for i, f in enumerate(f_fixed) for p in _varint_field(f, _deltas(fixed[:, i]))]


def _compact_column(values: np.ndarray, scale: float, f_float: int, f_fixed: int
                    ) -> list[bytes | memoryview]:
    """A column as sint64 varint deltas of its fixed-point values, or float64."""
    fixed = _fixed_point(values, scale)
    if fixed is None:
        return _packed(f_float, _le_bytes(values, "<f8"))
    return _varint_field(f_fixed, _deltas(fixed))


def encode_raw_compact(sensor_id: str, batch: RawBatch,
                       arrivals: tuple[Sequence[int], Sequence[int]] | None = None) -> bytes:
    """A ``recal.RawBatch`` in the log's compact form: ``t0_us`` + ``dt_us`` deltas, integer
    readings (ADC counts) as deltas ``x_counts_delta`` ... (each value minus the one before;
    readings that are not all integers stay float64 in ``x`` ...), all deltas zigzag varints.
    `decode_raw` reads both forms.

    ``arrivals``: (samples per arrival, log time of each in us after the message's) of a
    batch joined from several arrivals (`decode_raw_arrivals` reads them back)."""
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_time_fields(batch.t_us, _F_T0_US, _F_DT_US),
             *_compact_axes(batch.v, 1.0, (_F_X, _F_Y, _F_Z), (_F_X_FIX, _F_Y_FIX, _F_Z_FIX))]
    if arrivals is not None and len(arrivals[0]) > 1:
        sizes = np.asarray(arrivals[0], np.int64)
        parts += _varint_field(_F_RAW_ARRIVAL_SAMPLES, sizes)
        lag = _arrival_lag_us(batch.t_us, sizes)
        if lag is None:
            parts += _varint_field(_F_RAW_ARRIVAL_LOG_US, _deltas(np.asarray(arrivals[1])))
        else:
            parts += _varint_field(_F_RAW_ARRIVAL_LAG_US,
                                   _deltas(np.asarray(arrivals[1], np.int64) - lag))
    return _join(parts + _aux_fields(batch))


def _arrival_lag_us(t_us: np.ndarray, sizes: np.ndarray) -> np.ndarray | None:
    """Each arrival's last device time after the message's first (us), what an arrival's log
    time is coded against (``arrival_lag_delta_us``: the lag's deltas, a few bytes of jitter
    where the log times' own deltas carry the sample interval too); None if the sizes do not
    describe the batch or an arrival is empty (the log times are then coded on their own)."""
    if len(sizes) == 0 or sizes.sum() != len(t_us) or (sizes < 1).any():
        return None
    return t_us[np.cumsum(sizes) - 1] - t_us[0]


def encode_calibrated_compact(sensor_id: str, batch: CalibratedBatch) -> bytes:
    """A ``recal.CalibratedBatch`` in the log's compact form: times as ``t0_us`` + ``dt_us``
    deltas, values as deltas of their micro-g values (``x_ug_delta`` ...: each value minus the
    one before, the first as it is; Foxglove plots the ``plot`` topic, whose values are
    whole), the detector in 2 micro-g steps as second differences (``detector_2ug_delta2``),
    sigma on its 1 % steps (`sigma_steps`) as the steps' numbers' deltas
    (``sigma_step_delta``), the device stamps as ``t_dev - t_us`` deltas
    (``t_dev_offset_delta``), all zigzag varints; a column with a value that is not finite or
    beyond +-2147 g stays float64 in its old field. `decode_calibrated` reads every form."""
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_time_fields(batch.t_us, _F_T0_US, _F_DT_US),
             *_compact_axes(batch.a_g, UG_PER_G, (_F_X, _F_Y, _F_Z),
                            (_F_X_FIX, _F_Y_FIX, _F_Z_FIX)),
             *_packed(_F_CAL_QUASI_STATIC, _le_bytes(batch.quasi_static, "|u1")),
             *_detector_fields(batch.detector_g)]
    if batch.recorded:
        parts += [*_packed(_F_CAL_STATUS, _le_bytes(batch.status, "|u1")),
                  *_sigma_fields(sigma_steps(batch.sigma_mg))]
    if batch.t_dev is not None:
        # the device stamp's distance from t_us changes only when the time base does (a
        # reboot, a gap): its deltas are zeros where the stamps' own carry the jitter
        parts += _varint_field(_F_CAL_T_DEV_OFFSET, _deltas(batch.t_dev - batch.t_us))
    return _join(parts)


#: The detector's step in the log, g: within 1 micro-g of its value (it is compared with a
#: threshold of milli-g; one bit less a sample than micro-g steps).
DETECTOR_STEP_G = 2e-6


def _detector_fields(detector_g: np.ndarray) -> list[Any]:
    """The detector in steps of ``DETECTOR_STEP_G`` as second differences
    (``detector_2ug_delta2``: it is a low-pass filter's output, so its slope changes less
    than its value), or float64."""
    fixed = _fixed_point(detector_g, 1.0 / DETECTOR_STEP_G)
    if fixed is None:
        return _packed(_F_CAL_DETECTOR, _le_bytes(detector_g, "<f8"))
    return _varint_field(_F_CAL_DETECTOR_UG_2, _deltas(_deltas(fixed)))


def _sigma_fields(steps_mg: np.ndarray) -> list[Any]:
    """Sigma already on its ladder (`sigma_steps`) as the steps' numbers k (sigma =
    (1 + ``SIGMA_STEP``) ** k mg), differences (``sigma_step_delta``: a change of one step is
    the same byte at any sigma, which a micro-g difference is not); sigma that is not all on
    the ladder (zero, negative, not finite) as micro-g differences, or float64."""
    if len(steps_mg) and np.all(np.isfinite(steps_mg) & (steps_mg > 0)):
        k = np.rint(np.log(steps_mg) / _LOG_SIGMA_STEP)
        if np.array_equal(_ladder_mg(k), steps_mg):
            return _varint_field(_F_CAL_SIGMA_STEP, _deltas(k))
    return _compact_column(steps_mg, UG_PER_G / 1e3, _F_CAL_SIGMA, _F_CAL_SIGMA_UG)


def _ladder_mg(k: np.ndarray) -> np.ndarray:
    """Sigma, mg, of the ladder's steps ``k`` (`sigma_steps`)."""
    return np.exp(np.asarray(k, np.float64) * _LOG_SIGMA_STEP)


#: Relative step of the sigma the log keeps: sigma is itself an estimate (its own relative
#: uncertainty is several percent), so 1 % steps say all it means; between updates it then
#: stays on one step for long runs, which the delta field and zstd store in next to nothing
#: (the raw value wanders by parts per thousand from sample to sample).
SIGMA_STEP = 0.01
_LOG_SIGMA_STEP = math.log1p(SIGMA_STEP)


def sigma_steps(sigma_mg: np.ndarray) -> np.ndarray:
    """Each positive finite sigma on the nearest step of a geometric ladder of ratio
    1 + ``SIGMA_STEP`` (the steps are ``(1 + SIGMA_STEP) ** k`` mg, k an integer: within half
    a step, 0.5 %, of the value); zero, negative and non-finite values as they are. What the
    log's compact form keeps of sigma."""
    s = np.asarray(sigma_mg, np.float64)
    ok = np.isfinite(s) & (s > 0)
    if not ok.any():
        return s
    out = s.copy()
    out[ok] = _ladder_mg(np.rint(np.log(s[ok]) / _LOG_SIGMA_STEP))
    return out


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


def _small_varints(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> np.ndarray:
    """A repeated enum field of small values (packed and/or single varints) as uint8; a value
    above 255 (no status has one) reads as 0, not recorded."""
    runs = []
    for wire_type, start, end in occurrences or ():
        if wire_type not in (_WT_LEN, _WT_VARINT):
            continue
        run = np.frombuffer(buf, dtype=np.uint8, count=end - start, offset=start)
        if run.size and run.max() >= 0x80:  # multi-byte varints (a non-canonical writer)
            values = _unsigned_varints(run, what)
            run = np.where(values <= 0xFF, values, 0).astype(np.uint8)
        runs.append(run)
    if not runs:
        return np.zeros(0, np.uint8)
    return np.array(runs[0] if len(runs) == 1 else np.concatenate(runs), np.uint8)


def _multibyte_varints_nonzero(run: np.ndarray, what: str) -> np.ndarray:
    """Whether each varint of a packed run is nonzero (the rare non-canonical encoding)."""
    last_byte = run < 0x80
    if not last_byte[-1]:
        raise ValueError(f"packed field {what} ends inside a varint")
    starts = np.concatenate(([0], np.flatnonzero(last_byte)[:-1] + 1))
    return np.maximum.reduceat(run & 0x7F, starts)


def _same_length(t_us: np.ndarray, **columns: np.ndarray) -> None:
    """ValueError naming the first column whose length is not ``t_us``'s (a malformed message)."""
    for name, column in columns.items():
        if len(column) != len(t_us):
            raise ValueError(f"{name} has {len(column)} values but t_us has {len(t_us)}")


def _present(fields: dict[int, list[_Occurrence]], field: int, wire_types: tuple[int, ...]
             ) -> bool:
    """Whether the field occurs with a wire type of its own (protobuf skips the others as
    unknown fields)."""
    return any(wt in wire_types for wt, _, _ in fields.get(field, ()))


_VARINT_WT = (_WT_LEN, _WT_VARINT)


def _sint_varints(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> np.ndarray:
    """A repeated sint64 field (packed runs and/or single varints) as int64."""
    runs = [unzigzag_varints(np.frombuffer(buf, np.uint8, end - start, start), what)
            for wire_type, start, end in occurrences or () if wire_type in (_WT_LEN, _WT_VARINT)]
    if not runs:
        return np.zeros(0, np.int64)
    return runs[0] if len(runs) == 1 else np.concatenate(runs)


def _stamps(buf: bytes, fields: dict[int, list[_Occurrence]], f_abs: int, f_first: int,
            f_delta: int, what: str) -> np.ndarray | None:
    """A stamp column from its absolute field or from first value + deltas; None if the
    message has neither."""
    if _present(fields, f_first, (_WT_I64,)):
        first = _fixed64(buf, fields[f_first], "<i8", what)
        dt = _sint_varints(buf, fields.get(f_delta), what)
        t = np.empty(len(dt) + 1, np.int64)
        t[0] = first[-1]  # a singular field: the last occurrence wins
        np.cumsum(dt, out=t[1:])
        t[1:] += t[0]
        return t
    if f_abs in fields:
        return np.array(_fixed64(buf, fields[f_abs], "<i8", what), dtype=np.int64)
    return None


def _axes(buf: bytes, fields: dict[int, list[_Occurrence]], names: Sequence[str],
          scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Time stamps and the (N, 3) axis block (float64 fields, or the fixed-point deltas summed
    and divided by ``scale``), with the lengths checked against each other."""
    t_us = _stamps(buf, fields, _F_T_US, _F_T0_US, _F_DT_US, "t_us")
    if t_us is None:
        t_us = np.zeros(0, np.int64)
    if any(_present(fields, f, _VARINT_WT) for f in (_F_X_FIX, _F_Y_FIX, _F_Z_FIX)):
        columns = [np.cumsum(_sint_varints(buf, fields.get(f), name)) / scale
                   for f, name in zip((_F_X_FIX, _F_Y_FIX, _F_Z_FIX), names, strict=True)]
    else:
        columns = [_fixed64(buf, fields.get(f), "<f8", name)
                   for f, name in zip((_F_X, _F_Y, _F_Z), names, strict=True)]
    _same_length(t_us, **dict(zip(names, columns, strict=True)))
    v = np.empty((len(t_us), 3))
    for i, column in enumerate(columns):
        v[:, i] = column
    return t_us, v


def _column(buf: bytes, fields: dict[int, list[_Occurrence]], f_float: int, f_fixed: int,
            scale: float, what: str) -> np.ndarray:
    if _present(fields, f_fixed, _VARINT_WT):
        return np.cumsum(_sint_varints(buf, fields[f_fixed], what)) / scale
    return np.array(_fixed64(buf, fields.get(f_float), "<f8", what), dtype=np.float64)


_STAMP_FIELDS = (_F_T_US, _F_T0_US, _F_DT_US)
_RAW_FIELDS = frozenset((_F_SENSOR, *_STAMP_FIELDS, _F_X, _F_Y, _F_Z, _F_RAW_AUX_NAMES,
                         _F_RAW_AUX, _F_X_FIX, _F_Y_FIX, _F_Z_FIX, _F_RAW_ARRIVAL_SAMPLES,
                         _F_RAW_ARRIVAL_LOG_US, _F_RAW_ARRIVAL_LAG_US))
_CAL_FIELDS = frozenset((_F_SENSOR, *_STAMP_FIELDS, _F_X, _F_Y, _F_Z, _F_CAL_QUASI_STATIC,
                         _F_CAL_DETECTOR, _F_CAL_STATUS, _F_CAL_SIGMA, _F_CAL_T_DEV,
                         _F_X_FIX, _F_Y_FIX, _F_Z_FIX, _F_CAL_DETECTOR_UG, _F_CAL_SIGMA_UG,
                         _F_CAL_T_DEV0, _F_CAL_DT_DEV, _F_CAL_BODY_ROTATION,
                         _F_CAL_SIGMA_STEP, _F_CAL_DETECTOR_UG_2, _F_CAL_T_DEV_OFFSET,
                         _F_CAL_BODY_QUATERNION))


def _as_bytes(data: bytes | bytearray | memoryview) -> bytes:
    return data if isinstance(data, bytes) else bytes(data)


def decode_raw(data: bytes | bytearray | memoryview) -> tuple[str, RawBatch]:
    """Parse a ``recal.RawBatch`` message (either form) into (sensor_id, batch); ValueError if
    malformed."""
    sensor_id, batch, _ = decode_raw_arrivals(data)
    return sensor_id, batch


#: A joined raw message's arrivals: samples per arrival, and the log time of each in us after
#: the message's (None if the message has no log times).
Arrivals = tuple[np.ndarray, np.ndarray | None]


def decode_raw_arrivals(data: bytes | bytearray | memoryview
                        ) -> tuple[str, RawBatch, Arrivals | None]:
    """`decode_raw` and the message's arrivals in one reading of it: (sensor_id, batch,
    arrivals), arrivals None for a message of one arrival (any message of an older
    recording). ValueError if malformed, or if the arrival sizes do not add up to the
    message's samples."""
    buf = _as_bytes(data)
    fields = _scan(buf, _RAW_FIELDS)
    t_us, v = _axes(buf, fields, ("x", "y", "z"), 1.0)
    names = tuple(_strings(buf, fields.get(_F_RAW_AUX_NAMES)))
    aux = np.array(_fixed64(buf, fields.get(_F_RAW_AUX), "<f8", "aux"), dtype=np.float64)
    if len(aux) != len(t_us) * len(names):
        raise ValueError(f"aux has {len(aux)} values, expected {len(t_us)} samples x "
                         f"{len(names)} channels")
    batch = RawBatch(t_us, v, aux.reshape(len(t_us), len(names)), names)
    return _last_string(buf, fields.get(_F_SENSOR)), batch, _arrivals(buf, fields, t_us)


def _arrivals(buf: bytes, fields: dict[int, list[_Occurrence]], t_us: np.ndarray
              ) -> Arrivals | None:
    """The arrival fields of a raw message already scanned (None if it has none)."""
    if not _present(fields, _F_RAW_ARRIVAL_SAMPLES, _VARINT_WT):
        return None
    sizes = _sint_varints(buf, fields[_F_RAW_ARRIVAL_SAMPLES], "arrival_samples")
    if (sizes < 0).any() or sizes.sum() != len(t_us):
        raise ValueError("arrival_samples do not add up to the message's samples")
    log_us = None
    if _present(fields, _F_RAW_ARRIVAL_LAG_US, _VARINT_WT):
        lag = _arrival_lag_us(t_us, sizes)
        if lag is None:
            raise ValueError("arrival_lag_delta_us needs arrivals of at least one sample")
        log_us = np.cumsum(_sint_varints(buf, fields[_F_RAW_ARRIVAL_LAG_US],
                                         "arrival_lag_delta_us"))
        if len(log_us) == len(sizes):
            log_us += lag
    elif _F_RAW_ARRIVAL_LOG_US in fields:
        log_us = np.cumsum(_sint_varints(buf, fields[_F_RAW_ARRIVAL_LOG_US], "arrival_log_us"))
    if log_us is not None and len(log_us) != len(sizes):
        raise ValueError(f"arrival log times: {len(log_us)} values for {len(sizes)} arrivals")
    return sizes, log_us


def decode_calibrated(data: bytes | bytearray | memoryview) -> tuple[str, CalibratedBatch]:
    """Parse a ``recal.CalibratedBatch`` (either form) into (sensor_id, batch); ValueError if
    malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, _CAL_FIELDS)
    if any(_present(fields, f, (_WT_LEN, _WT_I64))
           for f in (_F_CAL_BODY_ROTATION, _F_CAL_BODY_QUATERNION)):
        raise ValueError("a body message of the log's form holds a rotation, not samples: "
                         "its samples are the calibrated topic's rotated (decode_body_rotation, "
                         "recording.read_all_calibrated)")
    t_us, a_g = _axes(buf, fields, ("x_g", "y_g", "z_g"), UG_PER_G)
    quasi = _bools(buf, fields.get(_F_CAL_QUASI_STATIC), "quasi_static")
    if _present(fields, _F_CAL_DETECTOR_UG_2, _VARINT_WT):
        detector = np.cumsum(np.cumsum(_sint_varints(
            buf, fields[_F_CAL_DETECTOR_UG_2], "detector_g"))) * DETECTOR_STEP_G
    else:
        detector = _column(buf, fields, _F_CAL_DETECTOR, _F_CAL_DETECTOR_UG, UG_PER_G,
                           "detector_g")
    _same_length(t_us, quasi_static=quasi, detector_g=detector)
    status = sigma = None  # absent: a recording from before statuses (not recorded, NaN)
    if (_F_CAL_STATUS in fields or _F_CAL_SIGMA in fields
            or _present(fields, _F_CAL_SIGMA_UG, _VARINT_WT)
            or _present(fields, _F_CAL_SIGMA_STEP, _VARINT_WT)):
        status = _small_varints(buf, fields.get(_F_CAL_STATUS), "status")
        if _present(fields, _F_CAL_SIGMA_STEP, _VARINT_WT):
            sigma = _ladder_mg(np.cumsum(_sint_varints(buf, fields[_F_CAL_SIGMA_STEP],
                                                       "sigma_mg")))
        else:
            sigma = _column(buf, fields, _F_CAL_SIGMA, _F_CAL_SIGMA_UG, UG_PER_G / 1e3,
                            "sigma_mg")
        _same_length(t_us, status=status, sigma_mg=sigma)
    # absent: a recording from before device times were kept
    if _present(fields, _F_CAL_T_DEV_OFFSET, _VARINT_WT):
        offset = np.cumsum(_sint_varints(buf, fields[_F_CAL_T_DEV_OFFSET], "t_dev"))
        _same_length(t_us, t_dev=offset)
        t_dev: np.ndarray | None = t_us + offset
    else:
        t_dev = _stamps(buf, fields, _F_CAL_T_DEV, _F_CAL_T_DEV0, _F_CAL_DT_DEV, "t_dev")
    if t_dev is not None:
        _same_length(t_us, t_dev=t_dev)
    return _last_string(buf, fields.get(_F_SENSOR)), CalibratedBatch(t_us, a_g, quasi, detector,
                                                                      status, sigma, t_dev)


def encode_body_rotation(sensor_id: str, t_us: np.ndarray, rotation: np.ndarray) -> bytes:
    """The log's body message: the times of its samples (``t0_us`` + ``dt_us``) and the
    rotation ``body_rotation`` (3 x 3, row-major) that turns the calibrated topic's samples at
    those times into the body frame (``R @ a``, `recal.core.alignment.to_body`); no value the
    calibrated topic and the alignment already say. `decode_body_rotation` reads it back."""
    r = np.asarray(rotation, np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must be 3 x 3, got shape {r.shape}")
    q = _quaternion(r)
    # a rotation in 4 numbers instead of 9, if they give it back to rounding (else the matrix)
    kept = (_packed(_F_CAL_BODY_QUATERNION, _le_bytes(q, "<f8"))
            if np.max(np.abs(_rotation_of(q) - r)) <= _QUATERNION_TOL
            else _packed(_F_CAL_BODY_ROTATION, _le_bytes(r.reshape(9), "<f8")))
    return _join([*_string_fields(_F_SENSOR, sensor_id),
                  *_time_fields(np.asarray(t_us, np.int64), _F_T0_US, _F_DT_US), *kept])


#: How far the matrix a body quaternion gives back may be from the rotation logged (each
#: element): a few float64 roundings, a body value 1e-14 g away (the matrix otherwise).
_QUATERNION_TOL = 1e-14


def _quaternion(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method:
    the largest of the four squared components first, for accuracy)."""
    tr = float(np.trace(r))
    diag = np.diag(r)
    i = int(np.argmax([tr, *diag]))
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        q = [(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4]
    out = np.array(q, np.float64) if s > 0 else np.full(4, np.nan)
    return -out if out[0] < 0 else out


def _rotation_of(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def decode_body_rotation(data: bytes | bytearray | memoryview
                         ) -> tuple[str, np.ndarray, np.ndarray] | None:
    """(sensor_id, t_us, rotation 3 x 3) of a body message in the log's form
    (`encode_body_rotation`), None for a message of samples (`decode_calibrated` reads it);
    ValueError if malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, frozenset((_F_SENSOR, *_STAMP_FIELDS, _F_CAL_BODY_ROTATION,
                                   _F_CAL_BODY_QUATERNION)))
    if _present(fields, _F_CAL_BODY_QUATERNION, (_WT_LEN, _WT_I64)):
        q = _fixed64(buf, fields[_F_CAL_BODY_QUATERNION], "<f8", "body_quaternion")
        if len(q) != 4:
            raise ValueError(f"body_quaternion has {len(q)} values, not 4")
        r = _rotation_of(q)
    elif _present(fields, _F_CAL_BODY_ROTATION, (_WT_LEN, _WT_I64)):
        values = _fixed64(buf, fields[_F_CAL_BODY_ROTATION], "<f8", "body_rotation")
        if len(values) != 9:
            raise ValueError(f"body_rotation has {len(values)} values, not 9")
        r = values.reshape(3, 3).copy()
    else:
        return None
    t_us = _stamps(buf, fields, _F_T_US, _F_T0_US, _F_DT_US, "t_us")
    return (_last_string(buf, fields.get(_F_SENSOR)),
            np.zeros(0, np.int64) if t_us is None else t_us, r)


def batch_extent(data: bytes | bytearray | memoryview) -> tuple[int, int | None, int | None]:
    """(sample count, first t_us, last t_us) of a RawBatch or CalibratedBatch message (either
    form).

    Reads only the time fields (both messages keep them as fields 2, 11 and 12), so summaries
    of long recordings need not decode the samples. Times are None for an empty batch.
    """
    buf = _as_bytes(data)
    fields = _scan(buf, frozenset(_STAMP_FIELDS))
    if _present(fields, _F_T0_US, (_WT_I64,)):
        t = _stamps(buf, fields, _F_T_US, _F_T0_US, _F_DT_US, "t_us")
        assert t is not None
        return len(t), int(t[0]), int(t[-1])
    runs = [(s, e) for wt, s, e in fields.get(_F_T_US, ())
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


def _last_real(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> float:
    """A singular float or double field (the last occurrence wins, as in protobuf): float32
    since the plot's values are floats, float64 in older recordings; 0.0 when absent; another
    wire type is an unknown field to protobuf, so it is skipped."""
    value = 0.0
    for wire_type, start, _end in occurrences or ():
        if wire_type == _WT_I32:
            value = float(np.frombuffer(buf, "<f4", 1, start)[0])
        elif wire_type == _WT_I64:
            value = float(np.frombuffer(buf, "<f8", 1, start)[0])
    return value
