"""Synthetic ActiGraph ``.gt3x`` files of the two layouts actfast does not read, written from
ActiGraph's published descriptions (``actigraph/GT3X-File-Format``: log record framing, checksum,
ACTIVITY, ACTIVITY2, PARAMETERS, METADATA, EVENT idle sleep; ``actigraph/NHANES-GT3X-File-Format``:
activity.bin, lux.bin, info.txt). They pack where the reader unpacks, with plain Python per
sample, so that writer and reader share no code path."""

from __future__ import annotations

import json
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DOTNET_TICKS_AT_UNIX_EPOCH = 621_355_968_000_000_000


def checksum(body: bytes) -> int:
    x = 0
    for b in body:
        x ^= b
    return (~x) & 0xFF


def record(kind: int, time_s: int, payload: bytes) -> bytes:
    """One log record: 0x1E, type, LE uint32 seconds, LE uint16 size, payload, checksum."""
    body = (bytes([0x1E, kind]) + int(time_s).to_bytes(4, "little")
            + len(payload).to_bytes(2, "little") + payload)
    return body + bytes([checksum(body)])


def pack12_yxz(counts_xyz: Sequence[Sequence[int]]) -> bytes:
    """Samples as 12-bit two's complement, YXZ, most significant nibble first; an odd count leaves
    a last zero nibble."""
    nibbles: list[int] = []
    for x, y, z in counts_xyz:
        for v in (y, x, z):
            u = int(v) & 0xFFF
            nibbles += [u >> 8, (u >> 4) & 0xF, u & 0xF]
    if len(nibbles) % 2:
        nibbles.append(0)
    return bytes((nibbles[i] << 4) | nibbles[i + 1] for i in range(0, len(nibbles), 2))


def pack16_xyz(counts_xyz: Sequence[Sequence[int]]) -> bytes:
    return b"".join(int(v).to_bytes(2, "little", signed=True) for s in counts_xyz for v in s)


def ssp_encode(f: float) -> int:
    """Parameters.md's float: fraction (24-bit two's complement, 2^23 x mantissa in [0.5, 1)) and
    an 8-bit signed power of two."""
    if f == 0:
        return 0
    m, e = abs(f), 0
    while m >= 1.0:
        m, e = m / 2, e + 1
    while m < 0.5:
        m, e = m * 2, e - 1
    frac = int(m * (1 << 23)) * (1 if f > 0 else -1)
    return ((e & 0xFF) << 24) | (frac & 0xFFFFFF)


def parameters_payload(params: dict[tuple[int, int], int]) -> bytes:
    return b"".join(a.to_bytes(2, "little") + i.to_bytes(2, "little") + (v & 0xFFFFFFFF)
                    .to_bytes(4, "little") for (a, i), v in params.items())


def info_txt(fields: dict[str, str]) -> bytes:
    return "".join(f"{k}: {v}\n" for k, v in fields.items()).encode()


def zip_gt3x(path: Path, entries: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return path


@dataclass
class LogFile:
    """What a synthetic log.bin holds, to write it and to check a reader against it.

    ``counts`` has one row per sample of every second not asleep; ``asleep`` lists the seconds
    (from the start) the device slept through (no ACTIVITY record; EVENT 0x08/0x09 around)."""

    counts: np.ndarray
    rate_hz: int
    start_s: int = 1_700_000_000
    kind: int = 0x1A
    scale: float = 256.0
    serial: str = "TAS1E23456789"
    asleep: tuple[int, ...] = ()
    battery_mv: dict[int, int] = field(default_factory=dict)   # second -> mV
    lux: dict[int, int] = field(default_factory=dict)          # second -> lux
    bad_checksum_seconds: tuple[int, ...] = ()
    imu_records: int = 0
    zero_padding: bool = True       # the description allows it; actfast 1.3 stops at it
    parameters: bool = True         # a PARAMETERS record (ACCEL_SCALE, rate, sleep mode on)

    def seconds(self) -> list[int]:
        """The seconds that hold samples, in order."""
        n_awake = len(self.counts) // self.rate_hz
        out, s = [], 0
        while len(out) < n_awake:
            if s not in self.asleep:
                out.append(s)
            s += 1
        return out

    def expected_t_us(self) -> np.ndarray:
        return np.array([(self.start_s + s) * 1_000_000 + round(i * 1e6 / self.rate_hz)
                         for s in self.seconds() if s not in self.bad_checksum_seconds
                         for i in range(self.rate_hz)], dtype=np.int64)

    def expected_counts(self) -> np.ndarray:
        keep = [k for k, s in enumerate(self.seconds()) if s not in self.bad_checksum_seconds]
        return self.counts.reshape(-1, self.rate_hz, 3)[keep].reshape(-1, 3)

    def log_bin(self) -> bytes:
        meta = json.dumps({"MetadataType": "Bio", "SubjectName": "synthetic"}).encode()
        params = {(0, 55): ssp_encode(self.scale), (1, 10): self.rate_hz, (1, 2): 1 << 2}
        out = [record(0x06, self.start_s, meta), b"\0\0\0" if self.zero_padding else b"",
               record(0x15, self.start_s, parameters_payload(params)) if self.parameters
               else b""]
        pack = pack16_xyz if self.kind == 0x1A else pack12_yxz
        by_sec = dict(zip(self.seconds(), self.counts.reshape(-1, self.rate_hz, 3), strict=True))
        last = max(self.seconds(), default=0)
        for s in range(last + 1):
            t = self.start_s + s
            if s in self.asleep and s - 1 not in self.asleep:
                out.append(record(0x03, t, bytes([0x08])))
            if s in by_sec:
                if s - 1 in self.asleep:
                    out.append(record(0x03, t, bytes([0x09])))
                r = bytearray(record(self.kind, t, pack(by_sec[s].tolist())))
                if s in self.bad_checksum_seconds:
                    r[-1] ^= 0xFF
                out.append(bytes(r))
            if s in self.battery_mv:
                out.append(record(0x02, t, self.battery_mv[s].to_bytes(2, "little")))
            if s in self.lux:
                out.append(record(0x05, t, self.lux[s].to_bytes(2, "little")))
        for k in range(self.imu_records):
            out.append(record(0x19, self.start_s + last, bytes(8 + k % 3)))
        out.append(record(self.kind, self.start_s + last + 1, b"\x01"))   # a USB event
        return b"".join(out)

    def entries(self) -> dict[str, bytes]:
        start_ticks = DOTNET_TICKS_AT_UNIX_EPOCH + self.start_s * 10_000_000
        return {"info.txt": info_txt({"Serial Number": self.serial, "Device Type": "GT9X",
                                      "Firmware": "1.7.2", "Sample Rate": str(self.rate_hz),
                                      "Start Date": str(start_ticks), "TimeZone": "01:00:00",
                                      "Acceleration Scale": "999.0"}),
                "log.bin": self.log_bin(),
                "calibration.json": json.dumps({"isCalibrated": True, "zeroGOffsetX": 3}).encode()}

    def write(self, path: Path) -> Path:
        return zip_gt3x(path, self.entries())


def nhanes_entries(counts: np.ndarray, rate_hz: int, start_s: int, lux_raw: Sequence[int],
                   serial: str = "NEO1C16110020") -> dict[str, bytes]:
    """An NHANES-era .gt3x's entries: activity.bin (samples packed continuously), lux.bin (one
    LE uint16 a second), info.txt with the start in .NET ticks."""
    ticks = DOTNET_TICKS_AT_UNIX_EPOCH + start_s * 10_000_000
    return {"info.txt": info_txt({"Serial Number": serial, "Firmware": "2.2.0",
                                  "Sample Rate": str(rate_hz), "Start Date": str(ticks),
                                  "Stop Date": "0"}),
            "activity.bin": pack12_yxz(counts.tolist()),
            "lux.bin": b"".join(int(v).to_bytes(2, "little") for v in lux_raw)}
