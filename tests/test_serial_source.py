"""SerialSource over real pseudo-terminals (PtyDevice), and loop:// where a pty cannot do it."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from recal.io.ascii_lines import AsciiLineParser
from recal.io.cobs_frames import CobsFrameParser, encode_cobs
from recal.io.serial_source import EVENT_KINDS, SerialSource, SourceEvent
from recal.io.wire_formats import make_parser
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice

AUX = ("temp_c", "vdd_v")


def _batch(n: int, t0_us: int = 0, rate_hz: float = 1000.0) -> RawBatch:
    rng = np.random.default_rng(n + t0_us)
    t = t0_us + np.round(np.arange(n) * 1e6 / rate_hz).astype(np.int64)
    return RawBatch(t, rng.integers(-2048, 2048, (n, 3)).astype(float),
                    np.round(rng.normal(25, 1, (n, 2)), 2).astype(np.float32), AUX)


def _read_until(source: SerialSource, done: Callable[[RawBatch, list[SourceEvent]], bool],
                timeout_s: float = 5.0, poll: bool = False) -> tuple[RawBatch, list[SourceEvent]]:
    """read_batch(0.05) (or with ``poll``, poll(), which never waits, every 5 ms) until
    ``done(samples, events)`` or the timeout; bounded in time and in count."""
    batches: list[RawBatch] = []
    events: list[SourceEvent] = []
    deadline_s = time.monotonic() + timeout_s
    for _ in range(int(timeout_s / 0.005) + 1):
        batch, new_events = source.poll() if poll else source.read_batch(0.05)
        events += new_events
        if len(batch):
            batches.append(batch)
        if done(_concat(batches), events) or time.monotonic() > deadline_s:
            break
        if poll:
            time.sleep(0.005)
    return _concat(batches), events


def _concat(batches: list[RawBatch]) -> RawBatch:
    if not batches:
        return RawBatch.empty(AUX)
    names = batches[-1].aux_names
    return RawBatch.concat([RawBatch(b.t_us, b.v, b.aux, names) for b in batches])


def _kinds(events: list[SourceEvent]) -> list[str]:
    return [e.kind for e in events]


@pytest.fixture
def link(tmp_path: Path) -> str:
    return str(tmp_path / "ttyRECAL0")


@pytest.fixture
def ascii_device(link: str) -> Iterator[PtyDevice]:
    with PtyDevice(link, "ascii", header=True) as device:
        yield device


@pytest.mark.parametrize("fmt", ["ascii", "cobs"])
def test_reads_every_sample_over_a_pty(link: str, fmt: str) -> None:
    batch = _batch(2000)
    with PtyDevice(link, fmt) as device, \
            SerialSource(link, make_parser(fmt, None if fmt == "ascii" else AUX)) as source:
        first, events = source.read_batch(0.0)  # opens the port (the device sent nothing yet)
        assert _kinds(events) == ["port_opened"] and len(first) == 0
        # From a thread: a pty buffers only a few kB, so one big write would wait for us.
        device.start_streaming(batch, rate_hz=1e6)
        got, events = _read_until(source, lambda s, e: len(s) >= len(batch))
        assert device.join(2.0)
    assert got.aux_names == AUX
    np.testing.assert_array_equal(got.t_us, batch.t_us)
    np.testing.assert_array_equal(got.v, batch.v)
    np.testing.assert_array_equal(got.aux, batch.aux)
    assert events == [] and source.parser.errors.total == 0


def test_parse_errors_are_reported_as_deltas(ascii_device: PtyDevice, link: str) -> None:
    with SerialSource(link, AsciiLineParser()) as source:
        source.read_batch(0.0)
        ascii_device.write_batch(_batch(5))
        ascii_device.write_garbage(b"\xff\xfe\x00 noise\n1,2\n")
        ascii_device.write_batch(_batch(5, t0_us=10_000))
        got, events = _read_until(source, lambda s, e: len(s) >= 10)
        assert got.t_us.tolist() == [*range(0, 5000, 1000), *range(10_000, 15_000, 1000)]
        deltas = [e.detail for e in events if e.kind == "parse_errors"]
        assert sum(d.get("non_utf8", 0) for d in deltas) == 1
        assert sum(d.get("wrong_columns", 0) for d in deltas) == 1
        ascii_device.write_garbage(b"1,2\n")
        ascii_device.write_batch(_batch(1, t0_us=20_000))
        _, events = _read_until(source, lambda s, e: len(s) >= 1)
        assert [e.detail for e in events if e.kind == "parse_errors"] == [
            {"port": link, "wrong_columns": 1}]
        assert all(e.kind in EVENT_KINDS for e in events)


@pytest.mark.parametrize("fmt", ["ascii", "cobs"])
def test_unplug_and_replug_while_streaming_reconnects_and_carries_on(link: str, fmt: str) -> None:
    batch = _batch(3000, rate_hz=1000.0)  # 3 s of data streamed at 3x: about 1 s
    with PtyDevice(link, fmt) as device, SerialSource(link, make_parser(fmt, AUX)) as source:
        source.read_batch(0.0)
        device.start_streaming(batch, speedup=3.0)
        before, events = _read_until(source, lambda s, e: len(s) >= 300)
        device.unplug()
        lost, more = _read_until(source, lambda s, e: "port_lost" in _kinds(e), 2.0)
        events += more
        assert not os.path.exists(link)
        time.sleep(0.1)
        device.replug()
        replug_index = device.samples_streamed
        after, more = _read_until(
            source, lambda s, e: len(s) > 0 and s.t_us[-1] >= batch.t_us[-1], 5.0)
        events += more
        assert device.join(2.0)
    kinds = _kinds(events)
    assert "port_lost" in kinds and "port_found" in kinds
    assert kinds.index("port_lost") < kinds.index("port_found")
    everything = _concat([before, lost, after])
    assert np.all(np.diff(everything.t_us) > 0)  # in order, nothing twice
    assert np.isin(everything.t_us, batch.t_us).all()  # nothing glued or invented
    assert after.t_us[-1] == batch.t_us[-1]
    assert np.count_nonzero(after.t_us > batch.t_us[replug_index]) > 100


@pytest.mark.parametrize("fmt", ["ascii", "cobs"])
def test_a_partial_line_before_an_unplug_is_dropped_not_glued(link: str, fmt: str) -> None:
    parser = make_parser(fmt, AUX)
    with PtyDevice(link, fmt) as device, SerialSource(link, parser) as source:
        source.read_batch(0.0)
        device.write_batch(_batch(5))
        device.write_garbage(b"12345,1,2" if fmt == "ascii" else b"\x05\x01\x02")
        got, _ = _read_until(source, lambda s, e: len(s) >= 5)
        source.read_batch(0.05)  # the half line is now the parser's pending tail
        device.unplug()
        _, events = _read_until(source, lambda s, e: "port_lost" in _kinds(e), 2.0)
        device.replug()
        _, more = _read_until(source, lambda s, e: "port_found" in _kinds(e), 2.0)
        events += more
        device.write_batch(_batch(5, t0_us=100_000))  # the device booted: header first
        after, more = _read_until(source, lambda s, e: len(s) >= 5)
        events += more
    assert got.t_us.tolist() == list(range(0, 5000, 1000))
    assert after.t_us.tolist() == list(range(100_000, 105_000, 1000))
    assert parser.errors.nonzero() == ({"truncated": 1, "header_lines": 2} if fmt == "ascii"
                                       else {"truncated": 1})
    assert {"port": link, "truncated": 1} in [e.detail for e in events
                                              if e.kind == "parse_errors"]


def test_open_failures_back_off_exponentially_then_the_device_appears(link: str) -> None:
    source = SerialSource(link, AsciiLineParser(AUX), backoff_initial_s=0.02, backoff_max_s=0.08)
    with source:
        _, events = source.read_batch(0.5)
        failed = [e for e in events if e.kind == "open_failed"]
        assert 4 <= len(failed) <= 12
        assert [e.detail["retry_in_s"] for e in failed[:5]] == [0.02, 0.04, 0.08, 0.08, 0.08]
        assert [e.detail["attempt"] for e in failed[:3]] == [1, 2, 3]
        with PtyDevice(link, "ascii") as device:
            _, events = _read_until(source, lambda s, e: "port_opened" in _kinds(e), 2.0)
            assert source.is_open
            device.write_batch(_batch(10))
            got, _ = _read_until(source, lambda s, e: len(s) >= 10)
            assert len(got) == 10


def test_a_link_pointing_at_another_device_is_noticed(link: str, tmp_path: Path) -> None:
    with PtyDevice(link, "ascii") as first, \
            PtyDevice(str(tmp_path / "other"), "ascii") as second, \
            SerialSource(link, AsciiLineParser(AUX), path_check_interval_s=0.02) as source:
        source.read_batch(0.0)
        first.write_batch(_batch(3))
        _read_until(source, lambda s, e: len(s) >= 3)
        os.replace(tmp_path / "other", link)  # first is still alive, but the path moved on
        _, events = _read_until(source, lambda s, e: "port_found" in _kinds(e), 3.0)
        assert "port_lost" in _kinds(events)
        second.write_batch(_batch(3, t0_us=50_000))
        got, _ = _read_until(source, lambda s, e: len(s) >= 3)
        assert got.t_us.tolist() == [50_000, 51_000, 52_000]


def test_loop_url_and_commands() -> None:
    # loop:// echoes what is written: a pty has no way to talk back to itself.
    with SerialSource("loop://", CobsFrameParser(AUX)) as source:
        source.read_batch(0.0)
        assert source.write(encode_cobs(_batch(20))) > 0
        got, events = _read_until(source, lambda s, e: len(s) >= 20)
        assert len(got) == 20 and events == []


def test_close_stops_everything(ascii_device: PtyDevice, link: str) -> None:
    source = SerialSource(link, AsciiLineParser(AUX))
    source.read_batch(0.0)
    assert source.is_open
    source.close()
    started_s = time.monotonic()
    batch, events = source.read_batch(1.0)
    assert len(batch) == 0 and events == [] and time.monotonic() - started_s < 0.5
    assert source.write(b"x") == 0


def test_pty_writes_give_up_when_nobody_reads(link: str) -> None:
    with PtyDevice(link, "ascii", write_timeout_s=0.2) as device:
        started_s = time.monotonic()
        written = device.write_garbage(b"x" * 4_000_000)
        assert time.monotonic() - started_s < 2.0
        assert 0 < written < 4_000_000 and device.bytes_dropped == 4_000_000 - written
        device.unplug()
        assert device.write_batch(_batch(3)) == 0  # unplugged: nobody hears it


def test_streaming_stops_on_request(link: str) -> None:
    with PtyDevice(link, "cobs", write_timeout_s=0.05) as device:
        device.start_streaming(_batch(100_000), rate_hz=1000.0)  # 100 s if left alone
        time.sleep(0.05)
        assert device.streaming
        device.stop()
        assert device.join(2.0) and not device.streaming
        assert device.samples_streamed < 100_000


def test_pty_is_raw_bytes_pass_unchanged(link: str) -> None:
    with PtyDevice(link, "ascii") as device, \
            SerialSource(link, AsciiLineParser(AUX)) as source:
        source.read_batch(0.0)
        # CR LF, bare CR and DEL would be translated or echoed by a cooked tty.
        device.write_garbage(b"#t_us,x,y,z,temp_c,vdd_v\r\n1,1,2,3,4,5\r\n\x7f\n2,1,2,3,4,5\n")
        got, events = _read_until(source, lambda s, e: len(s) >= 2)
        assert got.t_us.tolist() == [1, 2]
        assert [e.detail for e in events if e.kind == "parse_errors"] == [
            {"port": link, "garbage": 1}]
        assert source.parser.errors.empty_lines == 0  # no CR -> LF translation happened


# --------------------------------------------------------------------------- non-blocking poll


@pytest.mark.parametrize("fmt", ["ascii", "cobs"])
def test_poll_opens_reads_what_is_waiting_and_never_waits(link: str, fmt: str) -> None:
    sent = _batch(300)
    with PtyDevice(link, fmt) as device, \
            SerialSource(link, make_parser(fmt, AUX), read_timeout_s=5.0) as source:
        assert source.fileno() is None
        first, events = source.poll()  # opens; nothing is waiting yet
        assert len(first) == 0 and _kinds(events) == ["port_opened"]
        fd = source.fileno()
        assert isinstance(fd, int) and not os.get_blocking(fd)
        # With a 5 s pyserial timeout, a poll that read through pyserial (or waited for a
        # first byte) would take 5 s; 20 empty polls must all come back at once.
        started_s = time.monotonic()
        for _ in range(20):
            assert len(source.poll()[0]) == 0
        assert time.monotonic() - started_s < 2.0
        if fmt == "ascii":  # a header line ends the resync of a freshly opened port
            device.write_header(AUX)
        parts: list[RawBatch] = []
        for i in range(0, len(sent), 7):  # many small writes, read as they come (reading
            device.write_batch(sent[i:i + 7])  # only at the end can fill the pty under load)
            parts.append(source.poll()[0])
        rest, _ = _read_until(source, lambda s, e: sum(map(len, parts)) + len(s) >= len(sent),
                              poll=True)
        got = _concat([*parts, rest])
        assert device.bytes_dropped == 0
    np.testing.assert_array_equal(got.t_us, sent.t_us)
    np.testing.assert_array_equal(got.v, sent.v)


def test_poll_notices_an_unplug_and_reopens_after_a_replug(link: str) -> None:
    with PtyDevice(link, "ascii") as device, \
            SerialSource(link, AsciiLineParser(AUX), backoff_initial_s=0.02) as source:
        source.poll()
        device.write_header(AUX)
        device.write_batch(_batch(10))
        got, _ = _read_until(source, lambda s, e: len(s) >= 10, poll=True)
        assert len(got) == 10
        device.unplug()
        _, events = source.poll(readable=True)  # the selector reports a hung-up tty readable
        assert _kinds(events) == ["port_lost"] and source.fileno() is None
        device.replug()
        later = _batch(5, t0_us=10_000_000)
        _, events = _read_until(source, lambda s, e: "port_found" in _kinds(e), poll=True)
        assert "port_found" in _kinds(events) and source.fileno() is not None
        device.write_header(AUX)
        device.write_batch(later)
        got, _ = _read_until(source, lambda s, e: len(s) >= 5, poll=True)
    np.testing.assert_array_equal(got.t_us, later.t_us)


def test_write_nowait_never_blocks_and_reports_what_fit(link: str) -> None:
    with PtyDevice(link, "ascii") as device:
        assert device.write_nowait(b"1,2,3,4\n") == 8
        # nobody reads: the pty fills up, and then a write takes nothing instead of waiting
        taken = [device.write_nowait(b"x" * 65536) for _ in range(1000)]
        assert 0 in taken and 0 < sum(taken) < 1000 * 65536
        device.unplug()
        assert device.write_nowait(b"gone") == 0
