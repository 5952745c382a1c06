"""Schemas of the bus and the log: the protobuf messages of the sample batches and the
JSON schemas of the low-rate messages, as MCAP registers them.

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
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from google.protobuf import descriptor_pb2

from recal.core.status import Status

__all__ = [
    "CALIBRATED_MESSAGE_NAME",
    "CALIBRATED_SCHEMA",
    "CALIBRATION_STATE_SCHEMA",
    "EVENT_SCHEMA",
    "GENERIC_JSON_SCHEMA",
    "PLOT_MESSAGE_NAME",
    "PLOT_SCHEMA",
    "RAW_MESSAGE_NAME",
    "RAW_SCHEMA",
    "SchemaSpec",
    "file_descriptor_set",
    "protobuf_message_class",
]

PROTO_PACKAGE = "recal"
RAW_MESSAGE_NAME = "recal.RawBatch"
CALIBRATED_MESSAGE_NAME = "recal.CalibratedBatch"
PLOT_MESSAGE_NAME = "recal.PlotSample"

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
