"""Codecs: our numpy protobuf path against the official protobuf runtime, robustness, JSON."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from google.protobuf import descriptor_pb2
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recal.io import messages as m
from recal.samples import CalibratedBatch, RawBatch

OfficialRaw = m.protobuf_message_class("recal.RawBatch")
OfficialCalibrated = m.protobuf_message_class("recal.CalibratedBatch")
OfficialPlot = m.protobuf_message_class("recal.PlotSample")


def _raw(n: int = 50, aux_names: tuple[str, ...] = ("temp_c", "vdd"), seed: int = 0) -> RawBatch:
    rng = np.random.default_rng(seed)
    t_us = 1_700_000_000_000_000 + np.arange(n, dtype=np.int64) * 1000 - 5
    v = rng.normal(size=(n, 3)) * 1e3
    aux = rng.normal(size=(n, len(aux_names)))
    return RawBatch(t_us, v, aux, aux_names)


def _calibrated(n: int = 50, seed: int = 1) -> CalibratedBatch:
    rng = np.random.default_rng(seed)
    return CalibratedBatch(np.arange(n, dtype=np.int64) * 1000 - 3000, rng.normal(size=(n, 3)),
                           rng.random(n) > 0.5, rng.random(n))


def _assert_raw_equal(a: RawBatch, b: RawBatch) -> None:
    assert np.array_equal(a.t_us, b.t_us)
    assert np.array_equal(a.v, b.v, equal_nan=True)
    assert np.array_equal(a.aux, b.aux, equal_nan=True)
    assert a.aux_names == b.aux_names


def _assert_calibrated_equal(a: CalibratedBatch, b: CalibratedBatch) -> None:
    assert np.array_equal(a.t_us, b.t_us)
    assert np.array_equal(a.a_g, b.a_g, equal_nan=True)
    assert np.array_equal(a.quasi_static, b.quasi_static)
    assert np.array_equal(a.detector_g, b.detector_g, equal_nan=True)


def _official_raw(sensor_id: str, batch: RawBatch) -> bytes:
    msg = OfficialRaw(sensor_id=sensor_id, t_us=batch.t_us.tolist(), x=batch.v[:, 0].tolist(),
                      y=batch.v[:, 1].tolist(), z=batch.v[:, 2].tolist(),
                      aux_names=list(batch.aux_names), aux=batch.aux.ravel().tolist())
    return msg.SerializeToString()


def _official_calibrated(sensor_id: str, batch: CalibratedBatch) -> bytes:
    msg = OfficialCalibrated(sensor_id=sensor_id, t_us=batch.t_us.tolist(),
                             x_g=batch.a_g[:, 0].tolist(), y_g=batch.a_g[:, 1].tolist(),
                             z_g=batch.a_g[:, 2].tolist(),
                             quasi_static=batch.quasi_static.tolist(),
                             detector_g=batch.detector_g.tolist())
    return msg.SerializeToString()


def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _key(field: int, wire_type: int) -> bytes:
    return _varint(field << 3 | wire_type)


# ---------------------------------------------------------------------------------------------
# Schema
# ---------------------------------------------------------------------------------------------

def test_schema_is_a_file_descriptor_set_with_packed_fixed_width_fields() -> None:
    fds = descriptor_pb2.FileDescriptorSet.FromString(m.RAW_SCHEMA.data)
    (file_proto,) = fds.file
    assert file_proto.package == "recal" and file_proto.syntax == "proto3"
    messages = {msg.name: msg for msg in file_proto.message_type}
    assert set(messages) == {"RawBatch", "CalibratedBatch", "PlotSample"}
    fd = descriptor_pb2.FieldDescriptorProto
    for msg in messages.values():
        for field in msg.field:
            if field.label == fd.LABEL_REPEATED and field.type != fd.TYPE_STRING:
                assert field.options.packed, field.name
    raw_types = {f.name: f.type for f in messages["RawBatch"].field}
    assert raw_types["t_us"] == fd.TYPE_SFIXED64 and raw_types["x"] == fd.TYPE_DOUBLE
    assert m.RAW_SCHEMA.name == "recal.RawBatch"
    assert m.CALIBRATED_SCHEMA.name == "recal.CalibratedBatch"
    assert m.PLOT_SCHEMA.name == "recal.PlotSample"
    assert m.PLOT_SCHEMA.encoding == m.PLOT_SCHEMA.message_encoding == "protobuf"
    assert m.RAW_SCHEMA.encoding == m.RAW_SCHEMA.message_encoding == "protobuf"


@pytest.mark.parametrize("spec", [m.CALIBRATION_STATE_SCHEMA, m.EVENT_SCHEMA,
                                  m.GENERIC_JSON_SCHEMA])
def test_json_schemas_are_permissive_objects(spec: m.SchemaSpec) -> None:
    doc = json.loads(spec.data)
    assert doc["type"] == "object" and doc["title"] == spec.name
    assert "additionalProperties" not in doc
    assert spec.encoding == "jsonschema" and spec.message_encoding == "json"


# ---------------------------------------------------------------------------------------------
# Protobuf compatibility, both directions
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n, aux_names", [(0, ()), (1, ()), (50, ("temp_c", "vdd")),
                                          (1000, ("t",)), (3, ("", "ä"))])
def test_raw_roundtrip_and_official_runtime_agree(n: int, aux_names: tuple[str, ...]) -> None:
    batch = _raw(n, aux_names)
    ours = m.encode_raw("left-wrist", batch)
    sensor, back = m.decode_raw(ours)
    assert sensor == "left-wrist"
    _assert_raw_equal(back, batch)
    # The official runtime reads our bytes to the same values ...
    official = OfficialRaw.FromString(ours)
    assert official.sensor_id == "left-wrist"
    assert list(official.t_us) == batch.t_us.tolist()
    assert list(official.x) == batch.v[:, 0].tolist()
    assert list(official.z) == batch.v[:, 2].tolist()
    assert tuple(official.aux_names) == aux_names
    assert list(official.aux) == batch.aux.ravel().tolist()
    # ... writes the very same bytes, and we read what it writes.
    assert _official_raw("left-wrist", batch) == ours
    _assert_raw_equal(m.decode_raw(_official_raw("left-wrist", batch))[1], batch)


@pytest.mark.parametrize("n", [0, 1, 77])
def test_calibrated_roundtrip_and_official_runtime_agree(n: int) -> None:
    batch = _calibrated(n)
    ours = m.encode_calibrated("s1", batch)
    sensor, back = m.decode_calibrated(ours)
    assert sensor == "s1"
    _assert_calibrated_equal(back, batch)
    official = OfficialCalibrated.FromString(ours)
    assert list(official.quasi_static) == batch.quasi_static.tolist()
    assert list(official.detector_g) == batch.detector_g.tolist()
    assert list(official.y_g) == batch.a_g[:, 1].tolist()
    assert _official_calibrated("s1", batch) == ours
    _assert_calibrated_equal(m.decode_calibrated(_official_calibrated("s1", batch))[1], batch)


def test_special_floats_and_extreme_times_survive() -> None:
    t_us = np.array([np.iinfo(np.int64).min, -1, 0, np.iinfo(np.int64).max])
    v = np.array([[np.nan, np.inf, -np.inf], [-0.0, 5e-324, 1.7976931348623157e308],
                  [1.0, 2.0, 3.0], [0.1, 0.2, 0.3]])
    batch = RawBatch(t_us, v, np.zeros((4, 0)))
    back = m.decode_raw(m.encode_raw("s", batch))[1]
    _assert_raw_equal(back, batch)
    assert math.copysign(1.0, back.v[1, 0]) == -1.0
    assert list(OfficialRaw.FromString(m.encode_raw("s", batch)).t_us) == t_us.tolist()


def test_decoded_arrays_are_writable_and_independent_of_the_buffer() -> None:
    data = bytearray(m.encode_raw("s", _raw(10)))
    batch = m.decode_raw(data)[1]
    before = batch.v.copy()
    data[:] = bytes(len(data))
    assert np.array_equal(batch.v, before)
    assert batch.t_us.flags.writeable and batch.t_us.flags.aligned


def test_unknown_fields_and_mismatched_wire_types_are_skipped_like_protobuf() -> None:
    batch = _raw(20)
    before = _key(25, 0) + _varint(300) + _key(26, 1) + b"\x01" * 8
    after = (_key(27, 2) + _varint(3) + b"abc" + _key(28, 5) + b"\x02" * 4
             + _key(1000, 2) + _varint(0)
             + _key(3, 0) + _varint(7))  # field x as a varint: an unknown field to protobuf
    data = before + m.encode_raw("s", batch) + after
    _assert_raw_equal(m.decode_raw(data)[1], batch)
    official = OfficialRaw.FromString(data)
    assert list(official.x) == batch.v[:, 0].tolist()


def test_concatenated_messages_merge_like_protobuf() -> None:
    a, b = _raw(5, (), seed=1), _raw(7, (), seed=2)
    data = m.encode_raw("first", a) + m.encode_raw("second", b)
    sensor, merged = m.decode_raw(data)
    official = OfficialRaw.FromString(data)
    assert sensor == official.sensor_id == "second"  # the last singular value wins
    assert merged.t_us.tolist() == list(official.t_us)
    assert merged.v[:, 1].tolist() == list(official.y)
    assert merged.aux_names == tuple(official.aux_names) == a.aux_names + b.aux_names


def test_unpacked_and_non_canonical_encodings_are_accepted() -> None:
    t_us, x = [5, -6], [1.5, -2.5]
    data = b"".join(_key(2, 1) + struct.pack("<q", t) for t in t_us)
    for field in (3, 4, 5):
        data += b"".join(_key(field, 1) + struct.pack("<d", value) for value in x)
    # Bools: a packed run holding one non-canonical varint (0x81 0x00 is 1), then an
    # unpacked bool 128; both are true, and both forms are legal protobuf.
    data += _key(6, 2) + _varint(2) + b"\x81\x00" + _key(6, 0) + b"\x80\x01"
    data += _key(7, 1) + struct.pack("<d", 0.25) + _key(7, 1) + struct.pack("<d", 0.5)
    official = OfficialCalibrated.FromString(data)
    _, ours = m.decode_calibrated(data)
    assert ours.t_us.tolist() == list(official.t_us) == t_us
    assert ours.a_g[:, 2].tolist() == list(official.z_g) == x
    assert ours.quasi_static.tolist() == list(official.quasi_static)
    assert ours.detector_g.tolist() == list(official.detector_g) == [0.25, 0.5]


def test_batch_extent_reads_only_the_time_field() -> None:
    batch = _raw(30)
    assert m.batch_extent(m.encode_raw("s", batch)) == (30, int(batch.t_us[0]),
                                                        int(batch.t_us[-1]))
    assert m.batch_extent(m.encode_calibrated("s", _calibrated(4))) == (4, -3000, 0)
    assert m.batch_extent(m.encode_raw("s", RawBatch.empty())) == (0, None, None)


# ---------------------------------------------------------------------------------------------
# Malformed input: ValueError with a reason, never another exception
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("data, reason", [
    (_key(2, 2) + _varint(7) + b"\x00" * 7, "multiple of 8"),
    (_key(2, 2) + _varint(100) + b"\x00" * 8, "runs past the end"),
    (_key(2, 3), "wire type 3"),
    (b"\x80\x80", "truncated varint"),
    (_key(1, 0) + b"\xff" * 11, "longer than 10 bytes"),
    (_key(1, 2) + _varint(2) + b"\xff\xfe", "UTF-8"),
    (b"\x00", "field number 0"),
    (_key(2, 1) + struct.pack("<q", 1), "x has 0 values but t_us has 1"),
    (_key(6, 2) + _varint(1) + b"a" + _key(2, 1) + b"\x00" * 8
     + b"".join(_key(f, 1) + b"\x00" * 8 for f in (3, 4, 5)), "aux has 0 values"),
])
def test_malformed_raw_messages_raise_clear_value_errors(data: bytes, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        m.decode_raw(data)


def test_malformed_calibrated_lengths_are_reported() -> None:
    data = m.encode_calibrated("s", _calibrated(3)) + _key(6, 0) + b"\x01"
    with pytest.raises(ValueError, match="quasi_static has 4 values"):
        m.decode_calibrated(data)
    with pytest.raises(ValueError, match="ends inside a varint"):
        m.decode_calibrated(_key(6, 2) + _varint(2) + b"\x01\x80")


@pytest.mark.parametrize("decode, data", [
    (m.decode_raw, m.encode_raw("sensor", _raw(6))),
    (m.decode_calibrated, m.encode_calibrated("sensor", _calibrated(6))),
])
def test_every_truncation_is_a_value_error_or_a_valid_prefix(decode, data: bytes) -> None:
    ok = 0
    for cut in range(len(data)):
        try:
            decode(data[:cut])
            ok += 1
        except ValueError:
            pass
    assert ok >= 1  # at least the empty message decodes (to an empty batch)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=200))
def test_random_bytes_raise_only_value_error(data: bytes) -> None:
    for decode in (m.decode_raw, m.decode_calibrated, m.batch_extent):
        try:
            decode(data)
        except ValueError:
            pass


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_corrupted_messages_raise_only_value_error(data: st.DataObject) -> None:
    good = bytearray(m.encode_raw("s", _raw(4, ("a",))))
    flips = data.draw(st.lists(st.tuples(st.integers(0, len(good) - 1), st.integers(0, 255)),
                               min_size=1, max_size=4))
    for position, value in flips:
        good[position] = value
    try:
        m.decode_raw(bytes(good))
    except ValueError:
        pass


# ---------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------

def test_encode_json_converts_numpy_and_non_finite_values() -> None:
    state = {"params": np.array([1.0, np.nan, 3.0]), "update_count": np.int64(4),
             "observable": np.array([True, False]), "covariance": np.eye(2),
             "residual_g": np.float32(np.inf), "names": ("a", "b"), "nested": {1: None}}
    back = m.decode_json(m.encode_json(state))
    assert back == {"params": [1.0, None, 3.0], "update_count": 4,
                    "observable": [True, False], "covariance": [[1.0, 0.0], [0.0, 1.0]],
                    "residual_g": None, "names": ["a", "b"], "nested": {"1": None}}
    with pytest.raises(TypeError):
        m.encode_json({"x": object()})


def test_encode_json_fast_path_writes_what_the_careful_path_writes() -> None:
    # the C encoder handles a state with no NaN in it; the walk handles the rest: same text
    state = {"params": np.array([1.5, -2.0]), "n": np.int64(3), "f32": np.float32(0.25),
             "flags": (np.bool_(True), False), True: "t", None: 1, 2.5: "k",
             "nested": {"cov": np.eye(2), "s": "ä"}}
    walked = json.dumps(m._jsonable(state), separators=(",", ":"), allow_nan=False).encode()
    assert m.encode_json(state) == walked
    assert m.decode_json(walked)["true"] == "t" and m.decode_json(walked)["null"] == 1


def test_event_message_has_the_four_fields() -> None:
    event = m.decode_json(m.encode_event("connected", t_us=np.int64(12), sensor_id="s1",
                                         detail={"port": "/dev/ttyUSB0"}))
    assert event == {"t_us": 12, "kind": "connected", "sensor_id": "s1",
                     "detail": {"port": "/dev/ttyUSB0"}}
    assert m.decode_json(m.encode_event("start")) == {"t_us": None, "kind": "start",
                                                      "sensor_id": None, "detail": None}


def test_decode_json_rejects_garbage_with_value_error() -> None:
    for bad in (b"{", b"\xff\xfe", b""):
        with pytest.raises(ValueError):
            m.decode_json(bad)


def test_plot_messages_are_exact_per_sample_protobuf() -> None:
    batch = _calibrated(12)
    batch.a_g[3, 1] = np.nan
    batch.detector_g[4] = np.inf
    messages = m.encode_plot(batch)
    assert len(messages) == 12 and {len(d) for d in messages} == {m.PLOT_DTYPE.itemsize}
    for i, data in enumerate(messages):
        sample = m.decode_plot(data)
        official = OfficialPlot.FromString(data)  # the reference runtime reads the same
        assert set(sample) == {"t_us", "x_g", "y_g", "z_g", "norm_g", "quasi_static",
                               "detector_g", "status", "sigma_mg"}
        for name, value in sample.items():
            assert value == getattr(official, name) or (math.isnan(value)
                                                        and math.isnan(getattr(official, name)))
        assert sample["t_us"] == batch.t_us[i]
        assert sample["quasi_static"] is bool(batch.quasi_static[i])
        if i == 3:
            assert math.isnan(sample["y_g"]) and math.isnan(sample["norm_g"])
            continue
        # float32: the nearest to each double, within 1 micro-g below 16 g
        assert sample["x_g"] == np.float32(batch.a_g[i, 0])
        assert sample["z_g"] == np.float32(batch.a_g[i, 2])
        assert abs(sample["x_g"] - batch.a_g[i, 0]) < 1e-6
        assert sample["norm_g"] == np.float32(np.linalg.norm(batch.a_g[i]))
        assert sample["detector_g"] == np.float32(batch.detector_g[i])  # inf at 4 survives
        assert np.array_equal(sample["sigma_mg"], np.float32(batch.sigma_mg[i]), equal_nan=True)
    chosen = m.encode_plot(batch, [0, 5, 10])
    assert [m.decode_plot(d)["t_us"] for d in chosen] == batch.t_us[[0, 5, 10]].tolist()
    assert m.encode_plot(batch, np.array([], dtype=np.intp)) == []
    # what the official runtime writes (defaults omitted) decodes to the same sample
    official = OfficialPlot(t_us=int(batch.t_us[1]), x_g=float(batch.a_g[1, 0]))
    assert m.decode_plot(official.SerializeToString()) == {
        "t_us": int(batch.t_us[1]), "x_g": float(np.float32(batch.a_g[1, 0])), "y_g": 0.0,
        "z_g": 0.0,
        "norm_g": 0.0, "quasi_static": False, "detector_g": 0.0, "status": 0, "sigma_mg": 0.0}


@pytest.mark.parametrize("n", [0, 1, 77])
def test_the_device_time_field_round_trips_and_older_messages_still_decode(n: int) -> None:
    """Field 10 (t_dev) as the official runtime writes it (the same bytes) and reads it; a
    message written before it existed (the official runtime, without field 10) decodes with
    t_dev None and the rest unchanged."""
    rng = np.random.default_rng(n)
    base = _calibrated(n)
    t_dev = rng.integers(-2**40, 2**40, n, dtype=np.int64)
    status = rng.integers(1, 6, n).astype(np.uint8)
    batch = CalibratedBatch(base.t_us, base.a_g, base.quasi_static, base.detector_g, status,
                            rng.random(n), t_dev)
    ours = m.encode_calibrated("s1", batch)
    back = m.decode_calibrated(ours)[1]
    _assert_calibrated_equal(back, batch)
    if n:  # (an empty packed field is omitted, as protobuf does)
        assert back.t_dev is not None and np.array_equal(back.t_dev, t_dev)
    official = OfficialCalibrated.FromString(ours)
    assert list(official.t_dev) == t_dev.tolist()
    msg = OfficialCalibrated(sensor_id="s1", t_us=batch.t_us.tolist(),
                             x_g=batch.a_g[:, 0].tolist(), y_g=batch.a_g[:, 1].tolist(),
                             z_g=batch.a_g[:, 2].tolist(),
                             quasi_static=batch.quasi_static.tolist(),
                             detector_g=batch.detector_g.tolist(), status=status.tolist(),
                             sigma_mg=batch.sigma_mg.tolist(), t_dev=t_dev.tolist())
    assert msg.SerializeToString() == ours
    old = m.decode_calibrated(_official_calibrated("s1", batch))[1]
    _assert_calibrated_equal(old, batch)
    assert old.t_dev is None
    if n > 1:  # a length that differs from t_us is a malformed message
        short = m.encode_calibrated("s1", base) + bytes([0x52, 8]) + t_dev[:1].tobytes()
        with pytest.raises(ValueError, match="t_dev"):
            m.decode_calibrated(short)


def test_device_time_attached_to_a_batch_is_the_same_as_built_with_it() -> None:
    rng = np.random.default_rng(11)
    n = 7
    fields = (rng.integers(0, 2**40, n, dtype=np.int64), rng.normal(size=(n, 3)),
              rng.random(n) > 0.5, rng.random(n), rng.integers(1, 6, n).astype(np.uint8),
              rng.random(n))
    t_dev = rng.integers(0, 2**31, n, dtype=np.int32)  # converted like any time stamps
    built = CalibratedBatch(*fields, t_dev)
    attached = CalibratedBatch(*fields).with_device_time(t_dev)
    assert attached.t_dev is not None and attached.t_dev.dtype == np.int64
    assert m.encode_calibrated("s", attached) == m.encode_calibrated("s", built)
    with pytest.raises(ValueError, match="differ in length"):
        CalibratedBatch(*fields).with_device_time(t_dev[:-1])


def test_multi_byte_status_varints_decode_like_single_bytes_and_large_ones_as_not_recorded(
        ) -> None:
    data = m.encode_calibrated("s", _calibrated(4))  # (no statuses: all not recorded)
    sigma = _key(9, 2) + _varint(32) + struct.pack("<4d", 1.0, 2.0, 3.0, 4.0)
    # the statuses as one packed run of non-canonical and large varints: 0x83 0x00 is 3,
    # 0x82 0x80 0x00 is 2, 0x80 0x02 is 256 (beyond any status: 0, not recorded), 0x05
    run = b"\x83\x00\x82\x80\x00\x80\x02\x05"
    _, ours = m.decode_calibrated(data + _key(8, 2) + _varint(len(run)) + run + sigma)
    assert ours.status.tolist() == [3, 2, 0, 5]
    assert ours.status.tolist() == [s if s < 256 else 0 for s in
                                    OfficialCalibrated.FromString(data + _key(8, 2) + _varint(
                                        len(run)) + run + sigma).status]
    with pytest.raises(ValueError, match="ends inside a varint"):
        m.decode_calibrated(data + _key(8, 2) + _varint(2) + b"\x05\x83" + sigma)
