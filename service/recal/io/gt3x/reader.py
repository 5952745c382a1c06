"""ActiGraph ``.gt3x`` of both layouts as arrays: ``log.bin`` records (ACTIVITY, ACTIVITY2) and
the NHANES-era ``activity.bin`` / ``lux.bin``.

`Gt3xReader` opens a file, reads what must be known first (``info.txt``; for ``log.bin`` the
first chunk, which holds the METADATA and PARAMETERS records), then yields the samples chunk by
chunk (`Gt3xReader.chunks`): time stamps as the file gives them (the device's clock, Unix
microseconds) and acceleration in g = counts / the file's scale. Idle sleep and missing seconds
stay gaps: nothing is repeated to fill them. Battery, lux and wear (CAPSENSE) come as their own
low-rate series in `Gt3xReader.aux` once the samples have been read. `read_gt3x` reads it all.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recal.errors import DeviceFileError
from recal.io.gt3x import container as zc
from recal.io.gt3x import records as rec

# Activity.md: NEO/CLE (and NHANES-era MRA) 341 LSB/g (+-6 g), MOS 256 LSB/g (+-8 g); a Link
# (TAS) writes its ACCEL_SCALE in PARAMETERS, 256 where it is absent.
DEFAULT_SCALE_BY_SERIAL = (("NEO", 341.0), ("CLE", 341.0), ("MRA", 341.0), ("MOS", 256.0),
                           ("TAS", 256.0))
NHANES_SCALE_LSB_PER_G = 341.0      # activity.bin.md
NHANES_LUX = {"NEO": (1.25, 2500.0), "MRA": (3.25, 6000.0)}   # lux.bin.md: factor, maximum
RATE_RANGE_HZ = (1.0, 1000.0)
IMU_KINDS = (rec.SENSOR_SCHEMA, rec.SENSOR_DATA)
HEAD_BYTES = 1 << 16          # METADATA and PARAMETERS come first (Parameters.md)


@dataclass
class _Damage:
    """What was skipped or not used, counted over the chunks."""

    bad_checksums: int = 0
    stray_bytes: int = 0
    truncated: bool = False
    imu_records: int = 0
    samples: int = 0
    undocumented: dict[int, int] = field(default_factory=dict)   # record type -> count


@dataclass
class _Gaps:
    """Seconds without ACTIVITY records between records that have them (idle sleep, device off)."""

    count: int = 0
    seconds: int = 0
    backwards: int = 0
    last_s: int | None = None

    def add(self, record_time_s: np.ndarray) -> None:
        if not len(record_time_s):
            return
        t = record_time_s if self.last_s is None else np.concatenate(([self.last_s],
                                                                      record_time_s))
        d = np.diff(t)
        self.count += int(np.count_nonzero(d > 1))
        self.seconds += int(np.sum(d[d > 1] - 1))
        self.backwards += int(np.count_nonzero(d < 0))
        self.last_s = int(record_time_s[-1])


@dataclass
class _Series:
    """A low-rate channel gathered over chunks."""

    t_us: list[np.ndarray] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)

    def add(self, t_us: np.ndarray, v: np.ndarray) -> None:
        if len(t_us):
            self.t_us.append(np.asarray(t_us, dtype=np.int64))
            self.v.append(np.asarray(v, dtype=np.float64))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.t_us:
            return np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(self.t_us), np.concatenate(self.v)


def _serial_default(serial: str, table: tuple[tuple[str, float], ...]) -> float | None:
    return next((v for prefix, v in table if serial.upper().startswith(prefix)), None)


class Gt3xReader:
    """One ``.gt3x`` opened for reading; see the module docstring."""

    def __init__(self, path: str | Path, lenient: bool = True,
                 chunk_bytes: int = zc.CHUNK_BYTES) -> None:
        self.path, self.lenient = Path(path), lenient
        self._zf = zc.open_zip(self.path)
        raw_info = zc.read_entry(self._zf, "info.txt", zc.INFO_MAX_BYTES)
        if raw_info is None:
            raise DeviceFileError(f"{self.path}: not an ActiGraph .gt3x: no info.txt")
        self.info = zc.parse_info(raw_info)
        self.serial = self.info.get("Serial Number", "")
        self.notes: list[str] = []
        self.metadata: dict[str, object] = {"device": "ActiGraph", "serial": self.serial,
                                            "device_type": self.info.get("Device Type", ""),
                                            "firmware": self.info.get("Firmware", "")}
        self._series: dict[str, _Series] = {}
        self._damage, self._gaps = _Damage(), _Gaps()
        log = zc.entry_info(self._zf, "log.bin", zc.DATA_MAX_BYTES)
        nhanes = None if log else zc.entry_info(self._zf, "activity.bin", zc.DATA_MAX_BYTES)
        if log is None and nhanes is None:
            raise DeviceFileError(f"{self.path}: not an ActiGraph .gt3x: neither log.bin nor "
                             "activity.bin")
        self.layout = "log.bin" if log else "nhanes"
        self.rate_hz = self._rate(zc.info_float(self.info, "Sample Rate", str(self.path)))
        self._chunks = zc.iter_entry(self._zf, log or nhanes, max(chunk_bytes, 1 << 10))
        self._first = next(self._chunks, b"")
        self.scale_lsb_per_g = (self._open_log() if self.layout == "log.bin"
                                else self._open_nhanes())
        self.metadata.update(rate_hz=self.rate_hz, scale_lsb_per_g=self.scale_lsb_per_g,
                             layout=self.layout)
        self._calibration_json()
        if self.serial.upper().startswith("MOS") and self.metadata["firmware"] == "1.6.0":
            self.notes.append("firmware 1.6.0 of a wGT3X-BT swaps x and y (ActiGraph's note on "
                              "ACTIVITY records): the values are as written")

    # --- what must be known before the samples ------------------------------------------------
    def _rate(self, rate: float | None) -> float:
        if rate is None:
            raise DeviceFileError(f"{self.path}: info.txt has no Sample Rate")
        if not RATE_RANGE_HZ[0] <= rate <= RATE_RANGE_HZ[1]:
            raise DeviceFileError(f"{self.path}: info.txt Sample Rate {rate} Hz is not a rate "
                             f"between {RATE_RANGE_HZ[0]:g} and {RATE_RANGE_HZ[1]:g} Hz")
        return rate

    def _open_log(self) -> float:
        """METADATA and PARAMETERS from the first chunk; the scale the samples are read with."""
        head = self._first[:HEAD_BYTES]
        idx = rec.index_records(head, final=False)
        params: dict[tuple[int, int], int] = {}
        for i in np.flatnonzero(idx.ok & (idx.kind == rec.PARAMETERS))[:4]:
            params.update(rec.parameters(rec.record_payload(head, idx, int(i))))
        meta = [rec.metadata_json(rec.record_payload(head, idx, int(i)))
                for i in np.flatnonzero(idx.ok & (idx.kind == rec.METADATA))[:32]]
        self._time_basis({m.get("MetadataType"): m for m in meta if m}, params)
        scale = None
        if rec.PARAM_ACCEL_SCALE in params:
            scale = rec.ssp_float(params[rec.PARAM_ACCEL_SCALE])
            self.metadata["scale_from"] = "PARAMETERS ACCEL_SCALE"
        if scale is None or not 1.0 <= scale <= 1e5:
            scale = zc.info_float(self.info, "Acceleration Scale", str(self.path))
            self.metadata["scale_from"] = "info.txt Acceleration Scale"
        if scale is None:
            scale = _serial_default(self.serial, DEFAULT_SCALE_BY_SERIAL)
            self.metadata["scale_from"] = "the serial number's device default"
        if scale is None or not 1.0 <= scale <= 1e5:
            raise DeviceFileError(f"{self.path}: no acceleration scale: no PARAMETERS ACCEL_SCALE, "
                             f"no info.txt Acceleration Scale, unknown serial {self.serial!r}")
        sleep_mode = params.get(rec.PARAM_FEATURE_ENABLE, 0) & rec.FEATURE_SLEEP_MODE_BIT
        self.metadata["idle_sleep_mode"] = bool(sleep_mode)
        return scale

    def _time_basis(self, meta: dict[object, dict[str, object]],
                    params: dict[tuple[int, int], int]) -> None:
        """Record times are the device's clock; Metadata.md: UTC where LocalTimeLog.UsedUtc."""
        used_utc = bool(meta.get("LocalTimeLog", {}).get("UsedUtc", False))
        self.metadata["time_is_utc"] = used_utc
        offset = self.info.get("TimeZone") or str(meta.get("LocalTimeLog", {}).get("UtcOffset", ""))
        if not offset and rec.PARAM_UTC_OFFSET in params:
            seconds = params[rec.PARAM_UTC_OFFSET]
            seconds -= 1 << 32 if seconds >= 1 << 31 else 0
            sign, seconds = ("-" if seconds < 0 else "+"), abs(seconds)
            offset = f"{sign}{seconds // 3600:02d}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"
        self.metadata["utc_offset"] = offset
        self.notes.append("times are " + ("UTC (the file says it was initialised in UTC)"
                                          if used_utc else "the device's local clock as stored"
                                          + (f" (UTC offset {offset})" if offset else "")))

    def _open_nhanes(self) -> float:
        """NHANES-era file: times from info.txt's Start Date, the NHANES scale (341 LSB/g)."""
        start = zc.info_time_us(self.info, "Start Date", str(self.path))
        if start is None:
            raise DeviceFileError(f"{self.path}: NHANES .gt3x without an info.txt Start Date")
        self._start_us, self._n_done = start, 0
        self.metadata.update(time_is_utc=False, utc_offset="")
        self.notes.append("times are the device's local clock from info.txt's Start Date")
        return NHANES_SCALE_LSB_PER_G

    def _calibration_json(self) -> None:
        raw = zc.read_entry(self._zf, "calibration.json", zc.SIDE_MAX_BYTES)
        self.metadata["calibration_json_applied"] = False
        if raw is not None:
            cal = rec.metadata_json(raw) or {}
            self.metadata["calibration_json"] = {k: v for k, v in cal.items()
                                                 if isinstance(v, int | float | bool | str)}
            self.notes.append("calibration.json present (isCalibrated="
                              f"{cal.get('isCalibrated')}): not applied; acceleration is the "
                              "file's counts / scale")

    # --- the samples ---------------------------------------------------------------------------
    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(t_us int64, acc_g (N, 3) float64) chunk by chunk; `aux` and `notes` are complete
        once this is exhausted."""
        parts = self._log_chunks() if self.layout == "log.bin" else self._nhanes_chunks()
        for t_us, counts in parts:
            self._damage.samples += len(t_us)
            yield t_us, counts.astype(np.float64) / self.scale_lsb_per_g
        self._close()

    def _log_chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        buf, nxt = self._first, next(self._chunks, None)
        while True:
            final = nxt is None
            idx = rec.index_records(buf, final=final)
            self._check(idx)
            self._log_aux(buf, idx)
            s = rec.decode_activity(buf, idx, self.rate_hz)
            self._gaps.add(s.record_time_s)
            if len(s.t_us):
                yield s.t_us, s.counts
            if final:
                return
            buf, nxt = buf[idx.end:] + nxt, next(self._chunks, None)

    def _check(self, idx: rec.RecordIndex) -> None:
        if idx.garbage:
            raise DeviceFileError(f"{self.path}: log.bin is mostly not ActiGraph log records "
                                  f"({idx.stray_bytes} stray bytes in a row): refused")
        bad = int(np.count_nonzero(~idx.ok))
        d = self._damage
        d.bad_checksums, d.stray_bytes = d.bad_checksums + bad, d.stray_bytes + idx.stray_bytes
        d.truncated |= idx.truncated
        if not self.lenient and (bad or idx.stray_bytes or idx.truncated):
            raise DeviceFileError(f"{self.path}: log.bin is damaged ({bad} records with a bad "
                             f"checksum, {idx.stray_bytes} stray bytes"
                             + (", cut short" if idx.truncated else "") + "); lenient reads it")
        d.imu_records += int(np.count_nonzero(np.isin(idx.kind, IMU_KINDS)))
        kinds, counts = np.unique(idx.kind[~np.isin(idx.kind, rec.DOCUMENTED_KINDS)],
                                  return_counts=True)
        for k, c in zip(kinds.tolist(), counts.tolist(), strict=True):
            d.undocumented[k] = d.undocumented.get(k, 0) + c

    def _log_aux(self, buf: bytes, idx: rec.RecordIndex) -> None:
        for name, (t_s, v) in (("battery_v", rec.decode_u16_records(buf, idx, rec.BATTERY)),
                               ("lux", rec.decode_u16_records(buf, idx, rec.LUX)),
                               ("worn", rec.decode_capsense_worn(buf, idx)),
                               ("idle_sleep", rec.idle_sleep_events(buf, idx))):
            per = 1000.0 if name == "battery_v" else 1.0      # BATTERY is in millivolts
            self._series.setdefault(name, _Series()).add(t_s * 1_000_000, v / per)

    def _nhanes_chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """activity.bin: 9 bytes hold two 36-bit YXZ samples; chunks are cut on 9-byte bounds."""
        step_us = 1e6 / self.rate_hz
        buf, nxt = self._first, next(self._chunks, None)
        while True:
            final = nxt is None
            whole = len(buf) if final else len(buf) // 9 * 9
            rows = np.frombuffer(buf[:whole], dtype=np.uint8)
            counts = (rec.unpack12_yxz(rows[None, :]) if final
                      else rec.unpack12_yxz(rows.reshape(-1, 9))).reshape(-1, 3)
            i = self._n_done + np.arange(len(counts), dtype=np.int64)
            self._n_done += len(counts)
            if len(counts):
                yield self._start_us + np.rint(i * step_us).astype(np.int64), counts
            if final:
                self._nhanes_lux()
                return
            buf, nxt = buf[whole:] + nxt, next(self._chunks, None)

    def _nhanes_lux(self) -> None:
        """lux.bin.md: one LE uint16 a second from the start; < 20 and 0xFFFF are 0; scaled by
        the device's factor up to its maximum, rounded to whole lux."""
        raw = zc.read_entry(self._zf, "lux.bin", zc.DATA_MAX_BYTES // 64)
        if raw is None:
            return
        v = np.frombuffer(raw[: len(raw) // 2 * 2], dtype="<u2").astype(np.float64)
        factor, top = NHANES_LUX.get(self.serial[:3].upper(), NHANES_LUX["NEO"])
        lux = np.where((v < 20) | (v == 0xFFFF), 0.0, np.minimum(v * factor, top))
        t = self._start_us + np.arange(len(v), dtype=np.int64) * 1_000_000
        self._series.setdefault("lux", _Series()).add(t, np.floor(lux + 0.5))

    def _close(self) -> None:
        d, g = self._damage, self._gaps
        self.metadata.update(bad_records=d.bad_checksums, stray_bytes=d.stray_bytes,
                             truncated=d.truncated, gaps=g.count, gap_seconds=g.seconds)
        if d.bad_checksums or d.stray_bytes or d.truncated:
            self.notes.append(f"damaged log.bin read leniently: {d.bad_checksums} records with a "
                              f"bad checksum skipped, {d.stray_bytes} stray bytes"
                              + (", the last record cut short" if d.truncated else ""))
        if g.count:
            self.notes.append(f"{g.count} gaps ({g.seconds} s) without samples (idle sleep or "
                              "missing records): left as gaps, nothing repeated")
        if g.backwards:
            self.notes.append(f"the record clock went backwards {g.backwards} times")
        if d.imu_records:
            self.notes.append(f"{d.imu_records} IMU records (gyroscope, magnetometer) not "
                              "used")
        self._zf.close()
        other = ", ".join(f"0x{k:02X} x{c}" for k, c in sorted(d.undocumented.items()))
        if other and not d.samples:
            raise DeviceFileError(f"{self.path}: ActiGraph log.bin without ACTIVITY or ACTIVITY2 "
                                  f"samples; its records are of types ActiGraph's published "
                                  f"description does not cover ({other}): not readable")
        if other:
            self.notes.append(f"records of types the published description does not cover, "
                              f"not read: {other}")

    @property
    def aux(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """name -> (t_us, values): battery_v, lux, worn (CAPSENSE), idle_sleep (+1 enter,
        -1 leave); only the channels the file holds."""
        return {k: s.arrays() for k, s in self._series.items() if s.t_us}


@dataclass(frozen=True)
class Gt3xData:
    """A whole ``.gt3x`` read (`read_gt3x`)."""

    t_us: np.ndarray
    acc_g: np.ndarray
    aux: dict[str, tuple[np.ndarray, np.ndarray]]
    metadata: dict[str, object]
    notes: tuple[str, ...]
    rate_hz: float


def read_gt3x(path: str | Path, lenient: bool = True,
              chunk_bytes: int = zc.CHUNK_BYTES) -> Gt3xData:
    """Every sample of a ``.gt3x`` of either layout, in memory (read ``chunk_bytes`` of the
    zip entry at a time)."""
    r = Gt3xReader(path, lenient=lenient, chunk_bytes=chunk_bytes)
    parts = list(r.chunks())
    t = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
    a = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 3))
    return Gt3xData(t_us=t, acc_g=a, aux=r.aux, metadata=r.metadata, notes=tuple(r.notes),
                    rate_hz=r.rate_hz)


def read_gt3x_log(path: str | Path, lenient: bool = True
                  ) -> tuple[np.ndarray, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]],
                             dict[str, object], tuple[str, ...]]:
    """(t_us, acc_g, aux, metadata, notes) of a ``.gt3x`` (`read_gt3x` as a tuple)."""
    d = read_gt3x(path, lenient=lenient)
    return d.t_us, d.acc_g, d.aux, d.metadata, d.notes
