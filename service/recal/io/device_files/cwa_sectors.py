"""Axivity .cwa decoded with numpy: the header packet and every data sector at once, the
samples on threads. The values, stamps and tables are actfast 1.3's for the same file, bit for
bit (tests/test_cwa_sectors.py compares the two on every .cwa at hand, damaged ones too): the
decoding follows openmovement's Docs/ax3/cwa.h as actfast reads it. Why recal decodes this one
format itself: docs/design.md, "A .cwa decoded on threads".

A data sector (512 bytes, after the 1024-byte header) holds its time (packed, whole seconds,
plus a 15-bit fraction where the first sector's bit 15 at byte 4 says so), the sample index that
time belongs to, a row of light, temperature and battery, and 120 packed (3 x 10 bits and an
exponent) or 480 / (2 axes) int16 samples; AX6 sectors carry the gyroscope's three axes first.
The first sector that passes its checks sets the layout, scale and rate for all. A sector that
is not "AX", fails its checksum or whose time is no date is skipped with a warning (lenient) or
refused; a partial sector at the end is dropped.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from recal.errors import DeviceFileError

__all__ = ["read_cwa"]

HEADER_BYTES, SECTOR_BYTES = 1024, 512
#: the fields of a data sector recal reads (cwa.h's OM_READER_DATA_PACKET)
_SECTOR = np.dtype({
    "names": ["magic", "fraction", "stamp", "light", "temperature", "battery", "rate",
              "axes_bps", "offset", "count"],
    "formats": ["<u2", "<u2", "<u4", "<u2", "<u2", "u1", "u1", "u1", "<i2", "<u2"],
    "offsets": [0, 4, 14, 18, 20, 23, 24, 25, 26, 28], "itemsize": SECTOR_BYTES})
_DATA_AT, _DATA_BYTES = 30, 480
_HARDWARE = {0x64: "AX6", 0x00: "AX3", 0xFF: "AX3"}
#: Sectors decoded per piece of work (2.4 Mi samples of packed data): a few pieces per thread.
_PIECE = 20_000


def read_cwa(path: Path, lenient: bool = True, threads: int = 1) -> dict[str, Any]:
    """The file as actfast.read gives it (``metadata``, ``timeseries``: ``high_frequency``
    datetime and acceleration in g, ``low_frequency`` per sector; ``warnings``), but for the
    gyroscope, whose presence alone is given (``gyroscope``: None). DeviceFileError where
    actfast raises."""
    raw = np.memmap(path, np.uint8, "r") if path.stat().st_size else np.zeros(0, np.uint8)
    if len(raw) < HEADER_BYTES or bytes(raw[:2]) != b"MD":
        raise DeviceFileError("no CWA header packet ('MD')")
    metadata = _header(bytes(raw[:HEADER_BYTES]))
    n = (len(raw) - HEADER_BYTES) // SECTOR_BYTES
    sectors = raw[HEADER_BYTES:HEADER_BYTES + n * SECTOR_BYTES].reshape(n, SECTOR_BYTES)
    head = sectors.view(_SECTOR).reshape(n)
    fine, warnings = _checked(sectors, head, lenient)
    out: dict[str, Any] = {"format": "Axivity CWA", "metadata": metadata, "warnings": warnings}
    if not fine.any():
        none = np.zeros(0, np.int64)
        out["timeseries"] = _tables(none, np.zeros((0, 3), np.float32), none, head, none, False)
        return out
    layout = _Layout.of(head[int(np.flatnonzero(fine)[0])])
    origin_ns, dated = _origins(head, layout)
    bad_date = np.flatnonzero(fine & ~dated)
    if len(bad_date) and not lenient:
        raise DeviceFileError(_where(int(bad_date[0]), "a time stamp that is no date"))
    warnings += [_where(int(i), "a time stamp that is no date") for i in bad_date]
    used = np.flatnonzero(fine & dated)
    lf_t = origin_ns[used]
    if layout.bytes_per_sample == 0:  # actfast adds the sector's row, then fails on it
        if not lenient:
            raise DeviceFileError(_where(int(used[0]), "no bytes per sample"))
        warnings += [_where(int(i), "no bytes per sample") for i in used]
        t, v = np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    else:
        t, v = _samples(sectors, head, used, lf_t, layout, threads)
    out["timeseries"] = _tables(t, v, lf_t, head, used, layout.gyroscope)
    return out


class _Layout:
    """What the first sector that passes its checks says of every sector: samples' layout,
    the acceleration's scale (g a count), the sample period and the fraction's format."""

    def __init__(self, axes: int, packed: bool, scale: np.float32, period_ns: int,
                 fractional: bool) -> None:
        self.axes, self.packed, self.scale = axes, packed, scale
        self.period_ns, self.fractional = period_ns, fractional
        self.bytes_per_sample = 4 if packed else 2 * axes
        self.gyroscope = not packed and axes >= 6

    @classmethod
    def of(cls, first: np.void) -> _Layout:
        axes_bps = int(first["axes_bps"])
        axes, packed = axes_bps >> 4, axes_bps & 0x0F == 0
        if not packed and axes_bps & 0x0F != 2:
            raise DeviceFileError(f"numAxesBPS 0x{axes_bps:02x}: neither packed 10-bit (low "
                                  "nibble 0) nor 16-bit (2)")
        if not packed and 0 < axes < 3:
            raise DeviceFileError(f"16-bit samples of {axes} axes: not three")
        scale = np.float32(1.0) / np.float32(1 << (8 + ((int(first["light"]) >> 13) & 7)))
        return cls(axes, packed, scale, 312_500 << (15 - (int(first["rate"]) & 0x0F)),
                   bool(int(first["fraction"]) & 0x8000))


def _header(h: bytes) -> dict[str, dict[str, str]]:
    """The header packet's fields as actfast names them (strings)."""
    u16, u32 = (lambda at: int.from_bytes(h[at:at + 2], "little")), (
        lambda at: int.from_bytes(h[at:at + 4], "little"))
    upper = u16(11)
    device_id = (0 if upper == 0xFFFF else upper) << 16 | u16(5)
    rate_bits, range_bits = h[36] & 0x0F, (h[36] >> 6) & 0x03
    device = {"hardware_type": _HARDWARE.get(h[4], "Unknown"), "device_id": str(device_id),
              "session_id": str(u32(7)), "firmware_revision": str(h[41]),
              "time_zone": str(int.from_bytes(h[42:44], "little", signed=True))}
    conf = {"sample_rate_hz": str(3200 >> (15 - rate_bits)),
            "accelerometer_range_g": str(16 >> range_bits)}
    for key, at in (("logging_start", 13), ("logging_end", 17)):
        when = _date(u32(at))
        if when is not None:
            conf[key] = when.isoformat()
    if u32(21):
        conf["logging_capacity"] = str(u32(21))
    meta: dict[str, dict[str, str]] = {"device": device, "configuration": conf}
    note = h[64:512]
    end = next((i for i, b in enumerate(note) if b in (0, 0xFF)), len(note))
    try:
        text = note[:end].decode("utf-8").strip()
    except UnicodeDecodeError:
        text = ""
    if text:
        meta["session"] = {"annotation": text}
    return meta


def _date(packed: int) -> dt.datetime | None:
    """A packed cwa time (6 bits year - 2000, 4 month, 5 day, 5 hour, 6 minute, 6 second)."""
    try:
        return dt.datetime(2000 + (packed >> 26 & 0x3F), packed >> 22 & 0x0F, packed >> 17 & 0x1F,
                           packed >> 12 & 0x1F, packed >> 6 & 0x3F, packed & 0x3F,
                           tzinfo=dt.UTC)
    except ValueError:
        return None


def _where(i: int, what: str) -> str:
    return f"sector {i} (byte offset {HEADER_BYTES + i * SECTOR_BYTES}): {what}"


def _checked(sectors: np.ndarray, head: np.ndarray, lenient: bool
             ) -> tuple[np.ndarray, list[str]]:
    """Which sectors are data ("AX") whose 16-bit words sum to 0 (not checked where the rate
    byte is 0, as actfast), with a warning for each other one (an error unless lenient)."""
    magic = head["magic"] == 0x5841  # "AX"
    words = sectors.view("<u2")
    summed = np.zeros(len(head), np.uint16)
    for lo in range(0, len(head), 1 << 16):  # wraps modulo 2^16, as the checksum does
        summed[lo:lo + (1 << 16)] = words[lo:lo + (1 << 16)].sum(axis=1, dtype=np.uint16)
    fine = magic & ((summed == 0) | (head["rate"] == 0))
    warnings = [_where(int(i), "not a data sector ('AX')" if not magic[i] else "failed checksum")
                for i in np.flatnonzero(~fine)]
    if warnings and not lenient:
        raise DeviceFileError(warnings[0])
    return fine, warnings


_EPOCH_MONTH = np.datetime64("1970-01", "M")


def _origins(head: np.ndarray, layout: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """Each sector's first sample's time (ns, the device's clock as UTC) and whether its
    stamp is a date: the stamp plus its fraction, less the index it belongs to (offset, and
    the fraction in samples) times the period."""
    p = head["stamp"].astype(np.int64)
    year, month, day = 2000 + (p >> 26 & 0x3F), p >> 22 & 0x0F, p >> 17 & 0x1F
    hour, minute, second = p >> 12 & 0x1F, p >> 6 & 0x3F, p & 0x3F
    months = (year - 1970) * 12 + np.clip(month, 1, 12) - 1
    first_day = (_EPOCH_MONTH + months).astype("datetime64[D]").astype(np.int64)
    days_in = ((_EPOCH_MONTH + months + 1).astype("datetime64[D]").astype(np.int64)
               - first_day)
    dated = ((month >= 1) & (month <= 12) & (day >= 1) & (day <= days_in) & (hour < 24)
             & (minute < 60) & (second < 60))
    t_ns = ((first_day + day - 1) * 86_400 + hour * 3_600 + minute * 60 + second) * 10**9
    shift = head["offset"].astype(np.int64)
    if layout.fractional:
        fraction = (head["fraction"].astype(np.int64) & 0x7FFF) << 1  # 1/65536 s
        shift += (fraction * (10**9 // layout.period_ns)) >> 16  # the rate in whole Hz
        t_ns += (fraction * 10**9) >> 16
    return t_ns - shift * layout.period_ns, dated


def _samples(sectors: np.ndarray, head: np.ndarray, used: np.ndarray, origin_ns: np.ndarray,
             layout: _Layout, threads: int) -> tuple[np.ndarray, np.ndarray]:
    """The used sectors' samples (ns stamps, (N, 3) float32 g), pieces of sectors on threads."""
    per = _DATA_BYTES // layout.bytes_per_sample
    count = np.minimum(head["count"][used].astype(np.int64), per)
    at = np.concatenate(([0], np.cumsum(count)))
    t = np.empty(int(at[-1]), np.int64)
    v = np.empty((int(at[-1]), 3), np.float32)
    step_ns = np.arange(per, dtype=np.int64) * layout.period_ns

    def piece(lo: int) -> None:
        hi = min(len(used), lo + _PIECE)
        rows = used[lo:hi]
        block = (sectors[rows[0]:rows[-1] + 1] if rows[-1] - rows[0] == hi - lo - 1
                 else sectors[rows])  # a run of sectors: a view, no copy
        a, b = int(at[lo]), int(at[hi])
        whole = bool(np.all(count[lo:hi] == per))
        g = (v[a:b].reshape(hi - lo, per, 3) if whole
             else np.empty((hi - lo, per, 3), np.float32))
        _accel_g(block[:, _DATA_AT:_DATA_AT + per * layout.bytes_per_sample], layout, g)
        stamps = (t[a:b].reshape(hi - lo, per) if whole
                  else np.empty((hi - lo, per), np.int64))
        np.add(origin_ns[lo:hi, None], step_ns, out=stamps)
        if not whole:  # short sectors: their first count samples
            keep = np.arange(per) < count[lo:hi, None]
            v[a:b], t[a:b] = g[keep], stamps[keep]

    _run(piece, range(0, len(used), _PIECE), threads)
    return t, v


def _accel_g(data: np.ndarray, layout: _Layout, out: np.ndarray) -> None:
    """The acceleration in g (sectors, per, 3) from the sectors' sample bytes, into out: the
    counts times the scale (a power of two, so exact in float32)."""
    n = len(data)
    if not layout.packed:
        s = np.ascontiguousarray(data).view("<i2").reshape(n, -1, layout.axes)
        np.multiply(s[..., 3:6] if layout.gyroscope else s[..., :3], layout.scale, out=out)
        return
    # 3 x 10-bit two's complement, shifted left by a 2-bit exponent: each field moved to the
    # word's top and shifted back as a signed word (its sign extended), then by the exponent
    w = np.ascontiguousarray(data).view("<u4").reshape(n, -1)
    e = (w >> 30).view(np.int32)
    for k in range(3):
        c = np.left_shift(w, 22 - 10 * k).view(np.int32)
        c >>= 22
        c <<= e
        np.multiply(c, layout.scale, out=out[..., k])


def _run(work: Callable[[int], None], starts: range, threads: int) -> None:
    if threads <= 1 or len(starts) <= 1:
        for lo in starts:
            work(lo)
        return
    with ThreadPoolExecutor(min(threads, len(starts)), thread_name_prefix="recal-cwa") as pool:
        for f in [pool.submit(work, lo) for lo in starts]:
            f.result()


def _tables(t: np.ndarray, v: np.ndarray, lf_t: np.ndarray, head: np.ndarray, used: np.ndarray,
            gyroscope: bool) -> dict[str, dict[str, Any]]:
    """actfast's two tables: per sample, per used sector (light, temperature in °C and battery
    as actfast 1.3 scales them, in float32 operations in its order). Each field is taken
    before the sectors are picked: a pick of whole rows would copy 512 bytes a sector."""
    temp = (head["temperature"][used] & 0x3FF).astype(np.float32)
    battery = head["battery"][used].astype(np.float32)
    hf: dict[str, Any] = {"datetime": t, "acceleration": v if len(v) else v.reshape(0)}
    if gyroscope:
        hf["gyroscope"] = None
    return {"low_frequency": {
        "datetime": lf_t, "light": (head["light"][used] & 0x3FF).astype(np.uint16),
        "temperature": temp * np.float32(75.0) / np.float32(256.0) - np.float32(50.0),
        "battery_voltage": np.float32(3.0) * (battery / np.float32(256.0) + np.float32(1.0))},
        "high_frequency": hf}

