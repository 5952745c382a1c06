"""Faults a node must survive: a channel layout that changes across a restart, a crafted
stream, a device that reboots (its own time kept on every calibrated sample).

Real parts throughout: the node, checkpoints written to and read back from a real folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from recal.config import AlignmentConfig, PipelineSection, SensorConfig, model_and_prior
from recal.daemon.checkpoint_store import Checkpoints, checkpoint_path, load_checkpoint
from recal.node.node import CalibrationNode, NodeSettings, make_node
from recal.samples import RawBatch
from recal.sim import wearer as sim
from test_node import MemorySink

RATE_HZ = 50.0
SID = "wrist"


def _settings() -> NodeSettings:
    """A sensor without a prior (it bootstraps) and without configured aux names."""
    sensor = SensorConfig(SID, rate_hz=RATE_HZ)
    pipeline = PipelineSection()
    model, prior = model_and_prior(sensor, pipeline)
    return NodeSettings(SID, pipeline, model, prior, RATE_HZ, None, AlignmentConfig())


def _with_aux(raw: RawBatch, name: str) -> RawBatch:
    """The stream with one aux channel (a temperature), named as the device's header says."""
    temp = 25.0 + 0.01 * np.arange(len(raw)) / len(raw)
    return RawBatch(raw.t_us, raw.v, temp[:, None], (name,))


def _feed(node: CalibrationNode, raw: RawBatch, batch: int = 500) -> None:
    for i in range(0, len(raw), batch):
        b = raw[i:i + batch]
        node.process(b, 10**18 + int(b.t_us[0]) * 1000)


def _store(folder: Path) -> Checkpoints:
    """The state folder as the daemon opens it (its lines to the log)."""
    return Checkpoints(folder, 60.0, out=lambda _line: None)


def _keeper(folder: Path, lines: list[str], events: list[tuple[str, str, Any]]) -> Checkpoints:
    return Checkpoints(folder, 5.0, 2.0, out=lines.append,
                       event=lambda sid, kind, detail: events.append((sid, kind, detail)))


def test_a_restart_without_the_header_maps_the_unnamed_channel_and_keeps_saving(
        tmp_path: Path) -> None:
    """Run 1 hears the header (``temp_c``) and saves a checkpoint; run 2 restores it, but the
    device printed its header only at boot, so the same channel arrives as ``aux0``. The node
    maps it to the checkpoint's name (an event and an operator line say so), and every save
    after the restart succeeds and loads again: no NaN reaches the window buffer or the file."""
    raw = sim.simulate(20 / 60, RATE_HZ, 5, sim.SensorSpec()).raw
    half = len(raw) // 2
    lines: list[str] = []
    events: list[tuple[str, str, Any]] = []
    keeper = _keeper(tmp_path, lines, events)
    node1 = CalibrationNode(_settings(), MemorySink())
    _feed(node1, _with_aux(raw[:half], "temp_c"))
    keeper.save({SID: node1})
    assert keeper.saves == 1 and node1.pipeline is not None
    assert node1.pipeline.aux_names == ("temp_c",)

    sink, notes = MemorySink(), []
    node2 = make_node(_settings(), sink, _keeper(tmp_path, lines, events))
    node2.on_note = notes.append
    assert node2.start == "checkpoint"
    _feed(node2, _with_aux(raw[half:], "aux0"))
    assert node2.samples == len(raw) - half and node2.samples_skipped == 0
    assert sink.kinds().count("layout_mapped") == 1, sink.kinds()
    mapped = next(e for e in sink.events if e["kind"] == "layout_mapped")["detail"]
    assert mapped["got"] == ["aux0"] and mapped["mapped_to"] == ["temp_c"]
    assert any("aux0" in n and "temp_c" in n for n in notes), notes
    windows = node2.pipeline.buffer.windows()
    assert len(windows.aux) and np.isfinite(windows.aux).all()

    keeper2 = _keeper(tmp_path, lines, events)
    keeper2.save({SID: node2})
    assert keeper2.saves == 1 and keeper2.failed_saves == 0, lines
    doc = load_checkpoint(checkpoint_path(tmp_path, SID))
    assert doc is not None and doc["t_us"] == node2.last_t_us
    assert make_node(_settings(), MemorySink(), _store(tmp_path)).start == "checkpoint"


def test_a_channel_that_stays_missing_never_stops_the_saves(tmp_path: Path) -> None:
    """Run 2's stream lacks the checkpoint's channel outright (no aux at all: nothing to map):
    the channel is filled as missing, the node calibrates and bootstraps on, and its saves
    succeed; a value that strict JSON cannot hold is saved as null, said once with where it was
    (an event and a line), and the file loads again."""
    raw = sim.simulate(20 / 60, RATE_HZ, 5, sim.SensorSpec()).raw
    half = len(raw) // 2
    lines: list[str] = []
    events: list[tuple[str, str, Any]] = []
    node1 = CalibrationNode(_settings(), MemorySink())
    _feed(node1, _with_aux(raw[:half], "temp_c"))
    _keeper(tmp_path, lines, events).save({SID: node1})

    node2 = make_node(_settings(), MemorySink(), _store(tmp_path))
    assert node2.start == "checkpoint"
    _feed(node2, raw[half:])
    assert node2.samples == len(raw) - half
    keeper = _keeper(tmp_path, lines, events)
    for _ in range(3):
        keeper.save({SID: node2})
    assert keeper.saves == 3 and keeper.failed_saves == 0, lines
    dropped = [d for _, kind, d in events if kind == "checkpoint_values_dropped"]
    assert len(dropped) == 1 and dropped[0]["values"] > 0
    assert any("pipeline.buffer.aux" in p for p in dropped[0]["where"]), dropped
    assert sum("saved as null" in line for line in lines) == 1, lines
    doc = load_checkpoint(checkpoint_path(tmp_path, SID))
    assert doc is not None and doc["t_us"] == node2.last_t_us
    restored = make_node(_settings(), MemorySink(), _store(tmp_path))
    assert restored.start == "checkpoint" and restored.pipeline is not None
    assert restored.pipeline.bootstrapped == node2.pipeline.bootstrapped


def _configured(sid: str = SID) -> NodeSettings:
    """A sensor with a datasheet prior (1024 counts per g), as configured for a fleet."""
    from recal.config.settings import PriorConfig

    sensor = SensorConfig(sid, rate_hz=RATE_HZ, prior=PriorConfig(counts_per_g=1024.0))
    pipeline = PipelineSection()
    model, prior = model_and_prior(sensor, pipeline)
    return NodeSettings(sid, pipeline, model, prior, RATE_HZ, None, AlignmentConfig())


def _crafted(after_us: int, n: int, scale: float, seed: int = 1) -> RawBatch:
    """A crude fake stream: a clock ~17 years ahead, zero-g at 5120 counts on every axis, a
    'gravity' of ``scale`` counts in a new direction every 10 s."""
    rng = np.random.default_rng(seed)
    t = after_us + 17 * 365 * 86_400 * 10**6 + np.arange(n, dtype=np.int64) * 20_000
    dirs = np.repeat(rng.normal(size=(n // 500 + 1, 3)), 500, axis=0)[:n]
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    v = 5120.0 + dirs * scale + rng.normal(0.0, 0.5, (n, 3))
    return RawBatch(t, v, np.zeros((n, 0)), ())


def test_a_crafted_stream_cannot_move_time_or_adopt_an_estimate_the_node_could_not_save(
        tmp_path: Path) -> None:
    """A configured sensor calibrates, then a fake stream arrives on its id: a clock 17 years
    ahead and readings whose zero-g and scale no sensor of this configuration has. The jump is
    an event and a line, not a new time base (output time stays within seconds of the real
    stream's); no estimate out of the model's bounds is kept (the core does not relocate there;
    one the node's vetting refuses is an event ``estimate_refused``) and the node goes on from
    its last good one; every save succeeds and the file loads."""
    for scale in (1.0, 100.0, 1024.0):
        folder = tmp_path / f"s{scale:g}"
        raw = sim.simulate(10 / 60, RATE_HZ, 3, sim.SensorSpec()).raw
        sink, notes, lines = MemorySink(), [], []
        node = CalibrationNode(_configured(), sink)
        node.on_note = notes.append
        _feed(node, raw)
        assert node.pipeline is not None and node.accepted_updates > 0
        good = node.pipeline.params.copy()
        end_us = node.last_t_us
        assert end_us is not None
        keeper = _keeper(folder, lines, [])
        _feed(node, _crafted(int(raw.t_us[-1]), 30_000, scale))
        keeper.save({SID: node})
        assert keeper.saves == 1 and keeper.failed_saves == 0, (scale, lines)
        kinds = sink.kinds()
        assert "time_jump_refused" in kinds, kinds
        assert any("device time jumped +6205 days" in n for n in notes), notes
        # 30 000 samples at 50 Hz later: 600 s of output time, not 17 years
        assert node.last_t_us - end_us < 700 * 10**6
        # never adopted: whatever estimate the node holds is this sensor's (it may be
        # re-fitting, with none, while the fake windows contradict it); the core does not
        # relocate to a scale outside the model's bounds, and an estimate the node's vetting
        # refuses is said so
        est = node.pipeline.estimate
        assert est is None or np.all(np.abs(est.p[:3] - good[:3]) < 0.2 * 1024), (scale, est)
        assert abs(node.pipeline.model.s0 - 1024.0) < 0.5 * 1024, node.pipeline.model.s0
        assert (node.estimates_refused >= 1) == ("estimate_refused" in kinds), (scale, kinds)
        assert (node.estimates_refused >= 1) == any(
            n.startswith("calibration refused") for n in notes), notes
        restored = make_node(_configured(), MemorySink(), _store(folder))
        assert restored.start == "checkpoint", scale


def _read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path) as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def test_raw_and_calibrated_exports_join_on_the_device_time_across_a_reboot(
        tmp_path: Path) -> None:
    """A millis() device (milliseconds under the raw message's t_us) reboots mid-stream. The
    replayed recording's calibrated samples carry the device's own stamps (t_dev: MCAP and the
    wire); `recal export --topic raw` names its time column by its unit (t_ms), the calibrated
    export has device_t_ms, and every calibrated row joins its raw row on it exactly, although
    the calibrated t_us (the time base, never going back) left the device time at the reboot."""
    from recal import cli
    from recal.io import recording
    from recal.io.recording_writer import RecordingWriter

    rate = 50.0
    res = sim.simulate(12 / 60, rate, 8, sim.SensorSpec())
    n = len(res.raw)
    half = n // 2
    k = np.arange(n, dtype=np.int64)
    t_ms = np.where(k < half, 7_200_000 + 20 * k, 3_000 + 20 * (k - half))  # reboot at half
    raw = RawBatch(t_ms, res.raw.v, res.raw.aux, res.raw.aux_names)
    rec, out = tmp_path / "raw.mcap", tmp_path / "cal.mcap"
    with RecordingWriter(rec, overwrite=True) as writer:
        for i in range(0, n, 500):
            writer.write_raw(SID, raw[i:i + 500], 10**18 + i * 10**6)
    assert cli.main(["replay", str(rec), "--out", str(out), "--quiet"]) == 0
    cal = recording.read_all_calibrated(out, SID)
    assert cal.t_dev is not None
    np.testing.assert_array_equal(cal.t_dev, t_ms)
    assert np.all(np.diff(cal.t_us) > 0)  # the time base continues past the reboot

    raw_csv, cal_csv = tmp_path / "raw.csv", tmp_path / "cal.csv"
    assert cli.main(["export", str(out), "--topic", "raw", "--csv", str(raw_csv)]) == 0
    assert cli.main(["export", str(out), "--csv", str(cal_csv)]) == 0
    raw_head, raw_rows = _read_csv(raw_csv)
    cal_head, cal_rows = _read_csv(cal_csv)
    assert raw_head[0] == "t_ms" and "device_t_ms" in cal_head, (raw_head, cal_head)
    assert cal_head[0] == "t_us"
    dev = cal_rows[:, cal_head.index("device_t_ms")].astype(np.int64)
    raw_t = raw_rows[:, 0].astype(np.int64)
    assert len(np.unique(raw_t)) == n
    row_of = {int(t): i for i, t in enumerate(raw_t)}
    joined = np.array([row_of[int(t)] for t in dev])
    np.testing.assert_array_equal(joined, np.arange(n))  # every calibrated row, its raw row
    np.testing.assert_array_equal(raw_rows[joined, 1:4], res.raw.v)
    after = cal_rows[half:, 0].astype(np.int64)
    assert np.all(np.abs(after - dev[half:] * 1000) > 60 * 10**6)  # t_us could not join


def test_the_node_refuses_a_state_out_of_the_models_bounds_and_goes_back() -> None:
    """The node's last line of defence (`node.vetting.EstimateVet`), whatever the core takes
    on: an estimate whose zero-g no sensor of this configuration has is refused, the node goes
    back to the last state that passed, and says so once (event ``estimate_refused``, a note)."""
    from recal.core.estimate import Estimate
    from recal.core.pipeline import Pipeline
    from recal.node.events import NodeEvents
    from recal.node.vetting import EstimateVet

    st = _configured()
    sink, notes = MemorySink(), []
    events = NodeEvents(SID, sink)
    events.on_note = notes.append
    vet = EstimateVet((st.model, st.prior), events)
    pipe = Pipeline(st.pipeline.pipeline_config(RATE_HZ), st.model, st.prior, ())
    pipe.estimate = Estimate.from_prior(st.prior)
    assert vet.check(pipe, 0, 0) is None and vet.refused == 0
    bad = Estimate.from_prior(st.prior)
    bad.p[:3] += 50 * 1024.0  # zero-g 50 g away: outside any bound around the configured one
    pipe.estimate = bad
    back = vet.check(pipe, 1_000_000, 1)
    assert back is not None and vet.refused == 1
    assert np.array_equal(back.estimate.p, Estimate.from_prior(st.prior).p)
    assert sink.kinds() == ["estimate_refused"], sink.kinds()
    assert any(n.startswith("calibration refused") for n in notes), notes
