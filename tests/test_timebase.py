"""Device clocks -> one microsecond axis (recal.core.timebase), alone and in the calibration
node: wrapping 32-bit micros(), millis() under a t_us header, reboots, anomalies; and the
calibration they feed (simulated wearer, recal simulate's default random sensor, 1 s vector
error against the simulator's truth after 30 min)."""

from __future__ import annotations

import numpy as np
import pytest

from memory_sink import MemorySink
from recal.config import PipelineSection, PriorConfig, SensorConfig, model_and_prior
from recal.core import timebase as tb
from recal.io.ascii_lines import AsciiLineParser, encode_ascii
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec, SimResult, error_1s_mg, simulate

WRAP = 2**32
RATE_HZ = 25.0


def wearer(minutes: float, seed: int, start_us: int = 0, rate_hz: float = RATE_HZ) -> SimResult:
    spec = SensorSpec.random(np.random.default_rng(seed))  # recal simulate's default sensor
    return simulate(minutes / 60.0, rate_hz, seed, spec, start_us=start_us)


def node(rate_hz: float | None, sink: MemorySink) -> CalibrationNode:
    sensor = SensorConfig("s1", rate_hz=rate_hz, prior=PriorConfig(counts_per_g=1024.0))
    settings = PipelineSection()
    model, prior = model_and_prior(sensor, settings)
    return CalibrationNode(NodeSettings("s1", settings, model, prior, rate_hz), sink)


def feed(n: CalibrationNode, raw: RawBatch, batch: int = 500) -> None:
    for i in range(0, len(raw), batch):
        n.process(raw[i:i + batch], i)
    n.flush(len(raw))


def error_after_30_min_mg(sink: MemorySink, res: SimResult, rate_hz: float) -> float:
    t_out, a = sink.joined()
    assert len(t_out) == len(res.raw)
    assert np.isfinite(a).all()
    keep = np.arange(len(a)) >= 30 * 60 * rate_hz
    return error_1s_mg(a[keep], res.truth.a_true_g[keep], rate_hz)


# ---------------------------------------------------------------------------- the pure core


def _run(t_dev: np.ndarray, cfg: tb.TimebaseConfig, sizes: list[int]
         ) -> tuple[tb.TimebaseState, np.ndarray, list[dict]]:
    state, events = tb.start(t_dev[:50], cfg)
    out, i = [], 0
    for size in sizes:
        state, o, ev = tb.step(state, t_dev[i:i + size], cfg)
        out.append(o)
        events += ev
        i += size
    return state, np.concatenate(out), events


@pytest.mark.parametrize("sizes", [[1] * 300, [7] * 43, [300]])
def test_a_32_bit_micros_counter_is_unwrapped_the_same_in_any_batches(sizes: list[int]) -> None:
    truth = WRAP - 1_234_567 + np.arange(300, dtype=np.int64) * 40_000  # wraps at sample 31
    state, out, events = _run(truth % WRAP, tb.TimebaseConfig(rate_hz=RATE_HZ), sizes)
    np.testing.assert_array_equal(out, truth)  # the first value kept, the period added
    assert [e["kind"] for e in events] == ["time_wrap"]
    assert events[0]["detail"]["period"] == WRAP and state.wraps == 1
    assert state.counts() == {"wraps": 1, "reboots": 0, "backwards": 0, "duplicates": 0,
                              "jumps": 0, "refused": 0}


def test_a_16_bit_millisecond_counter_wraps_every_65_5_s() -> None:
    truth_ms = 60_000 + np.arange(3000, dtype=np.int64) * 40  # 2 min at 25 Hz: 2 wraps
    state, out, events = _run(truth_ms % 2**16, tb.TimebaseConfig(), [100] * 30)
    assert state.unit_us == 1000 and state.unit == "ms"
    np.testing.assert_array_equal(out, truth_ms * 1000)
    assert [e["kind"] for e in events] == ["time_units", "time_wrap", "time_wrap"]
    assert all(e["detail"]["period"] == 2**16 for e in events[1:])


@pytest.mark.parametrize(("step", "unit", "nominal"), [(40_000, 1, None), (40, 1000, None),
                                                       (1, 1000, None), (1, 1_000_000, 1.0),
                                                       (40, 1000, 25.0), (20, 1000, 50.0),
                                                       (10_000, 1, 100.0)])
def test_the_unit_is_the_one_whose_rate_is_plausible(step: int, unit: int,
                                                     nominal: float | None) -> None:
    # a step of 1 is 1 kHz in ms or 1 Hz in s: both plausible, the nominal rate decides
    t = 5000 + np.arange(60, dtype=np.int64) * step
    got, _ = tb.decide_unit(t, tb.TimebaseConfig(rate_hz=nominal))
    assert got == unit


def test_an_implausible_clock_in_every_unit_is_an_event() -> None:
    t = np.arange(60, dtype=np.int64) * 10 ** 8  # 100 s a sample even as microseconds
    state, events = tb.start(t, tb.TimebaseConfig())
    assert state.unit_us == 1 and [e["kind"] for e in events] == ["time_implausible"]


def test_a_reboot_is_an_event_and_time_goes_on() -> None:
    before = 7_200_000_000 + np.arange(100, dtype=np.int64) * 40_000  # 2 h after boot
    after = 3_000_000 + np.arange(100, dtype=np.int64) * 40_000  # restarted, 3 s after boot
    state, out, events = _run(np.concatenate([before, after]), tb.TimebaseConfig(RATE_HZ),
                              [64] * 3 + [8])
    assert [e["kind"] for e in events] == ["time_reboot"] and state.reboots == 1
    assert events[0]["index"] == 100 - 64  # in the second batch
    assert np.all(np.diff(out) > 0)
    np.testing.assert_array_equal(out[:100], before)
    np.testing.assert_array_equal(np.diff(out[100:]), 40_000)
    assert out[100] - out[99] == 40_000  # one nominal step after the last output


def test_anomalies_are_counted_and_the_output_never_goes_back() -> None:
    t = np.arange(200, dtype=np.int64) * 40_000 + 10**9
    t[50] = t[49]  # a duplicate
    t[120] = t[119] - 100_000  # a step back that is neither a wrap nor a reboot
    t[150:] += 10 * 10**6  # a 10 s gap (lost samples)
    state, out, events = _run(t, tb.TimebaseConfig(RATE_HZ), [33] * 7)
    assert state.counts() == {"wraps": 0, "reboots": 0, "backwards": 1, "duplicates": 1,
                              "jumps": 1, "refused": 0}
    assert np.all(np.diff(out) > 0)
    assert {e["kind"] for e in events} == {"time_anomalies"}
    assert sum(e["detail"].get("duplicates", 0) for e in events) == 1
    np.testing.assert_array_equal(out[:50], t[:50])  # untouched where nothing happened
    assert out[150] - out[149] == t[150] - t[149]  # a gap is real: kept


@pytest.mark.parametrize("sizes", [[1] * 300, [7] * 43, [300]])
def test_an_implausible_jump_either_way_is_refused_not_a_new_time_base(sizes: list[int]) -> None:
    """A clock that leaps 17 years ahead (a crafted stream) and later back to where it was: two
    refused jumps, one event per batch at most, and the output goes on one step at a time, so
    the real stream after it is still minutes, not years, from where it began."""
    t = 10**9 + np.arange(300, dtype=np.int64) * 40_000
    t[100:200] += 17 * 365 * 86_400 * 10**6
    state, out, events = _run(t, tb.TimebaseConfig(RATE_HZ), sizes)
    assert state.refused == 2 and state.counts()["jumps"] == 0
    refused = [e for e in events if e["kind"] == "time_jump_refused"]
    assert sum(e["detail"]["in_batch"] for e in refused) == 2
    assert len(refused) == (1 if len(sizes) == 1 else 2)  # one event per batch at most
    assert refused[0]["detail"]["jump_s"] > 17 * 365 * 86_400
    if len(refused) == 2:
        assert refused[1]["detail"]["jump_s"] < -16 * 365 * 86_400
    assert np.all(np.diff(out) > 0)
    np.testing.assert_array_equal(np.diff(out), 40_000)  # no gap either way
    np.testing.assert_array_equal(out[:100], t[:100])
    # a day is no jump to refuse: a real gap, kept
    t2 = 10**9 + np.arange(300, dtype=np.int64) * 40_000
    t2[150:] += 86_000 * 10**6
    state2, out2, _ = _run(t2, tb.TimebaseConfig(RATE_HZ), sizes)
    assert state2.refused == 0 and out2[150] - out2[149] == t2[150] - t2[149]


def test_state_round_trips_through_json_mid_stream() -> None:
    t = (WRAP - 400_000 + np.arange(100, dtype=np.int64) * 40_000) % WRAP
    cfg = tb.TimebaseConfig(RATE_HZ)
    state, _ = tb.start(t, cfg)
    state, a, _ = tb.step(state, t[:50], cfg)
    restored = tb.TimebaseState.from_dict(state.to_dict())
    _, b1, _ = tb.step(state, t[50:], cfg)
    _, b2, _ = tb.step(restored, t[50:], cfg)
    np.testing.assert_array_equal(b1, b2)
    assert b1[0] > a[-1]


# ---------------------------------------------------------------------------- in the node


def test_wrapping_micros_calibrates_with_time_strictly_increasing_and_unwrapped() -> None:
    start_us = WRAP - 10 * 60 * 10**6  # wraps 10 minutes in
    res = wearer(40.0, seed=1, start_us=start_us)
    dev = RawBatch(res.raw.t_us % WRAP, res.raw.v, res.raw.aux, res.raw.aux_names)
    assert np.any(np.diff(dev.t_us) < 0)
    sink = MemorySink()
    n = node(RATE_HZ, sink)
    feed(n, dev)
    t_out, _ = sink.joined()
    assert np.all(np.diff(t_out) > 0)
    np.testing.assert_array_equal(t_out, res.raw.t_us)  # the unwrapped device time
    assert sink.kinds().count("time_wrap") == 1
    assert error_after_30_min_mg(sink, res, RATE_HZ) <= 1.5
    doc = n.checkpoint()
    assert doc is not None and doc["timebase"]["wraps"] == 1


def test_millis_under_a_t_us_header_is_recognised_and_calibrates() -> None:
    res = wearer(35.0, seed=2)
    ms = RawBatch(res.raw.t_us // 1000, res.raw.v, res.raw.aux, res.raw.aux_names)
    sink = MemorySink()
    feed(node(None, sink), ms)  # no rate configured: as millis() seen as us, it is 25 kHz
    units = [e for e in sink.events if e["kind"] == "time_units"]
    assert len(units) == 1 and units[0]["detail"]["unit"] == "ms"
    assert units[0]["detail"]["rate_hz"] == pytest.approx(RATE_HZ)
    started = next(e for e in sink.events if e["kind"] == "node_started")
    assert started["detail"]["rate_hz"] == pytest.approx(RATE_HZ)
    t_out, _ = sink.joined()
    np.testing.assert_array_equal(t_out, ms.t_us * 1000)
    assert error_after_30_min_mg(sink, res, RATE_HZ) <= 1.5


def test_xyz_lines_with_a_rate_calibrate() -> None:
    """Lines without a time column (simple firmware) through the ASCII parser with a rate:
    every line a sample, 20 ms apart, and the calibration as good as with time stamps."""
    rate = 50.0
    res = wearer(32.0, seed=3, rate_hz=rate)
    text = encode_ascii(res.raw, header=False, time_column=False)
    parser = AsciiLineParser((), rate_hz=rate)
    parser.anchor_time(1_700_000_000_000_000)
    parsed = [parser.feed(text[i:i + 65536]) for i in range(0, len(text), 65536)]
    raw = RawBatch.concat(parsed)
    assert len(raw) == len(res.raw) and parser.errors.total == 0
    np.testing.assert_array_equal(raw.v, res.raw.v)
    np.testing.assert_array_equal(np.diff(raw.t_us), 20_000)
    sink = MemorySink()
    feed(node(rate, sink), raw)
    assert error_after_30_min_mg(sink, res, rate) <= 1.5


def test_recal_import_writes_the_time_base_and_says_so(tmp_path, capsys) -> None:
    """A CSV whose t_us column is a 16-bit millisecond counter (it wraps every 65.5 s) with a
    reboot: imported as unwrapped, never-backwards microseconds, each finding one line."""
    from recal.cli import main
    from recal.io import recording as rec

    n = 4000  # 160 s at 25 Hz: wraps twice, then the device reboots
    truth_ms = 1000 + np.arange(n, dtype=np.int64) * 40
    dev_ms = truth_ms % 2**16
    dev_ms[3400:] = 500 + np.arange(n - 3400) * 40  # rebooted: counts again from 0.5 s
    rows = "\n".join(f"{t},{i % 7},{-i % 5},1024" for i, t in enumerate(dev_ms.tolist()))
    (tmp_path / "in.csv").write_text("t_us,x,y,z\n" + rows + "\n")
    assert main(["import", str(tmp_path / "in.csv"), "--out", str(tmp_path / "o.mcap"),
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "the time column counts ms, not microseconds" in out
    assert "wrapped 2 time(s) (period 65536 ms)" in out
    assert "restarted near 0 1 time(s)" in out
    got = rec.read_all_raw(tmp_path / "o.mcap", "imported")
    assert len(got) == n and np.all(np.diff(got.t_us) > 0)
    np.testing.assert_array_equal(got.t_us[:3400], truth_ms[:3400] * 1000)
    np.testing.assert_array_equal(np.diff(got.t_us[3400:]), 40_000)


def test_frequent_anomalies_are_one_event_a_device_minute_with_totals() -> None:
    """A clock that repeats a stamp every 10th sample (a coarse ms clock): every repeat is
    counted, the output strictly increases, and the events stay one a device minute."""
    res = wearer(5.0, seed=4)
    t = res.raw.t_us.copy()
    t[10::10] = t[9::10][:len(t[10::10])]  # every 10th stamp repeats the one before
    sink = MemorySink()
    n = node(RATE_HZ, sink)
    feed(n, RawBatch(t, res.raw.v, res.raw.aux, res.raw.aux_names), batch=7)
    t_out, a = sink.joined()
    assert np.all(np.diff(t_out) > 0) and np.isfinite(a).all()
    said = [e for e in sink.events if e["kind"] == "time_anomalies"]
    assert 5 <= len(said) <= 6  # 5 device minutes
    assert n.timebase is not None and n.timebase.duplicates == len(t[10::10])
    assert said[-1]["detail"]["total"]["duplicates"] <= n.timebase.duplicates
    assert n.status()["node"]["time"]["duplicates"] == len(t[10::10])
