"""Every device file in ../shared/data/devices opens through `recal.io.device_files` with the
samples actfast reads, true times (no jump at every block boundary), its channels, metadata
and time zone as the file records them."""

from __future__ import annotations

from pathlib import Path

import actfast
import numpy as np
import pytest

from recal.io.device_files import is_device_file, open_device, sniff
from recal.samples import RawBatch

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
#: file -> (kind, device type, sensor id, nominal Hz, aux channels, UTC offset in h or None)
FILES = {
    "ggirread_ax3_testfile.cwa": ("axivity_cwa", "Axivity AX3", "AX3-39434", 100,
                                  ("temperature", "battery_voltage", "light"), None),
    "ggirread_ax6_testfile.cwa": ("axivity_cwa", "Axivity AX6", "AX6-6011834", 100,
                                  ("temperature", "battery_voltage", "light"), None),
    "skdh_ax3_sample.cwa": ("axivity_cwa", "Axivity AX3", "AX3-51888", 200,
                            ("temperature", "battery_voltage", "light"), None),
    "skdh_ax6_sample.cwa": ("axivity_cwa", "Axivity AX6", "AX6-6011802", 100,
                            ("temperature", "battery_voltage", "light"), None),
    "ggirread_GENEActiv_testfile.bin": ("geneactiv_bin", "GENEActiv 1.1", "GENEActiv-012967",
                                        85.7, ("temperature", "battery_voltage", "light"), 1),
    "actfast_geneactiv.bin": ("geneactiv_bin", "GENEActiv 1.2", "GENEActiv-101806", 60,
                              ("temperature", "battery_voltage", "light"), -5),
    "actfast_actigraph.gt3x": ("actigraph_gt3x", "ActiGraph wGT3XBT", "MOS2E17210537", 60,
                               ("light", "battery_voltage"), -5),
}


def _path(name: str) -> Path:
    path = DEVICES / name
    assert path.is_file(), f"device file missing: {path} (the tests need ../shared/data)"
    return path


def _actfast_samples(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """actfast's own stamps (ns) and values of the file's accelerometer."""
    ts = actfast.read(str(path), lenient=True)["timeseries"]
    table = ts.get("high_frequency") or ts["acceleration"]
    return np.asarray(table["datetime"], np.int64), np.asarray(table["acceleration"])


@pytest.mark.parametrize("name", sorted(FILES))
def test_each_file_opens_with_the_samples_actfast_reads(name: str) -> None:
    path = _path(name)
    kind, device_type, sensor_id, rate, aux, _tz = FILES[name]
    assert sniff(path) == kind and is_device_file(path)
    rec = open_device(path)
    b = RawBatch.concat(list(rec.batches(4096)))
    t_af, v_af = _actfast_samples(path)
    assert len(b) >= 0.95 * len(t_af) and len(b) == len(rec)
    np.testing.assert_array_equal(b.v, v_af.astype(np.float64))  # values as the reader gives
    assert rec.kind == kind and rec.sensor_id == sensor_id
    assert rec.metadata["device_type"] == device_type
    assert rec.metadata["nominal_rate_hz"] == pytest.approx(rate)
    assert b.aux_names == aux == rec.aux_names
    assert np.isfinite(b.aux).all()
    # the measured rate is the file's: samples over the time they span, within 3 %
    assert rec.rate_hz == pytest.approx((len(b) - 1) / (np.ptp(b.t_us) / 1e6), rel=1e-3)
    assert rec.rate_hz == pytest.approx(rate, rel=0.03)


@pytest.mark.parametrize("name", sorted(FILES))
def test_times_increase_without_a_jump_at_block_boundaries(name: str) -> None:
    """actfast's stamps jump at every sector (10 ms, then 21-34 ms): as gaps, a windower
    that calls a step over 3 periods a gap cuts the recording into 1.2 s pieces. Ours step
    evenly: every step within 5 % of the median (none of the files has a real gap; an AX6
    sector stamped 6 ms early makes its 40 steps 2.5 % short)."""
    rec = open_device(_path(name))
    t = RawBatch.concat(list(rec.batches())).t_us
    step = np.diff(t)
    assert (step > 0).all()
    med = np.median(step)
    assert np.abs(step - med).max() <= max(2.0, 0.05 * med), (step.min(), med, step.max())
    assert rec.skipped["gaps"] == 0 and rec.skipped["clock_changes"] == 0


@pytest.mark.parametrize("name", ["ggirread_ax3_testfile.cwa", "skdh_ax3_sample.cwa"])
def test_the_files_own_stamps_jump_where_ours_do_not(name: str) -> None:
    """The premise: actfast's stamps of these files do jump by 2 periods and more at sector
    boundaries, and the file's own stamps stay available sample for sample."""
    rec = open_device(_path(name))
    file_t = np.concatenate(list(rec.file_times()))
    t_af, _ = _actfast_samples(_path(name))
    np.testing.assert_array_equal(file_t, t_af // 1000)
    step = np.diff(file_t)
    assert step.max() > 2 * np.median(step)


def test_batches_are_the_same_in_any_size() -> None:
    rec = open_device(_path("skdh_ax6_sample.cwa"))
    a = RawBatch.concat(list(rec.batches(1000)))
    b = RawBatch.concat(list(rec.batches(65536)))
    np.testing.assert_array_equal(a.t_us, b.t_us)
    np.testing.assert_array_equal(a.aux, b.aux)


@pytest.mark.parametrize("name", sorted(FILES))
def test_time_zone_gives_utc_where_the_file_records_it(name: str) -> None:
    """Device stamps are local wall-clock written as if UTC: a recorded zone turns them into
    UTC (GENEActiv 'GMT +01:00': an hour earlier), else they stay local and the output says
    so."""
    rec = open_device(_path(name))
    tz_h = FILES[name][5]
    first_file_us = int(next(rec.file_times())[0])
    first_us = int(next(rec.batches()).t_us[0])
    if tz_h is None:
        assert "utc_offset_s" not in rec.metadata
        assert rec.metadata["time"].startswith("local")
        assert any("local wall-clock" in n and "not UTC" in n for n in rec.notes)
        assert first_us == first_file_us
    else:
        assert rec.metadata["utc_offset_s"] == tz_h * 3600
        assert rec.metadata["time"].startswith("UTC")
        assert any(n.startswith("times: UTC") for n in rec.notes)
        assert first_us == pytest.approx(first_file_us - tz_h * 3_600_000_000, abs=1)


def test_what_the_values_mean_is_said() -> None:
    gen = open_device(_path("actfast_geneactiv.bin"))
    assert "calibration from the header applied" in gen.metadata["values"]
    ax6 = open_device(_path("ggirread_ax6_testfile.cwa"))
    assert ax6.metadata["gyroscope"] == "ignored"
    assert any("gyroscope" in n and "ignored" in n for n in ax6.notes)
    ax3 = open_device(_path("ggirread_ax3_testfile.cwa"))
    assert "gyroscope" not in ax3.metadata
    for rec in (gen, ax6, ax3):
        assert rec.metadata["firmware"] and rec.metadata["device_id"]


def test_a_cut_short_geneactiv_says_how_many_pages_are_missing() -> None:
    """The GGIRread test file's header claims 222048 pages; it holds 17."""
    rec = open_device(_path("ggirread_GENEActiv_testfile.bin"))
    assert rec.skipped["pages"] == 222048 - -(-len(rec) // 300)  # the last page partial
    assert any("222048 pages" in n for n in rec.notes)


@pytest.mark.parametrize(("text", "seconds"), [
    ("GMT +01:00", 3600), ("GMT -05:00", -18000), ("-05:00:00", -18000), ("+0100", 3600),
    ("01:00:00", 3600),  # .NET writes a zone east of UTC unsigned (ActiGraph's info.txt)
    ("00:00:00", 0), ("-10:30", -37800),
    ("0100", None), ("", None), ("local", None), ("+25:00", None), (None, None)])
def test_time_zone_text(text: str | None, seconds: int | None) -> None:
    from recal.io.device_files.parsed import utc_offset_s

    assert utc_offset_s(text) == seconds
