"""The two .gt3x kinds actfast cannot read open through `recal.io.device_files` (recal's own
decoder), and on the command line: an ACTIVITY2 (Link) file and an NHANES-era file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from gt3x_writers import LogFile, nhanes_entries, zip_gt3x
from recal.io.device_files import open_device, sniff
from recal.samples import RawBatch


def _link(tmp_path: Path) -> tuple[LogFile, Path]:
    c = np.random.default_rng(7).integers(-900, 900, size=(30 * 40, 3))
    lf = LogFile(counts=c, rate_hz=30, asleep=(10, 11, 12), battery_mv={0: 4100, 30: 4000},
                 lux={5: 100, 35: 300}, imu_records=3, zero_padding=False)
    return lf, lf.write(tmp_path / "link.gt3x")


def test_an_activity2_file_opens_with_its_samples_gaps_and_channels(tmp_path: Path) -> None:
    lf, path = _link(tmp_path)
    assert sniff(path) == "actigraph_gt3x_activity2"
    rec = open_device(path)
    b = RawBatch.concat(list(rec.batches(500)))
    np.testing.assert_array_equal(b.v, lf.expected_counts() / 256.0)
    assert rec.sensor_id == "TAS1E23456789" and rec.aux_names == ("light", "battery_voltage")
    assert rec.metadata["calibration_json_applied"] is False and rec.metadata["gaps"] == 1
    # the file's zone (+01:00) makes the times UTC: an hour before the device's clock
    first = next(rec.file_times(10))
    assert b.t_us[0] == first[0] - 3_600_000_000 == (lf.start_s - 3600) * 1_000_000
    assert np.diff(b.t_us).max() > 3_000_000                  # the idle sleep stays a gap
    assert any("IMU records" in n for n in rec.notes)
    assert any("calibration.json" in n and "not applied" in n for n in rec.notes)


def test_zero_padding_between_records_does_not_hide_the_kind(tmp_path: Path) -> None:
    """ActiGraph's README: a few zero bytes may sit between valid records."""
    c = np.random.default_rng(9).integers(-900, 900, size=(30 * 5, 3))
    path = LogFile(counts=c, rate_hz=30, zero_padding=True).write(tmp_path / "padded.gt3x")
    assert sniff(path) == "actigraph_gt3x_activity2" and len(open_device(path)) == 150


def test_an_nhanes_file_opens_as_one_stream(tmp_path: Path) -> None:
    c = np.random.default_rng(8).integers(-2000, 2000, size=(40 * 60, 3))
    path = zip_gt3x(tmp_path / "nhanes.gt3x", nhanes_entries(c, 40, 1_250_000_000, [100] * 60))
    assert sniff(path) == "actigraph_gt3x_nhanes"
    rec = open_device(path)
    b = RawBatch.concat(list(rec.batches()))
    np.testing.assert_allclose(b.v, c / 341.0, rtol=0, atol=1e-6)   # float32 of counts/341
    assert np.all(np.diff(b.t_us) == 25_000) and rec.aux_names == ("light",)
    assert rec.metadata["time"].startswith("local")


def test_the_command_line_imports_an_activity2_file(tmp_path: Path) -> None:
    _, path = _link(tmp_path)
    out = tmp_path / "link.mcap"
    r = subprocess.run([sys.executable, "-m", "recal", "import", str(path), "--out", str(out),
                        "--quiet"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 30 * 37 * 3 * 2


def test_a_damaged_activity2_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    lf, _ = _link(tmp_path)
    e = lf.entries()
    e["info.txt"] = e["info.txt"].replace(b"Sample Rate: 30", b"Sample Rate: 3e9")
    path = zip_gt3x(tmp_path / "bad.gt3x", e)
    r = subprocess.run([sys.executable, "-m", "recal", "import", str(path), "--out",
                        str(tmp_path / "x.mcap"), "--quiet"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert r.stderr.startswith("recal: error:") and "Sample Rate" in r.stderr
