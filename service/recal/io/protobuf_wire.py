"""Protobuf wire primitives the batch codecs share: varints, keys, packed runs, zigzag
varints of whole columns in a few numpy passes, and a scanner that finds each field's
occurrences in a message.

The hot path does not use the protobuf runtime: a packed fixed-width field is a tag byte, a
varint byte length and the raw little-endian values, so numpy writes and reads the arrays
directly (``protobuf``'s Python runtime is slow for large repeated fields). The decoder
follows protobuf semantics (unknown fields and known fields with an unexpected wire type are
skipped, packed and unpacked repeated encodings are both accepted, the last singular string
wins) and raises ``ValueError`` with a reason on malformed input.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

# Wire types of the protobuf encoding.
_WT_VARINT = 0
_WT_I64 = 1
_WT_LEN = 2
_WT_I32 = 5


# ---------------------------------------------------------------------------------------------
# Protobuf encoding
# ---------------------------------------------------------------------------------------------

def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _key(field: int, wire_type: int) -> bytes:
    return _varint((field << 3) | wire_type)


def _len_prefixed(field: int, payload: bytes | memoryview) -> list[bytes | memoryview]:
    return [_key(field, _WT_LEN), _varint(len(payload)), payload]


def _packed(field: int, payload: bytes | memoryview) -> list[bytes | memoryview]:
    # proto3 omits empty repeated fields; the official serializer does the same.
    return _len_prefixed(field, payload) if len(payload) else []


def _string_fields(field: int, text: str) -> list[bytes | memoryview]:
    return _len_prefixed(field, text.encode()) if text else []


def _le_bytes(values: np.ndarray, dtype: str) -> memoryview:
    """The values as one C-ordered run of little-endian bytes (a copy only if needed).

    Few numpy calls on purpose: a gateway encodes every sample as it arrives, and each call
    costs microseconds there, more than the bytes themselves."""
    if values.dtype.str != dtype or not values.flags.c_contiguous:
        values = np.ascontiguousarray(values, dtype=dtype)
    return memoryview(values).cast("B") if values.size else memoryview(b"")


def zigzag_varints_many(columns: Sequence[np.ndarray]) -> list[bytes]:
    """Each column of signed integers as protobuf ``sint64`` packed varints (zigzag, 7 bits
    a byte): small magnitudes (deltas) take one or two bytes. All columns in one pass of a
    few numpy calls per byte of the widest value, whatever their number (a message's columns
    are encoded together)."""
    v = np.concatenate([np.asarray(c, np.int64) for c in columns])
    if len(v) == 0:
        return [b"" for _ in columns]
    z = ((v << 1) ^ (v >> 63)).view(np.uint64)
    if int(z.max()) < 1 << 32:  # (32-bit arithmetic is faster)
        z = z.astype(np.uint32)
    nbytes = np.ones(len(z), np.int64)
    rest = z >> 7
    for _ in range(9):  # a uint64 takes at most 10 bytes
        more = rest != 0
        if not more.any():
            break
        nbytes += more
        rest >>= 7
    ends = np.cumsum(nbytes)
    flat = np.empty(int(ends[-1]), np.uint8)
    # byte j of every value at once, then only the values that have a byte j + 1 (deltas:
    # most values end at the first or second byte, so the later passes are short)
    pos, zz = ends - nbytes, z
    for _ in range(10):
        more = zz >= 0x80
        flat[pos] = (zz & 0x7F).astype(np.uint8) | (more.view(np.uint8) << 7)
        if not more.any():
            break
        pos, zz = pos[more] + 1, zz[more] >> 7
    blob = flat.tobytes()
    out, start = [], 0
    for c, end in zip(columns, ends[np.cumsum([len(c) for c in columns]) - 1].tolist(),
                      strict=True):
        if len(c) == 0:
            out.append(b"")
            continue
        out.append(blob[start:end])
        start = end
    return out


def unzigzag_varints(run: np.ndarray, what: str) -> np.ndarray:
    """A column of `zigzag_varints_many` back (a packed run of bytes) as int64; ValueError
    if it ends inside a varint or a varint is longer than 10 bytes."""
    z = _unsigned_varints(run, what)
    return (z >> np.uint64(1)).view(np.int64) ^ -(z & np.uint64(1)).view(np.int64)


def _unsigned_varints(run: np.ndarray, what: str) -> np.ndarray:
    """A packed run of varints (bytes) as uint64, a few numpy calls per byte of the longest
    value; ValueError if it ends inside a varint or a varint is longer than 10 bytes (bits
    beyond 64 are dropped, as protobuf does)."""
    if run.size == 0:
        return np.zeros(0, np.uint64)
    last = run < 0x80
    if not last[-1]:
        raise ValueError(f"packed field {what} ends inside a varint")
    ends = np.flatnonzero(last)
    starts = np.concatenate(([0], ends[:-1] + 1))
    lengths = ends - starts + 1
    if lengths.max() > 10:
        raise ValueError(f"packed field {what} has a varint longer than 10 bytes")
    z = np.zeros(len(ends), np.uint64)
    for k in range(int(lengths.max())):
        sel = lengths > k
        z[sel] |= (run[starts[sel] + k] & 0x7F).astype(np.uint64) << np.uint64(7 * k)
    return z


class _Ints(NamedTuple):
    """A packed sint64 field waiting to be encoded with the message's others (`_join`)."""

    field: int
    values: np.ndarray


def _varint_field(field: int, values: np.ndarray) -> list[Any]:
    return [_Ints(field, values)] if len(values) else []


def _join(parts: list[Any]) -> bytes:
    """The message: its parts, with every sint64 field encoded in one pass."""
    ints = [p for p in parts if isinstance(p, _Ints)]
    if not ints:
        return b"".join(parts)
    encoded = iter(zigzag_varints_many([p.values for p in ints]))
    out: list[bytes | memoryview] = []
    for p in parts:
        if isinstance(p, _Ints):
            out += _len_prefixed(p.field, next(encoded))
        else:
            out.append(p)
    return b"".join(out)


def _deltas(values: np.ndarray) -> np.ndarray:
    """Each value minus the one before (the first as it is): what a delta field holds."""
    return np.diff(np.asarray(values, np.int64), prepend=0)


# ---------------------------------------------------------------------------------------------
# Protobuf decoding
# ---------------------------------------------------------------------------------------------

# One occurrence of a field: (wire type, payload start, payload end).
_Occurrence = tuple[int, int, int]


def _read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    """Decode the varint at ``pos``; return (value, position after it)."""
    end = len(buf)
    result = 0
    for shift in range(0, 70, 7):
        if pos >= end:
            raise ValueError(f"truncated varint at byte {pos}")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result, pos
    raise ValueError(f"varint longer than 10 bytes ending at byte {pos}")


def _scan(buf: bytes, wanted: frozenset[int]) -> dict[int, list[_Occurrence]]:
    """Walk the top-level fields of a message; keep the occurrences of ``wanted`` fields."""
    fields: dict[int, list[_Occurrence]] = {}
    end = len(buf)
    pos = 0
    # Every field consumes at least one byte, so len(buf) iterations always suffice.
    for _ in range(end):
        if pos >= end:
            break
        at = pos
        key, pos = _read_varint(buf, pos)
        field, wire_type = key >> 3, key & 7
        if field == 0:
            raise ValueError(f"field number 0 at byte {at}")
        start = pos
        if wire_type == _WT_VARINT:
            _, pos = _read_varint(buf, pos)
        elif wire_type == _WT_I64:
            pos += 8
        elif wire_type == _WT_LEN:
            length, start = _read_varint(buf, pos)
            pos = start + length
        elif wire_type == _WT_I32:
            pos += 4
        else:
            raise ValueError(f"unsupported wire type {wire_type} (field {field}, byte {at})")
        if pos > end:
            raise ValueError(f"field {field} at byte {at} runs past the end of the message "
                             f"({pos} > {end} bytes)")
        if field in wanted:
            fields.setdefault(field, []).append((wire_type, start, pos))
    return fields


def _last_string(buf: bytes, occurrences: list[_Occurrence] | None) -> str:
    strings = _strings(buf, occurrences)
    return strings[-1] if strings else ""


def _strings(buf: bytes, occurrences: list[_Occurrence] | None) -> list[str]:
    out = []
    for wire_type, start, end in occurrences or ():
        if wire_type != _WT_LEN:
            continue  # protobuf treats a mismatched wire type as an unknown field
        try:
            out.append(buf[start:end].decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise ValueError(f"string field at byte {start} is not valid UTF-8") from exc
    return out


def _fixed64(buf: bytes, occurrences: list[_Occurrence] | None, dtype: str,
             what: str) -> np.ndarray:
    """A repeated 8-byte field (packed runs and/or single values).

    Usually a read-only view into ``buf``; callers copy it into the batch's own arrays, so
    the batch is aligned, writable and does not pin the message buffer.
    """
    runs = []
    for wire_type, start, end in occurrences or ():
        if wire_type not in (_WT_LEN, _WT_I64):
            continue
        if (end - start) % 8:
            raise ValueError(f"packed field {what} has {end - start} bytes, not a multiple of 8")
        runs.append(np.frombuffer(buf, dtype=dtype, count=(end - start) // 8, offset=start))
    if not runs:
        return np.zeros(0, dtype)
    return runs[0] if len(runs) == 1 else np.concatenate(runs)


def _bools(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> np.ndarray:
    """A repeated bool field: packed varints and/or single varints."""
    runs = []
    for wire_type, start, end in occurrences or ():
        if wire_type not in (_WT_LEN, _WT_VARINT):
            continue
        run = np.frombuffer(buf, dtype=np.uint8, count=end - start, offset=start)
        if run.size and run.max() >= 0x80:
            run = _multibyte_varints_nonzero(run, what)
        runs.append(run != 0)
    if not runs:
        return np.zeros(0, bool)
    return runs[0] if len(runs) == 1 else np.concatenate(runs)


def _small_varints(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> np.ndarray:
    """A repeated enum field of small values (packed and/or single varints) as uint8; a value
    above 255 (no status has one) reads as 0, not recorded."""
    runs = []
    for wire_type, start, end in occurrences or ():
        if wire_type not in (_WT_LEN, _WT_VARINT):
            continue
        run = np.frombuffer(buf, dtype=np.uint8, count=end - start, offset=start)
        if run.size and run.max() >= 0x80:  # multi-byte varints (a non-canonical writer)
            values = _unsigned_varints(run, what)
            run = np.where(values <= 0xFF, values, 0).astype(np.uint8)
        runs.append(run)
    if not runs:
        return np.zeros(0, np.uint8)
    return np.array(runs[0] if len(runs) == 1 else np.concatenate(runs), np.uint8)


def _multibyte_varints_nonzero(run: np.ndarray, what: str) -> np.ndarray:
    """Whether each varint of a packed run is nonzero (the rare non-canonical encoding)."""
    last_byte = run < 0x80
    if not last_byte[-1]:
        raise ValueError(f"packed field {what} ends inside a varint")
    starts = np.concatenate(([0], np.flatnonzero(last_byte)[:-1] + 1))
    return np.maximum.reduceat(run & 0x7F, starts)


def _present(fields: dict[int, list[_Occurrence]], field: int, wire_types: tuple[int, ...]
             ) -> bool:
    """Whether the field occurs with a wire type of its own (protobuf skips the others as
    unknown fields)."""
    return any(wt in wire_types for wt, _, _ in fields.get(field, ()))


_VARINT_WT = (_WT_LEN, _WT_VARINT)


def _sint_varints(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> np.ndarray:
    """A repeated sint64 field (packed runs and/or single varints) as int64."""
    runs = [unzigzag_varints(np.frombuffer(buf, np.uint8, end - start, start), what)
            for wire_type, start, end in occurrences or () if wire_type in (_WT_LEN, _WT_VARINT)]
    if not runs:
        return np.zeros(0, np.int64)
    return runs[0] if len(runs) == 1 else np.concatenate(runs)


def _as_bytes(data: bytes | bytearray | memoryview) -> bytes:
    return data if isinstance(data, bytes) else bytes(data)


def _last_real(buf: bytes, occurrences: list[_Occurrence] | None, what: str) -> float:
    """A singular float or double field (the last occurrence wins, as in protobuf): float32
    since the plot's values are floats, float64 in older recordings; 0.0 when absent; another
    wire type is an unknown field to protobuf, so it is skipped."""
    value = 0.0
    for wire_type, start, _end in occurrences or ():
        if wire_type == _WT_I32:
            value = float(np.frombuffer(buf, "<f4", 1, start)[0])
        elif wire_type == _WT_I64:
            value = float(np.frombuffer(buf, "<f8", 1, start)[0])
    return value
