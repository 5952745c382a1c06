"""A gap in device time is a moment of doubt: the pipeline itself holds the output from the
sample after a gap longer than `status.GAP_S` until the first still window agrees with the
calibration, suspect at once if it contradicts (a device whose data stopped and came back,
perhaps another device under the id, without a port of the gateway closing)."""

from __future__ import annotations

from functools import cache

import numpy as np

from held_checks import held_until_agreed, held_until_contradicted
from memory_sink import MemorySink
from recal.config import PipelineSection, PriorConfig, SensorConfig, model_and_prior
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import GAP_S, Status
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import CalibratedBatch, RawBatch
from recal.sim import wearer as sim

RATE_HZ = 25.0
S0 = 1024.0
SID = "wrist"
GAP_US = round(1.5 * GAP_S * 1e6)  # a gap clearly beyond the threshold


def _spec(seed: int) -> sim.SensorSpec:
    return sim.SensorSpec.random(np.random.default_rng(seed), 40, 3, counts_per_g=S0)


def _node(sink: MemorySink) -> CalibrationNode:
    sensor = SensorConfig(SID, rate_hz=RATE_HZ, prior=PriorConfig(counts_per_g=S0))
    settings = PipelineSection()
    model, prior = model_and_prior(sensor, settings)
    return CalibrationNode(NodeSettings(SID, settings, model, prior, RATE_HZ), sink)


def _live(raw: RawBatch, batch: int = 250) -> CalibratedBatch:
    """raw through the live node, a message of ``batch`` samples at a time."""
    sink = MemorySink()
    node = _node(sink)
    for i in range(0, len(raw), batch):  # bounded: one pass over the data
        b = raw[i:i + batch]
        node.process(b, int(b.t_us[0]) * 1000)
    return sink.all()


def _gapped(raw: RawBatch, k: int, gap_us: int = GAP_US) -> RawBatch:
    """raw with gap_us of device time missing before sample k (no sample dropped)."""
    t_us = raw.t_us.copy()
    t_us[k:] += gap_us
    return RawBatch(t_us, raw.v, raw.aux, raw.aux_names)


@cache
def _same() -> tuple[RawBatch, int]:
    """One sensor for 50 min, a gap at 40 min (not at a message boundary)."""
    res = sim.simulate(50 / 60, RATE_HZ, 1, _spec(1))
    k = int(40 * 60 * RATE_HZ) + 117
    return _gapped(res.raw, k), k


def test_another_sensor_after_a_gap_is_not_calibrated_before_a_still_window_agrees() -> None:
    """Sensor B after a gap in device time, its clock running on and no port reopened: from
    the gap output is held, B's first still window contradicts, and no sample of B is marked
    calibrated before suspect (without the check: B's moving seconds were calibrated)."""
    res = sim.simulate(50 / 60, RATE_HZ, 1, _spec(1))
    b = sim.with_sensor(res, _spec(2))
    k = int(40 * 60 * RATE_HZ) + 117
    raw = _gapped(RawBatch(res.raw.t_us, np.concatenate([res.raw.v[:k], b.raw.v[k:]]),
                           res.raw.aux, res.raw.aux_names), k)
    out = _live(raw)
    assert out.status[k] == Status.HELD
    held_until_contradicted(out.status, k, RATE_HZ)


def test_the_same_sensor_after_a_gap_is_calibrated_again_at_its_first_still_window() -> None:
    """The check costs the time to the first still window that agrees, and nothing else."""
    raw, k = _same()
    held_until_agreed(_live(raw).status, k, RATE_HZ)


def test_a_step_within_the_threshold_is_no_gap() -> None:
    """A pause of less than GAP_S (a late message of a working link) leaves the status."""
    raw, k = _same()
    short = _gapped(raw, k + 5000, round(0.5 * GAP_S * 1e6))  # a second, shorter pause
    out, ref = _live(short), _live(raw)
    assert np.array_equal(out.status, ref.status)


def test_the_gap_is_seen_at_its_sample_however_the_samples_are_batched() -> None:
    """Live (a message at a time, the gap inside one), replay (messages joined: `step_joined`)
    and one whole step give the same statuses and sigma: the step is cut at the gap."""
    raw, k = _same()
    model, prior = model_and_prior(SensorConfig(SID, rate_hz=RATE_HZ,
                                                prior=PriorConfig(counts_per_g=S0)),
                                   PipelineSection())
    outs = []
    for sizes in ([250], [97], [len(raw)]):
        pipe = Pipeline(_config(), model, prior, raw.aux_names)
        n = sizes[0]
        lengths = [min(n, len(raw) - i) for i in range(0, len(raw), n)]
        joined = pipe.step_joined(raw, lengths) if n != len(raw) else [pipe.step(raw)]
        outs.append(CalibratedBatch.concat([o.calibrated for o in joined]))
    assert outs[0].status[k] == Status.HELD and outs[0].status[k - 1] == Status.CALIBRATED
    for o in outs[1:]:
        assert np.array_equal(o.status, outs[0].status)
        assert np.array_equal(o.sigma_mg, outs[0].sigma_mg)
    # and stepped message by message
    pipe = Pipeline(_config(), model, prior, raw.aux_names)
    one = CalibratedBatch.concat([pipe.step(raw[i:i + 250]).calibrated
                                  for i in range(0, len(raw), 250)])
    assert np.array_equal(one.status, outs[0].status)


def test_every_gap_of_a_joined_batch_is_seen_as_message_by_message() -> None:
    """Two gaps inside one step (replay joins thousands of samples): each holds the output
    from its own sample, as a message at a time does."""
    raw, k = _same()
    k2 = k + int(3 * 60 * RATE_HZ) + 31
    raw = _gapped(raw, k2)
    model, prior = model_and_prior(SensorConfig(SID, rate_hz=RATE_HZ,
                                                prior=PriorConfig(counts_per_g=S0)),
                                   PipelineSection())
    pipe = Pipeline(_config(), model, prior, raw.aux_names)
    one = CalibratedBatch.concat([pipe.step(raw[i:i + 250]).calibrated
                                  for i in range(0, len(raw), 250)])
    assert one.status[k2 - 1] == Status.CALIBRATED and one.status[k2] == Status.HELD
    for head in (k, 0):  # the first gap just before the step, or inside it
        pipe = Pipeline(_config(), model, prior, raw.aux_names)
        first = pipe.step(raw[:head]).calibrated if head else CalibratedBatch.empty()
        rest = pipe.step(raw[head:]).calibrated
        whole = CalibratedBatch.concat([first, rest])
        assert np.array_equal(whole.status, one.status)
        assert np.array_equal(whole.sigma_mg, one.sigma_mg)


def _config() -> PipelineConfig:
    return PipelineSection().pipeline_config(RATE_HZ)


def test_a_gap_before_any_estimate_doubts_nothing() -> None:
    """Nothing to doubt while bootstrapping: a pipeline without a prior sees the gap and its
    probation stays 0."""
    raw, _ = _same()
    pipe = Pipeline(_config(), *model_and_prior(SensorConfig(SID, rate_hz=RATE_HZ),
                                                PipelineSection()), raw.aux_names)
    pipe.step(_gapped(raw[:2000], 1000))
    assert pipe.watch.probation == 0


def test_a_configured_gap_doubt_of_zero_holds_nothing_after_a_gap() -> None:
    """``gap_doubt_s = 0`` (what `recal replay` of a device file sets: one device recorded
    every sample, a gap is the device asleep or off): the same statuses as the recording with
    its gap closed, and the sample after the gap calibrated where the default holds it."""
    raw, k = _same()
    model, prior = model_and_prior(SensorConfig(SID, rate_hz=RATE_HZ,
                                                prior=PriorConfig(counts_per_g=S0)),
                                   PipelineSection())
    cfg = PipelineSection(options={"gap_doubt_s": 0.0}).pipeline_config(RATE_HZ)
    outs = {}
    for name, c in (("off", cfg), ("default", _config())):
        pipe = Pipeline(c, model, prior, raw.aux_names)
        outs[name] = CalibratedBatch.concat([pipe.step(raw[i:i + 250]).calibrated
                                             for i in range(0, len(raw), 250)])
    assert outs["default"].status[k] == Status.HELD
    assert outs["off"].status[k - 1] == outs["off"].status[k] == Status.CALIBRATED
    assert not np.any(outs["off"].status[k:] == Status.HELD)
