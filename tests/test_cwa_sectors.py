"""recal's .cwa decoder (`cwa_sectors.read_cwa`) against actfast's reader, its reference: the
same stamps, values, per-sector tables and metadata, bit for bit, on the real files at hand, on
written ones (packed and 16-bit, gaps) and on damaged ones (a sector that is not data, a bad
checksum, a time that is no date, short sectors, a partial sector at the end); the same
refusals where actfast refuses; and the same on one thread and on several."""

from __future__ import annotations

import shutil
from pathlib import Path

import actfast
import numpy as np
import pytest

from device_writers import DeviceRun, device_signal, write_cwa
from recal.errors import DeviceFileError
from recal.io.device_files import cwa_sectors
from recal.io.device_files.cwa_sectors import HEADER_BYTES, SECTOR_BYTES, read_cwa
from recal.io.device_files.recording import open_device

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
REAL = sorted(DEVICES.glob("*.cwa"))
RUN = DeviceRun(hours=0.2, nominal_hz=50, real_hz=50 * 1.002, seed=5, gap_s=(300.0, 20.0))


def assert_same(ours: dict, theirs: dict) -> None:
    assert ours["metadata"] == theirs["metadata"]
    assert len(ours["warnings"]) == len(theirs["warnings"])
    for name in ("low_frequency", "high_frequency"):
        a, b = ours["timeseries"][name], theirs["timeseries"][name]
        assert set(a) == set(b), name
        for k in a:
            if k == "gyroscope":  # its presence alone: recal does not use it
                assert b[k] is not None and len(b[k]) == len(b["datetime"])
                continue
            assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, (name, k)
            assert np.array_equal(a[k], b[k]), (name, k)


def both(path: Path, lenient: bool = True, threads: int = 1) -> tuple[dict, dict]:
    return read_cwa(path, lenient, threads), actfast.read(str(path), lenient=lenient)


def test_real_files_are_at_hand() -> None:
    kinds = {f.name.split("_")[1] for f in REAL}
    assert len(REAL) >= 4 and {"ax3", "ax6"} <= kinds


@pytest.mark.parametrize("path", REAL, ids=[p.name for p in REAL])
def test_real_files_decode_as_actfast(path: Path) -> None:
    ours, theirs = both(path)
    assert len(theirs["timeseries"]["high_frequency"]["datetime"]) > 1000
    assert_same(ours, theirs)


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("cwa")
    sig = device_signal(RUN)
    out = {}
    for packed in (True, False):
        out["packed" if packed else "int16"] = write_cwa(
            folder / f"{packed}.cwa", sig, packed=packed).path
    return out


@pytest.mark.parametrize("layout", ["packed", "int16"])
@pytest.mark.parametrize("threads", [1, 3])
def test_written_files_decode_as_actfast(written: dict[str, Path], layout: str,
                                         threads: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cwa_sectors, "_PIECE", 97)  # many pieces, their ends anywhere
    assert_same(*both(written[layout], threads=threads))


def test_packed_words_of_every_exponent(written: dict[str, Path], tmp_path: Path) -> None:
    """Packed samples beyond +-511 counts carry an exponent (bits 30-31): words of every
    exponent and sign, written into a sector, decode as actfast decodes them."""
    rng = np.random.default_rng(3)
    words = rng.integers(0, 2**32, 120, dtype=np.uint64).astype("<u4")
    words[:4] = [0x80D0FC15, 0xFFFFFFFF, 0x00000000, 0x7FFFFFFF]  # cwa.h's and the edges
    bad = _damaged(written["packed"], tmp_path / "words.cwa", {4: (30, words.tobytes())})
    _fix_checksum(bad, 4)
    ours, theirs = both(bad)
    assert_same(ours, theirs)
    g = ours["timeseries"]["high_frequency"]["acceleration"][4 * 120:5 * 120]
    assert np.abs(g).max() > 8.0 and g[1].tolist() == [-8 / 256] * 3


def _damaged(src: Path, dst: Path, sectors: dict[int, tuple[int, bytes]],
             cut: int = 0) -> Path:
    """src copied with bytes set at (sector, offset) and the last `cut` bytes dropped."""
    shutil.copyfile(src, dst)
    with open(dst, "r+b") as fh:
        for s, (at, data) in sectors.items():
            fh.seek(HEADER_BYTES + s * SECTOR_BYTES + at)
            fh.write(data)
        if cut:
            fh.truncate(dst.stat().st_size - cut)
    return dst


def _fix_checksum(path: Path, sector: int) -> None:
    with open(path, "r+b") as fh:
        fh.seek(HEADER_BYTES + sector * SECTOR_BYTES)
        words = np.frombuffer(fh.read(SECTOR_BYTES), "<u2").copy()
        words[-1] = (-int(words[:-1].sum(dtype=np.uint64))) & 0xFFFF
        fh.seek(HEADER_BYTES + sector * SECTOR_BYTES)
        fh.write(words.tobytes())


def test_damaged_sectors_are_skipped_as_actfast_skips_them(written: dict[str, Path],
                                                           tmp_path: Path) -> None:
    bad = _damaged(written["packed"], tmp_path / "bad.cwa", {
        3: (0, b"ZZ"),              # not a data sector
        7: (100, b"\x01\x02"),      # a checksum that fails
        11: (14, b"\x00\x00\x00\x00"),  # a time that is no date (month 0) ...
        20: (28, b"\x07\x00"),      # a short sector: 7 samples ...
        25: (24, b"\x00"),          # rate byte 0: its checksum is not checked
    }, cut=100)                     # and a partial sector at the end
    for s in (11, 20):
        _fix_checksum(bad, s)  # ... that passes its checksum
    ours, theirs = both(bad)
    assert len(theirs["warnings"]) == 3
    assert_same(ours, theirs)
    short = 120 * (len(theirs["timeseries"]["low_frequency"]["datetime"]))
    assert len(theirs["timeseries"]["high_frequency"]["datetime"]) < short


def test_refusals_where_actfast_refuses(written: dict[str, Path], tmp_path: Path) -> None:
    bad = _damaged(written["int16"], tmp_path / "bad.cwa", {5: (0, b"ZZ")})
    with pytest.raises(Exception):  # noqa: B017 (actfast's own error types)
        actfast.read(str(bad), lenient=False)
    with pytest.raises(DeviceFileError, match=r"sector 5 .*not a data sector"):
        read_cwa(bad, lenient=False)
    assert_same(*both(bad, lenient=True))
    layout = _damaged(written["int16"], tmp_path / "layout.cwa", {0: (25, b"\x33")})
    _fix_checksum(layout, 0)
    with pytest.raises(Exception):  # noqa: B017
        actfast.read(str(layout), lenient=True)
    with pytest.raises(DeviceFileError, match="numAxesBPS 0x33"):
        read_cwa(layout)
    header = tmp_path / "header.cwa"
    header.write_bytes(b"XX" + written["int16"].read_bytes()[2:])
    with pytest.raises(DeviceFileError, match="header"):
        read_cwa(header)


def test_no_data_sector_gives_empty_tables(written: dict[str, Path], tmp_path: Path) -> None:
    only_header = tmp_path / "head.cwa"
    only_header.write_bytes(written["packed"].read_bytes()[:HEADER_BYTES + 200])
    ours, theirs = both(only_header)
    assert_same(ours, theirs)
    assert not len(ours["timeseries"]["high_frequency"]["datetime"])
    with pytest.raises(DeviceFileError, match="holds no samples"):
        open_device(only_header)


def test_threads_reach_the_decoder(written: dict[str, Path]) -> None:
    """open_device on threads gives the recording one thread gives (the same samples)."""
    one, three = open_device(written["packed"]), open_device(written["packed"], threads=3)
    assert len(one) == len(three) > 0
    assert np.array_equal(one.readings(0, len(one)), three.readings(0, len(three)))
    assert np.array_equal(one.batch(0, len(one)).t_us, three.batch(0, len(three)).t_us)
