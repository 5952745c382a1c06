"""Replay joins a recording's messages into bigger pipeline steps; the output must not change.

The pipeline is batch-size invariant, and `Pipeline.step_many` reports the state as of each
joined message's end, so `CalibrationNode.process_many` (and replay, which uses it) must
give, message for message, exactly what `process` gives one message at a time: the same
calibrated and body batches, plot samples, events and calibration states, with the same times.
"""

from __future__ import annotations

import json
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from recal.commands import replay as replay_mod
from recal.config import PipelineSection, PriorConfig, SensorConfig, model_and_prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.io import recording as rec
from recal.io.messages import encode_json
from recal.io.recording_writer import RecordingWriter
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import CalibratedBatch, RawBatch
from recal.sim.wearer import SensorSpec, WearerSpec, simulate

RATE_HZ = 50.0
SID = "s1"
T0_NS = 1_700_000_000_000_000_000


def _raw(minutes: float, seed: int) -> RawBatch:
    # short stills and moves: many windows, updates, alignment attempts in a short recording
    spec = SensorSpec.random(np.random.default_rng(seed), offset_mg=40.0, gain_pct=3.0)
    wearer = WearerSpec(still_s=(4.0, 25.0), move_s=(1.0, 5.0), p_upright=0.5, p_lying=0.3,
                        p_any=0.2)
    return simulate(minutes / 60.0, RATE_HZ, seed, spec, wearer).raw


def _messages(raw: RawBatch, rng: np.random.Generator, largest: int) -> list[tuple[RawBatch,
                                                                                    int]]:
    ends = np.cumsum(rng.integers(1, largest + 1, size=len(raw)))
    ends = [0, *ends[ends < len(raw)].tolist(), len(raw)]
    return [(raw[a:b], T0_NS + int(raw.t_us[a]) * 1000) for a, b in pairwise(ends)]


class Recorder:
    """A sink that keeps every call, in order, in comparable form."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    @staticmethod
    def _batch(b: CalibratedBatch) -> tuple:
        return (b.t_us.tobytes(), b.a_g.tobytes(), b.quasi_static.tobytes(),
                b.detector_g.tobytes())

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        self.calls.append(("raw", sensor_id, log_time_ns))

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        self.calls.append((suffix, sensor_id, log_time_ns, self._batch(batch)))

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        self.calls.append(("plot", sensor_id, log_time_ns, every_n, self._batch(batch)))

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        self.calls.append((suffix, sensor_id, log_time_ns, encode_json(obj)))


def _node(prior: bool, sink: Recorder) -> CalibrationNode:
    settings = PipelineSection()
    sensor = SensorConfig(id=SID, prior=PriorConfig(counts_per_g=1024.0) if prior
                          else PriorConfig())
    model, p = model_and_prior(sensor, settings)
    return CalibrationNode(NodeSettings(SID, settings, model, p, RATE_HZ), sink)


@pytest.mark.parametrize("prior, largest, seed", [(True, 60, 1), (False, 400, 2)])
def test_process_many_gives_what_process_gives_message_by_message(prior: bool, largest: int,
                                                                   seed: int) -> None:
    raw = _raw(25.0, seed)
    rng = np.random.default_rng(seed)
    msgs = _messages(raw, rng, largest)
    one, joined = Recorder(), Recorder()
    a, b = _node(prior, one), _node(prior, joined)
    for batch, log_ns in msgs:
        a.process(batch, log_ns)
    i = 0
    while i < len(msgs):  # random groups, from single messages to hundreds
        k = int(rng.integers(1, 300))
        b.process_many(msgs[i:i + k])
        i += k
    kinds = [c[0] for c in one.calls]
    # the recording exercised what can differ: updates, states, alignment and body output
    assert a.pipeline is not None and a.pipeline.counts["updates"] >= 20
    assert kinds.count("calibration") >= 20 and "body" in kinds
    assert any(c[0] == "events" and b'"alignment"' in c[3] for c in one.calls)
    assert len(joined.calls) == len(one.calls)
    for x, y in zip(one.calls, joined.calls, strict=True):
        assert x == y
    assert json.dumps(a.checkpoint()["pipeline"]) == json.dumps(b.checkpoint()["pipeline"])


def test_step_many_reports_the_state_after_each_message() -> None:
    raw = _raw(15.0, 3)
    model = SensorModel.diagonal(1024.0)
    rng = np.random.default_rng(3)
    msgs = [m for m, _ in _messages(raw, rng, 700)]
    ends = np.cumsum([len(m) for m in msgs]).tolist()
    seq = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, None, ())
    expected = {}
    for m, end in zip(msgs, ends, strict=True):
        if seq.step(m).updates:
            expected[end] = encode_json(seq.summary())
    joined = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, None, ())
    got = {}
    for lo in range(0, len(msgs), 7):  # 7 messages per step
        outs = joined.step_many(msgs[lo:lo + 7])
        assert len(outs) == len(msgs[lo:lo + 7])
        got |= {end: encode_json(out.state[1])
                for out, end in zip(outs, ends[lo:lo + 7], strict=True) if out.state is not None}
    assert len(expected) >= 10 and got == expected


def test_step_many_gives_each_batch_what_stepping_it_alone_gives() -> None:
    """Per batch: the calibrated slice, updates and watch events (batch-local indices), the
    windows committed in it, and the model and estimate in force at its end; an empty batch
    gives an empty output with the state as it was."""
    raw = _raw(15.0, 5)
    model = SensorModel.diagonal(1024.0)
    msgs = [m for m, _ in _messages(raw, np.random.default_rng(6), 400)]
    msgs.insert(3, raw[:0])
    seq = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, None, ())
    many = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, None, ())
    n_updates = n_windows = 0
    for lo in range(0, len(msgs), 9):
        outs = many.step_many(msgs[lo:lo + 9])
        assert len(outs) == len(msgs[lo:lo + 9])
        for m, got in zip(msgs[lo:lo + 9], outs, strict=True):
            want = seq.step(m)
            assert Recorder._batch(got.calibrated) == Recorder._batch(want.calibrated)
            np.testing.assert_array_equal(got.calibrated.status, want.calibrated.status)
            np.testing.assert_array_equal(got.calibrated.sigma_mg, want.calibrated.sigma_mg)
            assert got.updates == want.updates and got.watch == want.watch
            assert got.windows_committed == want.windows_committed
            assert got.model is seq.model or got.model.to_dict() == seq.model.to_dict()
            assert (got.estimate is None) == (seq.estimate is None)
            if got.estimate is not None:
                np.testing.assert_array_equal(got.estimate.p, seq.estimate.p)
            assert (got.state is not None) == bool(want.updates)
            n_updates += len(got.updates)
            n_windows += got.windows_committed
    assert n_updates >= 10 and n_windows >= 100
    assert json.dumps(many.state_dict()) == json.dumps(seq.state_dict())


def test_replay_joined_equals_replay_one_message_at_a_time(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    raw = _raw(20.0, 4)
    src = tmp_path / "in.mcap"
    with RecordingWriter(src, background_flush=False, fsync=False) as w:
        for batch, log_ns in _messages(raw, np.random.default_rng(4), 30):
            w.write_raw(SID, batch, log_ns)
    joined = replay_mod.replay(src, tmp_path / "joined.mcap", progress=False)
    monkeypatch.setattr(replay_mod, "JOIN_SAMPLES", 1)  # every message on its own
    single = replay_mod.replay(src, tmp_path / "single.mcap", progress=False)
    assert joined["samples"] == single["samples"] == len(raw)

    def topics(path: Path) -> dict[str, list[tuple]]:
        out: dict[str, list[tuple]] = {}
        for m in rec.iter_messages(path):
            out.setdefault(m.topic, []).append((m.data, m.log_time_ns, m.publish_time_ns,
                                                m.sequence))
        return out
    a, b = topics(tmp_path / "joined.mcap"), topics(tmp_path / "single.mcap")
    assert set(a) == set(b) and {f"/{SID}/calibration", f"/{SID}/body", f"/{SID}/plot"} <= set(a)
    for topic in a:
        assert a[topic] == b[topic], topic
