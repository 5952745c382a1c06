"""Fuzzing the serial input: the parsers (io/ascii_lines.py, io/cobs_frames.py) and SerialSource.

A stream is a sequence of items, each either a valid frame or one hostile item of a known kind
(garbage, truncated, bad CRC, NaN/inf, huge numbers, wrong column counts, non-UTF-8 bytes,
over-long lines, a frame glued to the cut-off tail of the previous one, ...). Every hostile item
ends at a delimiter, so it can corrupt only itself (the glued COBS frame is the one exception:
it takes the frame it is glued to down with it, and that frame is not counted as sent). The
property everywhere: no exception, the valid frames come out exactly once, in order, with their
values bit for bit, and every hostile item is counted exactly once under the error it is.

Three drivers: hypothesis (small streams, shrinking to a minimal failing kind sequence), a soak
of 1 M items per wire format split at random chunk boundaries, and a shorter soak written
through a real pseudo-terminal into SerialSource.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from cobs import cobs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recal.io.ascii_lines import AsciiLineParser
from recal.io.cobs_frames import (
    COBS_FLAG_XYZ_FLOAT32,
    CobsFrameParser,
    cobs_payload_bytes,
    encode_cobs,
)
from recal.io.frames import ParseErrors
from recal.io.serial_source import SerialSource
from recal.io.wire_formats import make_parser
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from test_frames import _assert_same, _frame
from test_frames import _payload as frame_payload

AUX = ("temp_c", "vdd_v")
HEADER = b"#t_us,x,y,z,temp_c,vdd_v"
# Time stamps cross 2**53 near the end of a 1 M stream: the vectorized ASCII path must hand
# those lines to the exact per-line path.
T0_US = 2**53 - 997 * 990_000
DT_US = 997
HYPOTHESIS = settings(max_examples=200, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow])

# Item kinds. Index 0 is a valid frame; the others are hostile (or harmless: blank, comment,
# header, idle), and for each the error it must be counted under.
ASCII_KINDS = ("valid", "garbage", "truncated", "non_finite", "huge", "columns", "non_utf8",
               "too_long", "blank", "comment", "header", "other_header")
COBS_KINDS = ("valid", "garbage", "truncated", "glued", "bad_crc", "non_finite", "huge",
              "columns", "version", "too_long", "idle")
# Errors a kind is counted under; kinds whose exact error depends on random bytes share a
# group (garbage or non_utf8 for a line of random bytes, and so on).
ASCII_GROUPS = {"wrong_columns": ("truncated", "columns"), "non_finite": ("non_finite",),
                "out_of_range": ("huge",), "too_long": ("too_long",),
                "garbage+non_utf8": ("garbage", "non_utf8"),
                "header_mismatch": ("other_header",)}
COBS_GROUPS = {"garbage+bad_length+bad_crc": ("garbage", "truncated", "glued", "bad_crc"),
               "non_finite": ("non_finite",), "out_of_range": ("huge",),
               "wrong_columns": ("columns",), "bad_version": ("version",),
               "too_long": ("too_long",)}
HARMLESS = {"blank", "comment", "header", "idle"}


@dataclass(frozen=True)
class Stream:
    """Bytes to feed, the samples they must give, and the hostile items by kind."""

    data: bytes
    expected: RawBatch
    kinds: Counter


def _weights(kinds: tuple[str, ...], hostile_fraction: float) -> np.ndarray:
    """Probability of each kind: 1 - hostile_fraction valid, the rest shared among the others
    (over-long lines and harmless items less often: they are big, or not errors)."""
    share = np.array([0.0, *(0.25 if k == "too_long" else 0.5 if k in HARMLESS else 1.0
                             for k in kinds[1:])])
    w = hostile_fraction * share / share.sum()
    w[0] = 1.0 - hostile_fraction
    return w


def _samples(n: int, rng: np.random.Generator, extremes: tuple[float, ...]) -> tuple[
        np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """t_us (increasing), x/y/z (integer counts or floats), aux, and which rows are floats.

    A few rows carry extreme but valid values: ``extremes`` in an aux channel (huge, denormal,
    negative zero) and x at exactly the +-1e9 limit.
    """
    t_us = T0_US + DT_US * np.arange(n, dtype=np.int64)
    is_float = rng.random(n) < 0.2
    v = np.where(is_float[:, None], rng.normal(0.0, 2.0, (n, 3)),
                 rng.integers(-32768, 32768, (n, 3)).astype(float))
    aux = np.column_stack([np.round(rng.normal(30.0, 3.0, n), 2),
                           np.round(rng.normal(3.3, 0.05, n), 3)])
    odd = np.flatnonzero(rng.random(n) < 0.01)
    aux[odd, 0] = rng.choice(extremes, len(odd))
    edge = np.flatnonzero(rng.random(n) < 0.001)
    v[edge, 0] = rng.choice([1e9, -1e9], len(edge))
    is_float[edge] = True
    return t_us, v, aux, is_float


def _splice(n: int, hostile_at: np.ndarray, valid_piece: Callable[[int, int], bytes],
            hostile_piece: Callable[[int], bytes]) -> bytes:
    """Valid items in runs between the hostile ones (few pieces to join, so it is fast)."""
    pieces, start = [], 0
    for i in hostile_at.tolist():
        if start < i:
            pieces.append(valid_piece(start, i))
        pieces.append(hostile_piece(i))
        start = i + 1
    if start < n:
        pieces.append(valid_piece(start, n))
    return b"".join(pieces)


# --------------------------------------------------------------------------- ASCII streams


def _ascii_lines(t_us: np.ndarray, v: np.ndarray, aux: np.ndarray,
                 is_float: np.ndarray) -> list[bytes]:
    """One line per sample as a device prints it (counts as integers, floats as repr)."""
    cols = [list(map(str, t_us.tolist()))]
    floats = np.flatnonzero(is_float).tolist()
    for j in range(3):
        col = list(map(str, v[:, j].astype(np.int64).tolist()))
        for i, text in zip(floats, map(repr, v[floats, j].tolist()), strict=True):
            col[i] = text
        cols.append(col)
    cols += [list(map(repr, aux[:, j].tolist())) for j in range(aux.shape[1])]
    return "\n".join(map(",".join, zip(*cols, strict=True))).encode().split(b"\n")


def _hostile_line(kind: str, line: bytes, rng: np.random.Generator) -> bytes:
    """A hostile line (without its newline) made from the valid ``line``."""
    fields = line.split(b",")
    if kind == "garbage":  # a control character makes sure it is never a sample or comment
        junk = bytes(rng.integers(0, 256, int(rng.integers(0, 60)), dtype=np.uint8))
        return b"\x01" + junk.replace(b"\n", b"")
    if kind == "truncated":  # cut before the last comma: at least one field lost
        return line[:int(rng.integers(1, line.rfind(b",")))]
    if kind == "non_finite":
        j = int(rng.integers(1, len(fields)))
        fields[j] = rng.choice([b"nan", b"NaN", b"inf", b"-inf", b"Infinity", b"1e400",
                                b"-1e999"])
        return b",".join(fields)
    if kind == "huge":
        if rng.random() < 0.7:
            j = int(rng.integers(1, 4))
            mantissa = rng.choice([-1, 1]) * rng.uniform(1.001, 1e3)
            fields[j] = f"{mantissa:.6g}e{rng.integers(9, 300)}".encode()
        else:  # a time stamp beyond int64, or negative
            fields[0] = rng.choice([b"9223372036854775808", b"99999999999999999999999", b"-1",
                                    b"-997"])
        return b",".join(fields)
    if kind == "columns":
        if rng.random() < 0.5:
            return line + b",1.5" * int(rng.integers(1, 4))
        del fields[int(rng.integers(1, len(fields)))]
        return b",".join(fields)
    if kind == "non_utf8":
        i = int(rng.integers(0, len(line) + 1))
        return line[:i] + rng.choice([b"\xff", b"\xc3\x28", b"\xe2\x82", b"\xed\xa0\x80",
                                      b"\x80"]) + line[i:]
    if kind == "too_long":
        return b"1," * 2100 + b"1"
    if kind == "blank":
        return rng.choice([b"", b"   ", b"\r"])
    if kind == "comment":
        return b"# device rebooted, firmware 1.2"
    if kind == "header":
        return HEADER
    if kind == "other_header":
        return b"#t_us,x,y,z,a,b"
    raise ValueError(kind)


def ascii_stream(kind_idx: np.ndarray, seed: int) -> Stream:
    """A header, then one item per entry of ``kind_idx`` (indices into ASCII_KINDS)."""
    rng = np.random.default_rng(seed)
    n = len(kind_idx)
    t_us, v, aux, is_float = _samples(n, rng, (1e300, -1e300, 5e-324, -0.0, 1.7976931348623157e308))
    lines = _ascii_lines(t_us, v, aux, is_float) if n else []
    crlf = rng.random(n) < 0.05
    for i in np.flatnonzero(crlf).tolist():
        lines[i] += b"\r"
    hostile_at = np.flatnonzero(kind_idx != 0)
    data = HEADER + b"\n" + _splice(
        n, hostile_at, lambda a, b: b"\n".join(lines[a:b]) + b"\n",
        lambda i: _hostile_line(ASCII_KINDS[kind_idx[i]], lines[i].rstrip(b"\r"), rng) + b"\n")
    ok = kind_idx == 0
    return Stream(data, RawBatch(t_us[ok], v[ok], aux[ok], AUX),
                  Counter(ASCII_KINDS[k] for k in kind_idx[~ok].tolist()))


# --------------------------------------------------------------------------- COBS streams


def _payload(t_us: int, xyz: tuple[float, float, float], aux: tuple[float, ...], *,
             version: int = 1, flags: int = COBS_FLAG_XYZ_FLOAT32) -> bytes:
    """`test_frames._payload` with float32 axes (its CRC is binascii's, not the parser's)."""
    return frame_payload(t_us, xyz, aux, version=version, flags=flags)  # type: ignore[arg-type]


def _hostile_frame(kind: str, t_us: int, frame: bytes, rng: np.random.Generator) -> bytes:
    """A hostile item (with its delimiter) in place of the valid ``frame`` (delimiter included)."""
    body = frame[:-1]
    if kind == "garbage":
        return bytes(rng.integers(1, 256, int(rng.integers(1, 80)), dtype=np.uint8)) + b"\x00"
    if kind == "truncated":
        return body[:int(rng.integers(1, len(body)))] + b"\x00"
    if kind == "glued":  # the tail and delimiter were lost: the next frame is glued on and lost
        return body[:int(rng.integers(1, len(body)))] + frame
    if kind == "bad_crc":
        payload = bytearray(cobs.decode(body))
        bit = int(rng.integers(0, 8 * len(payload)))
        payload[bit // 8] ^= 1 << (bit % 8)
        return _frame(bytes(payload))
    xyz, aux = [1.0, -2.0, 3.0], [25.0, 3.3]
    if kind == "non_finite":
        where = int(rng.integers(0, 5))
        bad = float(rng.choice([np.nan, np.inf, -np.inf]))
        if where < 3:
            xyz[where] = bad
        else:
            aux[where - 3] = bad
        return _frame(_payload(t_us, tuple(xyz), tuple(aux)))  # type: ignore[arg-type]
    if kind == "huge":
        if rng.random() < 0.7:
            xyz[int(rng.integers(0, 3))] = float(rng.choice([-1, 1]) * 10 ** rng.uniform(9.01, 38))
            return _frame(_payload(t_us, tuple(xyz), tuple(aux)))  # type: ignore[arg-type]
        return _frame(_payload(-int(rng.integers(1, 2**62)), tuple(xyz), tuple(aux)))  # type: ignore[arg-type]
    if kind == "columns":
        k = int(rng.choice([0, 1, 3, 7]))
        return _frame(_payload(t_us, tuple(xyz), tuple(aux[:1] * k)))  # type: ignore[arg-type]
    if kind == "version":
        if rng.random() < 0.5:
            return _frame(_payload(t_us, tuple(xyz), tuple(aux),  # type: ignore[arg-type]
                                   version=int(rng.choice([0, 2, 255]))))
        return _frame(_payload(t_us, tuple(xyz), tuple(aux),  # type: ignore[arg-type]
                               flags=int(rng.choice([0x03, 0x81, 0xFF]))))
    if kind == "too_long":
        return bytes(rng.integers(1, 256, int(rng.integers(513, 2000)), dtype=np.uint8)) + b"\x00"
    if kind == "idle":
        return b"\x00" * int(rng.integers(1, 4))
    raise ValueError(kind)


def cobs_stream(kind_idx: np.ndarray, seed: int) -> Stream:
    """A leading delimiter, then one item per entry of ``kind_idx`` (indices into COBS_KINDS)."""
    rng = np.random.default_rng(seed)
    n = len(kind_idx)
    t_us, v, aux, is_float = _samples(n, rng, (3e38, -3e38, 1e-45, -0.0))
    v = np.where(is_float[:, None], v.astype(np.float32), v)  # what float32 frames carry
    aux = aux.astype(np.float32).astype(np.float64)
    width = cobs_payload_bytes(len(AUX)) + 2  # one COBS code byte, the payload, the delimiter
    frames = np.zeros((n, width), np.uint8)
    for mask, xyz in ((is_float, "float32"), (~is_float, "int32")):
        if mask.any():
            enc = encode_cobs(RawBatch(t_us[mask], v[mask], aux[mask], AUX), xyz=xyz)
            frames[mask] = np.frombuffer(enc, np.uint8).reshape(-1, width)
    hostile_at = np.flatnonzero(kind_idx != 0)
    data = b"\x00" + _splice(
        n, hostile_at, lambda a, b: frames[a:b].tobytes(),
        lambda i: _hostile_frame(COBS_KINDS[kind_idx[i]], int(t_us[i]), frames[i].tobytes(), rng))
    ok = kind_idx == 0
    return Stream(data, RawBatch(t_us[ok], v[ok], aux[ok], AUX),
                  Counter(COBS_KINDS[k] for k in kind_idx[~ok].tolist()))


# --------------------------------------------------------------------------- checks


def _feed_chunks(parser: AsciiLineParser | CobsFrameParser, data: bytes,
                 cuts: np.ndarray) -> RawBatch:
    """Feed ``data`` split at ``cuts`` (sorted offsets), then flush; all samples joined."""
    out = []
    for a, b in zip([0, *cuts.tolist()], [*cuts.tolist(), len(data)], strict=True):
        batch = parser.feed(data[a:b])
        if len(batch):
            out.append(batch)
    tail = parser.flush()
    if len(tail):
        out.append(tail)
    return RawBatch.concat(out) if out else RawBatch.empty(AUX)


def _random_cuts(n_bytes: int, rng: np.random.Generator) -> np.ndarray:
    """Chunk boundaries: mostly read-sized chunks (up to 16 kB), some of 1-16 bytes."""
    m = n_bytes // 2000 + 2  # mean chunk ~5.7 kB: enough chunks to cover n_bytes
    sizes = np.where(rng.random(m) < 0.3, rng.integers(1, 17, m), rng.integers(1, 16384, m))
    cuts = np.cumsum(sizes)
    while cuts[-1] < n_bytes:  # bounded: each round at least doubles the covered length
        cuts = np.concatenate([cuts, cuts[-1] + np.cumsum(rng.integers(1, 16384, len(cuts)))])
    return cuts[cuts < n_bytes]


def _assert_delivered(got: RawBatch, stream: Stream) -> None:
    """The valid frames, exactly once, in order, bit for bit."""
    assert len(got) == len(stream.expected), (len(got), len(stream.expected))
    _assert_same(got, stream.expected)


def _assert_counted(errors: ParseErrors, stream: Stream,
                    groups: dict[str, tuple[str, ...]]) -> None:
    """Every hostile item counted exactly once, under its own error."""
    counts = errors.as_dict()
    for names, kinds in groups.items():
        got = sum(counts[name] for name in names.split("+"))
        assert got == sum(stream.kinds[k] for k in kinds), (names, errors.nonzero(), stream.kinds)
    assert errors.total == sum(n for k, n in stream.kinds.items() if k not in HARMLESS)


def _kinds(n: int, kinds: tuple[str, ...], hostile_fraction: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.choice(len(kinds), n, p=_weights(kinds, hostile_fraction))


# --------------------------------------------------------------------------- hypothesis

_ascii_kind_lists = st.lists(st.one_of(st.just(0), st.integers(0, len(ASCII_KINDS) - 1)),
                             max_size=60)
_cobs_kind_lists = st.lists(st.one_of(st.just(0), st.integers(0, len(COBS_KINDS) - 1)),
                            max_size=60)
_cuts = st.lists(st.integers(0, 10**6), max_size=20)


@given(kinds=_ascii_kind_lists, seed=st.integers(0, 2**32 - 1), cuts=_cuts)
@HYPOTHESIS
def test_ascii_valid_lines_survive_any_mix_of_hostile_lines(kinds: list[int], seed: int,
                                                            cuts: list[int]) -> None:
    stream = ascii_stream(np.array(kinds, np.int64), seed)
    cut_at = np.unique(np.array(cuts, np.int64) % (len(stream.data) + 1))
    parser = AsciiLineParser()
    _assert_delivered(_feed_chunks(parser, stream.data, cut_at), stream)
    _assert_counted(parser.errors, stream, ASCII_GROUPS)


@given(kinds=_cobs_kind_lists, seed=st.integers(0, 2**32 - 1), cuts=_cuts,
       min_frames=st.sampled_from([1, 32]))
@HYPOTHESIS
def test_cobs_valid_frames_survive_any_mix_of_hostile_frames(kinds: list[int], seed: int,
                                                             cuts: list[int],
                                                             min_frames: int) -> None:
    stream = cobs_stream(np.array(kinds, np.int64), seed)
    cut_at = np.unique(np.array(cuts, np.int64) % (len(stream.data) + 1))
    parser = CobsFrameParser(AUX, vectorize_min_frames=min_frames)
    _assert_delivered(_feed_chunks(parser, stream.data, cut_at), stream)
    _assert_counted(parser.errors, stream, COBS_GROUPS)


_ops = st.lists(st.one_of(
    st.tuples(st.just("feed"), st.binary(max_size=300)),
    st.tuples(st.just("feed"), st.sampled_from([HEADER + b"\n", b"1,2,3,4,5,6\n", b"\x00",
                                                b"1,2,3,4\n", b"\n"])),
    st.tuples(st.just("reset"), st.booleans()),
    st.tuples(st.just("flush"), st.none()),
), max_size=30)


@pytest.mark.parametrize("fmt", ["ascii", "cobs"])
@pytest.mark.parametrize("configured", [True, False])
@given(ops=_ops)
@HYPOTHESIS
def test_arbitrary_bytes_resets_and_flushes_never_raise_and_yield_only_sane_samples(
        fmt: str, configured: bool, ops: list[tuple[str, object]]) -> None:
    parser = make_parser(fmt, AUX if configured else None, max_abs_xyz=1e6)
    for op, arg in ops:
        if op == "feed":
            batch = parser.feed(arg)  # type: ignore[arg-type]
        elif op == "reset":
            parser.reset(resync=bool(arg))
            continue
        else:
            batch = parser.flush()
        # whatever came out is a well-formed batch of finite, in-range samples
        assert batch.v.shape == (len(batch), 3) and batch.aux.shape[0] == len(batch)
        assert batch.aux.shape[1] == len(batch.aux_names)
        assert np.isfinite(batch.v).all() and np.isfinite(batch.aux).all()
        assert (np.abs(batch.v) <= 1e6).all() and (batch.t_us >= 0).all()
        if configured:
            assert batch.aux_names == AUX
        assert all(v >= 0 for v in parser.errors.as_dict().values())
    pending = parser._pending  # the partial item kept between calls stays bounded
    assert len(pending) <= (parser.max_line_bytes if fmt == "ascii" else parser.max_frame_bytes)


# --------------------------------------------------------------------------- 1 M item soak

SOAK_ITEMS = 1_000_000
SOAK_HOSTILE = 0.10


@pytest.mark.slow
@pytest.mark.parametrize(("fmt", "kinds", "groups", "build"), [
    ("ascii", ASCII_KINDS, ASCII_GROUPS, ascii_stream),
    ("cobs", COBS_KINDS, COBS_GROUPS, cobs_stream),
])
def test_soak_one_million_items_split_at_random_chunk_boundaries(
        fmt: str, kinds: tuple[str, ...], groups: dict[str, tuple[str, ...]],
        build: Callable[[np.ndarray, int], Stream]) -> None:
    kind_idx = _kinds(SOAK_ITEMS, kinds, SOAK_HOSTILE, seed=17)
    stream = build(kind_idx, 18)
    assert sum(stream.kinds.values()) > 0.09 * SOAK_ITEMS and len(stream.kinds) == len(kinds) - 1
    cuts = _random_cuts(len(stream.data), np.random.default_rng(19))
    parser = make_parser(fmt, None if fmt == "ascii" else AUX)
    started = time.perf_counter()
    got = _feed_chunks(parser, stream.data, cuts)
    elapsed_s = time.perf_counter() - started
    _assert_delivered(got, stream)
    _assert_counted(parser.errors, stream, groups)
    print(f"\n{fmt}: {SOAK_ITEMS} items, {len(stream.data) / 1e6:.1f} MB in {len(cuts) + 1} "
          f"chunks, {len(got)} valid delivered, errors {parser.errors.nonzero()}, "
          f"parsed in {elapsed_s:.2f} s")


# --------------------------------------------------------------------------- through a real pty

PTY_ITEMS = 40_000


def _write_in_random_chunks(device: PtyDevice, data: bytes, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pos = 0
    for _ in range(len(data)):  # bounded: each round writes at least one byte or gives up
        if pos >= len(data):
            return
        n = int(rng.integers(1, 4096))
        written = device.write_bytes(data[pos:pos + n])
        if written == 0:
            return  # the reader stopped reading: the test fails on the count
        pos += written


@pytest.mark.parametrize(("fmt", "kinds", "groups", "build"), [
    ("ascii", ASCII_KINDS, ASCII_GROUPS, ascii_stream),
    ("cobs", COBS_KINDS, COBS_GROUPS, cobs_stream),
])
def test_soak_through_a_pty_into_serial_source(
        tmp_path: Path, fmt: str, kinds: tuple[str, ...], groups: dict[str, tuple[str, ...]],
        build: Callable[[np.ndarray, int], Stream]) -> None:
    stream = build(_kinds(PTY_ITEMS, kinds, 0.15, seed=23), 24)
    link = str(tmp_path / "ttyFUZZ")
    batches: list[RawBatch] = []
    reported: Counter = Counter()
    with PtyDevice(link, fmt, header=False, write_timeout_s=10.0) as device, \
            SerialSource(link, make_parser(fmt, None if fmt == "ascii" else AUX)) as source:
        _, events = source.read_batch(0.0)  # open before writing: opening flushes the input
        assert [e.kind for e in events] == ["port_opened"]
        writer = threading.Thread(target=_write_in_random_chunks,
                                  args=(device, stream.data, 25), daemon=True)
        writer.start()
        n_got, deadline = 0, time.monotonic() + 60.0
        for _ in range(100_000):  # bounded in count and (below) in time
            batch, events = source.read_batch(0.05)
            for e in events:
                assert e.kind == "parse_errors", e
                reported.update({k: v for k, v in e.detail.items() if k != "port"})
            if len(batch):
                batches.append(batch)
                n_got += len(batch)
            if (n_got >= len(stream.expected) and not writer.is_alive()) \
                    or time.monotonic() > deadline:
                break
        writer.join(5.0)
        _, events = source.read_batch(0.2)  # anything counted after the last sample
        for e in events:
            reported.update({k: v for k, v in e.detail.items() if k != "port"})
        assert device.bytes_dropped == 0
        errors = source.parser.errors
    got = RawBatch.concat(batches) if batches else RawBatch.empty(AUX)
    _assert_delivered(got, stream)
    _assert_counted(errors, stream, groups)
    # what SerialSource reported as events adds up to what the parser counted
    assert dict(reported) == {k: v for k, v in errors.nonzero().items()
                              if k not in ParseErrors.INFORMATIONAL}
