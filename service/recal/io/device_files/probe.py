"""What the sniff tests look at: a file's first bytes (expanded if gzip-compressed) and, for a
zip, its entry names and the first log records of its log.bin. Each is read once, bounded."""

from __future__ import annotations

import zipfile
from functools import cached_property
from pathlib import Path

from recal.io.device_files import guard

__all__ = ["Probe"]

#: bytes of a .gt3x's log.bin read to tell ACTIVITY from ACTIVITY2 records
LOG_PREFIX_BYTES = 1 << 20
LOG_SEPARATOR = 0x1E


class Probe:
    """A file's content as far as recognising its kind needs."""

    def __init__(self, path: Path) -> None:
        self.path = path

    @cached_property
    def head(self) -> bytes:
        try:
            return guard.read_head(self.path, 8192)
        except OSError:
            return b""

    @cached_property
    def gzipped(self) -> bool:
        try:
            return guard.is_gzip(self.path)
        except OSError:
            return False

    @cached_property
    def zip_names(self) -> frozenset[str]:
        """The entry names of a zip (empty for anything else or a zip that cannot be read)."""
        if self.gzipped or not self.head.startswith(b"PK\x03\x04"):
            return frozenset()
        try:
            with zipfile.ZipFile(self.path) as z:
                return frozenset(z.namelist()[:10_000])
        except guard.ZIP_DAMAGE:  # not a zip after all: no names
            return frozenset()

    @cached_property
    def log_record_types(self) -> frozenset[int]:
        """The types of the log records that start log.bin (ActiGraph's log: a 0x1E
        separator, a type byte, a 4-byte time, a 2-byte size, the payload, a checksum)."""
        if "log.bin" not in self.zip_names:
            return frozenset()
        try:
            with zipfile.ZipFile(self.path) as z, z.open("log.bin") as f:
                data = f.read(LOG_PREFIX_BYTES)
        except guard.ZIP_DAMAGE:
            return frozenset()
        found: set[int] = set()
        i = 0
        while i + 8 <= len(data) and data[i] in (LOG_SEPARATOR, 0):
            if data[i] == 0:   # zero bytes between records: allowed, not damage (README)
                i += 1
                continue
            found.add(data[i + 1])
            i += 8 + int.from_bytes(data[i + 6:i + 8], "little") + 1
        return frozenset(found)
