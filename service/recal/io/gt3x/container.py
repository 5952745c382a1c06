"""The ``.gt3x`` zip as untrusted input: entry sizes checked before anything is inflated, entries
read in bounded chunks, ``info.txt`` parsed, and every damage said as one `DeviceFileError` line.

A ``.gt3x`` is a zip (``actigraph/GT3X-File-Format`` README; ``NHANES-GT3X-File-Format`` README).
Nothing here trusts a size the file states: each entry's declared size is checked against a
ceiling before it is opened, ``zipfile`` stops inflating at the declared size (a member that
expands further fails its CRC), and entries are read ``CHUNK_BYTES`` at a time, so memory is the
chunk plus what is decoded, whatever the file claims.
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

from recal.errors import DeviceFileError

INFO_MAX_BYTES = 1 << 16          # a real info.txt is under 1 kB
SIDE_MAX_BYTES = 1 << 20          # calibration.json, and the like
DATA_MAX_BYTES = 8 << 30          # log.bin / activity.bin: 8 GiB is months at 100 Hz
CHUNK_BYTES = 8 << 20
# Deflate cannot expand more than ~1032 times; an entry that says it does lies about its size.
MAX_EXPANSION = 1100
DOTNET_TICKS_AT_UNIX_EPOCH = 621_355_968_000_000_000   # .NET ticks (100 ns) at 1970-01-01
# what zipfile raises on a damaged or crafted archive (a version it does not know:
# NotImplementedError; a bad offset: OSError; a cut header: struct.error)
_ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError,
               ValueError, OSError, struct.error, KeyError, IndexError, OverflowError)


def open_zip(path: Path) -> zipfile.ZipFile:
    """The file as a zip, or one line saying it is not a readable one."""
    if not Path(path).is_file():
        raise DeviceFileError(f"{path}: no such file")
    try:
        return zipfile.ZipFile(path)
    except _ZIP_ERRORS as exc:
        raise DeviceFileError(f"{path}: not a readable .gt3x (zip) file: {exc}") from None


def entry_info(zf: zipfile.ZipFile, name: str, max_bytes: int) -> zipfile.ZipInfo | None:
    """The entry ``name`` if present, refused before inflation when its declared size is over
    ``max_bytes`` or it is encrypted."""
    try:
        info = zf.getinfo(name)
    except KeyError:
        return None
    if info.file_size > max_bytes:
        raise DeviceFileError(f"{zf.filename}: {name} declares {info.file_size} bytes, over the "
                         f"{max_bytes}-byte limit for it: refused without inflating it")
    if info.file_size > max(MAX_EXPANSION * info.compress_size, 1 << 16):
        raise DeviceFileError(f"{zf.filename}: {name} declares {info.file_size} bytes from "
                         f"{info.compress_size} compressed, more than any deflate expands "
                         "(a zip bomb or a lying size): refused without inflating it")
    if info.flag_bits & 0x1:
        raise DeviceFileError(f"{zf.filename}: {name} is encrypted")
    return info


def read_entry(zf: zipfile.ZipFile, name: str, max_bytes: int) -> bytes | None:
    """A small entry whole (bounded by ``max_bytes``), or None if absent."""
    info = entry_info(zf, name, max_bytes)
    if info is None:
        return None
    return b"".join(iter_entry(zf, info, max_bytes))


def iter_entry(zf: zipfile.ZipFile, info: zipfile.ZipInfo,
               chunk_bytes: int = CHUNK_BYTES) -> Iterator[bytes]:
    """An entry's bytes in chunks; a corrupt or lying member is one `DeviceFileError`."""
    try:
        with zf.open(info) as f:
            while chunk := f.read(chunk_bytes):
                yield chunk
    except _ZIP_ERRORS as exc:
        raise DeviceFileError(f"{zf.filename}: {info.filename} is damaged: {exc}") from None


def parse_info(text: bytes) -> dict[str, str]:
    """info.txt's ``Key: Value`` lines (info.txt.md)."""
    out: dict[str, str] = {}
    for line in text.decode("utf-8-sig", errors="replace").splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip():
            out[key.strip()] = value.strip()
    return out


def info_float(info: dict[str, str], key: str, where: str) -> float | None:
    """A number from info.txt, None if absent; a value that is not a number is an error."""
    if key not in info or info[key] == "":
        return None
    try:
        return float(info[key])
    except ValueError:
        raise DeviceFileError(f"{where}: info.txt {key} is {info[key]!r}, not a number") from None


def ticks_to_unix_us(ticks: int) -> int:
    """.NET ticks (100 ns since 0001-01-01, NHANES technical.md) -> Unix microseconds."""
    return (ticks - DOTNET_TICKS_AT_UNIX_EPOCH) // 10


def info_time_us(info: dict[str, str], key: str, where: str) -> int | None:
    """An info.txt date (.NET ticks) as Unix microseconds of the same clock; None if absent or 0."""
    raw = info.get(key, "").strip()
    if not raw or raw == "0":
        return None
    try:
        ticks = int(raw)
    except ValueError:
        raise DeviceFileError(f"{where}: info.txt {key} is {raw!r}, not .NET ticks") from None
    if not 0 <= ticks - DOTNET_TICKS_AT_UNIX_EPOCH < 200 * 365 * 864 * 10**9:
        raise DeviceFileError(f"{where}: info.txt {key} {ticks} is not a date in 1970-2170")
    return ticks_to_unix_us(ticks)
