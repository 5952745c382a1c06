"""bench/regression_check.py's comparisons must be able to fail: a changed payload byte, a last
bit of a float, a -0.0 for a 0.0 are differences; metadata naming a version is not."""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from bench_modules import load_bench
from recal.io import messages
from recal.io.recording_writer import RecordingWriter
from recal.samples import CalibratedBatch, RawBatch

rc = load_bench("regression_check")


def _mcap(path: Path, payloads: list[bytes], metadata: dict[str, str] | None = None) -> Path:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        schema = w.register_schema("s", "jsonschema", b"{}")
        channel = w.register_channel("/a/calibration", "json", schema)
        for i, p in enumerate(payloads):
            w.add_message(channel, log_time=1000 + i, data=p, publish_time=1000 + i)
        w.add_metadata("recal", metadata or {"version": "1"})
        w.finish()
    return path


def test_mcap_identical_files_are_identical(tmp_path: Path) -> None:
    msgs = [json.dumps({"x": 0.1 * i}).encode() for i in range(5)]
    a, b = _mcap(tmp_path / "a.mcap", msgs), _mcap(tmp_path / "b.mcap", msgs)
    assert rc.mcap_verdict(a, b) == ("identical", "file bytes identical")


def test_mcap_one_changed_payload_is_found_with_its_message(tmp_path: Path) -> None:
    msgs = [json.dumps({"x": 0.1 * i}).encode() for i in range(5)]
    changed = list(msgs)
    changed[3] = json.dumps({"x": np.nextafter(0.1 * 3, 1.0)}).encode()  # one float's last bit
    verdict, note = rc.mcap_verdict(_mcap(tmp_path / "a.mcap", msgs),
                                    _mcap(tmp_path / "b.mcap", changed))
    assert verdict.startswith("message 3 (/a/calibration @ 1003)")
    assert "/x" in verdict and "max rel diff" in verdict
    assert note.startswith("file bytes differ")


def test_mcap_missing_message_is_a_difference(tmp_path: Path) -> None:
    msgs = [b'{"x": 1}', b'{"x": 2}']
    verdict, _ = rc.mcap_verdict(_mcap(tmp_path / "a.mcap", msgs),
                                 _mcap(tmp_path / "b.mcap", msgs[:1]))
    assert verdict == "2 vs 1 messages"


def test_mcap_version_metadata_is_named_but_not_a_difference(tmp_path: Path) -> None:
    msgs = [b'{"x": 1}']
    a = _mcap(tmp_path / "a.mcap", msgs, {"version": "0.9"})
    b = _mcap(tmp_path / "b.mcap", msgs, {"version": "1.0"})
    verdict, note = rc.mcap_verdict(a, b)
    assert verdict == "identical"
    assert "metadata recal.version '0.9' vs '1.0'" in note
    c = _mcap(tmp_path / "c.mcap", msgs, {"version": "0.9", "replay_of": "x.mcap"})
    assert rc.mcap_verdict(a, c)[0].startswith("metadata differs")


def test_json_floats_compare_bit_for_bit_and_timings_are_left_out() -> None:
    a = {"seconds": 1.0, "p": {"o": [1.0, 2.0]}, "n": 3}
    assert rc.json_verdict(a, {**a, "seconds": 2.0}) == "identical"
    b = {**a, "p": {"o": [1.0, float(np.nextafter(2.0, 3.0))]}}
    verdict = rc.json_verdict(a, b)
    assert verdict.startswith("1 differences, first /p/o[1]") and "max rel diff 2.22e-16" in verdict
    assert rc.json_verdict(a, {**a, "n": 3.0}) != "identical"  # an int became a float
    assert rc.json_verdict({"a": 1, "b": 2}, {"b": 2, "a": 1}) == ("1 differences, first /: "
                                                                   "key order differs")


@pytest.mark.parametrize(("x", "y", "same"), [
    (np.array([0.0, 1.0]), np.array([-0.0, 1.0]), False),
    (np.array([np.nan, 1.0]), np.array([np.nan, 1.0]), True),
    (np.array([1, 2], np.int64), np.array([1, 2], np.int32), False),
    (np.zeros((4, 3)), np.zeros((4, 3)), True),
])
def test_arrays_compare_bytes(x: np.ndarray, y: np.ndarray, same: bool) -> None:
    assert (rc.array_verdict("a", x, y) == "identical") is same


def test_array_difference_says_where_and_how_much() -> None:
    a = np.zeros((10, 3))
    b = a.copy()
    b[7, 1] = 2e-3
    assert rc.array_verdict("a_g", a, b) == ("a_g: 1 of 10 rows differ, first at row 7; max abs "
                                             "diff 0.002")


def test_stdout_timings_are_masked_and_the_rest_compared() -> None:
    old = "replayed 45000 samples of 1 sensor(s) in 0.12 s (0.38 M samples/s) into y.mcap"
    new = "replayed 45000 samples of 1 sensor(s) in 0.31 s (0.14 M samples/s) into y.mcap"
    assert rc.text_verdict(rc.mask_stdout(old), rc.mask_stdout(new)) == "identical"
    assert rc.text_verdict(rc.mask_stdout(old), rc.mask_stdout(new.replace("45000", "45001"))
                           ).startswith("line 1:")


def test_mcap_changed_schema_is_a_difference(tmp_path: Path) -> None:
    a = _mcap(tmp_path / "a.mcap", [b'{"x": 1}'])
    b = tmp_path / "b.mcap"
    with open(b, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        schema = w.register_schema("s", "jsonschema", b'{"type": "object"}')
        channel = w.register_channel("/a/calibration", "json", schema)
        w.add_message(channel, log_time=1000, data=b'{"x": 1}', publish_time=1000)
        w.add_metadata("recal", {"version": "1"})
        w.finish()
    assert rc.mcap_verdict(a, b)[0] == "channel or schema of /a/calibration differs"


def test_scalar_arrays_compare() -> None:
    assert rc.array_verdict("k", np.float64(1.0), np.float64(1.0)) == "identical"
    assert rc.array_verdict("k", np.array(1.0), np.array(2.0)).startswith("k: 1 of 1 rows")


@pytest.fixture
def tolerate_x() -> Iterator[None]:
    rc.TOLERATE["x"] = 1e-12
    try:
        yield
    finally:
        rc.TOLERATE.clear()


def test_tolerated_names_pass_within_and_fail_beyond(tolerate_x: None) -> None:
    a = np.array([1.0, 2.0])
    assert rc.array_verdict("x", a, a + 1e-13).startswith(rc.WITHIN)
    assert not rc.array_verdict("x", a, a + 1e-11).startswith(rc.WITHIN)
    assert not rc.array_verdict("y", a, a + 1e-13).startswith(rc.WITHIN)  # others: bit for bit
    assert not rc.array_verdict("x", a, np.array([np.nan, 2.0])).startswith(rc.WITHIN)
    assert rc.json_verdict({"d": {"x": [1.0]}}, {"d": {"x": [1.0 + 1e-13]}}).startswith(rc.WITHIN)
    verdict = rc.json_verdict({"x": 1.0, "y": 1.0}, {"x": 1.0 + 1e-13, "y": 1.5})
    assert verdict.startswith("1 differences, first /y")


def test_a_tolerated_message_does_not_hide_a_later_difference(tmp_path: Path,
                                                              tolerate_x: None) -> None:
    msgs = [json.dumps({"x": 0.1 * i, "y": i}).encode() for i in range(5)]
    close = [json.dumps({"x": 0.1 * i + 1e-14, "y": i}).encode() for i in range(5)]
    a = _mcap(tmp_path / "a.mcap", msgs)
    verdict, _ = rc.mcap_verdict(a, _mcap(tmp_path / "b.mcap", close))
    assert verdict.startswith(f"{rc.WITHIN}: 5 messages")
    close[4] = json.dumps({"x": 0.4, "y": 5}).encode()
    verdict, _ = rc.mcap_verdict(a, _mcap(tmp_path / "c.mcap", close))
    assert verdict.startswith("message 4") and "/y" in verdict
    assert not rc.Row("c", "m", verdict).ok


def test_plot_payloads_compare_field_by_field(tolerate_x: None) -> None:
    from recal.io import messages
    from recal.samples import CalibratedBatch

    def plot(detector_g: float, x_g: float) -> bytes:
        batch = CalibratedBatch(t_us=np.array([5], np.int64), a_g=np.array([[x_g, 0.0, 1.0]]),
                                quasi_static=np.array([True]), detector_g=np.array([detector_g]),
                                status=np.array([3], np.uint8), sigma_mg=np.array([0.5]))
        return messages.encode_plot(batch)[0]

    rc.TOLERATE["detector_g"] = 1e-8  # the plot's values are float32: steps of ~1e-9 at 0.01
    name = messages.PLOT_MESSAGE_NAME
    assert rc.payload_diff(name, plot(0.01, 0.1), plot(0.01 + 5e-9, 0.1)).startswith(
        f"payload {rc.WITHIN}: detector_g")
    assert rc.payload_diff(name, plot(0.01, 0.1), plot(0.01 + 5e-9, 0.1 + 1e-7)).startswith(
        "payload x_g: 1 of 1 rows differ")


def test_plot_of_doubles_compares_to_float32_plot() -> None:
    """An older log's plot sample (doubles) against the same sample as the plot logs it now
    (float32): within the format's rounding, and a real difference is still one."""
    from recal.io import messages

    def doubles(x_g: float) -> bytes:  # the older PlotSample: every value a double
        norm = math.sqrt(x_g * x_g + 1.0)
        return struct.pack("<BqBdBdBdBdBBBdBBBd", 1 << 3 | 1, 5, 2 << 3 | 1, x_g, 3 << 3 | 1,
                           0.0, 4 << 3 | 1, 1.0, 5 << 3 | 1, norm, 6 << 3, 1, 7 << 3 | 1, 0.01,
                           8 << 3, 3, 9 << 3 | 1, 0.5)

    batch = CalibratedBatch(t_us=np.array([5], np.int64), a_g=np.array([[0.1, 0.0, 1.0]]),
                            quasi_static=np.array([True]), detector_g=np.array([0.01]),
                            status=np.array([3], np.uint8), sigma_mg=np.array([0.5]))
    new = messages.encode_plot(batch)[0]
    old = doubles(0.1)
    assert len(new) < len(old) and messages.decode_plot(old)["x_g"] == 0.1
    assert abs(messages.decode_plot(new)["x_g"] - 0.1) < 1e-8
    name = messages.PLOT_MESSAGE_NAME
    assert rc.payload_diff(name, old, new) == f"payload {rc.WITHIN} (the plot's float32)"
    assert rc.payload_diff(name, doubles(0.1 + 1e-6), new).startswith("payload x_g")


def _batches_mcap(path: Path, cal: CalibratedBatch, raw: RawBatch, joined: bool) -> Path:
    """The first form (a float64 message per batch of 10) or the compact, joined one."""
    with RecordingWriter(path, background_flush=False, fsync=False, overwrite=True,
                         log_batch_samples=8192 if joined else 1) as w:
        for i in range(0, len(cal), 10):
            log_ns = 10**18 + i
            if joined:
                w.log_raw("s", raw[i:i + 10], log_ns)
                w.log_calibrated("s", cal[i:i + 10], log_ns)
            else:
                w.write_encoded("/s/raw", messages.encode_raw("s", raw[i:i + 10]), log_ns)
                w.write_encoded("/s/calibrated", messages.encode_calibrated("s", cal[i:i + 10]),
                                log_ns, schema=messages.CALIBRATED_SCHEMA)
    return path


def _random_calibrated(rng: np.random.Generator, n: int) -> tuple[np.ndarray, CalibratedBatch]:
    """n samples 10 ms apart with random values in every column, and their times."""
    t = np.arange(n, dtype=np.int64) * 10_000
    return t, CalibratedBatch(t, rng.normal(size=(n, 3)), rng.random(n) < 0.5,
                              rng.random(n) * 0.1, np.full(n, 3, np.uint8),
                              rng.random(n) * 5.0, t)


def test_batch_topics_compare_as_samples_within_the_log_micro_g_and_no_further(
        tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 100
    t, cal = _random_calibrated(rng, n)
    raw = RawBatch(t, rng.integers(-900, 900, (n, 3)).astype(float), np.zeros((n, 0)))
    first = _batches_mcap(tmp_path / "first.mcap", cal, raw, joined=False)
    verdict, _ = rc.mcap_verdict(first, _batches_mcap(tmp_path / "c.mcap", cal, raw, True))
    assert verdict.startswith(rc.WITHIN) and "/s/calibrated a_g" in verdict
    off = CalibratedBatch(t, cal.a_g + np.where(np.arange(n) == 40, 2e-6, 0.0)[:, None],
                          cal.quasi_static, cal.detector_g, cal.status, cal.sigma_mg, t)
    verdict, _ = rc.mcap_verdict(first, _batches_mcap(tmp_path / "d.mcap", off, raw, True))
    assert verdict.startswith("/s/calibrated a_g: max |diff|")
    raw2 = RawBatch(t, raw.v + (np.arange(n) == 7)[:, None], raw.aux)
    verdict, _ = rc.mcap_verdict(first, _batches_mcap(tmp_path / "e.mcap", cal, raw2, True))
    assert verdict.startswith("/s/raw v: max |diff| 1")
    # sigma: within its 1 % steps (half a percent) and a micro-g, and no further
    sigma_off = cal.sigma_mg * np.where(np.arange(n) == 12, 1.02, 1.0)
    off = CalibratedBatch(t, cal.a_g, cal.quasi_static, cal.detector_g, cal.status, sigma_off, t)
    verdict, _ = rc.mcap_verdict(first, _batches_mcap(tmp_path / "f.mcap", off, raw, True))
    assert verdict.startswith("/s/calibrated sigma_mg: max |diff|")


def test_other_topics_compare_topic_by_topic_whatever_their_interleaving(tmp_path: Path
                                                                         ) -> None:
    def write(path: Path, order: list[tuple[str, int]]) -> Path:
        with RecordingWriter(path, background_flush=False, fsync=False, overwrite=True) as w:
            for topic, i in order:
                w.write_json(f"/s/{topic}", {"i": i}, 10**18)
        return path
    a = write(tmp_path / "a.mcap", [("events", 1), ("calibration", 0), ("events", 2)])
    b = write(tmp_path / "b.mcap", [("calibration", 0), ("events", 1), ("events", 2)])
    assert rc.mcap_verdict(a, b)[0] == "identical"  # each topic's messages in their order
    c = write(tmp_path / "c.mcap", [("calibration", 0), ("events", 2), ("events", 1)])
    assert rc.mcap_verdict(a, c)[0] != "identical"  # within a topic, order still counts


def test_a_body_of_times_and_a_rotation_compares_as_the_calibrated_samples_turned(
        tmp_path: Path) -> None:
    from recal.core.alignment import to_body
    from recal.io import recording
    from recal.node.sinks import RecordingSink

    rng = np.random.default_rng(4)
    n = 50
    t, cal = _random_calibrated(rng, n)
    r = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

    def write(path: Path, rotation_form: bool, shift_g: float = 0.0) -> Path:
        body = CalibratedBatch(t, to_body(r, cal.a_g) + shift_g, cal.quasi_static,
                               cal.detector_g, cal.status, cal.sigma_mg, t)
        with RecordingWriter(path, background_flush=False, fsync=False, overwrite=True) as w:
            if rotation_form:
                sink = RecordingSink(w)
                sink.json("s", "events", {"kind": "alignment", "detail": {"rotation": r}}, 1)
                sink.calibrated("s", cal, 10**18)
                sink.calibrated("s", body, 10**18, "body")
            else:
                w.write_json("/s/events", {"kind": "alignment", "detail": {"rotation": r}}, 1)
                w.log_calibrated("s", cal, 10**18)
                w.log_calibrated("s", body, 10**18, "body")
        return path
    old, new = write(tmp_path / "old.mcap", False), write(tmp_path / "new.mcap", True)
    assert messages.decode_body_rotation(
        next(recording.iter_messages(new, "/s/body")).data) is not None
    verdict, _ = rc.mcap_verdict(old, new)
    assert verdict == "identical" or verdict.startswith(rc.WITHIN), verdict
    off = write(tmp_path / "off.mcap", False, 2e-6)  # an old body 2 micro-g away
    assert rc.mcap_verdict(off, new)[0].startswith("/s/body a_g: max |diff|")
