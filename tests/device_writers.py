"""Device files written as the devices write them, from the simulator: test code, not shipped.

`device_signal` runs the simulated wearer through a sensor at the device's *real* sample rate
(a clock off the nominal one), adds what a worn logger lives through (a stretch lying on a
table, a gap with the device off) and returns the counts with the truth behind them. The
writers turn that into the bytes a device leaves on its storage:

- `write_cwa`: an Axivity AX3 ``.cwa`` from the published layout (openmovement
  ``Docs/ax3/cwa.h`` and ``ax3-technical.md``): a 1024-byte header block ("MD": device id,
  session, rate code, time zone, url-encoded metadata) and 512-byte "AX" sectors of 120 packed
  (10-bit + exponent) or 80 unpacked (int16) samples in 1/256 g, each with its RTC stamp, the
  15-bit fraction and the sample index the stamp is for (the firmware's sector rule: the stamp
  is taken when the accelerometer's 25-sample FIFO fills), temperature and battery in their
  raw units, a sequence counter and a word-sum checksum of zero.
- `write_geneactiv_bin`: a GENEActiv ``.bin`` (the text layout GGIRread and actfast read: a
  59-line header with the factory calibration, then "Recorded Data" pages of 300 samples as
  12 hex digits each: 12-bit x, y, z, 10-bit light, button, a spare bit; page time to the
  millisecond, temperature to 0.1 °C, battery, measurement frequency).

Everything over samples is numpy; loops run over sectors' runs and pages' text lines only.
"""

from __future__ import annotations

import itertools
import math
import struct
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from recal.sim.sensor import SensorSpec, forward_model
from recal.sim.wearer import SimResult, WearerSpec, simulate

__all__ = ["DeviceRun", "Signal", "Written", "cwa_time", "device_signal", "idle_sleep_seconds",
           "write_cwa", "write_geneactiv_bin", "write_gt3x"]

_US = 1_000_000
_START = np.datetime64("2024-03-04T09:00:00", "us")


@dataclass(frozen=True)
class DeviceRun:
    """What the device and its wearer did.

    Attributes:
        hours: length of the simulated wear (before the gap is cut out).
        nominal_hz: the rate the device was set to (what its file says).
        real_hz: the rate its accelerometer's own oscillator really ran at, against the RTC.
        seed: the simulator's seed.
        sensor: the sensor's errors (counts_per_g is the format's: 256 for both).
        wearer: the simulated wearer (always_aux is forced on: both devices log temperature
            and battery).
        start: the device clock at the first sample (the RTC's local time).
        table_s: (start, length) in seconds: the device lies flat on a table, perfectly still.
        gap_s: (start, length) in seconds: the device is off; no samples are written.
    """

    hours: float = 2.0
    nominal_hz: int = 50
    real_hz: float = 50.15
    seed: int = 1
    sensor: SensorSpec = field(default_factory=lambda: SensorSpec(
        counts_per_g=256.0, full_scale_g=8.0))
    wearer: WearerSpec = field(default_factory=WearerSpec)
    start: np.datetime64 = _START
    table_s: tuple[float, float] | None = None
    gap_s: tuple[float, float] | None = None


@dataclass(frozen=True, eq=False)
class Signal:
    """The samples the device took, with the truth (arrays of the kept samples, in order).

    Attributes:
        t_us: (N,) true time of each sample on the device clock, µs since 1970 (naive: the
            RTC's local time read as if it were UTC, as the files store it).
        counts: (N,3) int64 sensor counts before the format's packing.
        a_true_g: (N,3) what a perfect calibration outputs.
        still: (N,) the simulator's still samples (and the table stretch).
        temp_c: (N,) the board temperature (what the offset follows).
        vdd_v: (N,) the battery.
        sim_index: (N,) index of each sample in the uncut simulation.
        runs: list of (first, stop) index ranges of samples logged without a break.
        sim: the uncut simulation.
        run: what the device and wearer did.
    """

    t_us: np.ndarray
    counts: np.ndarray
    a_true_g: np.ndarray
    still: np.ndarray
    temp_c: np.ndarray
    vdd_v: np.ndarray
    sim_index: np.ndarray
    runs: list[tuple[int, int]]
    sim: SimResult
    run: DeviceRun

    def __len__(self) -> int:
        return len(self.t_us)


@dataclass(frozen=True, eq=False)
class Written:
    """A file written, and what is in it.

    Attributes:
        path: the file.
        signal: the samples and truth behind it (only those written).
        counts: (N,3) int64 counts as a reader decodes them (packing loses bits, clipping).
        blocks: per sector (cwa) or page (bin) arrays: "first" (index of its first sample),
            "count", "stamp_us" (the time the block's stamp means, as written, µs since
            1970), "stamp_index" (the sample index within the block the stamp is for),
            "temp_c" (temperature as stored, in °C), and format fields.
        meta: what the header says.
    """

    path: Path
    signal: Signal
    counts: np.ndarray
    blocks: dict[str, np.ndarray]
    meta: dict[str, Any]


# --- the signal ------------------------------------------------------------------------------

def device_signal(run: DeviceRun) -> Signal:
    """The samples a device running at `run.real_hz` took (see `DeviceRun`)."""
    wearer = replace(run.wearer, always_aux=True)
    sim = simulate(run.hours, run.real_hz, run.seed, run.sensor, wearer)
    a = sim.truth.a_true_g.copy()
    still = sim.truth.still.copy()
    n = len(a)
    t_s = np.arange(n) / run.real_hz
    if run.table_s is not None:
        i0, i1 = (int(x * run.real_hz) for x in (run.table_s[0], sum(run.table_s)))
        flat = np.array([0.012, -0.02, 1.0])  # a table is never quite level
        a[i0:i1] = flat / np.linalg.norm(flat)
        still[i0:i1] = True
    temp = sim.raw.channel(run.sensor.temp_channel)
    vdd = sim.raw.channel(run.sensor.supply_channel)
    counts = forward_model(a, run.sensor, temp_c=temp, vdd_v=vdd, t_h=t_s / 3600.0,
                           rng=np.random.default_rng(run.seed + 7919)).astype(np.int64)
    keep = np.ones(n, bool)
    if run.gap_s is not None:
        keep[(t_s >= run.gap_s[0]) & (t_s < sum(run.gap_s))] = False
    idx = np.flatnonzero(keep)
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    edges = [0, *breaks.tolist(), len(idx)]
    t0_us = int(run.start.astype("datetime64[us]").astype(np.int64))
    return Signal(t0_us + sim.raw.t_us[idx], counts[idx], a[idx], still[idx], temp[idx],
                  vdd[idx], idx, list(itertools.pairwise(edges)), sim, run)


def _true_time_us(sig: Signal, run_first: int, k: np.ndarray) -> np.ndarray:
    """Device-clock time of sample k of the run starting at index run_first (k may run past
    the run's end: the oscillator keeps its rate), µs."""
    i = sig.sim_index[run_first] + k
    return (int(sig.t_us[run_first] - sig.sim.raw.t_us[sig.sim_index[run_first]])
            + np.round(i * _US / sig.run.real_hz).astype(np.int64))


# --- Axivity .cwa ----------------------------------------------------------------------------

_SECTOR = np.dtype([
    ("magic", "<u2"), ("length", "<u2"), ("fractional", "<u2"), ("session", "<u4"),
    ("sequence", "<u4"), ("stamp", "<u4"), ("light_scale", "<u2"), ("temperature", "<u2"),
    ("events", "u1"), ("battery", "u1"), ("rate_code", "u1"), ("axes_bps", "u1"),
    ("offset", "<i2"), ("count", "<u2"), ("data", "u1", (480,)), ("checksum", "<u2")])
assert _SECTOR.itemsize == 512
_FIFO = 25  # the AX3's accelerometer FIFO watermark: the RTC is read when it fills


def cwa_time(t_us: np.ndarray) -> np.ndarray:
    """Whole seconds of device-clock times (µs since 1970) packed as cwa.h says:
    YYYYYYMM MMDDDDDh hhhhmmmm mmssssss, year from 2000."""
    s = (np.asarray(t_us, np.int64) // _US).astype("datetime64[s]")
    year = s.astype("datetime64[Y]").astype(np.int64) + 1970 - 2000
    month = s.astype("datetime64[M]").astype(np.int64) % 12 + 1
    day = (s.astype("datetime64[D]") - s.astype("datetime64[M]")).astype(np.int64) + 1
    sec = (s - s.astype("datetime64[D]")).astype(np.int64)
    packed = ((year << 26) | (month << 22) | (day << 17) | ((sec // 3600) << 12)
              | ((sec // 60 % 60) << 6) | (sec % 60))
    return packed.astype(np.uint32)


def _rate_code(rate_hz: int, range_g: int) -> int:
    """cwa.h: frequency 3200 / (1 << (15 - (code & 15))), range 16 >> (code >> 6)."""
    n = 15 - round(math.log2(3200 / rate_hz))
    if 3200 / (1 << (15 - n)) != rate_hz:
        raise ValueError(f"no AX3 rate code for {rate_hz} Hz")
    return (round(math.log2(16 / range_g)) << 6) | n


def _pack_ax3(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Packed words (10-bit x, y, z and a 2-bit exponent: the fewest low bits dropped so each
    axis fits) and the values a reader gets back from them (arithmetic shift: floor)."""
    v = np.clip(v, -4096, 4095)
    worst = np.maximum(v, -v - 1).max(axis=1)
    e = np.select([worst <= 511, worst <= 1023, worst <= 2047], [0, 1, 2], 3).astype(np.int64)
    short = v >> e[:, None]
    word = ((e << 30) | ((short[:, 2] & 0x3FF) << 20) | ((short[:, 1] & 0x3FF) << 10)
            | (short[:, 0] & 0x3FF))
    return word.astype("<u4"), short << e[:, None]


def _cwa_header(hardware_type: int, device_id: int, session_id: int, rate_code: int,
                time_zone_min: int, metadata: str, first_us: int) -> bytes:
    """The 1024-byte "MD" block (cwa.h cwa_header_t, tightly packed)."""
    now = int(cwa_time(np.array([first_us]))[0])
    head = struct.pack("<2sHBHIHIIIB B8sBBIBh20s", b"MD", 1020, hardware_type,
                       device_id & 0xFFFF,
                       session_id, device_id >> 16, 0, 0xFFFFFFFF, 0, 0xFF, 1, b"\xff" * 8,
                       0, rate_code, now, 45, time_zone_min, b"\xff" * 20)
    assert len(head) == 64
    note = metadata.encode()[:448].ljust(448, b" ")
    return head + note + b"\xff" * 512


def write_cwa(path: str | Path, sig: Signal, *, packed: bool = True, device_id: int = 43_210,
              session_id: int = 77, time_zone_min: int = 60,
              metadata: str = "_c=synthetic&_s=wearer01", hardware_type: int = 0x17
              ) -> Written:
    """An AX3 ``.cwa`` of `sig` (see the module docstring); the device clock runs at the
    RTC's rate and the samples at ``sig.run.real_hz``. hardware_type: cwa.h lists 0x00,
    0xFF and 0x17 for an AX3."""
    run = sig.run
    per = 120 if packed else 80
    code = _rate_code(run.nominal_hz, 8)
    if packed:
        words, decoded = _pack_ax3(sig.counts)
        raw = words.view(np.uint8).reshape(-1, 4)
    else:
        decoded = np.clip(sig.counts, -32768, 32767)
        raw = decoded.astype("<i2").view(np.uint8).reshape(-1, 6)
    sectors, firsts, counts, stamp_idx, stamp_us = [], [], [], [], []
    for a, b in sig.runs:  # the FIFO restarts when logging resumes
        n_sec = -(-(b - a) // per)
        first = a + per * np.arange(n_sec)
        count = np.minimum(per, b - first)
        # the stamp: the RTC read when the FIFO last filled, for the sample index reached
        m = _FIFO * -(-(first - a + count) // _FIFO)
        data = np.zeros((n_sec * per, raw.shape[1]), np.uint8)
        data[:b - a] = raw[a:b]
        block = np.zeros(n_sec, _SECTOR)
        block["data"][:, :per * raw.shape[1]] = data.reshape(n_sec, -1)
        block["events"][0] = 1 if a > 0 else 0  # b0: logging resumed
        sectors.append(block)
        firsts.append(first)
        counts.append(count)
        stamp_idx.append(m - (first - a))
        stamp_us.append(_true_time_us(sig, a, m))
    blocks = np.concatenate(sectors)
    first, count = np.concatenate(firsts), np.concatenate(counts)
    k, t_stamp = np.concatenate(stamp_idx), np.concatenate(stamp_us)
    frac16 = (t_stamp % _US) * 65536 // _US  # the RTC's fraction, 1/65536 s
    last = first + count - 1
    temp_raw = np.clip(np.round((sig.temp_c[last] + 50.0) * 256.0 / 75.0), 0, 1023)
    battery = np.clip(np.round(sig.vdd_v[last] * 1024.0 / 6.0 - 512.0), 0, 255)
    blocks["magic"] = 0x5841
    blocks["length"] = 508
    blocks["fractional"] = 0x8000 | (frac16 >> 1)
    blocks["session"] = session_id
    blocks["sequence"] = np.arange(len(blocks))
    blocks["stamp"] = cwa_time(t_stamp)
    blocks["light_scale"] = 300  # accel scale code 0: 1/256 g
    blocks["temperature"] = temp_raw
    blocks["battery"] = battery
    blocks["rate_code"] = code
    blocks["axes_bps"] = 0x30 if packed else 0x32
    # the firmware's backward-compatible index: where the whole second would fall at the
    # nominal rate; a reader adds (fraction * rate) >> 16 back
    blocks["offset"] = k - ((frac16 * run.nominal_hz) >> 16)
    blocks["count"] = count
    words16 = blocks.view(np.uint8).reshape(-1, 256, 2).view("<u2").reshape(-1, 256)
    blocks["checksum"] = (-words16[:, :255].sum(axis=1, dtype=np.uint64)) & 0xFFFF
    path = Path(path)
    with open(path, "wb") as fh:
        fh.write(_cwa_header(hardware_type, device_id, session_id, code, time_zone_min, metadata,
                             int(sig.t_us[0])))
        fh.write(blocks.tobytes())
    # what the stored stamp means once read: whole seconds + the 15-bit fraction
    stored_ns = (t_stamp // _US) * 10**9 + ((frac16 >> 1) * 2 * 10**9) // 65536
    return Written(path, sig, decoded, {
        "first": first, "count": count, "stamp_index": k, "stamp_us": t_stamp,
        "stored_stamp_ns": stored_ns, "temp_raw": temp_raw.astype(np.int64),
        "temp_c": temp_raw * 75.0 / 256.0 - 50.0, "battery": battery.astype(np.int64),
        "events": blocks["events"].astype(np.int64)},
        {"device_id": device_id, "session_id": session_id, "time_zone_min": time_zone_min,
         "rate_hz": run.nominal_hz, "range_g": 8, "packed": packed, "metadata": metadata})


# --- GENEActiv .bin --------------------------------------------------------------------------

_PAGE = 300  # samples per "Recorded Data" page
_GENEACTIV_COUNTS_PER_G = 256.0


def _bin_time(t_us: int) -> str:
    """"YYYY-MM-DD hh:mm:ss:mmm", milliseconds truncated as the device counts them."""
    ms = np.datetime64(t_us // 1000, "ms").astype(str)  # 2024-03-04T09:00:00.123
    return ms.replace("T", " ")[:19] + ":" + ms[20:23]


def _factory_calibration(sensor: SensorSpec, factory_temp_c: float) -> dict[str, int]:
    """The header's gains and offsets (x_g = (x·100 − offset) / gain): the sensor's own
    offset and gain at the factory's temperature, as a factory calibration would find them
    (it sees neither the cross-axis terms nor how they move with temperature)."""
    dt = factory_temp_c - sensor.t_ref_c
    cal = {}
    for j, axis in enumerate("xyz"):
        gain = 1.0 + sensor.gain[j] + sensor.gain_tc_per_c[j] * dt
        offset = sensor.offset_g[j] + sensor.offset_tc_g_per_c[j] * dt
        cal[f"{axis} gain"] = round(100 * _GENEACTIV_COUNTS_PER_G * gain)
        cal[f"{axis} offset"] = round(100 * _GENEACTIV_COUNTS_PER_G * offset)
    return cal


def _bin_header(serial: str, nominal_hz: int, start: str, pages: int,
                cal: dict[str, int], time_zone: str) -> list[str]:
    lines = [
        "Device Identity", f"Device Unique Serial Code:{serial}", "Device Type:GENEActiv",
        "Device Model:1.2", "Device Firmware Version:Ver06.17 15June23",
        "Calibration Date:2023-09-08 14:14:04:000", "",
        "Device Capabilities", "Accelerometer Range:-8 to 8", "Accelerometer Resolution:0.0039",
        "Accelerometer Units:g", "Light Meter Range:0 to 20000", "Light Meter Resolution:3 to 48",
        "Light Meter Units:lux", "Temperature Sensor Range:0 to 70",
        "Temperature Sensor Resolution:0.1", "Temperature Sensor Units:deg. C", "",
        "Configuration Info", f"Measurement Frequency:{nominal_hz} Hz",
        "Measurement Period:168 Hours", f"Start Time:{start}", f"Time Zone:{time_zone}", "",
        "Trial Info", "Study Centre:synthetic", "Study Code:", "Investigator ID:",
        "Exercise Type:", "Config Operator ID:", f"Config Time:{start}", "Config Notes:",
        "Extract Operator ID:", f"Extract Time:{start}", "Extract Notes:", "",
        "Subject Info", "Device Location Code:left wrist", "Subject Code:wearer01",
        "Date of Birth:1900-01-01", "Sex:", "Height:", "Weight:", "Handedness Code:",
        "Subject Notes:", "",
        "Calibration Data", *(f"{k}:{v}" for k, v in cal.items()), "Volts:300", "Lux:800", "",
        "Memory Status", f"Number of Pages:{pages}", ""]
    assert len(lines) == 59, len(lines)  # the readers count lines: 59, then the pages
    return lines


def write_geneactiv_bin(path: str | Path, sig: Signal, *, serial: str = "054321",
                        factory_temp_c: float = 22.0, time_zone: str = "GMT +01:00",
                        newline: str = "\r\n") -> Written:
    """A GENEActiv ``.bin`` of `sig` (module docstring). Pages hold 300 samples; a run's
    last partial page is not written (the device writes whole pages)."""
    run = sig.run
    v = np.clip(sig.counts, -2048, 2047)  # 12-bit two's complement
    firsts = np.concatenate([np.arange(a, b - _PAGE + 1, _PAGE) for a, b in sig.runs])
    take = (firsts[:, None] + np.arange(_PAGE)).reshape(-1)
    light = np.full(len(take), 37, np.int64)
    word = (((v[take, 0] & 0xFFF) << 36) | ((v[take, 1] & 0xFFF) << 24)
            | ((v[take, 2] & 0xFFF) << 12) | (light << 2))  # button 0, spare bit 0
    hexes = word.astype(">u8").view(np.uint8).reshape(-1, 8)[:, 2:].tobytes().hex().upper()
    width = 12 * _PAGE
    stamp_us = sig.t_us[firsts]
    temp = np.round(sig.temp_c[firsts], 1)
    battery = np.round(sig.vdd_v[firsts], 2)
    cal = _factory_calibration(run.sensor, factory_temp_c)
    lines = _bin_header(serial, run.nominal_hz, _bin_time(int(stamp_us[0])), len(firsts), cal,
                        time_zone)
    for p in range(len(firsts)):
        lines += ["Recorded Data", f"Device Unique Serial Code:{serial}", f"Sequence Number:{p}",
                  f"Page Time:{_bin_time(int(stamp_us[p]))}", "Unassigned:",
                  f"Temperature:{temp[p]:.1f}", f"Battery voltage:{battery[p]:.4f}",
                  "Device Status:Recording", f"Measurement Frequency:{run.nominal_hz:.1f}",
                  hexes[p * width:(p + 1) * width]]
    path = Path(path)
    path.write_bytes((newline.join(lines) + newline).encode("ascii"))
    sub = _subset(sig, take)
    return Written(path, sub, v[take], {
        "first": np.arange(len(firsts)) * _PAGE, "count": np.full(len(firsts), _PAGE),
        "stamp_index": np.zeros(len(firsts), np.int64), "stamp_us": stamp_us,
        "stored_stamp_ns": stamp_us // 1000 * 10**6, "temp_c": temp, "battery_v": battery},
        {"serial": serial, "calibration": cal, "rate_hz": run.nominal_hz,
         "time_zone": time_zone, "light": 37})


def _subset(sig: Signal, take: np.ndarray) -> Signal:
    """The samples `take` of `sig` (the pages' samples), runs renumbered."""
    brk = np.flatnonzero(np.diff(sig.sim_index[take]) != 1) + 1
    edges = [0, *brk.tolist(), len(take)]
    return Signal(sig.t_us[take], sig.counts[take], sig.a_true_g[take], sig.still[take],
                  sig.temp_c[take], sig.vdd_v[take], sig.sim_index[take],
                  list(itertools.pairwise(edges)), sig.sim, sig.run)


# --- ActiGraph .gt3x -------------------------------------------------------------------------

_GT3X_SCALE = 256.0  # LSB per g of a wGT3X-BT ("MOS"), ±8 g
_TICKS_AT_1970 = 621_355_968_000_000_000  # .NET ticks (100 ns since 0001-01-01) at 1970
_IDLE_AFTER_S = 10  # idle sleep: the accelerometer sleeps after this long without movement


def _ssp(value: float) -> int:
    """A positive float in the PARAMETERS record's encoding (Parameters.md): a 24-bit two's
    complement fraction, 2^23 times the mantissa in [0.5, 1), and an 8-bit exponent."""
    mantissa, exponent = math.frexp(value)
    return ((exponent & 0xFF) << 24) | (round(mantissa * 2**23) & 0xFFFFFF)


def _records(kind: np.ndarray, stamp_s: np.ndarray, payload: np.ndarray) -> np.ndarray:
    """Log records of one payload size, (R, 9 + size) bytes: separator 0x1E, type, Unix
    time, size, payload, and the 1's complement of the XOR of all of them."""
    r, size = payload.shape
    out = np.zeros((r, 9 + size), np.uint8)
    out[:, 0] = 0x1E
    out[:, 1] = kind
    out[:, 2:6] = stamp_s.astype("<u4").view(np.uint8).reshape(r, 4)
    out[:, 6:8] = np.frombuffer(struct.pack("<H", size), np.uint8)
    out[:, 8:-1] = payload
    out[:, -1] = ~np.bitwise_xor.reduce(out[:, :-1], axis=1)
    return out


def _activity_payloads(v: np.ndarray, rate: int) -> np.ndarray:
    """(S, rate, 3) counts -> (S, bytes) ACTIVITY payloads: y, x, z as 12-bit two's
    complement, most significant bits first, a spare nibble after an odd count (Activity.md)."""
    y, x, z = (v[..., j].astype(np.int64) & 0xFFF for j in (1, 0, 2))
    word = (y << 24) | (x << 12) | z  # 36 bits a sample
    nib = (word[..., None] >> np.arange(32, -1, -4)) & 0xF  # (S, rate, 9)
    nib = nib.reshape(len(v), rate * 9)
    if nib.shape[1] % 2:
        nib = np.concatenate([nib, np.zeros((len(v), 1), np.int64)], axis=1)
    return ((nib[:, 0::2] << 4) | nib[:, 1::2]).astype(np.uint8)


def idle_sleep_seconds(still: np.ndarray, rate: int, after_s: int = _IDLE_AFTER_S) -> np.ndarray:
    """(S,) bool per whole second: asleep, i.e. every sample of it at least after_s into a
    still stretch (the device wakes at the first movement; a second it wakes in is logged)."""
    n = len(still) // rate * rate
    s = still[:n]
    # samples since the last moving sample (vectorized running count of a bool run)
    idx = np.arange(n)
    last_move = np.maximum.accumulate(np.where(~s, idx, -1))
    asleep = (idx - last_move) > after_s * rate
    return asleep.reshape(-1, rate).all(axis=1)


def write_gt3x(path: str | Path, sig: Signal, *, serial: str = "MOS2E22180349",
               idle_sleep: bool = True, time_zone: str = "01:00:00") -> Written:
    """A wGT3X-BT ``.gt3x`` (GT3X-File-Format): a zip of info.txt and log.bin, whose
    records are PARAMETERS (sample rate, acceleration scale, idle sleep on or off), an ACTIVITY
    record a second of `rate` samples, BATTERY once a minute, and EVENT 0x08 / 0x09 where the
    device enters and leaves idle sleep (no ACTIVITY records in between). An ActiGraph samples
    on its RTC: ``sig.run.real_hz`` must be the nominal rate, starting on a whole second."""
    import zipfile

    run = sig.run
    rate = run.nominal_hz
    if run.real_hz != rate or sig.t_us[0] % _US:
        raise ValueError("an ActiGraph's samples are whole seconds of exactly the nominal rate")
    v = np.clip(sig.counts, -2048, 2047)
    # whole seconds of each run (the device off between runs)
    firsts = np.concatenate([np.arange(a, b - rate + 1, rate) for a, b in sig.runs])
    asleep = np.zeros(len(firsts), bool)
    if idle_sleep:
        for a, b in sig.runs:
            sel = (firsts >= a) & (firsts < b)
            asleep[sel] = idle_sleep_seconds(sig.still[a:b], rate)[:sel.sum()]
    sec = sig.t_us[firsts] // _US
    awake = firsts[~asleep]
    take = (awake[:, None] + np.arange(rate)).reshape(-1)
    activity = _records(np.zeros(len(awake)), sec[~asleep],
                        _activity_payloads(v[take].reshape(-1, rate, 3), rate))
    # entering / leaving idle sleep: EVENT 0x08 at the first asleep second, 0x09 at waking
    edge = np.diff(np.concatenate([[False], asleep, [False]]).astype(np.int8))
    enter, leave = np.flatnonzero(edge == 1), np.flatnonzero(edge == -1)
    ev_t = np.concatenate([sec[enter], sec[np.minimum(leave, len(sec) - 1)]])
    ev_p = np.concatenate([np.full(len(enter), 8), np.full(len(leave), 9)])[:, None]
    events = _records(np.full(len(ev_t), 3), ev_t, ev_p.astype(np.uint8))
    minute = firsts[sec % 60 == 0]
    mv = np.round(sig.vdd_v[minute] * 1000).astype("<u2").view(np.uint8).reshape(-1, 2)
    battery = _records(np.full(len(minute), 2), sig.t_us[minute] // _US, mv)
    # ACCEL_SCALE (space 0, id 55), SAMPLE_RATE (1, 10), FEATURE_ENABLE (1, 2; bit 2 sleep)
    params = struct.pack("<IIIIII", (55 << 16) | 0, _ssp(_GT3X_SCALE), (10 << 16) | 1, rate,
                         (2 << 16) | 1, 4 if idle_sleep else 0)
    head = _records(np.array([0x15]), sec[:1], np.frombuffer(params, np.uint8)[None, :])
    # every record in time order (at one second: EVENT, then ACTIVITY, then BATTERY)
    rows = [head[0].tobytes()]
    keyed = ([(t, 0, r.tobytes()) for t, r in zip(ev_t, events, strict=True)]
             + [(t, 1, r.tobytes()) for t, r in zip(sec[~asleep], activity, strict=True)]
             + [(t, 2, r.tobytes()) for t, r in zip(sig.t_us[minute] // _US, battery,
                                                    strict=True)])
    keyed.sort(key=lambda k: (k[0], k[1]))
    rows += [r for _, _, r in keyed]
    ticks = lambda t_s: int(t_s) * 10_000_000 + _TICKS_AT_1970  # noqa: E731
    info = "\r\n".join([
        f"Serial Number: {serial}", "Device Type: wGT3XBT", "Firmware: 1.9.2",
        f"Battery Voltage: {sig.vdd_v[-1]:.2f}", f"Sample Rate: {rate}",
        f"Start Date: {ticks(sec[0])}", "Stop Date: 0", f"Last Sample Time: {ticks(sec[-1] + 1)}",
        f"TimeZone: {time_zone}", f"Download Date: {ticks(sec[-1] + 600)}", "Board Revision: 4",
        "Unexpected Resets: 0", f"Acceleration Scale: {_GT3X_SCALE:.1f}",
        "Acceleration Min: -8.0", "Acceleration Max: 8.0", "Subject Name: wearer01",
        "Serial Prefix: MOS"]) + "\r\n"
    path = Path(path)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("info.txt", info)
        z.writestr("log.bin", b"".join(rows))
    sub = _subset(sig, take)
    return Written(path, sub, v[take], {
        "first": np.arange(len(awake)) * rate, "count": np.full(len(awake), rate),
        "stamp_index": np.zeros(len(awake), np.int64), "stamp_us": sec[~asleep] * _US,
        "stored_stamp_ns": sec[~asleep] * 10**9, "asleep_s": sec[asleep],
        "events": np.column_stack([ev_t, ev_p[:, 0]])},
        {"serial": serial, "rate_hz": rate, "time_zone": time_zone,
         "seconds_asleep": int(asleep.sum()), "seconds": len(sec)})
