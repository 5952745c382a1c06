"""Wire-format parsers and encoders: recal.io.frames, ascii_lines, cobs_frames (pure, no I/O)."""

from __future__ import annotations

import binascii

import numpy as np
import pytest
from cobs import cobs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recal.errors import ConfigError
from recal.io.ascii_lines import AsciiLineParser, encode_ascii
from recal.io.cobs_frames import (
    COBS_FLAG_XYZ_FLOAT32,
    CobsFrameParser,
    cobs_payload_bytes,
    crc16_ccitt_false,
    encode_cobs,
)
from recal.io.frames import ParseErrors
from recal.io.wire_formats import make_parser
from recal.samples import RawBatch

HYPOTHESIS = settings(max_examples=150, deadline=None,
                      suppress_health_check=[HealthCheck.too_slow])
AUX = ("temp_c", "vdd_v")


def _batch(n: int, n_aux: int = 2, *, counts: bool = True, seed: int = 0,
           t0_us: int = 1_000_000) -> RawBatch:
    rng = np.random.default_rng(seed)
    v = rng.integers(-32768, 32768, (n, 3)).astype(float) if counts else rng.normal(0, 1, (n, 3))
    aux = np.round(rng.normal(25.0, 2.0, (n, n_aux)), 3)
    return RawBatch(t0_us + 1000 * np.arange(n), v, aux, AUX[:n_aux] if n_aux <= 2 else
                    tuple(f"c{i}" for i in range(n_aux)))


def _assert_same(a: RawBatch, b: RawBatch) -> None:
    """Bit-identical samples (so -0.0 and 0.0 differ) and the same channel names."""
    assert a.aux_names == b.aux_names
    np.testing.assert_array_equal(a.t_us, b.t_us)
    assert a.v.shape == b.v.shape and a.aux.shape == b.aux.shape
    assert np.array_equal(a.v.view(np.int64), b.v.view(np.int64))
    assert np.array_equal(a.aux.view(np.int64), b.aux.view(np.int64))


def _feed_split(parser: AsciiLineParser | CobsFrameParser, data: bytes,
                cuts: list[int]) -> RawBatch:
    pieces, last = [], 0
    for cut in [*sorted(c % (len(data) + 1) for c in cuts), len(data)]:
        pieces.append(parser.feed(data[last:cut]))
        last = cut
    # Positional names (aux0, ...) are placeholders until a header names the channels, and a
    # header names the whole stream: compare under the names the parser ends with.
    nonempty = [p for p in pieces if len(p)] or [pieces[-1]]
    names = parser.aux_names
    return RawBatch.concat([RawBatch(p.t_us, p.v, p.aux, names) for p in nonempty])


# --------------------------------------------------------------------------- ASCII basics


@pytest.mark.parametrize("header", [b"#t_us,x,y,z,temp_c,vdd_v\n", b"t_us,x,y,z,temp_c,vdd_v\n",
                                    b"# time , ax, ay, az, temp_c , vdd_v \r\n"])
def test_ascii_header_names_aux_channels(header: bytes) -> None:
    parser = AsciiLineParser()
    out = parser.feed(header + b"10,1,2,3,25.5,3.3\n20,-4,5.25,6e2,26,3.31\r\n")
    assert out.aux_names == ("temp_c", "vdd_v")
    np.testing.assert_array_equal(out.t_us, [10, 20])
    np.testing.assert_array_equal(out.v, [[1, 2, 3], [-4, 5.25, 600]])
    np.testing.assert_array_equal(out.channel("vdd_v"), [3.3, 3.31])
    assert parser.errors.header_lines == 1 and parser.errors.total == 0


def test_ascii_config_names_win_over_a_disagreeing_header() -> None:
    parser = AsciiLineParser(aux_names=("temperature",))
    out = parser.feed(b"#t_us,x,y,z,temperature\n1,1,2,3,20\n#t_us,x,y,z,other\n2,1,2,3,21\n")
    assert out.aux_names == ("temperature",) and len(out) == 2
    assert parser.errors.header_lines == 1 and parser.errors.header_mismatch == 1


def test_ascii_without_header_names_positionally_then_a_header_renames() -> None:
    parser = AsciiLineParser()
    first = parser.feed(b"1,1,2,3,20,3.3\n")
    assert first.aux_names == ("aux0", "aux1")
    second = parser.feed(b"t_us,x,y,z,temp_c,vdd_v\n2,1,2,3,21,3.3\n")
    assert second.aux_names == ("temp_c", "vdd_v") and len(second) == 1
    parser.feed(b"#t_us,x,y,z,a,b,c\n")  # a different layout mid-stream is not adopted
    assert parser.errors.header_mismatch == 1
    assert len(parser.feed(b"3,1,2,3,4,5,6\n")) == 0 and parser.errors.wrong_columns == 1


def test_ascii_no_aux_columns() -> None:
    out = AsciiLineParser().feed(b"#t_us,x,y,z\n5,1,2,3\n")
    assert out.aux.shape == (1, 0) and out.aux_names == ()


def test_ascii_comments_and_empty_lines_are_informational() -> None:
    parser = AsciiLineParser(AUX)
    out = parser.feed(b"# booting firmware 1.2\n\n\r\n1,1,2,3,4,5\n")
    assert len(out) == 1
    assert parser.errors.comment_lines == 1 and parser.errors.empty_lines == 2
    assert parser.errors.total == 0


@pytest.mark.parametrize(("line", "error"), [
    (b"1,nan,2,3,4,5", "non_finite"),
    (b"1,1,inf,3,4,5", "non_finite"),
    (b"1,1,2,3,-Infinity,5", "non_finite"),
    (b"1,1e400,2,3,4,5", "non_finite"),  # overflows to inf when parsed
    (b"1,2e9,2,3,4,5", "out_of_range"),
    (b"-1,1,2,3,4,5", "out_of_range"),
    (b"9223372036854775808,1,2,3,4,5", "out_of_range"),  # 2**63: not an int64
    (b"99999999999999999999999,1,2,3,4,5", "out_of_range"),
    (b"1.5,1,2,3,4,5", "non_numeric"),
    (b"1,1,2,3,4", "wrong_columns"),
    (b"1,1,2,3,4,5,6", "wrong_columns"),
    (b"1,1,2,,4,5", "non_numeric"),
    (b"1,1,2,3x,4,5", "non_numeric"),
    (b"1,1,2,1_0,4,5", "non_numeric"),
    (b"1,1,2,0x10,4,5", "non_numeric"),
    (b"1,1,2\xff\xfe,3,4,5", "non_utf8"),
    (b"1,1,2\x00,3,4,5", "garbage"),
    (b"1,1,2,3,4,5" + b"0" * 5000, "too_long"),
])
@pytest.mark.parametrize("vectorized", [True, False])
def test_ascii_bad_line_is_counted_and_neighbours_kept(line: bytes, error: str,
                                                       vectorized: bool) -> None:
    parser = AsciiLineParser(AUX, vectorized=vectorized, vectorize_min_lines=1)
    out = parser.feed(b"10,1,2,3,4,5\n" + line + b"\n20,1,2,3,4,5\n")
    np.testing.assert_array_equal(out.t_us, [10, 20])
    assert parser.errors.nonzero() == {error: 1}
    assert parser.errors.total == 1


def test_ascii_time_stamps_exact_beyond_float_precision() -> None:
    big = 2**62 + 1  # not representable as float64
    out = AsciiLineParser(AUX).feed(f"{big},1,2,3,4,5\n{2**63 - 1},1,2,3,4,5\n".encode())
    assert out.t_us.tolist() == [big, 2**63 - 1]


def test_ascii_max_abs_xyz_is_configurable() -> None:
    parser = AsciiLineParser((), max_abs_xyz=100.0)
    out = parser.feed(b"1,100,0,0\n2,-100.5,0,0\n3,0,0,1e3\n")
    assert out.t_us.tolist() == [1] and parser.errors.out_of_range == 2


def test_ascii_too_long_line_split_anywhere_is_counted_once_and_memory_stays_bounded() -> None:
    parser = AsciiLineParser(AUX, max_line_bytes=64)
    parser.feed(b"1,1,2,3,4,5\n")
    for _ in range(1000):  # 100 kB of a line that never ends
        parser.feed(b"1234567890" * 10)
        assert len(parser._pending) <= 64
    out = parser.feed(b"\n2,1,2,3,4,5\n")
    assert out.t_us.tolist() == [2] and parser.errors.too_long == 1


def test_ascii_partial_line_waits_for_its_end() -> None:
    parser = AsciiLineParser(AUX)
    assert len(parser.feed(b"1,1,2,3,4")) == 0
    assert parser.feed(b",5\n").t_us.tolist() == [1]


def test_ascii_flush_parses_an_unterminated_last_line() -> None:
    parser = AsciiLineParser(AUX)
    parser.feed(b"1,1,2,3,4,5\n2,1,2,3,4,5")
    assert parser.flush().t_us.tolist() == [2]
    assert len(parser.flush()) == 0


def test_ascii_reset_drops_the_partial_line_and_resyncs() -> None:
    parser = AsciiLineParser()
    parser.feed(b"#t_us,x,y,z,temp_c\n1,1,2,3,4\n2,1,2")
    parser.reset(resync=True)
    # The first line after a reset may be the tail of a line ("3,45,67" of "1003,45,67"):
    # dropped, not glued to the partial "2,1,2" and not taken as a sample.
    out = parser.feed(b"2,3,4\n5,1,2,3,4\n")
    assert out.t_us.tolist() == [5] and out.aux_names == ("temp_c",)
    assert parser.errors.truncated == 1 and parser.errors.resync_dropped == 1


def test_ascii_header_survives_resync_and_a_new_layout_is_learnt_after_reset() -> None:
    parser = AsciiLineParser()
    parser.feed(b"#t_us,x,y,z,temp_c\n1,1,2,3,4\n")
    parser.reset()
    out = parser.feed(b"#t_us,x,y,z,a,b\n2,1,2,3,4,5\n")
    assert out.aux_names == ("a", "b") and out.t_us.tolist() == [2]
    parser.reset()
    out = parser.feed(b"junk\n3,1,2,3\n")  # another device without header: no aux channels
    assert out.aux_names == () and out.t_us.tolist() == [3]


def test_ascii_crlf_and_spaces_around_fields() -> None:
    out = AsciiLineParser(AUX).feed(b"1, 1 ,2,3,4,5\r\n2,1,2,3,4,5\r\n")
    assert out.t_us.tolist() == [1, 2]


def test_ascii_garbage_storm_keeps_every_valid_sample_in_order() -> None:
    batch = _batch(500, counts=False, seed=1)
    lines = encode_ascii(batch, header=True).splitlines(keepends=True)
    rng = np.random.default_rng(2)
    junk = [b"\xff\xfe\x00\n", b"hello world\n", b"1,2\n", b"#\n", b",,,,,\n", b"nan\n",
            bytes(rng.integers(1, 256, 300, dtype=np.uint8)).replace(b"\n", b"") + b"?\n"]
    stream = lines[0] + b"".join(line + junk[i % len(junk)] for i, line in enumerate(lines[1:]))
    for vectorized in (True, False):
        parser = AsciiLineParser(vectorized=vectorized)
        _assert_same(parser.feed(stream), batch)
        assert parser.errors.total + parser.errors.comment_lines == 500  # "#" is a comment


def test_ascii_a_line_per_feed_gives_what_the_vectorized_path_gives() -> None:
    """A sensor read as it sends gives a line or two per feed, which take the per-line path
    (below ``vectorize_min_lines``): the same samples and counts as the stream vectorized."""
    batch = _batch(300, counts=False, seed=3)
    lines = encode_ascii(batch, header=True).splitlines(keepends=True)
    junk = [b"\xff\xfe\x00\n", b"hello world\n", b"1,2\n", b"5,nan,1,2,3,4\n", b"6,1,2\n"]
    stream = lines[0] + b"".join(line + junk[i % len(junk)] for i, line in enumerate(lines[1:]))
    whole = AsciiLineParser(vectorize_min_lines=1)
    expected = whole.feed(stream)
    few = AsciiLineParser()
    got = [few.feed(stream[i:i + 40]) for i in range(0, len(stream), 40)]
    _assert_same(RawBatch.concat([b for b in got if len(b)]), expected)
    assert few.errors == whole.errors and whole.errors.total == 300  # every junk line
    assert len(expected) == 300


def test_make_parser() -> None:
    assert isinstance(make_parser("ascii", AUX), AsciiLineParser)
    cobs_parser = make_parser("cobs", AUX, max_frame_bytes=100)
    assert isinstance(cobs_parser, CobsFrameParser) and cobs_parser.max_frame_bytes == 100
    with pytest.raises(ConfigError, match="unknown wire format"):
        make_parser("protobuf")


def test_parse_errors_arithmetic() -> None:
    errors = ParseErrors(garbage=2, header_lines=5)
    snapshot = errors.copy()
    errors.add("bad_crc", 3)
    assert errors.total == 5
    assert (errors - snapshot).nonzero() == {"bad_crc": 3}


# --------------------------------------------------------------------------- ASCII properties

_finite = st.floats(allow_nan=False, allow_infinity=False)
_finite32 = st.floats(allow_nan=False, allow_infinity=False, width=32)
_xyz32 = st.one_of(st.integers(-40000, 40000).map(float),
                   st.floats(-2e9, 2e9, allow_nan=False, width=32))
_xyz = st.floats(min_value=-1e9, max_value=1e9, allow_nan=False)


@st.composite
def _ascii_samples(draw: st.DrawFn, n_aux: int) -> RawBatch:
    n = draw(st.integers(0, 20))
    t = draw(st.lists(st.integers(0, 2**63 - 1), min_size=n, max_size=n))
    v = draw(st.lists(st.tuples(_xyz, _xyz, _xyz), min_size=n, max_size=n))
    aux = draw(st.lists(st.lists(_finite, min_size=n_aux, max_size=n_aux), min_size=n,
                        max_size=n))
    return RawBatch(np.array(t, np.int64), np.array(v).reshape(n, 3),
                    np.array(aux).reshape(n, n_aux), AUX[:n_aux])


@given(data=st.data(), n_aux=st.integers(0, 2), crlf=st.booleans())
@HYPOTHESIS
def test_ascii_round_trip_is_exact(data: st.DataObject, n_aux: int, crlf: bool) -> None:
    batch = data.draw(_ascii_samples(n_aux))
    encoded = encode_ascii(batch, header=True, line_ending="\r\n" if crlf else "\n")
    parser = AsciiLineParser()
    _assert_same(parser.feed(encoded), batch)
    assert parser.errors.total == 0


_junk_piece = st.one_of(
    st.binary(max_size=40),
    st.sampled_from([b"\n", b"\r\n", b"#t_us,x,y,z,temp_c,vdd_v\n", b"# comment\n",
                     b"1,nan,2,3,4,5\n", b"-5,1,2,3,4,5\n", b"1,1,2,3\n", b"1,2e10,1,1,1,1\n",
                     b"\xff\xfe\n", b"1.5,1,2,3,4,5\n", b"99999999999999999999,1,1,1,1,1\n",
                     b"7,1,2,3,4,5", b"0" * 250,
                     # pass the byte and comma checks of the fast path, fail np.fromstring
                     b"1,,2,3,4,5\n", b"1,2,3-4,5,6,7\n", b"1,e5,2,3,4,5\n", b"1.2.3,1,2,3,4,5\n",
                     b"1,2,3,4,5,6\r7\n", b"12345678901234567890,1,2,3,4,5\n", b"1e3,1,2,3,4,5\n",
                     b"9007199254740993,1,2,3,4,5\n", b"-0,1,2,3,4,5\n", b"1,.5,5.,+.5e-3,-0,1\n"]),
)


@st.composite
def _ascii_stream(draw: st.DrawFn) -> bytes:
    pieces = []
    for _ in range(draw(st.integers(0, 12))):
        if draw(st.booleans()):
            pieces.append(encode_ascii(draw(_ascii_samples(2))))
        else:
            pieces.append(draw(_junk_piece))
    return b"".join(pieces)


@given(stream=_ascii_stream(), cuts=st.lists(st.integers(0, 10**6), max_size=12),
       config=st.booleans(), resync=st.booleans())
@HYPOTHESIS
def test_ascii_split_anywhere_gives_identical_output_and_counts(
        stream: bytes, cuts: list[int], config: bool, resync: bool) -> None:
    def parser(vectorized: bool = True) -> AsciiLineParser:
        made = AsciiLineParser(AUX if config else None, max_line_bytes=200, vectorized=vectorized,
                               vectorize_min_lines=1)
        made.reset(resync=resync)
        return made

    whole_parser, split_parser, ref_parser = parser(), parser(), parser(vectorized=False)
    whole = whole_parser.feed(stream)
    _assert_same(_feed_split(split_parser, stream, cuts), whole)
    assert split_parser.errors == whole_parser.errors
    # The vectorized path agrees with the per-line reference path.
    _assert_same(ref_parser.feed(stream), whole)
    assert ref_parser.errors == whole_parser.errors


_plain_junk = st.sampled_from([
    b"1,e,2,3,4,5\n", b"1,1e,2,3,4,5\n", b"+1,1,2,3,4,5\n", b"1,1,2,3,4,5,\n", b",1,2,3,4,5\n",
    b"1,1.,.5,+.5E-3,-0,1\r\n", b"1,1,2,3,4\r5\n", b"1,--1,2,3,4,5\n", b"1,1,2,3,4,5\r\r\n",
    b"e,e,e,e,e,e\n", b"1,1,2,3,4,5e999\n", b"1,1e400,2,3,4,5\n", b"00,0,0,0,0,0\n"])


@given(pieces=st.lists(st.one_of(_ascii_samples(2).map(encode_ascii), _junk_piece, _plain_junk),
                       max_size=12),
       config=st.booleans(), resync=st.booleans())
@HYPOTHESIS
def test_ascii_one_line_per_feed_is_the_per_line_reference(
        pieces: list[bytes], config: bool, resync: bool) -> None:
    """A sensor handled as it sends gives the parser one line per call, which a settled
    layout reads the short way (`AsciiLineParser._one_settled`): the same samples and counts
    as the per-line reference path on the whole stream."""
    stream = b"".join(pieces)

    def parser(vectorized: bool = True) -> AsciiLineParser:
        made = AsciiLineParser(AUX if config else None, max_line_bytes=200, vectorized=vectorized)
        made.reset(resync=resync)
        return made

    one_parser, ref_parser = parser(), parser(vectorized=False)
    lines = [ln + b"\n" for ln in stream.split(b"\n")]
    lines[-1] = lines[-1][:-1]  # the unfinished tail, if any, as it came
    one = _feed_split(one_parser, stream, np.cumsum([len(ln) for ln in lines]).tolist())
    _assert_same(one, ref_parser.feed(stream))
    assert one_parser.errors == ref_parser.errors


@given(lines=st.lists(st.tuples(st.booleans(), st.binary(max_size=30)), max_size=30),
       cuts=st.lists(st.integers(0, 10**5), max_size=8))
@HYPOTHESIS
def test_ascii_every_valid_sample_after_garbage_lines_is_kept_once(
        lines: list[tuple[bool, bytes]], cuts: list[int]) -> None:
    parts, expected_t = [b"#t_us,x,y,z,temp_c,vdd_v\n"], []
    for i, (valid, junk) in enumerate(lines):
        if valid:
            parts.append(f"{i},1,-2,3.5,25,3.3\n".encode())
            expected_t.append(i)
        else:  # '?' makes sure the junk line is never a valid sample
            parts.append(junk.replace(b"\n", b"") + b"?\n")
    out = _feed_split(AsciiLineParser(), b"".join(parts), cuts)
    assert out.t_us.tolist() == expected_t


# --------------------------------------------------------------------------- COBS


def _frame(payload: bytes) -> bytes:
    return cobs.encode(payload) + b"\x00"


def _payload(t_us: int = 5, xyz: tuple[int, int, int] = (1, 2, 3), aux: tuple[float, ...] = (),
             *, version: int = 1, flags: int = 0, n_aux: int | None = None,
             crc: int | None = None) -> bytes:
    k = len(aux) if n_aux is None else n_aux
    body = bytes([version, flags, k]) + int(t_us).to_bytes(8, "little", signed=True)
    body += np.array(xyz, "<f4" if flags & COBS_FLAG_XYZ_FLOAT32 else "<i4").tobytes()
    body += np.array(aux, "<f4").tobytes()
    crc = binascii.crc_hqx(body, 0xFFFF) if crc is None else crc
    return body + crc.to_bytes(2, "little")


def test_cobs_payload_layout_is_as_documented() -> None:
    payload = _payload(t_us=0x0102030405060708, xyz=(-1, 0, 7), aux=(1.5,))
    assert len(payload) == cobs_payload_bytes(1) == 29
    encoded = encode_cobs(RawBatch([0x0102030405060708], [[-1, 0, 7]], [[1.5]], ("a",)))
    assert encoded == _frame(payload)
    assert encoded.count(b"\x00") == 1 and encoded.endswith(b"\x00")


def test_cobs_int32_round_trip_is_exact() -> None:
    batch = _batch(3000, seed=4)
    batch = RawBatch(batch.t_us, batch.v, batch.aux.astype(np.float32), AUX)
    parser = CobsFrameParser(AUX)
    _assert_same(parser.feed(encode_cobs(batch)), batch)
    assert parser.errors.total == 0


def test_cobs_float32_round_trip_at_float32_precision() -> None:
    batch = _batch(2000, counts=False, seed=5)
    out = CobsFrameParser(AUX).feed(encode_cobs(batch))
    np.testing.assert_array_equal(out.t_us, batch.t_us)
    np.testing.assert_array_equal(out.v, batch.v.astype(np.float32))
    np.testing.assert_array_equal(out.aux, batch.aux.astype(np.float32))


def test_cobs_without_names_learns_the_channel_count() -> None:
    out = CobsFrameParser().feed(_frame(_payload(aux=(1.0, 2.0, 3.0))))
    assert out.aux_names == ("aux0", "aux1", "aux2")


@pytest.mark.parametrize(("frame", "error"), [
    (_frame(_payload(crc=0x1234)), "bad_crc"),
    (_frame(_payload(aux=(1.0, 2.0))[:-7]), "bad_crc"),  # truncated payload
    (_frame(b"\x01\x00"), "bad_length"),
    (_frame(_payload(version=2, aux=(1.0, 2.0))), "bad_version"),
    (_frame(_payload(flags=0x80, aux=(1.0, 2.0))), "bad_version"),
    (_frame(_payload(n_aux=3, aux=(1.0, 2.0))), "bad_length"),
    (_frame(_payload(aux=(1.0,))), "wrong_columns"),
    (_frame(_payload(aux=(np.nan, 1.0))), "non_finite"),
    (_frame(_payload(xyz=(np.inf, 0, 0), flags=1, aux=(1.0, 2.0))), "non_finite"),
    (_frame(_payload(xyz=(2e9, 0, 0), flags=1, aux=(1.0, 2.0))), "out_of_range"),
    (_frame(_payload(t_us=-1, aux=(1.0, 2.0))), "out_of_range"),
    (b"\x05\x01\x02\x00", "garbage"),  # code byte claims more bytes than the frame has
    (b"\x07" * 600 + b"\x00", "too_long"),
])
@pytest.mark.parametrize("vectorized", [True, False])
def test_cobs_bad_frame_is_counted_and_neighbours_kept(frame: bytes, error: str,
                                                      vectorized: bool) -> None:
    parser = CobsFrameParser(AUX, vectorized=vectorized, vectorize_min_frames=1)
    good = [_frame(_payload(t_us=t, aux=(1.0, 2.0))) for t in (10, 20)]
    out = parser.feed(good[0] + frame + good[1])
    assert out.t_us.tolist() == [10, 20]
    assert parser.errors.nonzero() == {error: 1}


def test_cobs_idle_delimiters_are_not_errors() -> None:
    parser = CobsFrameParser(AUX)
    out = parser.feed(b"\x00\x00" + _frame(_payload(aux=(1.0, 2.0))) + b"\x00")
    assert len(out) == 1 and parser.errors.total == 0


def test_cobs_reset_counts_partial_frame_and_resync_is_quiet() -> None:
    parser = CobsFrameParser(AUX)
    frame = _frame(_payload(t_us=1, aux=(1.0, 2.0)))
    parser.feed(frame + frame[:10])
    parser.reset(resync=True)
    # Connected mid-frame: the tail before the first delimiter is not a CRC alarm.
    out = parser.feed(frame[15:] + _frame(_payload(t_us=2, aux=(1.0, 2.0))))
    assert out.t_us.tolist() == [2]
    assert parser.errors.nonzero() == {"truncated": 1, "resync_dropped": 1}
    parser.reset(resync=True)  # a whole first frame after a reset is kept
    assert parser.feed(frame).t_us.tolist() == [1]


@given(data=st.binary(max_size=200))
@HYPOTHESIS
def test_crc16_matches_binascii(data: bytes) -> None:
    rows = np.frombuffer(data, np.uint8).reshape(1, -1)
    assert int(crc16_ccitt_false(rows)[0]) == binascii.crc_hqx(data, 0xFFFF)


@st.composite
def _cobs_stream(draw: st.DrawFn) -> bytes:
    pieces = []
    for _ in range(draw(st.integers(0, 10))):
        kind = draw(st.integers(0, 3))
        n = draw(st.integers(0, 12))
        batch = RawBatch(draw(st.lists(st.integers(-5, 2**63 - 1), min_size=n, max_size=n)),
                         np.array(draw(st.lists(_xyz32, min_size=3 * n, max_size=3 * n))),
                         np.array(draw(st.lists(_finite32, min_size=2 * n, max_size=2 * n))),
                         AUX)
        encoded = encode_cobs(batch, xyz=draw(st.sampled_from(["auto", "float32"])))
        if kind == 1 and encoded:  # flip one bit somewhere
            i = draw(st.integers(0, len(encoded) - 1))
            encoded = encoded[:i] + bytes([encoded[i] ^ (1 << draw(st.integers(0, 7)))]) + \
                encoded[i + 1:]
        if kind == 2 and encoded:  # lose a slice
            i, j = sorted(draw(st.lists(st.integers(0, len(encoded)), min_size=2, max_size=2)))
            encoded = encoded[:i] + encoded[j:]
        pieces.append(encoded if kind != 3 else draw(st.binary(max_size=60)))
    return b"".join(pieces)


@given(stream=_cobs_stream(), cuts=st.lists(st.integers(0, 10**6), max_size=12),
       config=st.booleans(), resync=st.booleans())
@HYPOTHESIS
def test_cobs_split_anywhere_gives_identical_output_and_counts(
        stream: bytes, cuts: list[int], config: bool, resync: bool) -> None:
    def parser(vectorized: bool = True) -> CobsFrameParser:
        made = CobsFrameParser(AUX if config else None, max_frame_bytes=60,
                               vectorized=vectorized, vectorize_min_frames=1)
        made.reset(resync=resync)
        return made

    whole_parser, split_parser, ref_parser = parser(), parser(), parser(vectorized=False)
    whole = whole_parser.feed(stream)
    _assert_same(_feed_split(split_parser, stream, cuts), whole)
    assert split_parser.errors == whole_parser.errors
    _assert_same(ref_parser.feed(stream), whole)
    assert ref_parser.errors == whole_parser.errors


@given(valid=st.lists(st.booleans(), max_size=40), noise=st.binary(min_size=1, max_size=20),
       cuts=st.lists(st.integers(0, 10**5), max_size=8))
@HYPOTHESIS
def test_cobs_every_valid_frame_after_garbage_is_kept_once(
        valid: list[bool], noise: bytes, cuts: list[int]) -> None:
    parts, expected = [], []
    for i, ok in enumerate(valid):
        if ok:
            parts.append(_frame(_payload(t_us=i, aux=(1.0, 2.0))))
            expected.append(i)
        else:  # noise ended by a delimiter can corrupt only itself
            parts.append(noise + b"\x00")
    out = _feed_split(CobsFrameParser(AUX), b"".join(parts), cuts)
    assert out.t_us.tolist() == expected
