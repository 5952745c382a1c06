"""The log's compact form: what it keeps, that the official protobuf runtime (Foxglove's view)
reads it, that batches arriving one at a time are joined per flush, and that a recording in the
first, float64 form (a fixture written by that release) still replays, exports and calibrates."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recal import cli
from recal.commands.replay import replay
from recal.io import messages as m
from recal.io import protobuf_wire
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.samples import CalibratedBatch, RawBatch

FIXTURE = Path(__file__).parent / "fixtures" / "release_0_demo.mcap"
SID = "demo"  # the fixture's sensor


def _calibrated(n: int, seed: int = 0, t0: int = 1_700_000_000_000_000) -> CalibratedBatch:
    rng = np.random.default_rng(seed)
    t_us = t0 + np.cumsum(rng.integers(9_000, 11_000, n))
    return CalibratedBatch(t_us, rng.normal(0.0, 1.5, (n, 3)), rng.random(n) < 0.5,
                           rng.random(n) * 0.2, rng.integers(1, 6, n).astype(np.uint8),
                           rng.random(n) * 50.0, t_us // 1000 - 7)


def _raw(n: int, seed: int = 0) -> RawBatch:
    rng = np.random.default_rng(seed)
    t_us = np.arange(n, dtype=np.int64) * 10_000 - 5_000_000
    return RawBatch(t_us, rng.integers(-32768, 32768, (n, 3)).astype(float),
                    rng.normal(30.0, 1.0, (n, 1)), ("temp_c",))


# ---------------------------------------------------------------------------------------------
# The compact form
# ---------------------------------------------------------------------------------------------

def test_compact_calibrated_keeps_values_to_half_a_micro_g_and_integers_exactly() -> None:
    batch = _calibrated(700)
    sid, got = m.decode_calibrated(m.encode_calibrated_compact("s1", batch))
    assert sid == "s1"
    assert np.array_equal(got.t_us, batch.t_us) and np.array_equal(got.t_dev, batch.t_dev)
    assert np.max(np.abs(got.a_g - batch.a_g)) <= 0.5e-6 + 1e-12
    assert np.max(np.abs(got.detector_g - batch.detector_g)) <= 1e-6 + 1e-12
    # sigma on its 1 % ladder: within half a step (0.5 %), the step itself kept exactly
    assert np.all(np.abs(got.sigma_mg - batch.sigma_mg) <= 0.005 * batch.sigma_mg + 1e-12)
    assert np.array_equal(got.sigma_mg, m.sigma_steps(batch.sigma_mg))
    assert np.array_equal(got.status, batch.status)
    assert np.array_equal(got.quasi_static, batch.quasi_static)
    assert len(m.encode_calibrated_compact("s1", batch)) < 0.6 * len(
        m.encode_calibrated("s1", batch))
    assert m.batch_extent(m.encode_calibrated_compact("s1", batch)) == (
        700, int(batch.t_us[0]), int(batch.t_us[-1]))


def test_sigma_steps_are_one_percent_apart_and_a_wandering_sigma_logs_as_zero_deltas() -> None:
    sigma = np.array([0.0, -1.0, np.inf, np.nan, 1.0, 180.27, 180.37, 180.19, 181.9, 0.01])
    steps = m.sigma_steps(sigma)
    assert np.array_equal(steps[:4], sigma[:4], equal_nan=True)  # as they are
    k = np.log(steps[4:]) / np.log(1.01)
    assert np.allclose(k, np.rint(k), atol=1e-9) and steps[4] == 1.0
    assert np.all(np.abs(steps[4:] / sigma[4:] - 1.0) <= 0.005 + 1e-12)
    # a sigma wandering by parts per thousand stays on one step: deltas 0 after the first
    rng = np.random.default_rng(1)
    batch = _calibrated(200)
    batch.sigma_mg[:] = 180.4 * (1.0 + 1e-3 * rng.standard_normal(200))
    official = m.protobuf_message_class("recal.CalibratedBatch").FromString(
        m.encode_calibrated_compact("s1", batch))
    assert list(official.sigma_step_delta)[1:] == [0] * 199
    assert not official.sigma_ug_delta


def test_compact_raw_keeps_integer_counts_and_falls_back_to_float64_otherwise() -> None:
    batch = _raw(300)
    _, got = m.decode_raw(m.encode_raw_compact("s1", batch))
    assert np.array_equal(got.t_us, batch.t_us) and np.array_equal(got.v, batch.v)
    assert got.aux_names == batch.aux_names and np.array_equal(got.aux, batch.aux)
    floats = RawBatch(batch.t_us, batch.v / 1024.0, batch.aux, batch.aux_names)
    _, got = m.decode_raw(m.encode_raw_compact("s1", floats))
    assert np.array_equal(got.v, floats.v)  # not integers: float64 as before, exact


def test_values_the_fixed_point_cannot_hold_stay_float64_per_column() -> None:
    batch = _calibrated(50)
    batch.a_g[3, 1] = np.nan
    batch.sigma_mg[7] = np.inf  # a zeroed, non-finite sample's sigma
    batch.t_us[20:] += 3_000_000_000  # a gap beyond int32 microseconds
    _, got = m.decode_calibrated(m.encode_calibrated_compact("s1", batch))
    assert np.array_equal(got.a_g, batch.a_g, equal_nan=True)
    assert np.array_equal(got.sigma_mg, m.sigma_steps(batch.sigma_mg))  # float64, its steps
    assert np.isinf(got.sigma_mg[7])
    assert np.array_equal(got.t_us, batch.t_us)
    assert np.max(np.abs(got.detector_g - batch.detector_g)) <= 1e-6 + 1e-12


def test_the_official_protobuf_runtime_reads_the_compact_form() -> None:
    batch = _calibrated(40)
    official = m.protobuf_message_class("recal.CalibratedBatch").FromString(
        m.encode_calibrated_compact("s1", batch))
    assert official.sensor_id == "s1" and official.t0_us == batch.t_us[0]
    assert list(official.dt_us) == np.diff(batch.t_us).tolist()
    x_ug = np.rint(batch.a_g[:, 0] * 1e6).astype(int)
    assert list(official.x_ug_delta) == np.diff(x_ug, prepend=0).tolist()
    k = np.rint(np.log(m.sigma_steps(batch.sigma_mg)) / np.log1p(m.SIGMA_STEP)).astype(int)
    assert list(official.sigma_step_delta) == np.diff(k, prepend=0).tolist()
    detector_2ug = np.rint(batch.detector_g * 5e5).astype(int)
    assert list(official.detector_2ug_delta2) == np.diff(np.diff(detector_2ug, prepend=0),
                                                         prepend=0).tolist()
    assert list(official.t_dev_offset_delta) == np.diff(batch.t_dev - batch.t_us,
                                                        prepend=0).tolist()
    raw = _raw(30)
    data = m.encode_raw_compact("s1", raw, ([10, 20], [0, 999]))  # (log times: deltas)
    official = m.protobuf_message_class("recal.RawBatch").FromString(data)
    assert list(official.y_counts_delta) == np.diff(raw.v[:, 1], prepend=0).astype(int).tolist()
    assert list(official.arrival_samples) == [10, 20]
    # each arrival's log time less its last device time after the first, as deltas
    lag = np.array([0, 999]) - (raw.t_us[[9, 29]] - raw.t_us[0])
    assert list(official.arrival_lag_delta_us) == np.diff(lag, prepend=0).tolist()
    _, back, arrivals = m.decode_raw_arrivals(data)
    assert arrivals is not None and np.array_equal(back.v, raw.v)
    sizes, log_us = arrivals
    assert sizes.tolist() == [10, 20] and log_us is not None and log_us.tolist() == [0, 999]
    assert m.decode_raw_arrivals(m.encode_raw_compact("s1", raw))[2] is None  # one arrival
    with pytest.raises(ValueError, match="add up"):
        m.decode_raw_arrivals(m.encode_raw_compact("s1", raw, ([10, 19], [0, 999])))


# ---------------------------------------------------------------------------------------------
# Joining in the writer
# ---------------------------------------------------------------------------------------------

class _Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def test_single_sample_arrivals_are_joined_per_flush_with_their_arrivals(tmp_path: Path) -> None:
    clock = _Clock()
    raw, cal = _raw(250), _calibrated(250)
    path = tmp_path / "joined.mcap"
    with RecordingWriter(path, clock=clock, background_flush=False, fsync=False) as w:
        for i in range(250):  # one sample per arrival, 100 Hz, a flush every second
            clock.now_s = i / 100.0
            log_ns = 10**18 + i * 10_000_000
            bus = w.write_raw(SID, raw[i:i + 1], log_ns)
            assert m.decode_raw(bus)[1].v.tolist() == raw.v[i:i + 1].tolist()  # float64 form
            w.write_calibrated(SID, cal[i:i + 1], log_ns)
    logged = list(rec.iter_raw_logged(path))
    # one message per flush interval (a write that finds a flush due is in it)
    assert [len(b) for _, b, _, _ in logged] == [101, 100, 49]
    joined = RawBatch.concat([b for _, b, _, _ in logged])
    assert np.array_equal(joined.v, raw.v) and np.array_equal(joined.t_us, raw.t_us)
    assert logged[1][3] is not None
    sizes, log_us = logged[1][3]
    assert sizes.tolist() == [1] * 100 and log_us is not None
    assert log_us.tolist() == list(range(0, 1_000_000, 10_000))
    assert logged[1][2].log_time_ns == 10**18 + 101 * 10_000_000
    got = rec.read_all_calibrated(path, SID)
    assert np.array_equal(got.t_us, cal.t_us)
    assert np.max(np.abs(got.a_g - cal.a_g)) <= 0.5e-6 + 1e-12


# ---------------------------------------------------------------------------------------------
# A recording in the first form (float64, a message per arrival) still works
# ---------------------------------------------------------------------------------------------

def test_fixture_of_the_first_form_reads_back() -> None:
    raw = rec.read_all_raw(FIXTURE, SID)
    cal = rec.read_all_calibrated(FIXTURE, SID)
    body = rec.read_all_calibrated(FIXTURE, SID, "body")
    assert len(raw) == len(cal) > 10_000 and 0 < len(body) < len(cal)
    assert np.array_equal(raw.v, np.rint(raw.v))  # ADC counts
    assert (cal.status == 3).any()  # calibrated by the end
    assert rec.summary(FIXTURE).message_count > 2000


@pytest.mark.float_sensitive
def test_fixture_of_the_first_form_replays_to_what_its_live_run_logged(tmp_path: Path) -> None:
    out = tmp_path / "again.mcap"
    summary = replay(FIXTURE, out, progress=False)
    assert summary["sensors"][SID]["start"] == "recording"
    live = rec.read_all_calibrated(FIXTURE, SID)
    again = rec.read_all_calibrated(out, SID)
    assert np.array_equal(again.t_us, live.t_us)
    assert np.array_equal(again.status, live.status)
    assert np.array_equal(again.quasi_static, live.quasi_static)
    assert np.max(np.abs(again.a_g - live.a_g)) <= 1e-6  # the log keeps 0.5 ug
    assert np.array_equal(rec.read_all_raw(out, SID).v, rec.read_all_raw(FIXTURE, SID).v)
    live_states = [o["params"] for _, o, _ in rec.iter_json(FIXTURE, f"/{SID}/calibration")]
    again_states = [o["params"] for _, o, _ in rec.iter_json(out, f"/{SID}/calibration")]
    # the fixture was written on another CPU: the same parameters, to the last bits' worth
    assert len(again_states) == len(live_states)
    for a, b in zip(again_states, live_states, strict=True):
        assert a.keys() == b.keys()
        for name in a:
            assert a[name] == pytest.approx(b[name], rel=1e-9, abs=1e-9), name
    assert FIXTURE.stat().st_size > 2 * out.stat().st_size  # (plot and setup as they were)


def test_fixture_of_the_first_form_exports_and_calibrates(tmp_path: Path) -> None:
    live = _exported_as_logged(FIXTURE, SID, tmp_path)
    out = tmp_path / "hind.mcap"
    assert cli.main(["hindsight", str(FIXTURE), "--out", str(out), "--quiet"]) in (0, 1)
    if out.exists():
        assert len(rec.read_all_calibrated(out, SID)) == len(live)


@pytest.mark.parametrize("n", [0, 1])
def test_tiny_batches_round_trip(n: int) -> None:
    cal = _calibrated(n)
    _, got = m.decode_calibrated(m.encode_calibrated_compact("s", cal))
    assert np.array_equal(got.t_us, cal.t_us) and len(got) == n
    raw = _raw(n)
    _, got_raw = m.decode_raw(m.encode_raw_compact("s", raw))
    assert np.array_equal(got_raw.v, raw.v) and len(got_raw) == n


def test_zigzag_varints_of_every_width_read_back_by_the_official_runtime() -> None:
    rng = np.random.default_rng(5)
    widths = [rng.integers(-(2**k), 2**k, 50) for k in range(0, 63, 7)]
    extremes = np.array([np.iinfo(np.int64).min, -1, 0, 1, np.iinfo(np.int64).max])
    columns = [np.concatenate(widths), np.zeros(0, np.int64), extremes, np.array([-64, 63, 64])]
    encoded = m.zigzag_varints_many(columns)
    assert encoded[1] == b""
    official = m.protobuf_message_class("recal.RawBatch")
    for column, data in zip(columns, encoded, strict=True):
        if not len(column):
            continue
        msg = official.FromString(bytes([12 << 3 | 2]) + protobuf_wire._varint(len(data)) + data)
        assert list(msg.dt_us) == column.tolist()  # (field 12, sint64)
        assert m.unzigzag_varints(np.frombuffer(data, np.uint8), "t").tolist() == column.tolist()
    assert len(encoded[3]) == 1 + 1 + 2  # 127 and 126 fit one byte, 128 takes two


def test_the_log_keeps_the_body_as_times_and_a_rotation_and_reads_it_back(tmp_path: Path
                                                                          ) -> None:
    from recal.core.alignment import to_body
    from recal.node.sinks import RecordingSink

    r = np.array([[0.99, -0.1, 0.0], [0.1, 0.99, 0.0], [0.0, 0.0, 1.0]])
    r2 = r.T.copy()  # a second mounting, from a later alignment
    cal = _calibrated(300)
    path = tmp_path / "body.mcap"
    with RecordingWriter(path, background_flush=False, fsync=False) as w:
        sink = RecordingSink(w)
        sink.json(SID, "events", {"kind": "alignment", "detail": {"rotation": r.tolist()}}, 1)
        for i in range(300):  # one sample per arrival: calibrated, then rotated (as a node)
            if i == 200:
                sink.json(SID, "calibration", {"alignment": {"rotation": r2.tolist()}}, 1)
            one = cal[i:i + 1]
            sink.calibrated(SID, one, 10**18 + i)
            rot = r if i < 200 else r2
            body = CalibratedBatch(one.t_us, to_body(rot, one.a_g), one.quasi_static,
                                   one.detector_g, one.status, one.sigma_mg, one.t_dev)
            if i == 250:  # not what the rotation gives: logged as the values it has
                body.a_g[0, 0] += 1e-3
            sink.calibrated(SID, body, 10**18 + i, "body")
    data = [mm.data for mm in rec.iter_messages(path, f"/{SID}/body")]
    forms = [m.decode_body_rotation(d) is not None for d in data]
    assert forms == [True, True, False, True]  # r, r2, the odd one, r2 again
    official = m.protobuf_message_class("recal.CalibratedBatch").FromString(data[0])
    assert list(official.body_rotation) == r.reshape(9).tolist() and len(official.dt_us) == 199
    # 200 samples as their times and 9 doubles, against their values
    assert len(data[0]) < 0.25 * len(m.encode_calibrated_compact(SID, cal[:200]))
    with pytest.raises(ValueError, match="rotation"):
        m.decode_calibrated(data[0])
    got = rec.read_all_calibrated(path, SID, "body")
    logged = rec.read_all_calibrated(path, SID)
    want = np.concatenate([to_body(r, logged.a_g[:200]), to_body(r2, logged.a_g[200:])])
    want[250, 0] = cal.a_g[250] @ r2[0] + 1e-3
    assert np.array_equal(got.t_us, cal.t_us) and np.array_equal(got.status, cal.status)
    assert np.max(np.abs(got.a_g - want)) <= 1e-6  # (the odd sample: its own micro-g)
    # within a micro-g of the body the node computed (the calibrated values' micro-g, turned)
    exact = np.concatenate([to_body(r, cal.a_g[:200]), to_body(r2, cal.a_g[200:])])
    exact[250, 0] += 1e-3
    assert np.max(np.abs(got.a_g - exact)) <= 0.87e-6


def test_a_body_rotation_is_logged_as_its_quaternion_and_any_other_matrix_as_it_is() -> None:
    from scipy.spatial.transform import Rotation

    t_us = np.arange(100, dtype=np.int64) * 10_000
    official = m.protobuf_message_class("recal.CalibratedBatch")
    for seed in range(50):
        r = Rotation.random(random_state=seed).as_matrix()
        data = m.encode_body_rotation("s1", t_us, r)
        msg = official.FromString(data)
        assert len(msg.body_quaternion) == 4 and not msg.body_rotation
        assert msg.body_quaternion[0] >= 0.0
        _, got_t, got_r = m.decode_body_rotation(data)
        assert np.array_equal(got_t, t_us) and np.max(np.abs(got_r - r)) <= 1e-14
    skewed = np.array([[0.99, -0.1, 0.0], [0.1, 0.99, 0.0], [0.0, 0.0, 1.0]])  # not a rotation
    msg = official.FromString(m.encode_body_rotation("s1", t_us, skewed))
    assert list(msg.body_rotation) == skewed.reshape(9).tolist() and not msg.body_quaternion


# ---------------------------------------------------------------------------------------------
# A recording in the first compact form (before the second: sigma steps, the detector's second
# differences, device stamps from t_us, arrival lags, the body's quaternion) still works
# ---------------------------------------------------------------------------------------------

FIXTURE_V1 = Path(__file__).parent / "fixtures" / "compact_v1_steady.mcap"
SID_V1 = "s1"


def _relog(src: Path, dst: Path) -> None:
    """Every batch of ``src`` logged again by today's writer, as logged (arrivals kept, the
    body as its times and rotation)."""
    with RecordingWriter(dst, background_flush=False, fsync=False) as w:
        for mm in rec.iter_messages(src):
            suffix = mm.topic.rsplit("/", 1)[1]
            if suffix == "raw":  # a new second: the last one's messages out, as logged
                w.flush()
                _, batch, arrivals = m.decode_raw_arrivals(mm.data)
                w.log_raw(SID_V1, batch, mm.log_time_ns, arrivals)
            elif suffix == "calibrated":
                w.log_calibrated(SID_V1, m.decode_calibrated(mm.data)[1], mm.log_time_ns)
            elif suffix == "body":
                body = m.decode_body_rotation(mm.data)
                assert body is not None  # (the fixture's body is all in the rotation form)
                cal = rec.read_all_calibrated(src, SID_V1)
                i = np.searchsorted(cal.t_us, body[1])
                w.log_body(SID_V1, cal[i], body[2], mm.log_time_ns)


def test_fixture_of_the_first_compact_form_reads_back_and_logs_again_the_same(
        tmp_path: Path) -> None:
    raw = list(rec.iter_raw_logged(FIXTURE_V1, SID_V1))
    assert len(raw) == 20 and all(a is not None and a[0].tolist() == [1] * len(b)
                                  for _, b, _, a in raw)
    cal = rec.read_all_calibrated(FIXTURE_V1, SID_V1)
    body = rec.read_all_calibrated(FIXTURE_V1, SID_V1, "body")
    assert len(cal) == len(body) == sum(len(b) for _, b, _, _ in raw) == 2000
    assert np.isin(cal.status, (3, 4)).all() and np.all(np.isfinite(cal.sigma_mg))
    again = tmp_path / "again.mcap"
    _relog(FIXTURE_V1, again)
    # the same samples in today's form: raw, times, statuses and arrivals exactly, values as
    # logged, the detector within its 2 micro-g steps, sigma on the same 1 % step (the old
    # form kept the step to the micro-g)
    raw2 = list(rec.iter_raw_logged(again, SID_V1))
    for (_, b1, m1, a1), (_, b2, m2, a2) in zip(raw, raw2, strict=True):
        assert np.array_equal(b1.v, b2.v) and np.array_equal(b1.t_us, b2.t_us)
        assert a1 is not None and a2 is not None and a1[1] is not None and a2[1] is not None
        assert np.array_equal(a1[0], a2[0]) and np.array_equal(a1[1], a2[1])
        assert m1.log_time_ns == m2.log_time_ns
    cal2 = rec.read_all_calibrated(again, SID_V1)
    assert np.array_equal(cal2.t_us, cal.t_us) and np.array_equal(cal2.t_dev, cal.t_dev)
    assert np.array_equal(cal2.status, cal.status)
    assert np.array_equal(cal2.quasi_static, cal.quasi_static)
    assert np.max(np.abs(cal2.a_g - cal.a_g)) <= 1e-12
    assert np.max(np.abs(cal2.detector_g - cal.detector_g)) <= 1.5e-6
    assert np.max(np.abs(cal2.sigma_mg - cal.sigma_mg)) <= 0.5e-3 + 1e-12
    body2 = rec.read_all_calibrated(again, SID_V1, "body")
    assert np.array_equal(body2.t_us, body.t_us)
    assert np.max(np.abs(body2.a_g - body.a_g)) <= 1e-12
    official = m.protobuf_message_class("recal.CalibratedBatch").FromString(
        next(rec.iter_messages(again, f"/{SID_V1}/body")).data)
    assert len(official.body_quaternion) == 4 and not official.body_rotation
    assert again.stat().st_size < FIXTURE_V1.stat().st_size


def test_fixture_of_the_first_compact_form_replays_and_exports(tmp_path: Path) -> None:
    out = tmp_path / "replayed.mcap"
    replay(FIXTURE_V1, out, progress=False)
    assert np.array_equal(rec.read_all_raw(out, SID_V1).v, rec.read_all_raw(FIXTURE_V1, SID_V1).v)
    assert len(rec.read_all_calibrated(out, SID_V1)) == 2000
    _exported_as_logged(FIXTURE_V1, SID_V1, tmp_path)


def _exported_as_logged(fixture: Path, sid: str, tmp_path: Path) -> CalibratedBatch:
    """`recal export` of a fixture gives its logged calibrated values (to the micro-g);
    those values."""
    csv = tmp_path / "cal.csv"
    assert cli.main(["export", str(fixture), "--csv", str(csv)]) == 0
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    live = rec.read_all_calibrated(fixture, sid)
    assert len(rows) == len(live)
    assert np.allclose(rows[:, 1:4], live.a_g, rtol=0, atol=1e-6)
    return live
