"""The commands that take a recording take a device file, recognised by content: import,
replay, hindsight and discover run on a shared device file, write their outputs and carry the
device's metadata (calibration accuracy on device files is tested on longer synthetic ones)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from recal.cli import main
from recal.io import recording
from recal.io.device_files import open_device
from recal.io.sources import recording_kind
from recal.samples import RawBatch

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
CWA = DEVICES / "skdh_ax3_sample.cwa"  # AX3, 200 Hz, 5 min, some still stretches


@pytest.fixture
def cwa(tmp_path: Path) -> Path:
    """The file under a name that says nothing of its kind: content decides."""
    path = tmp_path / "wrist.dat"
    shutil.copyfile(CWA, path)
    return path


def _device_metadata(path: Path) -> dict[str, str]:
    return {k: v for k, v in recording.metadata(path).items() if k.startswith("device_")}


def test_recording_kind_reads_content(tmp_path: Path, cwa: Path) -> None:
    csv = tmp_path / "x.mcap"  # a CSV under an MCAP name is a CSV
    csv.write_text("t_us,x,y,z\n0,0,0,1\n")
    assert recording_kind(cwa) == "device" and recording_kind(csv) == "csv"
    junk = tmp_path / "junk.cwa"  # a device's extension, not its content
    junk.write_bytes(np.random.default_rng(0).bytes(3000))
    assert recording_kind(junk) == "unknown"


def test_hindsight_of_bytes_of_no_kind_says_so(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.cwa"
    junk.write_bytes(np.random.default_rng(0).bytes(3000))
    assert main(["hindsight", str(junk), "--out", str(tmp_path / "o.mcap"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "neither an MCAP recording, a device file" in err[0], err


def test_import_writes_the_samples_and_the_device(tmp_path: Path, cwa: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "wrist.mcap"
    assert main(["import", str(cwa), "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "imported 58800 samples" in said and "AX3-51888" in said and "not UTC" in said
    raw = recording.read_all_raw(out, "AX3-51888")
    want = RawBatch.concat(list(open_device(cwa).batches()))
    np.testing.assert_array_equal(raw.t_us, want.t_us)
    np.testing.assert_allclose(raw.v, want.v, atol=1e-6)
    assert raw.aux_names == ("temperature", "battery_voltage", "light")
    meta = _device_metadata(out)
    assert meta["device_kind"] == "axivity_cwa" and meta["device_device_id"] == "51888"
    assert "local wall-clock" in meta["device_notes"]


def test_replay_streams_every_sample_through_the_node(tmp_path: Path, cwa: Path) -> None:
    out, report = tmp_path / "replayed.mcap", tmp_path / "replay.json"
    assert main(["replay", str(cwa), "--out", str(out), "--json", str(report),
                 "--quiet"]) == 0
    summary = json.loads(report.read_text())
    assert summary["samples"] == 58800
    assert summary["sensors"]["AX3-51888"]["samples"] == 58800
    assert summary["device"]["device_type"] == "Axivity AX3"
    cal = recording.read_all_calibrated(out, "AX3-51888")
    assert len(cal) == 58800 and (np.diff(cal.t_us) > 0).all()
    assert _device_metadata(out)["device_rate_hz"].startswith("197.2")
    # one device recorded every sample: a gap is the device asleep or off, not a doubt
    setups = [m for _, m, _ in recording.iter_json(out, "*/setup")]
    state = json.loads(setups[0]["pipeline_state_json"])
    assert state["config"]["gap_doubt_s"] == 0.0


@pytest.mark.parametrize("suffix", [".mcap", ".csv"])
def test_hindsight_calibrates_a_device_file(tmp_path: Path, cwa: Path, suffix: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    out, report = tmp_path / f"calibrated{suffix}", tmp_path / "fit.json"
    assert main(["hindsight", str(cwa), "--out", str(out), "--json", str(report),
                 "--quiet"]) == 0
    assert "Axivity AX3 51888" in capsys.readouterr().out
    summary = json.loads(report.read_text())
    assert summary["samples"] == 58800 and summary["windows"] > 0
    assert summary["device"]["kind"] == "axivity_cwa"
    # the reader's rate, measured between block stamps (1 / the median step of interpolated
    # stamps is off by their microsecond rounding)
    assert summary["rate_hz"] == open_device(cwa).rate_hz
    assert any("gap" in n or "stamped" in n for n in summary["device_notes"])
    if suffix == ".mcap":
        assert _device_metadata(out)["device_device_id"] == "51888"
        assert len(recording.read_all_calibrated(out, "AX3-51888")) == 58800
    else:
        assert len(out.read_text().splitlines()) == 58800 + 1


def test_discover_reports_the_device(tmp_path: Path, cwa: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    report = tmp_path / "discover.json"
    assert main(["discover", str(cwa), "--json", str(report), "--quiet"]) == 0
    assert "Axivity AX3 51888" in capsys.readouterr().out
    found = json.loads(report.read_text())
    assert found["device"]["device_id"] == "51888" and found["input"]["windows"] > 0
    assert found["device"]["time"].startswith("local")
