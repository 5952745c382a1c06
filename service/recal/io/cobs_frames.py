"""COBS binary frames, one sample a frame: the parser, its CRC, and the device-side encoder.

Each sample is one payload, COBS-encoded and ended by a zero byte (COBS guarantees no zero
inside an encoded frame). Payload, all little-endian, 25 + 4*K bytes::

    offset  size  field
    0       1     version, 1
    1       1     flags: bit 0 set = x, y, z are float32; clear = int32 counts (exact);
                  other bits reserved, must be 0
    2       1     K, number of auxiliary channels (0..32); fixes the payload length
    3       8     t_us, int64
    11      12    x, y, z: 3 x int32 or 3 x float32 (see flags)
    23      4*K   aux channels, float32 each
    23+4K   2     CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 0 .. 22+4K,
                  i.e. ``binascii.crc_hqx(payload[:-2], 0xFFFF)``, as uint16

A payload is at most 153 bytes, so an encoded frame is 1 byte longer than its payload (one
COBS block, no 0xFF code). Binary frames carry no channel names: they come from the
configuration (``aux_names``), else the channels are named by position.

The stream part (carry-over, resync, error counts) is `recal.io.frames`; why a vectorized
decode beside ``cobs.decode``: docs/design.md, "Figures behind choices".
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Sequence

import numpy as np
from cobs import cobs

from recal.io.frames import (
    DEFAULT_MAX_ABS_XYZ,
    DelimitedParser,
    DeviceStyle,
    Rows,
    WireFormat,
    check_values,
    keep_valid,
)
from recal.samples import RawBatch

__all__ = [
    "COBS_FLAG_XYZ_FLOAT32",
    "COBS_MAX_AUX",
    "COBS_VERSION",
    "DEFAULT_MAX_FRAME_BYTES",
    "WIRE_FORMAT",
    "CobsFrameParser",
    "cobs_decode_rows",
    "cobs_payload_bytes",
    "crc16_ccitt_false",
    "encode_cobs",
]

COBS_VERSION = 1
COBS_FLAG_XYZ_FLOAT32 = 0x01
COBS_MAX_AUX = 32
_COBS_FIXED_BYTES = 25  # version, flags, K, t_us, x, y, z, CRC

DEFAULT_MAX_FRAME_BYTES = 512


def cobs_payload_bytes(n_aux: int) -> int:
    """Length of a decoded binary payload with ``n_aux`` auxiliary channels."""
    return _COBS_FIXED_BYTES + 4 * n_aux


def _crc_tables() -> tuple[np.ndarray, np.ndarray]:
    """Byte-at-a-time and 16-bit-at-a-time tables of CRC-16/CCITT-FALSE (poly 0x1021)."""
    table8 = np.zeros(256, np.uint16)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table8[byte] = crc & 0xFFFF
    # For a 16-bit CRC, two byte steps depend only on crc ^ (b0 << 8 | b1): after 16 shifts
    # no bit of the old register is left, so one lookup per 2 bytes does the work of two.
    x = np.arange(65536, dtype=np.uint32)
    once = ((x << 8) & 0xFFFF) ^ table8[x >> 8]  # step with data byte 0 (b0 already mixed in)
    table16 = (((once << 8) & 0xFFFF) ^ table8[once >> 8]).astype(np.uint16)
    return table8, table16


_CRC_TABLE8, _CRC_TABLE16 = _crc_tables()


def crc16_ccitt_false(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of each row of a (F, n) uint8 array; equals ``crc_hqx(row, 0xFFFF)``.

    The loop runs over the bytes of one frame (two at a time), vectorized over frames.
    """
    rows = np.asarray(rows, np.uint8)
    n_pairs = rows.shape[1] // 2
    words = np.ascontiguousarray(rows[:, :2 * n_pairs]).view(">u2").astype(np.uint16)
    crc = np.full(len(rows), 0xFFFF, np.uint16)
    for j in range(n_pairs):
        crc = _CRC_TABLE16[crc ^ words[:, j]]
    if rows.shape[1] % 2:
        crc = ((crc << 8) & 0xFFFF).astype(np.uint16) ^ _CRC_TABLE8[(crc >> 8) ^ rows[:, -1]]
    return crc


def _payload_dtype(n_aux: int, xyz: str) -> np.dtype:
    return np.dtype([("version", "u1"), ("flags", "u1"), ("n_aux", "u1"), ("t_us", "<i8"),
                     ("xyz", xyz, (3,)), ("aux", "<f4", (n_aux,)), ("crc", "<u2")])


def cobs_decode_rows(enc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorized COBS decode of (F, E) encoded frames whose payload is shorter than 254 bytes
    (for every COBS-framed wire format).

    Returns (decoded (F, E-1), ok (F,)): ok is False where the code-byte chain does not end
    exactly at the frame end (those frames need ``cobs.decode`` to say what is wrong).
    """
    width = enc.shape[1]
    decoded = enc[:, 1:].copy()
    code_pos = enc[:, 0].astype(np.int64)  # each code byte says where the next zero was
    for _ in range(width):
        active = np.flatnonzero(code_pos < width)
        if not len(active):
            break
        decoded[active, code_pos[active] - 1] = 0
        code_pos[active] += enc[active, code_pos[active]]
    return decoded, code_pos == width


class CobsFrameParser(DelimitedParser):
    """Streaming parser of COBS binary frames (layout in the module docstring).

    After :meth:`reset` with ``resync``, the bytes before the first delimiter are kept only if
    they form a valid frame, else counted ``resync_dropped`` (not as a CRC or COBS error).

    Args:
        aux_names: names of the K auxiliary channels (frames carry no names); None learns K
            from the first valid frame and names the channels ``aux0, aux1, ...``.
        max_frame_bytes: longer encoded frames are ``too_long``; bounds the kept partial frame.
        max_abs_xyz: samples with a larger |x|, |y| or |z| are ``out_of_range``.
        vectorized: False decodes frame by frame with ``cobs.decode`` (tests, debugging).
        vectorize_min_frames: a chunk with fewer well-sized frames than this goes frame by
            frame, which is cheaper at serial-port read sizes (the vectorized decode has a
            fixed set-up cost; docs/design.md, "Figures behind choices").
    """

    _DELIMITER = b"\x00"

    def __init__(self, aux_names: Sequence[str] | None = None, *,
                 max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
                 max_abs_xyz: float = DEFAULT_MAX_ABS_XYZ, vectorized: bool = True,
                 vectorize_min_frames: int = 32) -> None:
        super().__init__(aux_names, max_frame_bytes, max_abs_xyz, vectorized)
        self.vectorize_min_frames = int(vectorize_min_frames)

    @property
    def max_frame_bytes(self) -> int:
        """Longest encoded frame taken (longer ones are ``too_long``); bounds the partial one."""
        return self.max_record_bytes

    def _parse_records(self, buf: bytes, last: int, rows: Rows) -> None:
        """Parse the frames of ``buf`` before its zero byte at ``last`` (zero-separated)."""
        chunk = buf[:last]
        arr = np.frombuffer(chunk, np.uint8)
        ends = np.concatenate((np.flatnonzero(arr == 0), [len(arr)]))
        starts = np.concatenate(([0], ends[:-1] + 1))
        first = 0
        while first < len(ends) and (self._resync or not self._layout.settled
                                     or not self.vectorized):
            self._one_frame(chunk[starts[first]:ends[first]], rows)
            first += 1
        if first < len(ends):
            self._fast_frames(chunk, arr, starts[first:], ends[first:], rows)

    def _one_frame(self, frame: bytes, rows: Rows) -> None:
        resync, self._resync = self._resync, False
        if not frame:
            return  # back-to-back delimiters: idle line or a sync byte, not an error
        result = self._frame_result(frame)
        if isinstance(result, tuple):
            rows.add_one(*result)
        elif resync and result != "too_long":  # too_long must not depend on where we split
            self.errors.resync_dropped += 1
        else:
            self.errors.add(result)

    def _frame_result(self, frame: bytes) -> tuple[int, list[float]] | str:
        """One encoded frame (no delimiter): a sample or the error name (the reference path)."""
        if len(frame) > self.max_record_bytes:
            return "too_long"
        try:
            payload = cobs.decode(frame)
        except cobs.DecodeError:
            return "garbage"
        if len(payload) < _COBS_FIXED_BYTES:
            return "bad_length"
        if binascii.crc_hqx(payload[:-2], 0xFFFF) != int.from_bytes(payload[-2:], "little"):
            return "bad_crc"
        version, flags, n_aux = payload[0], payload[1], payload[2]
        if version != COBS_VERSION or flags & ~COBS_FLAG_XYZ_FLOAT32:
            return "bad_version"
        if n_aux > COBS_MAX_AUX or len(payload) != cobs_payload_bytes(n_aux):
            return "bad_length"
        if self._layout.settled and n_aux != self._layout.n_aux:
            return "wrong_columns"
        xyz = "f" if flags & COBS_FLAG_XYZ_FLOAT32 else "i"
        t_us, *values = struct.unpack_from(f"<q3{xyz}{n_aux}f", payload, 3)
        vals = [float(x) for x in values]
        error = check_values(t_us, vals, self.max_abs_xyz)
        if error is not None:
            return error
        self._layout.accept(n_aux)
        return t_us, vals

    def _fast_frames(self, chunk: bytes, arr: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                     rows: Rows) -> None:
        """Decode all frames of the expected length at once; others go frame by frame."""
        n_aux = self._layout.n_aux or 0
        payload_bytes = cobs_payload_bytes(n_aux)
        lengths = ends - starts
        t_us = np.zeros(len(ends), np.int64)
        vals = np.zeros((len(ends), 3 + n_aux))
        keep = np.zeros(len(ends), bool)
        fast = np.zeros(len(ends), bool)
        cand = np.flatnonzero(lengths == payload_bytes + 1)
        if len(cand) >= max(1, self.vectorize_min_frames):
            width = payload_bytes + 1
            if len(cand) == len(ends) and len(arr) == len(ends) * (width + 1) - 1:
                # Clean stream: frames are back to back, so the chunk is a matrix already.
                enc = np.frombuffer(chunk + b"\x00", np.uint8).reshape(-1, width + 1)[:, :width]
            else:
                enc = arr[starts[cand, None] + np.arange(width)]
            decoded, ok = cobs_decode_rows(enc)
            crc = decoded[:, -2].astype(np.uint32) | (decoded[:, -1].astype(np.uint32) << 8)
            ok &= crc16_ccitt_false(decoded[:, :-2]) == crc
            ok &= (decoded[:, 0] == COBS_VERSION) & (decoded[:, 2] == n_aux)
            ok &= (decoded[:, 1] & ~np.uint8(COBS_FLAG_XYZ_FLOAT32)) == 0
            as_int = decoded.view(_payload_dtype(n_aux, "<i4")).reshape(-1)
            as_float = decoded.view(_payload_dtype(n_aux, "<f4")).reshape(-1)
            is_float = (decoded[:, 1] & COBS_FLAG_XYZ_FLOAT32).astype(bool)
            xyz = np.where(is_float[:, None], as_float["xyz"], as_int["xyz"])
            t_cand = as_int["t_us"]
            ok &= t_cand >= 0  # negative t_us: let the reference path count it
            good = cand[ok]
            fast[good] = True
            t_us[good] = t_cand[ok]
            vals[good, :3] = xyz[ok]
            vals[good, 3:] = as_int["aux"][ok]
            keep[good] = keep_valid(vals[good], self.max_abs_xyz, self.errors)
        for i in np.flatnonzero(~fast & (lengths > 0)).tolist():
            result = self._frame_result(chunk[starts[i]:ends[i]])
            if isinstance(result, tuple):
                t_us[i], vals[i] = result
                keep[i] = True
            else:
                self.errors.add(result)
        rows.add_many(t_us[keep], vals[keep])


# --------------------------------------------------------------------------- device side


def encode_cobs(batch: RawBatch, xyz: str = "auto") -> bytes:
    """Device side of the binary format: one COBS frame + ``b"\\x00"`` per sample.

    Args:
        xyz: "int32" (exact for integer counts), "float32", or "auto": int32 when every x, y, z
            is an integer that fits, else float32. Aux channels are always float32.
    """
    n_aux = batch.aux.shape[1]
    if n_aux > COBS_MAX_AUX:
        raise ValueError(f"at most {COBS_MAX_AUX} auxiliary channels fit a frame")
    if xyz == "auto":
        v = batch.v
        fits = np.isfinite(v).all() and (v == np.round(v)).all() and (np.abs(v) < 2**31).all()
        xyz = "int32" if fits else "float32"
    if xyz not in ("int32", "float32"):
        raise ValueError("xyz must be 'auto', 'int32' or 'float32'")
    is_float = xyz == "float32"
    records = np.zeros(len(batch), _payload_dtype(n_aux, "<f4" if is_float else "<i4"))
    records["version"] = COBS_VERSION
    records["flags"] = COBS_FLAG_XYZ_FLOAT32 if is_float else 0
    records["n_aux"] = n_aux
    records["t_us"] = batch.t_us
    records["xyz"] = batch.v if is_float else np.round(batch.v).astype(np.int32)
    records["aux"] = batch.aux
    payloads = records.view(np.uint8).reshape(len(batch), records.dtype.itemsize)
    records["crc"] = crc16_ccitt_false(payloads[:, :-2])
    raw = records.tobytes()
    size = records.dtype.itemsize
    return b"".join(cobs.encode(raw[i:i + size]) + b"\x00" for i in range(0, len(raw), size))


def _device_frames(batch: RawBatch, style: DeviceStyle) -> bytes:
    return encode_cobs(batch, xyz=style.xyz)


# frames carry no channel names, so no header; nor records without time
WIRE_FORMAT = WireFormat("cobs", CobsFrameParser, _device_frames)
