"""recal's device-file reader (`io.device_files`) on files written as the devices write them
(`device_writers`), against what was written: the device's name, the channels in their
units, and each sample's true time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from device_writers import DeviceRun, Signal, device_signal, write_cwa, write_geneactiv_bin
from recal.io.device_files import open_device
from recal.samples import RawBatch

RUN = DeviceRun(hours=0.25, nominal_hz=25, real_hz=25 * 1.003, seed=11, gap_s=(400.0, 30.0))


@pytest.fixture(scope="module")
def signal() -> Signal:
    return device_signal(RUN)


def _all(path: Path) -> tuple[RawBatch, dict]:
    rec = open_device(path)
    return RawBatch.concat(list(rec.batches())), rec.metadata


def test_cwa_device_channels_and_times(tmp_path: Path, signal: Signal) -> None:
    w = write_cwa(tmp_path / "dev.cwa", signal, time_zone_min=-300)
    raw, meta = _all(w.path)
    assert meta["device_type"] == "Axivity AX3"  # header byte 0x17 (cwa.h)
    assert len(raw) == len(w.signal)
    np.testing.assert_array_equal(raw.v * 256.0, w.counts)
    # battery as cwa.h converts the byte: (b + 512) 6 / 1024 V, the cell's own volts (at a
    # sector's first sample its own value; between, interpolated)
    first = w.blocks["first"]
    volts = (w.blocks["battery"] + 512) * 6.0 / 1024.0
    np.testing.assert_allclose(raw.channel("battery_voltage")[first], volts, atol=1e-9)
    assert np.abs(volts - w.signal.vdd_v[first + w.blocks["count"] - 1]).max() < 3.0 / 1024.0
    # temperature: the sectors' 10-bit readings (75/256 °C), interpolated to the samples
    np.testing.assert_allclose(raw.channel("temperature")[first], w.blocks["temp_c"], atol=1e-4)
    # times in UTC (the zone -5 h); early by at most the stamp's reach at the nominal period
    err_us = raw.t_us - 5 * 3600e6 - w.signal.t_us
    reach = (w.blocks["stamp_index"].max() + 1) * 1e6 * abs(1 / 25 - 1 / RUN.real_hz)
    assert np.abs(err_us).max() < reach + 1e3
    assert meta["rate_hz"] == pytest.approx(RUN.real_hz, rel=1e-4)
    assert meta["gaps"] == 1


def test_bin_device_channels_and_times(tmp_path: Path, signal: Signal) -> None:
    w = write_geneactiv_bin(tmp_path / "dev.bin", signal)
    raw, meta = _all(w.path)
    assert len(raw) == len(w.signal)
    cal = w.meta["calibration"]
    gain = np.array([cal[f"{a} gain"] for a in "xyz"], np.float64)
    offset = np.array([cal[f"{a} offset"] for a in "xyz"], np.float64)
    np.testing.assert_array_equal(np.round((raw.v * gain + offset) / 100.0), w.counts)
    first = w.blocks["first"]  # a page's own temperature at its first sample
    np.testing.assert_allclose(raw.channel("temperature")[first], w.blocks["temp_c"], atol=1e-4)
    np.testing.assert_allclose(raw.channel("battery_voltage")[first], w.blocks["battery_v"],
                               atol=1e-5)
    # page times to the millisecond, the samples between them at the measured rate
    assert np.abs(raw.t_us + 3600e6 - w.signal.t_us).max() < 1.5e3  # UTC: the zone +1 h
    assert meta["rate_hz"] == pytest.approx(RUN.real_hz, rel=1e-4)
    assert meta["gaps"] == 1
