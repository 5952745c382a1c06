"""The ActiGraph .gt3x decoder (recal.io.gt3x): the published examples, synthetic files of both
layouts read back value by value, damage and crafted zips, and actfast on the ACTIVITY layout."""

from __future__ import annotations

import zipfile
from pathlib import Path

import actfast
import numpy as np
import pytest

from gt3x_writers import LogFile, nhanes_entries, zip_gt3x
from recal.errors import DeviceFileError
from recal.io.gt3x import read_gt3x
from recal.io.gt3x import records as rec

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"


def _hex(s: str) -> bytes:
    return bytes.fromhex(s.replace(" ", ""))


# --- ActiGraph's own worked examples ------------------------------------------------------------
def test_the_activity_example_unpacks_as_published() -> None:
    """Activity.md / activity.bin.md: 14 bytes, three YXZ samples, the last nibble unused."""
    rows = np.frombuffer(_hex("00 60 08 EB D0 07 00 9E BF 00 70 08 EB F0"), np.uint8)[None]
    assert rec.unpack12_yxz(rows)[0].tolist() == [[8, 6, -323], [9, 7, -321], [8, 7, -321]]


def test_the_activity2_example_unpacks_as_published() -> None:
    rows = np.frombuffer(_hex("00 00 00 00 00 00 30 00 cc ff 42 01"), np.uint8)[None]
    assert rec.unpack16_xyz(rows)[0].tolist() == [[0, 0, 0], [48, -52, 322]]


def test_the_metadata_example_checksum_is_published_one() -> None:
    payload = (b'{"MetadataType":"Bio","SubjectName":"CLE2A14151617","Race":"","Limb":"",'
               b'"Side":"","Dominance":"","Parsed":false,"JSON":null}')
    buf = _hex("1E 06 71 E8 B4 54 7C 00") + payload + b"\xF8"
    idx = rec.index_records(buf, final=True)
    assert idx.ok.tolist() == [True] and idx.time_s.tolist() == [1421142129]
    assert rec.metadata_json(rec.record_payload(buf, idx, 0))["SubjectName"] == "CLE2A14151617"


def test_the_parameters_example_scales() -> None:
    """Parameters.md: ACCEL_SCALE 00 00 40 09 is 256 LSB/g, IMU_ACCEL_SCALE 00 00 40 0C 2048,
    IMU_TEMP_OFFSET 00 00 54 05 21 degC, a negative offset -183."""
    p = rec.parameters(_hex("00 00 37 00 00 00 40 09 00 00 31 00 00 00 40 0C "
                            "00 00 3A 00 00 00 54 05 01 00 04 00 49 FF FF FF"))
    assert rec.ssp_float(p[(0, 55)]) == 256.0 and rec.ssp_float(p[(0, 49)]) == 2048.0
    assert rec.ssp_float(p[(0, 58)]) == 21.0 and p[(1, 4)] - (1 << 32) == -183


# --- synthetic files, read back value by value -------------------------------------------------
def _counts(n: int, lo: int, hi: int, seed: int) -> np.ndarray:
    c = np.random.default_rng(seed).integers(lo, hi + 1, size=(n, 3))
    c[:3] = [[lo, hi, 0], [hi, lo, -1], [0, 1, lo]]      # the extremes and the sign boundary
    return c


def _activity2(**kw: object) -> LogFile:
    base: dict[str, object] = dict(counts=_counts(30 * 20, -32768, 32767, 1), rate_hz=30,
                                   asleep=(5, 6, 7), battery_mv={0: 4100, 15: 4087},
                                   lux={3: 250}, bad_checksum_seconds=(12,), imu_records=4)
    base.update(kw)
    return LogFile(**base)  # type: ignore[arg-type]


def test_activity2_reads_back_value_by_value(tmp_path: Path) -> None:
    lf = _activity2()
    d = read_gt3x(lf.write(tmp_path / "link.gt3x"))
    np.testing.assert_array_equal(d.t_us, lf.expected_t_us())
    np.testing.assert_array_equal(d.acc_g, lf.expected_counts() / 256.0)
    assert len(d.t_us) == 30 * 19                      # one second lost to its checksum
    m = d.metadata
    assert (m["serial"], m["rate_hz"], m["scale_lsb_per_g"]) == ("TAS1E23456789", 30.0, 256.0)
    assert m["scale_from"] == "PARAMETERS ACCEL_SCALE"  # over info.txt's (999 here)
    assert m["bad_records"] == 1 and m["idle_sleep_mode"] and not m["calibration_json_applied"]
    assert m["gaps"] == 2 and m["gap_seconds"] == 4     # asleep 5-7, and second 12's record
    notes = " ".join(d.notes)
    assert "IMU records" in notes and "not applied" in notes and "nothing repeated" in notes


def test_the_scale_falls_back_to_info_txt_then_the_serial(tmp_path: Path) -> None:
    """Activity2.md: ACCEL_SCALE where PARAMETERS has it; else info.txt's Acceleration Scale;
    else the device's default by serial (NEO/CLE 341, MOS 256)."""
    lf = _activity2(parameters=False, bad_checksum_seconds=())
    d = read_gt3x(lf.write(tmp_path / "info_scale.gt3x"))
    assert d.metadata["scale_from"] == "info.txt Acceleration Scale"
    np.testing.assert_array_equal(d.acc_g, lf.expected_counts() / 999.0)
    e = lf.entries()
    e["info.txt"] = e["info.txt"].replace(b"Acceleration Scale: 999.0\n", b"").replace(
        b"TAS1E23456789", b"CLE2A14151617")
    d = read_gt3x(zip_gt3x(tmp_path / "serial_scale.gt3x", e))
    assert d.metadata["scale_lsb_per_g"] == 341.0
    np.testing.assert_array_equal(d.acc_g, lf.expected_counts() / 341.0)


def test_idle_sleep_is_a_gap_not_repeated_samples(tmp_path: Path) -> None:
    lf = _activity2(bad_checksum_seconds=())
    d = read_gt3x(lf.write(tmp_path / "sleep.gt3x"))
    step = np.diff(d.t_us)
    assert step.max() == 4 * 1_000_000 - round(29e6 / 30)   # 5..7 asleep: 4 s from last to next
    assert np.count_nonzero(step > 40_000) == 1
    t, v = d.aux["idle_sleep"]
    assert ((t - d.t_us[0]) // 1_000_000).tolist() == [5, 8] and v.tolist() == [1.0, -1.0]


def test_battery_and_lux_come_as_their_own_series(tmp_path: Path) -> None:
    lf = _activity2()
    d = read_gt3x(lf.write(tmp_path / "aux.gt3x"))
    t, v = d.aux["battery_v"]
    assert ((t // 1_000_000) - lf.start_s).tolist() == [0, 15] and v.tolist() == [4.1, 4.087]
    assert d.aux["lux"][1].tolist() == [250.0]


def test_activity_12_bit_reads_as_actfast_reads_it(tmp_path: Path) -> None:
    """An odd rate leaves a spare nibble in every record; actfast reads the same file."""
    lf = LogFile(counts=_counts(25 * 12, -2046, 2046, 2), rate_hz=25, kind=0x00,
                 serial="MOS2E17210537", asleep=(4,), zero_padding=False)
    path = lf.write(tmp_path / "act.gt3x")
    d = read_gt3x(path)
    np.testing.assert_array_equal(d.acc_g, lf.expected_counts() / 256.0)
    np.testing.assert_array_equal(d.t_us, lf.expected_t_us())
    af = actfast.read(str(path))["timeseries"]["acceleration"]
    np.testing.assert_array_equal(af["acceleration"], d.acc_g.astype(np.float32))


def test_nhanes_reads_back_value_by_value(tmp_path: Path) -> None:
    counts = _counts(31 * 60 + 1, -2046, 2046, 3)          # an odd total: the last nibble spare
    lux_raw = [0, 19, 20, 0xFFFF, 2200, 1100]
    path = zip_gt3x(tmp_path / "nhanes.gt3x", nhanes_entries(counts, 31, 1_200_000_000, lux_raw))
    i = np.arange(len(counts))
    for d in (read_gt3x(path, chunk_bytes=1000), read_gt3x(path)):   # chunks cut samples apart
        np.testing.assert_array_equal(d.acc_g, counts / 341.0)
        np.testing.assert_array_equal(d.t_us, 1_200_000_000_000_000 + np.rint(i * 1e6 / 31))
    t, lux = d.aux["lux"]
    assert lux.tolist() == [0.0, 0.0, 25.0, 0.0, 2500.0, 1375.0]
    assert np.diff(t).tolist() == [1_000_000] * 5 and d.metadata["layout"] == "nhanes"


@pytest.mark.parametrize("kind", [0x00, 0x1A])
def test_long_runs_and_small_chunks_read_the_same(tmp_path: Path, kind: int) -> None:
    """Over 4096 equal records (more than one run probe) and chunks that cut records apart."""
    lim = 2046 if kind == 0x00 else 32767
    lf = LogFile(counts=_counts(2 * 5000, -lim, lim, 4), rate_hz=2, kind=kind, asleep=(4500,),
                 battery_mv={4200: 3900})
    path = lf.write(tmp_path / "long.gt3x")
    whole, cut = read_gt3x(path), read_gt3x(path, chunk_bytes=1000)
    for d in (whole, cut):
        np.testing.assert_array_equal(d.t_us, lf.expected_t_us())
        np.testing.assert_array_equal(d.acc_g, lf.expected_counts() / 256.0)
        assert d.metadata["gaps"] == 1 and d.aux["battery_v"][1].tolist() == [3.9]


def test_records_interleaved_every_second_read_the_same(tmp_path: Path) -> None:
    """ACTIVITY2 then LUX every second, and a battery record now and then: runs of a two-record
    pattern, broken and taken up again."""
    lf = LogFile(counts=_counts(2 * 3000, -32768, 32767, 5), rate_hz=2,
                 lux={s: s % 1000 for s in range(3001)}, battery_mv={700: 4000, 2900: 3800},
                 asleep=(1500, 1501))
    path = lf.write(tmp_path / "interleaved.gt3x")
    for d in (read_gt3x(path), read_gt3x(path, chunk_bytes=5000)):
        np.testing.assert_array_equal(d.t_us, lf.expected_t_us())
        np.testing.assert_array_equal(d.acc_g, lf.expected_counts() / 256.0)
        lux = d.aux["lux"][1]
        assert len(lux) == 3001 and lux[1234] == 234 and d.aux["battery_v"][1].tolist() == [4, 3.8]


# --- damage ------------------------------------------------------------------------------------
def test_a_cut_short_log_reads_what_is_whole(tmp_path: Path) -> None:
    lf = _activity2(asleep=(), bad_checksum_seconds=())
    e = lf.entries()
    e["log.bin"] = e["log.bin"][: len(e["log.bin"]) // 2]
    path = zip_gt3x(tmp_path / "cut.gt3x", e)
    d = read_gt3x(path)
    whole = len(d.t_us) // 30
    assert 8 <= whole < 20 and len(d.t_us) == whole * 30
    np.testing.assert_array_equal(d.acc_g, lf.expected_counts()[: whole * 30] / 256.0)
    assert d.metadata["truncated"] and "cut short" in " ".join(d.notes)
    with pytest.raises(DeviceFileError, match="damaged"):
        read_gt3x(path, lenient=False)


def test_a_stray_byte_costs_records_not_the_file(tmp_path: Path) -> None:
    lf = _activity2(asleep=(), bad_checksum_seconds=())
    e = lf.entries()
    log = bytearray(e["log.bin"])
    at = log.index(b"\x1e\x1a" + (lf.start_s + 10).to_bytes(4, "little"))
    log[at + 7] ^= 0x40                                     # a damaged size field
    e["log.bin"] = bytes(log)
    d = read_gt3x(zip_gt3x(tmp_path / "stray.gt3x", e))
    assert 30 * 17 <= len(d.t_us) < 30 * 20 and d.metadata["stray_bytes"] > 0


def _patch_sizes(path: Path, name: bytes, file_size: int) -> None:
    """Rewrite an entry's declared uncompressed size in both its headers (a lying zip)."""
    b = bytearray(path.read_bytes())
    for sig, off in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):
        at = 0
        while (at := b.find(sig, at)) >= 0:
            name_len = int.from_bytes(b[at + (26 if sig == b"PK\x03\x04" else 28):][:2], "little")
            head = 30 if sig == b"PK\x03\x04" else 46
            if b[at + head: at + head + name_len] == name:
                b[at + off: at + off + 4] = file_size.to_bytes(4, "little")
            at += 4
    path.write_bytes(bytes(b))


@pytest.mark.parametrize("declared", [0xFFFF_FFF0, 1000])
def test_a_lying_size_is_one_line(tmp_path: Path, declared: int) -> None:
    path = _activity2().write(tmp_path / "lie.gt3x")
    _patch_sizes(path, b"log.bin", declared)
    with pytest.raises(DeviceFileError, match=r"log.bin"):
        read_gt3x(path)


def test_a_log_of_undocumented_sample_records_says_so(tmp_path: Path) -> None:
    """CentrePoint's .agdc writes samples in record type 0x1B, which ActiGraph's description does
    not cover: one line that names the types, not an empty recording."""
    lf = LogFile(counts=_counts(30 * 3, -2046, 2046, 9), rate_hz=30, kind=0x1B)
    with pytest.raises(DeviceFileError, match="0x1B x4"):
        read_gt3x(lf.write(tmp_path / "agdc.gt3x"))


def test_a_log_of_near_records_is_refused_not_stepped_through(tmp_path: Path) -> None:
    """Separators whose sizes never frame a record would cost a loop step per byte: the walk
    stops once over 1 MiB and half of what it has seen is stray."""
    e = _activity2().entries()
    e["log.bin"] = e["log.bin"][:400] + b"\x1e\x01" * (3 << 20)
    with pytest.raises(DeviceFileError, match="mostly not ActiGraph log records"):
        read_gt3x(zip_gt3x(tmp_path / "near.gt3x", e))


def test_a_zip_of_an_unknown_version_is_one_line(tmp_path: Path) -> None:
    path = _activity2().write(tmp_path / "version.gt3x")
    b = bytearray(path.read_bytes())
    at = b.find(b"PK\x01\x02")
    b[at + 6] = 64                                   # "needs zip 6.4 to extract"
    path.write_bytes(bytes(b))
    with pytest.raises(DeviceFileError, match="not a readable"):
        read_gt3x(path)


def test_not_a_gt3x_is_one_line(tmp_path: Path) -> None:
    junk = tmp_path / "junk.gt3x"
    junk.write_bytes(b"PK\x03\x04" + bytes(100))
    with pytest.raises(DeviceFileError, match="not a readable"):
        read_gt3x(junk)
    with pytest.raises(DeviceFileError, match=r"neither log.bin nor activity.bin"):
        read_gt3x(zip_gt3x(tmp_path / "empty.gt3x", {"info.txt": b"Sample Rate: 30\n"}))
    with pytest.raises(DeviceFileError, match="Sample Rate"):
        read_gt3x(zip_gt3x(tmp_path / "rate.gt3x", {"info.txt": b"Sample Rate: 0\n",
                                                     "log.bin": b""}))


# --- a real file against an independent reader --------------------------------------------------
def test_the_public_activity_file_matches_actfast() -> None:
    path = DEVICES / "actfast_actigraph.gt3x"
    d = read_gt3x(path)
    af = actfast.read(str(path))["timeseries"]["acceleration"]
    assert len(d.t_us) >= 0.95 * len(af["datetime"]) and len(d.t_us) == len(af["datetime"])
    np.testing.assert_array_equal(d.acc_g.astype(np.float32), af["acceleration"])
    assert np.abs(d.t_us - af["datetime"] // 1000).max() <= 1       # actfast truncates to ns
    assert d.metadata["serial"] == "MOS2E17210537" and d.metadata["utc_offset"] == "-05:00:00"
    assert set(d.aux) == {"battery_v", "lux", "worn"} and d.metadata["gaps"] == 0


def test_zip_entries_are_refused_before_inflating(tmp_path: Path) -> None:
    """The declared-size ceiling is checked on the central directory alone."""
    path = _activity2().write(tmp_path / "big.gt3x")
    with zipfile.ZipFile(path) as z:
        assert z.getinfo("log.bin").file_size < 1 << 20
    _patch_sizes(path, b"info.txt", 1 << 20)
    with pytest.raises(DeviceFileError, match=r"info.txt declares"):
        read_gt3x(path)
