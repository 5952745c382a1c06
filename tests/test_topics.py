"""The topic registry (recal.io.topics): the one table the bus, the recording writer and
reader, the sinks and the gateway read; an unknown topic fails where it is first resolved."""

from __future__ import annotations

import ast
import socket
from pathlib import Path

import numpy as np
import pytest

from recal.errors import RecalError
from recal.io import bus_keys, messages, topics
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.node.sinks import BusSink, LoggedBusSink, NullSink, RecordingSink, make_sink
from recal.samples import CalibratedBatch

SERVICE = Path(__file__).resolve().parents[1] / "service" / "recal"
SID = "s1"


def _calibrated(n: int = 5) -> CalibratedBatch:
    t_us = np.arange(n, dtype=np.int64) * 10_000
    return CalibratedBatch(t_us, np.tile([0.0, 0.0, 1.0], (n, 1)), np.ones(n, bool),
                           np.full(n, 0.01))


def _writer(path: Path) -> RecordingWriter:
    return RecordingWriter(path, background_flush=False, fsync=False)


# suffix: (payload, log schema, published, queryable, live, node output): the layout the bus,
# the writer, the sinks and the gateway each spelt out before the registry
_LAYOUT = {
    "raw": ("raw", messages.RAW_SCHEMA, True, False, True, True),
    "calibrated": ("calibrated", messages.CALIBRATED_SCHEMA, True, False, True, True),
    "body": ("calibrated", messages.CALIBRATED_SCHEMA, True, False, True, True),
    "calibration": ("json", messages.CALIBRATION_STATE_SCHEMA, True, False, False, True),
    "status": ("query", None, False, True, False, False),
    "events": ("json", messages.EVENT_SCHEMA, True, False, False, True),
    "align": ("query", None, False, True, False, False),
    "plot": ("plot", messages.PLOT_SCHEMA, False, False, False, True),
    "setup": ("json", messages.GENERIC_JSON_SCHEMA, False, False, False, True),
}


def test_the_registry_gives_the_layout_every_component_used_to_spell_out() -> None:
    for name, expected in _LAYOUT.items():
        t = topics.topic(name)
        assert (t.payload, t.schema, t.published, t.queryable, t.live, t.node_output) == \
            expected, name
    # the sets the components read, in the table's order where order is kept
    old_keys = ("raw", "calibrated", "body", "calibration", "status", "events", "align")
    assert [k for k in bus_keys.TOPICS if k in _LAYOUT] == list(old_keys)
    assert {"status", "align"} <= bus_keys.QUERYABLE_TOPICS
    assert [k for k in topics.live_topics() if k in _LAYOUT] == ["raw", "calibrated", "body"]
    for t in topics.TOPICS.values():  # a query topic is answered, never logged nor streamed
        assert (t.payload == "query") == (t.queryable and not t.logged and not t.published)
        assert t.on_bus == (t.suffix in bus_keys.TOPICS)
        assert topics.log_schemas().get(t.suffix) is t.schema


def test_an_unknown_topic_is_a_recal_error_naming_the_known_ones() -> None:
    with pytest.raises(topics.UnknownTopicError) as err:
        topics.topic("no_such_topic")
    assert isinstance(err.value, RecalError) and isinstance(err.value, ValueError)
    for name in topics.TOPICS:
        assert name in str(err.value)
    with pytest.raises(topics.UnknownTopicError, match="calibrated topic 'raw'"):
        topics.require(["calibrated", "raw"], "calibrated")


def test_a_bus_key_exists_for_bus_topics_only() -> None:
    assert bus_keys.key(SID, "events") == "recal/s1/events"
    assert bus_keys.parse_key("recal/s1/align") == (SID, "align")
    for name in ("plot", "setup", "nope"):  # log only, or unknown
        with pytest.raises(topics.UnknownTopicError, match="known: raw, calibrated"):
            bus_keys.key(SID, name)
        with pytest.raises(topics.UnknownTopicError):
            bus_keys.parse_key(f"recal/{SID}/{name}")


def test_a_sink_refuses_an_unknown_topic_before_logging_anything(tmp_path: Path) -> None:
    path = tmp_path / "out.mcap"
    with _writer(path) as w:
        sink = RecordingSink(w)
        sink.calibrated(SID, _calibrated(), 1_000)
        with pytest.raises(topics.UnknownTopicError, match="unknown topic 'nope'"):
            sink.calibrated(SID, _calibrated(), 2_000, "nope")
        with pytest.raises(topics.UnknownTopicError, match="calibrated topic 'events'"):
            sink.calibrated(SID, _calibrated(), 2_000, "events")
        with pytest.raises(topics.UnknownTopicError, match="unknown topic 'notes'"):
            sink.json(SID, "notes", {"t_us": 1}, 3_000)
        sink.json(SID, "setup", {"t_us": 1}, 3_000)
    assert set(rec.summary(path).topics) == {"/s1/calibrated", "/s1/setup"}
    assert [m.schema_name for m in rec.iter_messages(path, "/s1/setup")] == ["recal.Json"]


def test_the_reader_resolves_its_batch_topic_at_the_call(tmp_path: Path) -> None:
    missing = tmp_path / "never-written.mcap"  # not opened: the topic fails first
    with pytest.raises(topics.UnknownTopicError):
        rec.iter_calibrated(missing, SID, topic_suffix="raw")
    with pytest.raises(topics.UnknownTopicError):
        rec.iter_calibrated(missing, SID, topic_suffix="bodyx")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_make_sink_wires_a_recording_a_bus_both_or_neither(tmp_path: Path) -> None:
    from recal.io.bus import Bus
    from recal.io.bus_config import loopback_endpoint, zenoh_config

    assert isinstance(make_sink(None, None), NullSink)
    with _writer(tmp_path / "a.mcap") as w, Bus(zenoh_config(
            mode="peer", listen=[loopback_endpoint(_free_port())])) as bus:
        only_log = make_sink(w, None)
        assert type(only_log) is RecordingSink
        only_bus = make_sink(None, bus)
        assert type(only_bus) is BusSink
        both = make_sink(w, bus)
        assert type(both) is LoggedBusSink
        received = bus.receiver(bus_keys.key_pattern("events"), capacity=8)
        assert bus.publisher(bus_keys.key(SID, "events")).wait_for_subscribers(5.0)
        both.json(SID, "setup", {"t_us": 1}, 1_000)  # log only: not published
        both.json(SID, "events", {"t_us": 2, "kind": "k"}, 2_000)
        got = received.recv(timeout=5.0)
        assert got is not None and got.key == "recal/s1/events"
        assert messages.decode_json(got.payload)["kind"] == "k"
        assert received.recv(timeout=0.2) is None
        with pytest.raises(topics.UnknownTopicError):
            only_bus.calibrated(SID, _calibrated(), 3_000, "nope")
        assert isinstance(only_bus, BusSink) and only_bus.dropped == 0


def _sink_suffixes(path: Path) -> set[str]:
    """The suffixes a module hands a sink as literals (``sink.json(sid, "events", ...)``,
    ``sink.calibrated(sid, batch, log_ns, "body")``)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in ("json", "calibrated")
                and isinstance(node.func.value, ast.Attribute)
                and node.func.value.attr == "sink"):
            found |= {a.value for a in node.args
                      if isinstance(a, ast.Constant) and isinstance(a.value, str)}
    return found


def test_every_topic_a_node_hands_its_sink_is_a_registered_output() -> None:
    """The node names its outputs as literals: each is among those it declares (``EMITS``,
    checked against the registry when the node module loads, so a process with an
    unregistered one stops at start), and each is a registered node output."""
    from recal.node.node import EMITS

    suffixes = set()
    for path in [*(SERVICE / "node").glob("*.py"), SERVICE / "daemon" / "remote_node.py"]:
        suffixes |= _sink_suffixes(path)
    declared = {name for names in EMITS.values() for name in names}
    assert {"setup", "calibration", "events"} <= suffixes
    assert suffixes <= declared, suffixes - declared
    assert declared <= set(topics.node_outputs()), declared - set(topics.node_outputs())
    for payload, names in EMITS.items():
        assert all(topics.topic(n).payload == payload for n in names), (payload, names)
