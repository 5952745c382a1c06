"""MCAP recordings: real files written, read back with the mcap reader, killed and repaired."""

from __future__ import annotations

import json
import os
import random
import select
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter

from recal.errors import RecordingError, UsageError
from recal.io import messages
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.io.repair import repair
from recal.samples import CalibratedBatch, RawBatch

T0_NS = 1_700_000_000_000_000_000


class FakeClock:
    """Monotonic seconds that only move when the test says so."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def _raw(i: int, n: int = 20, aux_names: tuple[str, ...] = ("temp_c",)) -> RawBatch:
    t_us = (i * n + np.arange(n, dtype=np.int64)) * 1000
    v = np.column_stack([np.full(n, float(i)), np.arange(n) * 0.5, -np.arange(n) * 1.0])
    return RawBatch(t_us, v, np.full((n, len(aux_names)), 25.0 + i), aux_names)


def _calibrated(i: int, n: int = 20) -> CalibratedBatch:
    t_us = (i * n + np.arange(n, dtype=np.int64)) * 1000
    a_g = np.tile([0.0, 0.0, 1.0], (n, 1)) + i * 1e-3
    return CalibratedBatch(t_us, a_g, np.arange(n) % 2 == 0, np.full(n, 0.01 * i))


def _writer(path: Path, **kwargs) -> RecordingWriter:
    kwargs.setdefault("background_flush", False)
    kwargs.setdefault("fsync", False)
    # one message per batch, as the file mechanics below count them (joining: its own tests)
    kwargs.setdefault("log_batch_samples", 1)
    return RecordingWriter(path, **kwargs)


def _all_messages(path: Path) -> list:
    with open(path, "rb") as f:
        return list(make_reader(f).iter_messages(log_time_order=False))


# ---------------------------------------------------------------------------------------------
# Layout and round trip
# ---------------------------------------------------------------------------------------------

def _write_full_session(path: Path) -> None:
    with _writer(path, metadata={"site": "lab"}) as w:
        w.write_event("started", T0_NS, detail={"version": "test"})
        for i in range(5):
            log_ns = T0_NS + (i + 1) * 20_000_000
            for sensor in ("s1", "s2"):
                w.write_raw(sensor, _raw(i), log_ns)
                w.write_calibrated(sensor, _calibrated(i), log_ns)
            w.write_calibrated("s1", _calibrated(i), log_ns, topic_suffix="body")
            w.write_plot("s1", _calibrated(i), log_ns, every_n=5)
        w.write_calibration("s1", {"t_us": 99_000, "params": np.array([1.0, np.nan]),
                                   "update_count": 3}, T0_NS + 200_000_000)
        w.write_event("clipped", T0_NS + 210_000_000, sensor_id="s2", t_us=5, detail="x axis")


def test_topics_schemas_and_encodings_follow_the_layout(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write_full_session(path)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    schemas = {s.id: s for s in summary.schemas.values()}
    layout = {c.topic: (schemas[c.schema_id].name, schemas[c.schema_id].encoding,
                        c.message_encoding) for c in summary.channels.values()}
    assert layout == {
        "/gateway/events": ("recal.Event", "jsonschema", "json"),
        "/s1/raw": ("recal.RawBatch", "protobuf", "protobuf"),
        "/s2/raw": ("recal.RawBatch", "protobuf", "protobuf"),
        "/s1/calibrated": ("recal.CalibratedBatch", "protobuf", "protobuf"),
        "/s2/calibrated": ("recal.CalibratedBatch", "protobuf", "protobuf"),
        "/s1/body": ("recal.CalibratedBatch", "protobuf", "protobuf"),
        "/s1/plot": ("recal.PlotSample", "protobuf", "protobuf"),
        "/s1/calibration": ("recal.CalibrationState", "jsonschema", "json"),
        "/s2/events": ("recal.Event", "jsonschema", "json"),
    }
    # Each schema once per file, and what Foxglove needs to decode it.
    assert len({s.name for s in schemas.values()}) == len(schemas)
    for schema in schemas.values():
        if schema.encoding == "protobuf":
            fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
            names = {f"{f.package}.{m.name}" for f in fds.file for m in f.message_type}
            assert schema.name in names
        else:
            assert json.loads(schema.data)["type"] == "object"
    assert summary.statistics is not None and len(summary.chunk_indexes) >= 1
    with open(path, "rb") as f:
        (meta,) = list(make_reader(f).iter_metadata())
    assert meta.name == "recal" and meta.metadata["site"] == "lab"
    assert meta.metadata["part"] == "0" and "version" in meta.metadata


def test_readers_give_back_what_was_written(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write_full_session(path)
    raw = list(rec.iter_raw(path))
    assert [s for s, _, _ in raw] == ["s1", "s2"] * 5
    for k, (_, batch, log_ns) in enumerate(raw):
        expected = _raw(k // 2)
        assert np.array_equal(batch.v, expected.v) and np.array_equal(batch.t_us, expected.t_us)
        assert batch.aux_names == ("temp_c",) and log_ns == T0_NS + (k // 2 + 1) * 20_000_000
    s2 = rec.read_all_raw(path, "s2")
    assert np.array_equal(s2.t_us, np.arange(100) * 1000)
    body = rec.read_all_calibrated(path, "s1", "body")
    assert np.array_equal(body.a_g, CalibratedBatch.concat([_calibrated(i)
                                                            for i in range(5)]).a_g)
    assert [s for s, _, _ in rec.iter_calibrated(path)] == ["s1", "s2"] * 5
    assert rec.sensors(path) == ["s1", "s2"]
    (state,) = list(rec.iter_json(path, "/*/calibration"))
    assert state[0] == "/s1/calibration" and state[1]["params"] == [1.0, None]
    events = [obj for _, obj, _ in rec.iter_json(path, "*/events")]
    assert [e["kind"] for e in events] == ["started", "clipped"]
    assert events[1] == {"t_us": 5, "kind": "clipped", "sensor_id": "s2", "detail": "x axis"}
    assert list(rec.iter_raw(path, "nobody")) == []


def test_times_and_sequences(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write_full_session(path)
    by_topic: dict[str, list] = {}
    for _, channel, message in _all_messages(path):
        by_topic.setdefault(channel.topic, []).append(message)
    raws = by_topic["/s1/raw"]
    assert [m.sequence for m in raws] == list(range(5))
    assert [m.publish_time for m in raws] == [i * 20 * 1000 * 1000 for i in range(5)]
    assert [m.log_time for m in raws] == [T0_NS + (i + 1) * 20_000_000 for i in range(5)]
    (state,) = by_topic["/s1/calibration"]
    assert state.publish_time == 99_000 * 1000
    (started,) = by_topic["/gateway/events"]
    assert started.publish_time == started.log_time == T0_NS


def test_plot_is_decimated_continuously_and_spread_in_log_time(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    sizes = [5, 7, 4, 9]
    with _writer(path) as w:
        start = 0
        for k, n in enumerate(sizes):
            t_us = start + np.arange(n, dtype=np.int64)
            batch = CalibratedBatch(t_us * 1000, np.ones((n, 3)), np.ones(n, bool), np.zeros(n))
            written = w.write_plot("s1", batch, T0_NS + k * 10**9, every_n=3)
            assert written == len(range((-start) % 3, n, 3))
            start += n
    plots = [(obj, log_ns) for _, obj, log_ns in rec.iter_plot(path, "s1")]
    assert [p["t_us"] // 1000 for p, _ in plots] == list(range(0, sum(sizes), 3))
    assert plots[0][0]["norm_g"] == pytest.approx(3 ** 0.5)
    # Within a batch, log times step back from the batch's log time by device time.
    first_batch = [log_ns for p, log_ns in plots if p["t_us"] < 5000]
    assert first_batch == [T0_NS - 4_000_000, T0_NS - 1_000_000]
    summary = rec.summary(path)
    assert summary.topics["/s1/plot"].sample_count == len(plots)


def test_summary_counts_messages_samples_and_times(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write_full_session(path)
    s = rec.summary(path)
    assert s.topics["/s1/raw"].message_count == 5
    assert s.topics["/s1/raw"].sample_count == 100
    assert (s.topics["/s2/raw"].first_t_us, s.topics["/s2/raw"].last_t_us) == (0, 99_000)
    assert s.topics["/s1/calibration"].sample_count == 0
    assert s.start_log_time_ns == T0_NS
    assert s.topics["/s1/plot"].first_log_time_ns == T0_NS + 20_000_000 - 19_000_000
    assert s.end_log_time_ns == T0_NS + 210_000_000
    assert s.message_count == len(_all_messages(path))
    assert s.sensors == ["s1", "s2"]


def test_unindexed_files_are_read_too(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f, use_chunking=False)
        w.start()
        sid = w.register_schema(messages.RAW_SCHEMA.name, "protobuf", messages.RAW_SCHEMA.data)
        cid = w.register_channel("/x1/raw", "protobuf", sid)
        for i in range(3):
            w.add_message(cid, T0_NS + i, messages.encode_raw("x1", _raw(i)), 0)
        w.finish()
    assert len(rec.read_all_raw(path, "x1")) == 60
    assert rec.summary(path).topics["/x1/raw"].message_count == 3


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_compressions_round_trip(tmp_path: Path, compression: str) -> None:
    path = tmp_path / f"{compression}.mcap"
    with _writer(path, compression=compression, chunk_size=4096) as w:
        for i in range(30):
            w.write_raw("s1", _raw(i), T0_NS + i)
    assert len(rec.read_all_raw(path, "s1")) == 600


def test_invalid_use_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with _writer(path) as w:
        for bad in ("", "gateway", "a/b", "-x", "a b"):
            with pytest.raises(UsageError, match="invalid sensor id"):
                w.write_raw(bad, _raw(0), T0_NS)
        with pytest.raises(ValueError, match="not JSON"):
            w.write_json("/s1/raw", {}, T0_NS)
        with pytest.raises(ValueError, match="reserved"):
            w.write_calibrated("s1", _calibrated(0), T0_NS, topic_suffix="raw")
        for topic in ("s1/notes", "/s1/", "/a/b/c", "/s1/no spaces"):
            with pytest.raises(ValueError, match="invalid topic"):
                w.write_json(topic, {}, T0_NS)
        w.write_json("/s1/notes", {"a": 1}, T0_NS)
        with pytest.raises(ValueError, match=r"carries recal\.Json"):
            w.write_encoded("/s1/notes", b"", T0_NS, schema=messages.RAW_SCHEMA)
        with pytest.raises(ValueError, match="unsigned"):
            w.write_raw("s1", _raw(0), -1)
    with pytest.raises(ValueError, match="closed"):
        w.write_raw("s1", _raw(0), T0_NS)
    with pytest.raises(FileExistsError):
        RecordingWriter(path)
    with pytest.raises(UsageError, match="compression"):
        RecordingWriter(tmp_path / "other.mcap", compression="gzip")  # type: ignore[arg-type]


def test_a_recording_that_cannot_be_used_as_asked_says_why(tmp_path: Path) -> None:
    """Errors a user can act on are recal.errors classes (the command line shows their text)."""
    path = tmp_path / "two.mcap"
    with _writer(path) as w:
        w.write_raw("s1", _raw(0), T0_NS)
        w.write_raw("s2", _raw(1), T0_NS + 1)
    assert rec.pick_sensor(path, rec.sensors(path), "s2") == "s2"
    with pytest.raises(RecordingError, match="several sensors"):
        rec.pick_sensor(path, rec.sensors(path), None)
    with pytest.raises(UsageError, match="is the input"):
        rec.refuse_input_as_output(path, path)


def test_reading_an_unfinished_file_says_to_repair(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write_full_session(path)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match="repair"):
        list(rec.iter_raw(cut))


# ---------------------------------------------------------------------------------------------
# Flushing
# ---------------------------------------------------------------------------------------------

def _recoverable(path: Path, tmp_path: Path) -> int:
    """Messages a crash right now would keep: repair a snapshot of the open file."""
    snapshot = tmp_path / "snapshot.mcap"
    snapshot.write_bytes(path.read_bytes())
    return repair(snapshot, tmp_path / "snapshot-fixed.mcap").messages_recovered


def test_flush_is_driven_by_the_injected_clock(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    clock = FakeClock()
    w = _writer(path, flush_interval_s=1.0, clock=clock)
    for i in range(5):
        w.write_raw("s1", _raw(i, n=5), T0_NS + i)  # small: stays in the open chunk
    assert w.messages_flushed == 0 and _recoverable(path, tmp_path) == 0
    clock.now_s += 0.99
    w.write_raw("s1", _raw(5, n=5), T0_NS + 5)
    assert w.flush_count == 0
    clock.now_s += 0.02
    w.write_raw("s1", _raw(6, n=5), T0_NS + 6)
    assert w.flush_count == 1 and w.messages_flushed == 7
    assert _recoverable(path, tmp_path) == 7
    w.write_raw("s1", _raw(7, n=5), T0_NS + 7)
    w.flush()
    assert w.flush_count == 2 and _recoverable(path, tmp_path) == 8
    w.flush()  # nothing new: no extra flush
    assert w.flush_count == 2
    w.close()
    assert len(_all_messages(path)) == 8


def test_background_thread_flushes_a_quiet_writer(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with RecordingWriter(path, flush_interval_s=0.05, fsync=True, log_batch_samples=1) as w:
        for i in range(3):
            w.write_raw("s1", _raw(i, n=5), T0_NS + i)
        deadline = time.monotonic() + 5.0
        while w.messages_flushed < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.messages_flushed == 3
        assert _recoverable(path, tmp_path) == 3


# ---------------------------------------------------------------------------------------------
# Rotation
# ---------------------------------------------------------------------------------------------

def _sequences_across(paths: list[Path]) -> list[int]:
    return [int(batch.v[0, 0]) for _, batch, _ in rec.iter_raw(paths)]


def test_rotation_by_size_loses_and_duplicates_nothing(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with _writer(path, rotate_bytes=20_000, chunk_size=4096, compression="none") as w:
        for i in range(200):
            w.write_raw("s1", _raw(i), T0_NS + i * 1000)
            if i % 10 == 0:
                w.write_event("tick", T0_NS + i * 1000, sensor_id="s1", t_us=i)
    parts = rec.recording_parts(path)
    assert parts == w.paths and len(parts) > 3
    assert parts[1].name == "rec-0001.mcap"
    assert _sequences_across(parts) == list(range(200))
    sequences = [m.sequence for p in parts for _, c, m in _all_messages(p)
                 if c.topic == "/s1/raw"]
    assert sequences == list(range(200))
    for part in parts:  # each part stands alone: indexed, with its own schemas and channels
        assert part.stat().st_size < 20_000 + 3 * 4096 + 4096
        assert rec.summary(part).topics["/s1/raw"].message_count > 0
    assert [e["t_us"] for _, e, _ in rec.iter_json(parts, "/s1/events")] == list(
        range(0, 200, 10))


def test_rotation_by_log_time(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with _writer(path, rotate_s=1.0) as w:
        for i in range(10):
            w.write_raw("s1", _raw(i), T0_NS + i * 250_000_000)
    parts = rec.recording_parts(path)
    counts = [rec.summary(p).message_count for p in parts]
    assert counts == [4, 4, 2]
    assert _sequences_across(parts) == list(range(10))


def test_overwrite_removes_stale_parts(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    with _writer(path, rotate_s=1.0) as w:
        for i in range(10):
            w.write_raw("s1", _raw(i), T0_NS + i * 500_000_000)
    assert len(rec.recording_parts(path)) == 5
    with _writer(path, overwrite=True) as w:
        w.write_raw("s1", _raw(0), T0_NS)
    assert rec.recording_parts(path) == [path]
    assert rec.summary(path).message_count == 1


# ---------------------------------------------------------------------------------------------
# Crash and repair
# ---------------------------------------------------------------------------------------------

_KILLED_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from recal.io.recording_writer import RecordingWriter
    from recal.samples import RawBatch

    w = RecordingWriter(sys.argv[1], flush_interval_s=0.1)
    n, i, reported = 50, 0, -1
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        t_us = (i * n + np.arange(n)) * 1000
        w.write_raw("s1", RawBatch(t_us, np.full((n, 3), float(i)), np.zeros((n, 0))),
                    time.time_ns())
        w.write_json("/s1/calibration", {"t_us": int(t_us[0]), "update_count": i},
                     time.time_ns())
        i += 1
        if w.flush_count != reported:
            reported = w.flush_count
            print(reported, w.messages_flushed, flush=True)
        time.sleep(0.0005)
""")


def test_sigkilled_writer_loses_at_most_the_last_flush_interval(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(path)],
                            stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    flushed = 0
    try:
        deadline = time.monotonic() + 15.0
        flushes = 0
        while flushes < 6 and time.monotonic() < deadline:
            ready, _, _ = select.select([proc.stdout], [], [], 0.5)
            if ready:
                line = proc.stdout.readline()  # type: ignore[union-attr]
                assert line, "writer exited early"
                flushes, flushed = map(int, line.split())
        assert flushes >= 6, "the writer did not flush in time"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        proc.stdout.close()  # type: ignore[union-attr]
    assert proc.returncode == -signal.SIGKILL
    fixed = tmp_path / "fixed.mcap"
    report = repair(path, fixed)
    assert report.truncated
    assert report.messages_recovered >= 0.99 * flushed > 0
    with open(fixed, "rb") as f:  # a valid, indexed file
        reader = make_reader(f)
        assert reader.get_summary() is not None
        assert sum(1 for _ in reader.iter_messages()) == report.messages_recovered
    # The writer joins a flush interval's batches into one message: the samples, whatever
    # the messages, are a prefix of what was written, whole batches, nothing missing inside.
    messages = [b for _, b, _ in rec.iter_raw(fixed)]
    values = np.concatenate([b.v[:, 0] for b in messages])
    assert len(values) % 50 == 0 and len(values) > 0
    assert np.array_equal(values, np.repeat(np.arange(len(values) // 50), 50))
    assert report.messages_per_topic["/s1/raw"] == len(messages)


@pytest.fixture(scope="module")
def good_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("good") / "good.mcap"
    with _writer(path, chunk_size=2048) as w:
        for i in range(60):
            w.write_raw("s1", _raw(i, n=10), T0_NS + i)
            w.write_calibration("s1", {"update_count": i}, T0_NS + i)
            if i % 7 == 0:
                w.flush()
    return path


def test_repairing_a_complete_file_copies_everything(good_file: Path, tmp_path: Path) -> None:
    report = repair(good_file, tmp_path / "copy.mcap")
    assert not report.truncated and report.error is None
    assert report.messages_per_topic == {"/s1/raw": 60, "/s1/calibration": 60}
    assert report.bytes_read == report.input_bytes == good_file.stat().st_size
    assert np.array_equal(rec.read_all_raw(tmp_path / "copy.mcap", "s1").v,
                          rec.read_all_raw(good_file, "s1").v)


def test_repair_at_random_truncations_is_monotone(good_file: Path, tmp_path: Path) -> None:
    data = good_file.read_bytes()
    rng = random.Random(7)
    offsets = sorted({*range(0, 12), *rng.sample(range(12, len(data)), 60), len(data)})
    cut, fixed = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"
    recovered = []
    for offset in offsets:
        cut.write_bytes(data[:offset])
        report = repair(cut, fixed)
        recovered.append(report.messages_recovered)
        assert report.bytes_read <= offset
        assert report.truncated == (offset < len(data))
        with open(fixed, "rb") as f:
            assert sum(1 for _ in make_reader(f).iter_messages()) == recovered[-1]
    assert recovered == sorted(recovered)
    assert recovered[0] == 0 and recovered[-1] == 120


def test_repair_refuses_a_file_that_is_not_mcap(tmp_path: Path) -> None:
    bogus = tmp_path / "bogus.mcap"
    bogus.write_bytes(b"hello, world, this is not mcap")
    with pytest.raises(RecordingError, match="not an MCAP"):
        repair(bogus, tmp_path / "out.mcap")
