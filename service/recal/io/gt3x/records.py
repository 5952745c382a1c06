"""ActiGraph ``log.bin`` log records, from bytes to arrays (no files, no zip).

Written from ActiGraph's published description (``actigraph/GT3X-File-Format``: README's log
record table, ``LogRecords/Activity.md``, ``Activity2.md``, ``Parameters.md``, ``Metadata.md``,
``Capsense.md``). A record is

    0x1E | type (1) | time (4, Unix seconds, LE) | size (2, LE) | payload (size) | checksum (1)

where the checksum is the one's complement of the XOR of header and payload. Framing is a walk
(a record's place depends on the size before it), the one Python loop here: one pass per record,
a few integer operations each. Checksums, payload gathering and sample unpacking are vectorized
over all records of a chunk (records of one payload size are unpacked as one 2-D array).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

SEPARATOR = 0x1E
HEADER_BYTES = 8
ACTIVITY, BATTERY, EVENT, LUX, METADATA, CAPSENSE = 0x00, 0x02, 0x03, 0x05, 0x06, 0x0D
PARAMETERS, SENSOR_SCHEMA, SENSOR_DATA, ACTIVITY2 = 0x15, 0x18, 0x19, 0x1A
EVENT_IDLE_SLEEP_ENTER, EVENT_IDLE_SLEEP_EXIT = 0x08, 0x09
# PARAMETERS keys (address space, identifier) used here; Parameters.md's table.
PARAM_ACCEL_SCALE = (0, 55)
PARAM_FIRMWARE_VERSION = (0, 13)
PARAM_FEATURE_ENABLE = (1, 2)
PARAM_SAMPLE_RATE = (1, 10)
PARAM_UTC_OFFSET = (1, 40)
FEATURE_SLEEP_MODE_BIT = 1 << 2
# the record types README's tables describe (samples, aux, epochs, diagnostics, IMU)
DOCUMENTED_KINDS = (0, 2, 3, 4, 5, 6, 7, 9, 11, 12, 13, 14, 15, 16, 19, 20, 21, 24, 25, 26)


@dataclass(frozen=True)
class RecordIndex:
    """Where the whole records of a byte chunk are, and how many bytes fitted no record.

    Attributes:
        pos: (R,) int64 offset of each record's separator, in file order.
        kind: (R,) uint8 record type.
        time_s: (R,) int64 header time stamp (Unix seconds of the device's clock).
        size: (R,) int64 payload size in bytes.
        ok: (R,) bool, True where the checksum matches.
        stray_bytes: bytes between records that are neither records nor the zero padding the
            description allows.
        end: offset of the first byte not consumed (an incomplete record the next chunk
            completes; ``len(buf)`` when everything was consumed).
        truncated: the chunk was the last and ends inside a record.
        garbage: the chunk is mostly not records (the walk stopped early).
    """

    pos: np.ndarray
    kind: np.ndarray
    time_s: np.ndarray
    size: np.ndarray
    ok: np.ndarray
    stray_bytes: int
    end: int
    truncated: bool
    garbage: bool = False


RUN_PROBE = (16, 4096)   # periods checked at once when guessing that a run goes on: first, most
MAX_PERIOD = 3           # records in a repeating pattern (ACTIVITY2 then CAPSENSE every second)
# A chunk more than half stray bytes (and over 1 MiB of them) is not a damaged log but something
# else: the walk stops there rather than step through it a byte at a time.
GARBAGE_BYTES = 1 << 20


def _run_after(arr: np.ndarray, base: int, offs: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               period: int) -> int:
    """How many more periods of a pattern of records (at ``base + offs``, ``period`` bytes in
    all, size bytes ``lo``, ``hi``) follow back to back, every record where the pattern puts it
    with a separator and the same size. Checked a probe at a time, the probe doubling from 16 to
    4096 periods while the run goes on: a file of one record a second is framed with a few
    numpy calls per run. The last period found is left for the careful walk to check."""
    total, probe, last = 0, RUN_PROBE[0], len(arr) - 1
    while True:
        m = min(probe, (last - base - int(offs[-1])) // period)
        if m <= 1:
            return total
        at = base + period * np.arange(1, m + 1)[:, None] + offs[None, :]
        good = ((arr[at] == SEPARATOR) & (arr[np.minimum(at + 6, last)] == lo)
                & (arr[np.minimum(at + 7, last)] == hi)).all(axis=1)
        k = m if good.all() else int(np.argmin(good))
        if k < m or m < probe:
            return total + max(k - 1, 0)
        total, base, probe = total + m - 1, base + period * (m - 1), min(2 * probe, RUN_PROBE[1])


def _pattern_runs(buf: bytes, arr: np.ndarray, recent: list[int], end: int
                  ) -> tuple[np.ndarray, int, list[int]]:
    """Records found by repeating the last 1..MAX_PERIOD records (``recent``: back to back,
    ending at ``end``): their offsets, where the careful walk resumes, the new ``recent``."""
    for p in range(1, min(MAX_PERIOD, len(recent)) + 1):
        first = recent[-p]
        if buf[end + 6: end + 8] != buf[first + 6: first + 8]:
            continue                     # the next record does not start the pattern again
        period = end - first
        offs = np.asarray(recent[-p:], np.int64) - first
        lo, hi = arr[first + offs + 6], arr[first + offs + 7]
        run = _run_after(arr, first, offs, lo, hi, period)
        if run:
            found = (first + period * np.arange(1, run + 1, dtype=np.int64)[:, None]
                     + offs[None, :]).reshape(-1)
            return found, end + period * run, [int(x) for x in found[-p:]]
    return np.zeros(0, np.int64), end, recent


def _walk(buf: bytes, final: bool) -> tuple[list[np.ndarray], int, int, bool | None]:
    """Record offsets by following each record's size; resynchronises on the next separator
    where a record's framing is implausible (its end is not followed by a separator or the
    description's zero padding), so one damaged size costs a record, not the rest of the file.
    Runs of a repeating pattern of records are taken whole (`_pattern_runs`). The last value
    is None where the chunk is mostly not records (GARBAGE_BYTES)."""
    arr = np.frombuffer(buf, dtype=np.uint8)
    n, pos, stray, truncated = len(buf), 0, 0, False
    found: list[np.ndarray] = []
    single: list[int] = []
    recent: list[int] = []               # the last records found, back to back
    find = buf.find
    while pos < n:
        if buf[pos] != SEPARATOR:
            nxt = find(b"\x1e", pos + 1)
            nxt = n if nxt < 0 else nxt
            stray += (nxt - pos) - buf.count(0, pos, nxt)
            pos, recent = nxt, []
            continue
        end = pos + HEADER_BYTES + 1 + (
            buf[pos + 6] | buf[pos + 7] << 8 if pos + HEADER_BYTES <= n else 0)
        if end > n or (end == n and not final):
            if not final:
                break              # the next chunk completes it
            truncated = True       # cut short, or a damaged size: look for a later record
        elif end == n or buf[end] == SEPARATOR or buf[end] == 0:
            single.append(pos)
            recent = [*recent[-(MAX_PERIOD - 1):], pos]
            pos = end
            if end + HEADER_BYTES < n and buf[end] == SEPARATOR:
                run, pos, recent = _pattern_runs(buf, arr, recent, end)
                if len(run):
                    found += [np.asarray(single, np.int64), run]
                    single = []
            continue
        stray += 1
        pos, recent = pos + 1, []
        if stray > GARBAGE_BYTES and stray > pos // 2:
            truncated = None       # not a log: the caller refuses it
            break
    found.append(np.asarray(single, np.int64))
    return found, stray, (n if final else pos), truncated


def index_records(buf: bytes, final: bool) -> RecordIndex:
    """The records of ``buf`` (a chunk of ``log.bin`` that starts at a record boundary).

    ``final`` says no more bytes follow; otherwise a record cut by the chunk's end is left for
    the next chunk (``end``)."""
    found, stray, end, cut = _walk(buf, final)
    arr = np.frombuffer(buf, dtype=np.uint8)
    pos = np.concatenate(found)
    size = arr[pos + 6].astype(np.int64) | (arr[pos + 7].astype(np.int64) << 8)
    time_s = np.zeros(len(pos), dtype=np.int64)
    for k in range(4):                     # little-endian uint32, vectorized over records
        time_s |= arr[pos + 2 + k].astype(np.int64) << (8 * k)
    ok = np.zeros(len(pos), dtype=bool)
    if len(pos):
        # XOR of each record's header and payload: one reduceat over [pos, checksum) spans
        # (the odd spans, checksum and padding, are not used).
        last = pos + HEADER_BYTES + size
        spans = np.empty(2 * len(pos), np.int64)
        spans[0::2], spans[1::2] = pos, last
        x = np.bitwise_xor.reduceat(arr, spans)[0::2]
        ok = (~x & 0xFF) == arr[last]
    return RecordIndex(pos=pos, kind=arr[pos + 1].copy(), time_s=time_s, size=size, ok=ok,
                       stray_bytes=stray, end=end, truncated=bool(cut), garbage=cut is None)


def payload_rows(buf: bytes, pos: np.ndarray, size: int) -> np.ndarray:
    """(len(pos), size) uint8: the payloads of records of one size, gathered in one step."""
    arr = np.frombuffer(buf, dtype=np.uint8)
    if not len(pos):
        return np.zeros((0, size), np.uint8)
    stride = size + HEADER_BYTES + 1
    first = int(pos[0]) + HEADER_BYTES
    if np.all(np.diff(pos) == stride):      # back to back (the usual run): a strided view
        return np.lib.stride_tricks.as_strided(arr[first:], shape=(len(pos), size),
                                               strides=(stride, 1), writeable=False)
    # rows of a strided window view: one contiguous copy per record, no per-byte index array
    return np.lib.stride_tricks.sliding_window_view(arr, size)[pos + HEADER_BYTES]


def unpack12_yxz(rows: np.ndarray) -> np.ndarray:
    """(K, S) bytes of 12-bit big-endian two's complement samples in YXZ order (Activity.md,
    NHANES activity.bin.md) -> (K, S*8//36, 3) int16 counts in XYZ order. A last unused
    nibble (odd sample count) is dropped."""
    k, s = rows.shape
    n = s * 8 // 36
    nib = np.empty((k, 2 * s), dtype=np.int16)
    nib[:, 0::2] = rows >> 4
    nib[:, 1::2] = rows & 0x0F
    tri = nib[:, : n * 9].reshape(k, n, 3, 3)
    v = (tri[..., 0] << 8) | (tri[..., 1] << 4) | tri[..., 2]
    v -= (v >= 2048).astype(np.int16) * 4096          # sign extension of 12 bits
    return v[:, :, [1, 0, 2]]


def unpack16_xyz(rows: np.ndarray) -> np.ndarray:
    """(K, S) bytes of little-endian int16 XYZ samples (Activity2.md) -> (K, S//6, 3) int16."""
    k, s = rows.shape
    n = s // 6
    return np.ascontiguousarray(rows[:, : n * 6]).view("<i2").reshape(k, n, 3)


def samples_per_record(kind: int, size: np.ndarray) -> np.ndarray:
    """How many XYZ samples an ACTIVITY or ACTIVITY2 payload of ``size`` bytes holds; a
    1-byte payload is a USB connection event, not samples (Activity.md, Activity2.md)."""
    n = size * 8 // 36 if kind == ACTIVITY else size // 6
    return np.where(size <= 1, 0, n)


@dataclass(frozen=True)
class Samples:
    """Accelerometer samples of a chunk: counts as stored, stamped from their record's second."""

    t_us: np.ndarray        # (N,) int64
    counts: np.ndarray      # (N, 3) int16, XYZ
    record_time_s: np.ndarray  # (M,) int64 header second of each record that held samples


def decode_activity(buf: bytes, idx: RecordIndex, rate_hz: float) -> Samples:
    """Every ACTIVITY and ACTIVITY2 record with a good checksum, in file order. Sample i of a
    record is at the record's second + i / rate (the description's one second per record)."""
    sel = np.flatnonzero(idx.ok & ((idx.kind == ACTIVITY) | (idx.kind == ACTIVITY2)))
    kinds, sizes = idx.kind[sel], idx.size[sel]
    n_of = np.zeros(len(sel), dtype=np.int64)
    for kind in (ACTIVITY, ACTIVITY2):
        is_k = kinds == kind
        n_of[is_k] = samples_per_record(kind, sizes[is_k])
    sel, kinds, sizes, n_of = sel[n_of > 0], kinds[n_of > 0], sizes[n_of > 0], n_of[n_of > 0]
    start = np.concatenate(([0], np.cumsum(n_of)))
    counts = np.empty((int(start[-1]), 3), dtype=np.int16)
    t_us = np.empty(int(start[-1]), dtype=np.int64)
    step_us = 1e6 / rate_hz
    groups = [(kind, unpack, size) for kind, unpack in ((ACTIVITY, unpack12_yxz),
                                                        (ACTIVITY2, unpack16_xyz))
              for size in np.unique(sizes[kinds == kind])]
    for kind, unpack, size in groups:
        grp = np.flatnonzero((kinds == kind) & (sizes == size))
        v = unpack(payload_rows(buf, idx.pos[sel[grp]], int(size)))
        n = v.shape[1]
        t = (idx.time_s[sel[grp]][:, None] * 1_000_000
             + np.rint(np.arange(n) * step_us).astype(np.int64))
        if len(groups) == 1:          # the usual chunk: every record alike, already in order
            counts, t_us = v.reshape(-1, 3), t.reshape(-1)
            break
        rows = start[grp][:, None] + np.arange(n)
        counts[rows], t_us[rows] = v, t
    return Samples(t_us=t_us, counts=counts, record_time_s=idx.time_s[sel])


def decode_u16_records(buf: bytes, idx: RecordIndex, kind: int) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, value) of the good records of ``kind`` whose payload starts with a
    little-endian uint16 (BATTERY: millivolts; LUX: lux; CAPSENSE: signal, state at byte 4)."""
    sel = np.flatnonzero(idx.ok & (idx.kind == kind) & (idx.size >= 2))
    arr = np.frombuffer(buf, dtype=np.uint8)
    p = idx.pos[sel] + HEADER_BYTES
    return idx.time_s[sel], arr[p].astype(np.int64) | (arr[p + 1].astype(np.int64) << 8)


def decode_capsense_worn(buf: bytes, idx: RecordIndex) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, worn 0/1) of the good CAPSENSE records (Capsense.md: state byte at offset 4)."""
    sel = np.flatnonzero(idx.ok & (idx.kind == CAPSENSE) & (idx.size >= 6))
    arr = np.frombuffer(buf, dtype=np.uint8)
    return idx.time_s[sel], (arr[idx.pos[sel] + HEADER_BYTES + 4] != 0).astype(np.int64)


def idle_sleep_events(buf: bytes, idx: RecordIndex) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, +1 entering / -1 leaving) idle sleep, from EVENT records (README's table)."""
    sel = np.flatnonzero(idx.ok & (idx.kind == EVENT) & (idx.size >= 1))
    arr = np.frombuffer(buf, dtype=np.uint8)
    code = arr[idx.pos[sel] + HEADER_BYTES]
    keep = (code == EVENT_IDLE_SLEEP_ENTER) | (code == EVENT_IDLE_SLEEP_EXIT)
    return idx.time_s[sel][keep], np.where(code[keep] == EVENT_IDLE_SLEEP_ENTER, 1, -1)


def ssp_float(value: int) -> float:
    """Parameters.md's float: a 24-bit two's-complement fraction (2^23 x mantissa) and a signed
    8-bit power of two; 0x007FFFFF and 0x00800000 mean +/- too large."""
    if value == 0x007FFFFF:
        return float("inf")
    if value == 0x00800000:
        return float("-inf")
    exponent = (value >> 24) & 0xFF
    exponent -= 256 if exponent >= 128 else 0
    fraction = value & 0xFFFFFF
    fraction -= 1 << 24 if fraction & 0x800000 else 0
    return fraction / float(1 << 23) * 2.0 ** exponent


def parameters(payload: bytes) -> dict[tuple[int, int], int]:
    """A PARAMETERS payload's 8-byte (address space, identifier, value) triples, LE."""
    a = np.frombuffer(payload[: len(payload) // 8 * 8], dtype="<u2").reshape(-1, 4)
    value = a[:, 2].astype(np.int64) | (a[:, 3].astype(np.int64) << 16)
    return {(int(s), int(i)): int(v) for s, i, v in zip(a[:, 0], a[:, 1], value, strict=True)}


def record_payload(buf: bytes, idx: RecordIndex, i: int) -> bytes:
    """The payload bytes of record ``i`` (for the few records read whole: metadata, parameters)."""
    p = int(idx.pos[i]) + HEADER_BYTES
    return buf[p: p + int(idx.size[i])]


def metadata_json(payload: bytes) -> dict[str, object] | None:
    """A METADATA payload as a JSON object (Metadata.md), or None where it is not one."""
    try:
        obj = json.loads(payload.decode("utf-8", errors="replace"))
    except ValueError:
        return None
    return obj if isinstance(obj, dict) else None
