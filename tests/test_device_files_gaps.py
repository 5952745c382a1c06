"""Real gaps stay gaps, a clock set back is an event, and damaged files are read up to what
is whole with a count of what was skipped: copies of the shared files made in the test."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from recal.errors import DeviceFileError
from recal.io.device_files import block_times as bt
from recal.io.device_files import open_device
from recal.samples import RawBatch

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
AX3 = DEVICES / "ggirread_ax3_testfile.cwa"  # 100 Hz, 120 samples a sector, 145 sectors
HEADER, SECTOR = 1024, 512


def _sectors(path: Path) -> tuple[bytes, list[bytes]]:
    data = path.read_bytes()
    body = data[HEADER:]
    return data[:HEADER], [body[i:i + SECTOR] for i in range(0, len(body), SECTOR)]


def _times(path: Path) -> np.ndarray:
    return RawBatch.concat(list(open_device(path).batches())).t_us


def test_missing_sectors_stay_a_gap(tmp_path: Path) -> None:
    """Sectors 40-44 removed: one step of about 6 s (5 sectors of 1.2 s and the usual step),
    every other step the ordinary one; the sector before the gap is not stretched over it."""
    head, sectors = _sectors(AX3)
    cut = tmp_path / "cut.cwa"
    cut.write_bytes(head + b"".join(sectors[:40] + sectors[45:]))
    t = _times(cut)
    step = np.diff(t)
    med = np.median(step)
    big = np.flatnonzero(step > 3 * med)
    assert len(big) == 1 and big[0] == 40 * 120 - 1
    whole = np.diff(_times(AX3))
    assert step[big[0]] == pytest.approx(whole[40 * 120 - 1: 45 * 120].sum(), rel=0.01)
    others = np.delete(step, big)
    assert np.abs(others - med).max() <= 0.02 * med
    rec = open_device(cut)
    assert rec.skipped["gaps"] == 1 and any("gap" in n for n in rec.notes)


def test_a_clock_set_back_continues_the_time_axis(tmp_path: Path) -> None:
    """Sectors 20-59 again after sector 99: the file's time steps back about 97 s. The block
    whose time goes back continues where the previous one's samples end, and it is counted
    as a clock change."""
    head, sectors = _sectors(AX3)
    back = tmp_path / "back.cwa"
    back.write_bytes(head + b"".join(sectors[:100] + sectors[20:60]))
    rec = open_device(back)
    t = RawBatch.concat(list(rec.batches())).t_us
    assert (np.diff(t) > 0).all()
    assert rec.skipped["clock_changes"] == 1
    assert any("clock change" in n for n in rec.notes)
    own = np.concatenate(list(rec.file_times()))
    assert (np.diff(own) < 0).sum() == 1  # the file's own stamps keep the step back


def test_a_corrupt_sector_is_skipped_and_counted(tmp_path: Path) -> None:
    head, sectors = _sectors(AX3)
    bad = bytearray(sectors[20])
    bad[100:110] = bytes(10)  # its checksum fails
    damaged = tmp_path / "damaged.cwa"
    damaged.write_bytes(head + b"".join([*sectors[:20], bytes(bad), *sectors[21:]]))
    rec = open_device(damaged)
    assert len(rec) == 144 * 120
    assert rec.skipped["sectors"] == 1 and rec.skipped["gaps"] == 1
    assert any("1 of 145 sectors skipped" in n for n in rec.notes)
    assert any("skipped damaged data 1 time(s)" in n and "checksum" in n for n in rec.notes)
    with pytest.raises(DeviceFileError, match=r"Axivity \.cwa that cannot be read"):
        open_device(damaged, lenient=False)


def test_a_file_cut_inside_a_sector_keeps_the_whole_sectors(tmp_path: Path) -> None:
    short = tmp_path / "short.cwa"
    short.write_bytes(AX3.read_bytes()[:HEADER + 30 * SECTOR + 200])
    rec = open_device(short)
    assert len(rec) == 30 * 120
    assert rec.skipped["partial_sector"] == 1
    assert any("partial sector" in n for n in rec.notes)


def test_a_cut_short_gt3x_or_geneactiv_gives_what_is_whole_or_one_error(tmp_path: Path) -> None:
    """A zip cut short loses its directory (one error); a GENEActiv cut in a page keeps the
    pages before it."""
    gt3x = tmp_path / "short.gt3x"
    data = (DEVICES / "actfast_actigraph.gt3x").read_bytes()
    gt3x.write_bytes(data[:len(data) // 2])
    with pytest.raises(DeviceFileError):
        open_device(gt3x)
    gen = tmp_path / "short.bin"
    data = (DEVICES / "actfast_geneactiv.bin").read_bytes()
    gen.write_bytes(data[:len(data) // 2])
    rec = open_device(gen)
    assert 0 < len(rec) < 6000 and rec.skipped["pages"] > 0


def test_block_times_spread_each_block_to_the_next() -> None:
    """Three blocks of 4 samples stamped at 10 ms from the block time, real period 11 ms; a
    gap of 1 s before the fourth: spread within the first two, the measured 11 ms before the
    gap and in the last."""
    p_ns = 10_000_000
    starts_ns = np.array([0, 44, 88, 1088], np.int64) * 1_000_000
    file_t = (starts_ns[:, None] + np.arange(4) * p_ns).ravel()
    start = bt.block_starts(file_t, p_ns, starts_ns)
    np.testing.assert_array_equal(start, [0, 4, 8, 12])
    b = bt.block_times(file_t, start, p_ns)
    t = b.times_ns(0, 16)
    np.testing.assert_array_equal(np.diff(t)[:8], 11_000_000)
    assert b.measured_period_ns == 11_000_000
    assert t[11] == 88_000_000 + 33_000_000 and t[12] == 1_088_000_000
    assert b.gaps == 1 and b.gap_s == pytest.approx(1.088 - 0.088 - 0.044)
    np.testing.assert_array_equal(b.times_ns(5, 7), t[5:7])  # any slice, the same times


def test_block_starts_are_the_same_in_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    """The steps are looked at a chunk at a time (bounded memory): a boundary at a chunk's
    edge is still found."""
    rng = np.random.default_rng(3)
    file_t = np.cumsum(rng.choice([10_000_000] * 5 + [23_000_000], size=500)).astype(np.int64)
    whole = bt.block_starts(file_t, 1e7)
    monkeypatch.setattr(bt, "CHUNK", 7)
    np.testing.assert_array_equal(bt.block_starts(file_t, 1e7), whole)
    step = np.diff(file_t)
    np.testing.assert_array_equal(whole, np.r_[0, np.flatnonzero(step != 10_000_000) + 1])


def _log_records(log: bytes) -> list[bytes]:
    """ActiGraph log.bin split into its records (0x1E, type, 4-byte time, 2-byte size,
    payload, checksum)."""
    out, i = [], 0
    while i + 8 <= len(log) and log[i] == 0x1E:
        end = i + 8 + int.from_bytes(log[i + 6:i + 8], "little") + 1
        out.append(log[i:end])
        i = end
    assert i == len(log)
    return out


def test_actigraph_seconds_without_records_stay_a_gap(tmp_path: Path) -> None:
    """Idle sleep: the device writes no ACTIVITY record for the seconds it sleeps. Five such
    seconds are a gap of five seconds, not samples repeated or spread over them."""
    import zipfile

    src = DEVICES / "actfast_actigraph.gt3x"
    with zipfile.ZipFile(src) as z:
        entries = {n: z.read(n) for n in z.namelist()}
    records = _log_records(entries["log.bin"])
    activity = [i for i, r in enumerate(records) if r[1] == 0x00]
    asleep = set(activity[30:35])
    entries["log.bin"] = b"".join(r for i, r in enumerate(records) if i not in asleep)
    slept = tmp_path / "slept.gt3x"
    with zipfile.ZipFile(slept, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    rec = open_device(slept)
    t = RawBatch.concat(list(rec.batches())).t_us
    assert len(t) == 4860 - 5 * 60
    step = np.diff(t)
    big = np.flatnonzero(step > 2 * np.median(step))
    assert len(big) == 1 and step[big[0]] == pytest.approx(6e6 - 1e6 / 60 * 59, abs=2)
    assert rec.skipped["gaps"] == 1
