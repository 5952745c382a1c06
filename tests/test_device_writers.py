"""The synthetic device files (`device_writers`: .cwa, .bin, .gt3x) read back by actfast, an
independent reader, value by value against what was written: so the writers and recal's own
reader cannot share a misreading of the formats."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import actfast
import numpy as np
import pytest

from device_writers import (
    DeviceRun,
    Signal,
    _pack_ax3,
    cwa_time,
    device_signal,
    idle_sleep_seconds,
    write_cwa,
    write_geneactiv_bin,
    write_gt3x,
)
from recal.sim.sensor import SensorSpec

NS = 1_000
RUN = DeviceRun(hours=0.4, nominal_hz=50, real_hz=50.15, seed=3,
                sensor=SensorSpec(counts_per_g=256.0, full_scale_g=8.0,
                                  offset_g=(0.03, -0.02, 0.045), gain=(0.01, -0.015, 0.02),
                                  offset_tc_g_per_c=(0.001, -0.0008, 0.0005)),
                table_s=(200.0, 150.0), gap_s=(700.0, 45.0))


@pytest.fixture(scope="module")
def signal() -> Signal:
    return device_signal(RUN)


def test_signal_has_the_device_behaviour(signal: Signal) -> None:
    assert len(signal.runs) == 2  # the gap splits the logging
    a = signal.runs[1][0]
    jump_s = (signal.t_us[a] - signal.t_us[a - 1]) / 1e6
    assert jump_s == pytest.approx(45.0, abs=2 / RUN.real_hz)
    dt_s = np.diff(signal.t_us[:a]) / 1e6
    assert np.mean(dt_s) == pytest.approx(1 / RUN.real_hz, rel=1e-6)
    # on the table: the truth does not move, the counts only by noise and quantization
    t_s = (signal.t_us - signal.t_us[0]) / 1e6
    table = (t_s >= 201) & (t_s < 349)
    assert np.ptp(signal.a_true_g[table], axis=0).max() == 0.0
    assert signal.still[table].all()
    assert np.all(signal.counts == np.round(signal.counts))


@pytest.mark.parametrize("packed", [True, False])
def test_cwa_read_back_by_actfast(tmp_path: Path, signal: Signal, packed: bool) -> None:
    w = write_cwa(tmp_path / "dev.cwa", signal, packed=packed)
    assert (w.path.stat().st_size - 1024) % 512 == 0
    got = actfast.read(w.path)  # strict: a bad checksum or magic raises
    assert got["format"] == "Axivity CWA"
    meta = got["metadata"]
    assert meta["device"]["device_id"] == str(w.meta["device_id"])
    assert meta["device"]["session_id"] == str(w.meta["session_id"])
    assert meta["device"]["time_zone"] == str(w.meta["time_zone_min"])
    assert meta["configuration"]["sample_rate_hz"] == "50"
    assert meta["configuration"]["accelerometer_range_g"] == "8"
    assert meta["session"]["annotation"] == w.meta["metadata"]

    hf, lf = got["timeseries"]["high_frequency"], got["timeseries"]["low_frequency"]
    # every sample, to the bit: 1/256 g is exact in float32
    assert hf["acceleration"].shape == w.counts.shape
    np.testing.assert_array_equal(hf["acceleration"].astype(np.float64) * 256.0, w.counts)
    if packed:  # packing keeps 1/256 g within ±2 g, drops low bits beyond
        small = np.abs(w.signal.counts).max(axis=1) < 512
        np.testing.assert_array_equal(w.counts[small], w.signal.counts[small])
        assert np.abs(w.counts - w.signal.counts).max() < 8
    else:
        np.testing.assert_array_equal(w.counts, w.signal.counts)

    # sectors: the reader's time of the sample the stamp is for is the stamp as stored, and
    # the stored stamp is the true time to the 15-bit fraction
    b = w.blocks
    n_sec = len(b["first"])
    assert len(lf["datetime"]) == n_sec
    period_ns = 10**9 // RUN.nominal_hz
    assert np.abs(b["stored_stamp_ns"] - b["stamp_us"] * NS).max() <= 31_000
    origin_ns = lf["datetime"] + b["stamp_index"] * period_ns
    # actfast undoes the firmware's index adjustment with the 15 stored bits: the same sample
    # but where the dropped 16th bit tipped the floor, one nominal period over
    off = origin_ns - b["stored_stamp_ns"]
    assert np.all(np.isin(off, [0, -period_ns]))
    assert np.mean(off == 0) > 0.9
    # each sample: the reader puts the stamp's sample right and steps at the nominal rate
    first_ns = hf["datetime"][b["first"]]
    np.testing.assert_array_equal(first_ns, lf["datetime"])
    k = np.arange(len(w.counts)) - np.repeat(b["first"], b["count"])
    drift_ns = np.abs(hf["datetime"] - w.signal.t_us * NS)
    bound_ns = (np.abs(k - np.repeat(b["stamp_index"], b["count"]))
                * abs(1e9 / RUN.nominal_hz - 1e9 / RUN.real_hz) + period_ns + 31e3)
    assert np.all(drift_ns <= bound_ns)

    # temperature and battery in their raw units
    np.testing.assert_allclose(lf["temperature"], b["temp_raw"] * 75.0 / 256.0 - 50.0,
                               atol=1e-4)
    true_temp = w.signal.temp_c[b["first"] + b["count"] - 1]
    assert np.abs(lf["temperature"] - true_temp).max() <= 75.0 / 512.0 + 1e-3
    assert np.ptp(lf["temperature"]) > 1.0  # the temperature does change
    # actfast reads the byte as 3 (b / 256 + 1) V; cwa.h says (b + 512) 6 / 1024 V
    np.testing.assert_allclose(lf["battery_voltage"], 3.0 * (b["battery"] / 256.0 + 1.0),
                               rtol=1e-6)
    assert b["events"].sum() == 1 and b["events"][np.searchsorted(b["first"],
                                                                  signal.runs[1][0])] == 1


def test_cwa_packed_time_fields() -> None:
    t_us = np.array(["2024-03-04T09:00:00", "2031-12-31T23:59:59"], "datetime64[us]")
    packed = cwa_time(t_us.astype(np.int64))
    assert packed[0] == (24 << 26) | (3 << 22) | (4 << 17) | (9 << 12)
    assert packed[1] == (31 << 26) | (12 << 22) | (31 << 17) | (23 << 12) | (59 << 6) | 59


def test_cwa_packing_keeps_what_fits_and_floors_the_rest() -> None:
    v = np.stack([np.arange(-4096, 4096), np.zeros(8192, np.int64), np.full(8192, 300)], 1)
    words, back = _pack_ax3(v)
    e = words >> 30
    worst = np.maximum(np.maximum(v[:, 0], -v[:, 0] - 1), 300)  # two's complement reach
    assert np.all(e[worst < 512] == 0) and np.all(e[worst >= 2048] == 3)
    np.testing.assert_array_equal(back[:, 0], (v[:, 0] >> e) << e)
    # the bits as cwa.h lays them out: x in 0-9, y in 10-19, z in 20-29, sign-extended
    x = ((words & 0x3FF).astype(np.int64) ^ 0x200) - 0x200
    z = (((words >> 20) & 0x3FF).astype(np.int64) ^ 0x200) - 0x200
    np.testing.assert_array_equal(x << e, back[:, 0])
    np.testing.assert_array_equal(z << e, back[:, 2])


def test_cwa_rejected_when_a_sector_is_damaged(tmp_path: Path, signal: Signal) -> None:
    """The checksums are real: one flipped bit fails actfast's strict read."""
    w = write_cwa(tmp_path / "dev.cwa", signal)
    data = bytearray(w.path.read_bytes())
    data[1024 + 512 * 5 + 100] ^= 0x04
    bad = tmp_path / "bad.cwa"
    bad.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="checksum"):
        actfast.read(bad)
    lenient = actfast.read(bad, lenient=True)
    assert len(lenient["timeseries"]["low_frequency"]["datetime"]) == len(w.blocks["first"]) - 1


@pytest.mark.parametrize("newline", ["\r\n", "\n"])
def test_geneactiv_read_back_by_actfast(tmp_path: Path, signal: Signal, newline: str) -> None:
    w = write_geneactiv_bin(tmp_path / "dev.bin", signal, newline=newline)
    got = actfast.read(w.path)
    assert got["format"] == "GeneActiv BIN"
    meta = got["metadata"]
    assert meta["Device Identity"]["Device Unique Serial Code"] == w.meta["serial"]
    assert meta["Configuration Info"]["Measurement Frequency"] == "50 Hz"
    assert meta["Configuration Info"]["Time Zone"] == w.meta["time_zone"]
    cal = w.meta["calibration"]
    for key, value in cal.items():
        assert meta["Calibration Data"][key] == str(value)
    hf, lf = got["timeseries"]["high_frequency"], got["timeseries"]["low_frequency"]
    n_pages = len(w.blocks["first"])
    assert meta["Memory Status"]["Number of Pages"] == str(n_pages)
    assert len(lf["datetime"]) == n_pages and len(hf["datetime"]) == 300 * n_pages

    # every sample: actfast applies the header's calibration, x_g = (x·100 − offset) / gain;
    # undone, it gives back the 12-bit counts written
    gain = np.array([cal[f"{a} gain"] for a in "xyz"], np.float64)
    offset = np.array([cal[f"{a} offset"] for a in "xyz"], np.float64)
    counts = (hf["acceleration"].astype(np.float64) * gain + offset) / 100.0
    assert np.abs(counts - w.counts).max() < 0.01
    np.testing.assert_array_equal(np.round(counts), w.counts)
    assert np.all(hf["light"] == pytest.approx(w.meta["light"] * 800 / 300))
    # the header's calibration is the factory's: close to the truth at rest, not exact
    at_rest = w.signal.still
    err_g = np.abs(hf["acceleration"][at_rest] - w.signal.a_true_g[at_rest])
    assert 0.005 < np.percentile(err_g, 95) < 0.1

    # pages: the page time to the millisecond, samples at the stated frequency after it
    np.testing.assert_array_equal(lf["datetime"], w.blocks["stored_stamp_ns"])
    assert np.abs(lf["datetime"] - w.blocks["stamp_us"] * NS).max() < 10**6
    k = np.tile(np.arange(300), n_pages)
    np.testing.assert_array_equal(hf["datetime"],
                                  np.repeat(lf["datetime"], 300) + k * (10**9 // 50))
    late_ns = np.repeat(lf["datetime"], 300) - np.repeat(w.blocks["stamp_us"] * NS, 300)
    drift_ns = hf["datetime"] - w.signal.t_us * NS - late_ns
    np.testing.assert_allclose(drift_ns, k * (1e9 / 50 - 1e9 / RUN.real_hz), atol=1e3)

    np.testing.assert_allclose(lf["temperature"], w.blocks["temp_c"], atol=1e-5)
    page_temp = w.signal.temp_c[w.blocks["first"]]
    assert np.abs(lf["temperature"] - page_temp).max() <= 0.05 + 1e-4  # 0.1 °C, float32
    np.testing.assert_allclose(lf["battery_voltage"], w.blocks["battery_v"], atol=1e-5)
    # the gap: one page time jumps by the time the device was off
    step_s = np.diff(lf["datetime"]) / 1e9
    assert np.sum(step_s > 300 / 50 + 1) == 1
    assert step_s.max() == pytest.approx(45.0 + 300 / RUN.real_hz, abs=300 / RUN.real_hz)


GT3X_RUN = replace(RUN, nominal_hz=30, real_hz=30.0)


def test_idle_sleep_seconds_follow_stillness() -> None:
    rate = 10
    still = np.zeros(100 * rate, bool)
    still[50:700] = True  # still from 5.0 s to 69.9 s
    asleep = idle_sleep_seconds(still, rate, after_s=10)
    # asleep from the first whole second 10 s into the stillness (15 s), awake again in the
    # second the movement starts (70 s)
    assert np.flatnonzero(asleep).tolist() == list(range(15, 70))


def test_gt3x_read_back_by_actfast(tmp_path: Path) -> None:
    sig = device_signal(GT3X_RUN)
    w = write_gt3x(tmp_path / "dev.gt3x", sig)
    got = actfast.read(w.path)  # strict: a bad separator or record raises
    assert got["format"] == "Actigraph GT3X"
    info = got["metadata"]["info"]
    assert info["Serial Number"] == w.meta["serial"] and info["Sample Rate"] == "30"
    assert info["TimeZone"] == w.meta["time_zone"]
    assert got["metadata"]["device_feature_enabled"]["sleep_mode"] == "true"
    acc = got["timeseries"]["acceleration"]
    # every sample written, to the bit (ACCEL_SCALE 256 from the PARAMETERS record)
    np.testing.assert_array_equal(acc["acceleration"].astype(np.float64) * 256.0, w.counts)
    np.testing.assert_array_equal(w.counts, np.clip(w.signal.counts, -2048, 2047))
    # the samples a second apart from their record's whole second, at the nominal rate
    assert np.abs(acc["datetime"] - w.signal.t_us * NS).max() < 1_000
    # idle sleep: most of the still time is not in the file, and no record is for a second
    # the device slept
    assert w.meta["seconds_asleep"] > 0.4 * w.meta["seconds"]
    written_s = np.unique(acc["datetime"] // 10**9)
    assert not np.isin(w.blocks["asleep_s"], written_s).any()
    assert len(written_s) + w.meta["seconds_asleep"] == w.meta["seconds"]
    assert not w.signal.still.all() and w.signal.still.mean() < sig.still.mean()
    # a BATTERY record a minute, in mV
    bat = got["timeseries"]["battery_voltage"]
    assert len(bat["datetime"]) == pytest.approx(w.meta["seconds"] / 60, abs=1)
    assert np.all((bat["battery_voltage"] > 3500) & (bat["battery_voltage"] < 4200))


def test_gt3x_without_idle_sleep_keeps_every_second(tmp_path: Path) -> None:
    sig = device_signal(GT3X_RUN)
    w = write_gt3x(tmp_path / "dev.gt3x", sig, idle_sleep=False)
    got = actfast.read(w.path)
    assert got["metadata"]["device_feature_enabled"]["sleep_mode"] == "false"
    acc = got["timeseries"]["acceleration"]
    assert len(acc["datetime"]) == len(w.signal) == w.meta["seconds"] * 30
    np.testing.assert_array_equal(acc["acceleration"].astype(np.float64) * 256.0, w.counts)


def test_gt3x_needs_the_rtc_rate(tmp_path: Path, signal: Signal) -> None:
    with pytest.raises(ValueError, match="nominal rate"):
        write_gt3x(tmp_path / "dev.gt3x", signal)  # 50.15 Hz on a 50 Hz device
