"""Checks on a device file before a reader touches it: a device file is input from outside.

A crafted or damaged file must give one line, in bounded memory and time. The native reader
(actfast) reads a whole file into memory and trusts some header fields, so what it cannot
bound is bounded here first:

* a gzip-compressed file is expanded in chunks to a temporary file, up to a cap proportional
  to the compressed size and an absolute cap (a gzip bomb stops at the cap);
* a .gt3x (a zip) has its entries' declared sizes checked and the entries actfast reads
  expanded once, counting, up to the same kind of caps (a zip bomb, an entry that lies about
  its size);
* a GENEActiv header's page count (actfast reserves memory for that many pages) must fit the
  file or a plausible recording.

Hand-written because no library bounds these for us: zipfile and zlib expand what they are
given.
"""

from __future__ import annotations

import os
import re
import struct
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

from recal.errors import DeviceFileError

__all__ = ["MAX_EXPANDED_BYTES", "MAX_RATIO", "ZIP_DAMAGE", "check_geneactiv_pages",
           "check_zip", "gunzip_to", "is_gzip", "read_head"]

#: an expanded file (a .cwa.gz, a .gt3x's log.bin) may be at most this many times its
#: compressed size, and never more than MAX_EXPANDED_BYTES (a month at 100 Hz fits both)
MAX_RATIO = 200
MAX_EXPANDED_BYTES = 8 << 30
CHUNK_BYTES = 1 << 20
GZIP_MAGIC = b"\x1f\x8b"
#: what zipfile raises on a damaged archive (a bad offset seeks before the start: OSError)
ZIP_DAMAGE = (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, OSError,
              ValueError, struct.error, KeyError, IndexError, OverflowError)
#: a GENEActiv page holds 300 samples as 3600 hex digits plus its header lines
GENEACTIV_PAGE_MIN_BYTES = 3600
#: pages a plausible GENEActiv recording holds whatever its size: 14 days at 100 Hz
GENEACTIV_MAX_PAGES = 14 * 86400 * 100 // 300


def is_gzip(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == GZIP_MAGIC


def _cap(compressed_bytes: int) -> int:
    return min(MAX_EXPANDED_BYTES, max(1 << 20, MAX_RATIO * compressed_bytes))


def read_head(path: Path, n: int = 4096) -> bytes:
    """The first ``n`` bytes of the file, expanded if it is gzip-compressed (bounded: at most
    ``n`` bytes are produced whatever the input)."""
    with open(path, "rb") as f:
        raw = f.read(n if not is_gzip(path) else 1 << 16)
    if raw[:2] != GZIP_MAGIC:
        return raw
    try:
        return zlib.decompressobj(wbits=31).decompress(raw, n)
    except zlib.error:
        return b""


def gunzip_to(path: Path, folder: str | None = None) -> Path:
    """The gzip file expanded into a new temporary file (the caller deletes it); a
    DeviceFileError when the expansion would pass the cap or the stream is damaged. A stream
    cut short keeps what it expanded to (the reader then skips the last partial block)."""
    cap = _cap(path.stat().st_size)
    fd, name = tempfile.mkstemp(suffix=".cwa", dir=folder)
    out = Path(name)
    try:
        with os.fdopen(fd, "wb") as dst, open(path, "rb") as src:
            _expand(src, dst, cap, path)
    except zlib.error as e:
        out.unlink(missing_ok=True)
        raise DeviceFileError(f"{path}: damaged gzip stream ({e})") from None
    except BaseException:
        out.unlink(missing_ok=True)
        raise
    return out


def _expand(src: BinaryIO, dst: BinaryIO, cap: int, path: Path) -> None:
    """zlib in bounded steps (at most CHUNK_BYTES out per call, whatever the input), member
    after member."""
    written = 0
    d = zlib.decompressobj(wbits=31)
    while chunk := src.read(CHUNK_BYTES):
        while chunk:
            piece = d.decompress(chunk, CHUNK_BYTES)
            written += len(piece)
            if written > cap:
                raise DeviceFileError(
                    f"{path}: gzip-compressed file expands beyond {cap >> 20} MiB "
                    f"({MAX_RATIO}x its size or {MAX_EXPANDED_BYTES >> 30} GiB): refused")
            dst.write(piece)
            if d.eof:  # another member may follow
                chunk = d.unused_data
                d = zlib.decompressobj(wbits=31)
            else:
                chunk = d.unconsumed_tail


def check_zip(path: Path, entries: tuple[str, ...]) -> None:
    """A .gt3x's zip checked before a reader expands it: every entry's declared size within
    the caps, and the ``entries`` the reader expands expanded once here, counting, so that
    one that lies about its size or fails its checksum is refused."""
    size = path.stat().st_size
    cap = _cap(size)
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
            if len(infos) > 1000:
                raise DeviceFileError(f"{path}: ActiGraph .gt3x zip with {len(infos)} entries: "
                                      "refused (a damaged or crafted file)")
            total = sum(i.file_size for i in infos)
            if total > cap:
                raise DeviceFileError(
                    f"{path}: ActiGraph .gt3x zip declares {total >> 20} MiB expanded from "
                    f"{size >> 20} MiB: refused (a zip bomb or a damaged file)")
            for info in infos:
                if info.filename in entries:
                    _expand_counting(z, info, path, cap)
    except ZIP_DAMAGE as e:
        raise DeviceFileError(f"{path}: ActiGraph .gt3x is not a readable zip ({e})") from None


def _expand_counting(z: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, cap: int) -> None:
    seen = 0
    with z.open(info) as f:
        while chunk := f.read(CHUNK_BYTES):
            seen += len(chunk)
            if seen > info.file_size or seen > cap:
                raise DeviceFileError(
                    f"{path}: ActiGraph .gt3x entry {info.filename} expands beyond its "
                    f"declared {info.file_size} bytes or the cap: refused (a zip bomb or a "
                    "damaged file)")


_PAGES = re.compile(rb"Number of Pages:\s*(\d+)")


def check_geneactiv_pages(path: Path, head: bytes) -> int | None:
    """The page count the GENEActiv header claims (None if it names none); a DeviceFileError
    if it is more than the file can hold and more than a plausible recording (the reader
    would reserve memory for every page claimed)."""
    m = _PAGES.search(head)
    if m is None:
        return None
    pages = int(m.group(1)) if len(m.group(1)) < 18 else 1 << 62
    fits = path.stat().st_size // GENEACTIV_PAGE_MIN_BYTES + 1
    if pages > max(fits, GENEACTIV_MAX_PAGES):
        raise DeviceFileError(f"{path}: GENEActiv .bin header claims {pages} pages, the file "
                              f"holds at most {fits}: refused (a damaged or crafted header)")
    return pages
