"""The wire-format registry: every format it lists goes from its device-side encoder through a
real pty to its parser unchanged, and the config, the pty device and the parser protocol ask
the registry instead of naming formats."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from recal.config import FORMATS, SensorConfig, parse_config
from recal.errors import ConfigError, UsageError
from recal.io.frames import DelimitedParser, DeviceStyle
from recal.io.serial_source import SerialSource
from recal.io.wire_formats import DEFAULT_FORMAT, WIRE_FORMATS, make_parser, wire_format
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice

NAMES = sorted(WIRE_FORMATS)


def _plain_batch(n: int, t0_us: int = 1_000_000) -> RawBatch:
    """Samples every format can carry: small integer counts, no auxiliary channel, times
    below 2**32 us (the narrowest fields a binary format may choose)."""
    rng = np.random.default_rng(n)
    t_us = t0_us + 10_000 * np.arange(n, dtype=np.int64)
    return RawBatch(t_us, rng.integers(-2000, 2000, (n, 3)).astype(float), np.zeros((n, 0)), ())


def _read(source: SerialSource, want: int, timeout_s: float = 5.0) -> RawBatch:
    """Poll until ``want`` samples came or the timeout; bounded in count and in time."""
    got: list[RawBatch] = []
    deadline_s = time.monotonic() + timeout_s
    for _ in range(int(timeout_s / 0.005) + 1):
        batch, _events = source.poll()
        if len(batch):
            got.append(batch)
        if sum(map(len, got)) >= want or time.monotonic() > deadline_s:
            break
        time.sleep(0.005)
    return RawBatch.concat(got) if got else RawBatch.empty()


@pytest.mark.parametrize("name", NAMES)
def test_every_format_round_trips_through_a_real_pty(tmp_path: Path, name: str) -> None:
    link = str(tmp_path / "tty")
    first, sent = _plain_batch(1, t0_us=600_000), _plain_batch(50)
    parser = make_parser(name)
    with PtyDevice(link, name) as device, SerialSource(link, parser) as source:
        source.open_now()
        device.write_batch(first)  # (after the boot header, where the format has one)
        device.write_batch(sent)
        got = _read(source, 1 + len(sent))
    np.testing.assert_array_equal(got.t_us, np.concatenate((first.t_us, sent.t_us)))
    np.testing.assert_array_equal(got.v, np.concatenate((first.v, sent.v)))
    assert parser.errors.total == 0


@pytest.mark.parametrize("name", NAMES)
def test_each_format_declares_itself_under_its_name(name: str) -> None:
    wire = wire_format(name)
    assert wire.name == name
    parser = wire.parser(None)
    assert isinstance(parser, DelimitedParser)  # the shared byte stream and the protocol
    record = wire.encode(_plain_batch(1), DeviceStyle())
    assert record and not parser.partial
    parser.feed(record[:-1])  # all but the delimiter: a record waiting for its end
    assert parser.partial
    assert not parser.needs_time_anchor  # no rate given: nothing to stamp


def test_the_config_takes_its_formats_and_default_from_the_registry() -> None:
    assert FORMATS == tuple(WIRE_FORMATS)
    assert SensorConfig(id="s").format == DEFAULT_FORMAT
    cfg = parse_config({"sensors": [{"id": "s", "port": "/dev/null-not-checked"}]},
                       Path("."), "test")
    assert cfg.sensors[0].format == DEFAULT_FORMAT
    with pytest.raises(ConfigError, match="format"):
        parse_config({"sensors": [{"id": "s", "format": "protobuf"}]}, Path("."), "test")


def test_an_unknown_format_names_the_known_ones() -> None:
    with pytest.raises(ConfigError) as err:
        wire_format("protobuf")
    assert all(repr(n) in str(err.value) for n in WIRE_FORMATS)
    with pytest.raises(UsageError, match="unknown wire format 'protobuf'"):
        PtyDevice("/nonexistent/never-made", "protobuf")


def test_the_rate_reaches_only_a_parser_that_stamps_records_by_it() -> None:
    for name, wire in WIRE_FORMATS.items():
        parser = make_parser(name, rate_hz=100.0)  # no TypeError for a format without
        assert getattr(parser, "rate_hz", None) == (100.0 if wire.untimed_by_rate else None)
    ascii_parser = make_parser("ascii", rate_hz=100.0)
    assert ascii_parser.needs_time_anchor  # lines without time may come: the shell anchors
    ascii_parser.anchor_time(5_000_000)
    assert not ascii_parser.needs_time_anchor
    batch = ascii_parser.feed(b"x,y,z\n1,2,3\n4,5,6\n")
    assert batch.t_us.tolist() == [5_000_000, 5_010_000]


@pytest.mark.parametrize("name", NAMES)
def test_the_device_offers_what_the_format_has(tmp_path: Path, name: str) -> None:
    wire = wire_format(name)
    if not wire.untimed_by_rate:
        with pytest.raises(UsageError, match="clock"):
            PtyDevice(str(tmp_path / "tty"), name, clock="none")
    with PtyDevice(str(tmp_path / "tty"), name) as device:
        if wire.header is None:
            with pytest.raises(UsageError, match="no header"):
                device.write_header(())
        else:
            assert device.write_header(()) > 0
