"""Crafted and damaged device files give one line (DeviceFileError; exit 2 through the real
command line), in bounded memory and time: zip bombs, lying sizes and header counts, garbage,
an empty file; and the kinds recal recognises but cannot read say which kind they are."""

from __future__ import annotations

import gzip
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from recal.errors import DeviceFileError
from recal.io.device_files import guard, open_device, sniff
from recal.samples import RawBatch

DEVICES = Path(__file__).resolve().parents[2] / "shared" / "data" / "devices"
GT3X = DEVICES / "actfast_actigraph.gt3x"


def _gt3x_with(path: Path, entries: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return path


def _log_record(kind: int, payload: bytes) -> bytes:
    head = bytes([0x1E, kind]) + struct.pack("<IH", 1_700_000_000, len(payload))
    return head + payload + b"\x00"


def test_a_zip_bomb_gt3x_is_refused_before_the_reader(tmp_path: Path) -> None:
    """log.bin of 64 MiB of zeros compresses about 1000 to 1: past the cap (200x)."""
    with zipfile.ZipFile(GT3X) as z:
        info = z.read("info.txt")
    bomb = _gt3x_with(tmp_path / "bomb.gt3x", {"info.txt": info, "log.bin": bytes(64 << 20)})
    assert bomb.stat().st_size < 1 << 20 and sniff(bomb) == "actigraph_gt3x"
    with pytest.raises(DeviceFileError, match="zip bomb"):
        open_device(bomb)


def test_a_gt3x_entry_that_lies_about_its_size_is_refused(tmp_path: Path) -> None:
    """The central directory says log.bin is 100 bytes; it expands to far more."""
    src = tmp_path / "copy.gt3x"
    src.write_bytes(GT3X.read_bytes())
    with zipfile.ZipFile(src) as z:
        real = z.getinfo("log.bin").file_size
    data = bytearray(src.read_bytes())
    patched = 0
    for at in range(len(data) - 46):
        if data[at:at + 4] == b"PK\x01\x02":
            name_len = struct.unpack_from("<H", data, at + 28)[0]
            if data[at + 46:at + 46 + name_len] == b"log.bin":
                struct.pack_into("<I", data, at + 24, 100)  # uncompressed size
                patched += 1
    assert patched == 1 and real > 100
    liar = tmp_path / "liar.gt3x"
    liar.write_bytes(bytes(data))
    with pytest.raises(DeviceFileError):
        open_device(liar)


def test_a_geneactiv_header_that_claims_too_many_pages_is_refused(tmp_path: Path) -> None:
    """actfast reserves memory for every page the header claims: a claim the file cannot
    hold and no recording needs is refused before it reads."""
    data = (DEVICES / "actfast_geneactiv.bin").read_bytes()
    assert b"Number of Pages:20" in data
    liar = tmp_path / "liar.bin"
    liar.write_bytes(data.replace(b"Number of Pages:20", b"Number of Pages:999999999999"))
    with pytest.raises(DeviceFileError, match="claims 999999999999 pages"):
        open_device(liar)


@pytest.mark.parametrize("content", [b"", bytes(1000), np.random.default_rng(1).bytes(5000),
                                     b"MD\xfc\x03" + bytes(100), b"PK\x03\x04garbage",
                                     b"Device Identity\r\n" + b"x" * 50])
def test_garbage_gives_one_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "garbage.cwa"
    path.write_bytes(content)
    with pytest.raises(DeviceFileError) as err:
        open_device(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_gzipped_cwa_reads_as_the_cwa(tmp_path: Path) -> None:
    src = DEVICES / "ggirread_ax3_testfile.cwa"
    gz = tmp_path / "ax3.cwa.gz"
    gz.write_bytes(gzip.compress(src.read_bytes()))
    assert sniff(gz) == "axivity_cwa"
    a, b = open_device(src), open_device(gz)
    ba, bb = RawBatch.concat(list(a.batches())), RawBatch.concat(list(b.batches()))
    np.testing.assert_array_equal(ba.t_us, bb.t_us)
    np.testing.assert_array_equal(ba.v, bb.v)
    assert a.metadata["device_id"] == b.metadata["device_id"]


def test_the_expanded_copy_is_removed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    guard.tempfile.tempdir = None  # let tempfile see TMPDIR
    try:
        gz = tmp_path / "ax3.cwa.gz"
        gz.write_bytes(gzip.compress((DEVICES / "ggirread_ax3_testfile.cwa").read_bytes()))
        assert len(open_device(gz)) == 17400
        assert not list((tmp_path / "tmp").iterdir())
    finally:
        guard.tempfile.tempdir = None


def test_a_gzip_bomb_stops_at_the_cap(tmp_path: Path) -> None:
    """64 MiB of a .cwa header and zeros in about 64 KiB: the expansion stops at 200x."""
    cwa = (DEVICES / "ggirread_ax3_testfile.cwa").read_bytes()[:1024] + bytes(64 << 20)
    gz = tmp_path / "bomb.cwa.gz"
    gz.write_bytes(gzip.compress(cwa, compresslevel=9))
    assert gz.stat().st_size * guard.MAX_RATIO < 64 << 20
    with pytest.raises(DeviceFileError, match="expands beyond"):
        open_device(gz)


def test_a_cut_gzip_keeps_what_was_whole(tmp_path: Path) -> None:
    data = gzip.compress((DEVICES / "skdh_ax3_sample.cwa").read_bytes())
    gz = tmp_path / "cut.cwa.gz"
    gz.write_bytes(data[:len(data) // 2])
    rec = open_device(gz)
    assert 0 < len(rec) < 58800


UNREADABLE = {
    "genea_bin": lambda p: p.write_bytes(b"GENEA Header\r\n" + bytes(2000)),
}


@pytest.mark.parametrize("kind", sorted(UNREADABLE))
def test_kinds_recal_cannot_read_say_what_they_are_through_the_cli(
        tmp_path: Path, kind: str) -> None:
    path = tmp_path / "recording.dat"  # the extension says nothing
    UNREADABLE[kind](path)
    assert sniff(path) == kind
    done = subprocess.run([sys.executable, "-m", "recal", "hindsight", str(path), "--out",
                           str(tmp_path / "out.mcap")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recal: error:"), done.stderr
    name = {"genea_bin": "Genea .bin"}[kind]
    assert name in lines[0] and "cannot read this kind of file yet" in lines[0]
    assert not (tmp_path / "out.mcap").exists()
