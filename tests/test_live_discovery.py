"""Effect discovery in a streaming node, on by default: the evidence it keeps, when it runs,
what it adopts and says, and that a checkpoint carries it (the daemon through a real pty and
Zenoh: tests/test_live_discovery_daemon.py).

The recordings are the wearer of tests/test_discovery.py (a board temperature that wanders
within minutes), 25 Hz; the node runs with the defaults unless a test says otherwise.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from recal.config import PipelineSection, RediscoveryConfig, parse_config
from recal.core.buffer import Windows
from recal.core.estimator import Prior
from recal.core.evidence import SLACK, EvidenceConfig, EvidenceStore
from recal.core.model import SensorModel
from recal.errors import InputError
from recal.node.checkpoint_doc import finite_document, parse_document
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import RawBatch
from recal.sim import wearer as sim
from test_discovery import OFFSET_TC, RATE_HZ, SEED, WEARER, _Capture, _sensor

MODEL = SensorModel.diagonal(1024.0)
BATCH = 500


def _node(cfg: RediscoveryConfig | None = None, sink: _Capture | None = None
          ) -> tuple[CalibrationNode, _Capture]:
    sink = sink or _Capture()
    settings = NodeSettings("s1", PipelineSection(), MODEL, Prior.default(MODEL), RATE_HZ,
                            **({} if cfg is None else {"rediscovery": cfg}))
    return CalibrationNode(settings, sink), sink


def _feed(node: CalibrationNode, raw: RawBatch, lo: int = 0) -> None:
    for i in range(lo, len(raw), BATCH):  # bounded: one pass over the recording
        node.process(raw[i:i + BATCH], 0)


def _events(sink: _Capture, kind: str = "discovery") -> list[dict]:
    return [o for s, o in sink.json_messages if s == "events" and o["kind"] == kind]


@pytest.fixture(scope="module")
def temperature_raw() -> RawBatch:
    return sim.simulate(0.5, RATE_HZ, SEED, _sensor(offset_tc_g_per_c=OFFSET_TC), WEARER).raw


@pytest.mark.slow
def test_a_node_with_the_defaults_adopts_the_undeclared_effect_and_says_so(
        temperature_raw: RawBatch) -> None:
    raw = temperature_raw
    node, sink = _node()
    notes: list[str] = []
    node.on_note = notes.append
    _feed(node, raw)
    events = _events(sink)
    adopted = [e for e in events if e["detail"]["adopted"]]
    assert len(adopted) == 1 and adopted[0]["detail"]["added"] == ["offset[board_temp]"]
    d = adopted[0]["detail"]
    assert d["heldout_error_mg"]["final"] < 0.5 * d["heldout_error_mg"]["base"]
    assert d["windows"] >= RediscoveryConfig().min_windows
    # the first run (first_h after the stream began) selects it, the second (first_h
    # later) confirms it, and it is taken on adopt_after_s after that run began
    cfg = RediscoveryConfig()
    assert events[0]["detail"]["pending"] and events[0]["detail"]["added"] == d["added"]
    started = d["started_t_us"] - int(raw.t_us[0])
    assert 2 * cfg.first_h * 3.6e9 <= started < 2 * cfg.first_h * 3.6e9 + BATCH / RATE_HZ * 1e6
    assert 0 <= adopted[0]["t_us"] - d["started_t_us"] - cfg.adopt_after_s * 1e6 < (
        BATCH / RATE_HZ * 1e6)
    said = [n for n in notes if n.startswith("discovery:")]
    assert len(said) == 1 and "added offset[board_temp]" in said[0] and "->" in said[0]
    states = [o for s, o in sink.json_messages if s == "calibration"
              and o["reason"] == "discovery"]
    assert len(states) == 1 and {f"o_board_temp_{ax}" for ax in "xyz"} <= set(
        states[0]["param_names"])
    # until it is taken on, the output is exactly a node's without discovery
    t, a = sink.calibrated_output()
    off, sink0 = _node(RediscoveryConfig(enabled=False))
    _feed(off, raw)
    t0, a0 = sink0.calibrated_output()
    np.testing.assert_array_equal(t, t0)
    before = t <= adopted[0]["t_us"]
    np.testing.assert_array_equal(a[before], a0[before])
    assert not _events(sink0)
    # and after, the error against the truth is smaller than without it
    truth = sim.simulate(0.5, RATE_HZ, SEED, _sensor(offset_tc_g_per_c=OFFSET_TC),
                         WEARER).truth.a_true_g
    err = sim.error_1s_mg(a[~before], truth[~before], RATE_HZ)
    err0 = sim.error_1s_mg(a0[~before], truth[~before], RATE_HZ)
    assert err < 0.8 * err0, (err, err0)


@pytest.mark.slow
def test_nothing_is_adopted_on_a_clean_sensor() -> None:
    raw = sim.simulate(0.5, RATE_HZ, SEED, _sensor(), WEARER).raw
    node, sink = _node()
    _feed(node, raw)
    events = _events(sink)
    assert len(events) >= 2  # it ran (10, 20 min in) and found nothing to add
    assert not any(e["detail"]["adopted"] for e in events), [e["detail"] for e in events]
    assert node.pipeline is not None and node.pipeline.model.names == MODEL.names


def test_a_setting_turns_it_off_and_old_files_keep_their_meaning(tmp_path) -> None:
    def cfg(table: dict | None) -> RediscoveryConfig:
        doc: dict = {"sensors": [{"id": "s1", "port": "/dev/null"}]}
        if table is not None:
            doc["discovery"] = table
        return parse_config(doc, tmp_path, "test").discovery

    assert cfg(None).active and RediscoveryConfig().active
    assert not cfg({"every_h": 0.0}).active  # an older file's explicit off
    assert not cfg({"enabled": False}).active
    assert cfg({"every_h": 0.5}).active and cfg({"every_h": 0.5}).every_h == 0.5
    raw = sim.simulate(0.25, RATE_HZ, SEED, _sensor(offset_tc_g_per_c=OFFSET_TC), WEARER).raw
    for off in (RediscoveryConfig(enabled=False), RediscoveryConfig(every_h=0.0)):
        node, sink = _node(off)
        _feed(node, raw)
        assert node.discovery.evidence is None and not _events(sink)
        assert node.checkpoint()["discovery"] is None


def _windows(t_s: np.ndarray, temp: np.ndarray, v: np.ndarray | None = None) -> Windows:
    m = len(t_s)
    v = np.tile([0.0, 0.0, 1024.0], (m, 1)) if v is None else v
    return Windows(v, temp[:, None], (t_s * 1e6).astype(np.int64), np.full(m, 50),
                   np.full(m, 4.0))


def test_the_evidence_is_bounded_and_keeps_the_rare_windows() -> None:
    store = EvidenceStore(EvidenceConfig(capacity=200), 1)
    t = np.arange(3000) * 2.0  # 100 min of windows at one temperature ...
    temp = np.full(3000, 30.0)
    temp[1500:1520] = 22.0  # ... but for 40 s in the cold
    v = np.tile([0.0, 0.0, 1024.0], (3000, 1))
    v[2500:2510] = [1024.0, 0.0, 0.0]  # and 20 s lying on the side
    for i in range(0, 3000, 37):  # bounded: as a node adds them, a batch at a time
        store.add(_windows(t[i:i + 37], temp[i:i + 37], v[i:i + 37]))
    assert 200 - 200 // SLACK <= len(store) <= 200 and store.added == 3000
    assert store.nbytes <= 200 * 8 * (3 + 1 + 3)
    kept = store.windows()
    assert np.all(np.diff(kept.t_us) > 0)
    assert (kept.aux[:, 0] == 22.0).sum() >= 10  # the rare temperature stays
    assert (kept.v[:, 0] > 500).sum() >= 5  # the rare pose stays
    # spread over the whole time, not the last 200 windows
    hist = np.histogram(kept.t_us / 1e6, bins=10, range=(0, 6000))[0]
    assert hist.min() >= 5, hist


def test_the_evidence_round_trips_through_its_dict_and_strict_json() -> None:
    store = EvidenceStore(EvidenceConfig(capacity=100), 1)
    rng = np.random.default_rng(1)
    temp = 30 + rng.normal(0, 2, 80)
    temp[3] = np.nan  # a channel the stream lacked for a moment: saved as null
    store.add(_windows(np.arange(80) * 2.0, temp, rng.normal(0, 600, (80, 3))))
    doc, where, _ = finite_document({"evidence": store.to_dict()})
    assert where == ["evidence.aux"]
    text = json.dumps({"format": 1, **doc}).encode()
    back = EvidenceStore.from_dict(parse_document(text, "test")["evidence"])
    assert len(back) == len(store) == 80 and back.added == 80
    a, b = store.windows(), back.windows()
    np.testing.assert_array_equal(a.t_us, b.t_us)
    np.testing.assert_allclose(b.v, a.v, rtol=0, atol=1e-5 * np.abs(a.v).max())
    np.testing.assert_allclose(b.aux, a.aux, rtol=1e-8)
    assert np.isnan(b.aux).sum() == np.isnan(a.aux).sum()
    with pytest.raises(InputError):
        bad = store.to_dict()
        bad["t_us"] = bad["t_us"][::-1]
        EvidenceStore.from_dict(bad)


@pytest.mark.slow
def test_the_adopted_model_and_the_evidence_survive_a_restart(
        temperature_raw: RawBatch) -> None:
    raw = temperature_raw
    cut = int(np.searchsorted(raw.t_us, raw.t_us[0] + 25 * 60e6))
    cut -= cut % BATCH
    node, sink = _node()
    _feed(node, raw[:cut])
    assert any(e["detail"]["adopted"] for e in _events(sink))
    doc = json.loads(json.dumps(node.checkpoint()))
    assert len(doc["discovery"]["evidence"]["t_us"]) == len(node.discovery.evidence)
    back = CalibrationNode.from_checkpoint(node.settings, _Capture(), doc)
    assert back.pipeline is not None and back.pipeline.model.has("offset", "board_temp")
    ev = back.discovery.evidence
    assert ev is not None and len(ev) == len(node.discovery.evidence)
    assert ev.added == node.discovery.evidence.added
    assert back.discovery.schedule.next_us == node.discovery.schedule.next_us
    assert back.discovery.schedule.gap_us == node.discovery.schedule.gap_us
    assert back.discovery.pending == node.discovery.pending
    # a checkpoint from before discovery kept anything loads: the evidence starts anew
    old = {k: v for k, v in doc.items() if k != "discovery"}
    fresh = CalibrationNode.from_checkpoint(node.settings, _Capture(), old)
    assert fresh.discovery.evidence is not None and len(fresh.discovery.evidence) == 0
    assert fresh.pipeline is not None and fresh.pipeline.model.has("offset", "board_temp")


@pytest.mark.slow
def test_a_run_pending_at_a_checkpoint_runs_again_after_the_restart(
        temperature_raw: RawBatch) -> None:
    raw = temperature_raw
    first_us = RediscoveryConfig().first_h * 3.6e9
    cut = int(np.searchsorted(raw.t_us, raw.t_us[0] + first_us + 30e6))  # a run going on
    cut -= cut % BATCH
    node, _ = _node()
    _feed(node, raw[:cut])
    assert node.discovery.schedule.run is not None
    doc = json.loads(json.dumps(node.checkpoint()))
    assert doc["next_discovery_us"] <= doc["t_us"]  # due again: the pending run is not saved
    restored, sink = _node()
    restored = CalibrationNode.from_checkpoint(node.settings, sink, doc)
    _feed(restored, raw, cut)
    events = _events(sink)
    assert events and events[0]["detail"]["started_t_us"] == int(
        raw.t_us[min(cut + BATCH, len(raw)) - 1])
    assert events[0]["detail"]["added"] == ["offset[board_temp]"]


@pytest.mark.slow
def test_joined_steps_start_and_adopt_at_the_batch_a_live_node_does(
        temperature_raw: RawBatch) -> None:
    raw = temperature_raw
    live, live_sink = _node()
    _feed(live, raw)
    joined, sink = _node()
    items = [(raw[i:i + BATCH], 0) for i in range(0, len(raw), BATCH)]
    for k in range(0, len(items), 37):  # bounded: replay's way, many messages a step
        joined.process_many(items[k:k + 37])
    ev_live, ev = _events(live_sink), _events(sink)
    assert [(e["t_us"], e["detail"]["started_t_us"], e["detail"]["added"]) for e in ev] == [
        (e["t_us"], e["detail"]["started_t_us"], e["detail"]["added"]) for e in ev_live]
    t, a = sink.calibrated_output()
    t0, a0 = live_sink.calibrated_output()
    np.testing.assert_array_equal(t, t0)
    np.testing.assert_allclose(a, a0, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_a_replay_of_a_resumed_node_runs_and_adopts_as_it_did(
        temperature_raw: RawBatch) -> None:
    from recal.commands.replay import _node_for
    from recal.config import ServiceConfig

    raw = temperature_raw
    cut = int(np.searchsorted(raw.t_us, raw.t_us[0] + 15 * 60e6))  # one run pending
    cut -= cut % BATCH
    first, _ = _node()
    _feed(first, raw[:cut])
    assert first.discovery.pending is not None and "offset[board_temp]" in first.discovery.pending
    # waiting for the next run's word, the selection widens sigma (`core.pending`)
    assert first.pipeline is not None and first.pipeline.pending is not None
    assert first.pipeline.pending.label == "offset[board_temp]"
    resumed_sink = _Capture()
    resumed = CalibrationNode.from_checkpoint(first.settings, resumed_sink,
                                              json.loads(json.dumps(first.checkpoint())))
    _feed(resumed, raw, cut)
    setup = next(o for s, o in resumed_sink.json_messages if s == "setup")
    replay_sink = _Capture()
    node, start = _node_for("s1", ServiceConfig(), None, setup, replay_sink)
    assert start == "recording"
    _feed(node, raw, cut)
    live, again = _events(resumed_sink), _events(replay_sink)
    assert any(e["detail"]["adopted"] for e in live)  # the pending one, confirmed
    assert resumed.pipeline is not None and resumed.pipeline.pending is None
    assert [(e["t_us"], e["detail"]["adopted"]) for e in again] == [
        (e["t_us"], e["detail"]["adopted"]) for e in live]


@pytest.mark.slow
def test_with_no_delay_a_run_is_taken_on_where_it_starts(temperature_raw: RawBatch) -> None:
    node, sink = _node(RediscoveryConfig(adopt_after_s=0.0))
    _feed(node, temperature_raw)
    events = _events(sink)
    assert events and all(e["t_us"] == e["detail"]["started_t_us"] for e in events)
    assert any(e["detail"]["adopted"] for e in events)


def test_a_waiting_selection_is_confirmed_a_quarter_gap_later() -> None:
    """Once the gap has doubled to hours, a selection waiting for the next run's word is
    judged again a quarter of the gap later (at least first_h), not a whole gap later; a slot
    already sooner stays."""
    from recal.node.rediscovery import RediscoverySchedule

    hour_us = round(3.6e9)
    cfg = RediscoveryConfig()
    first_us = round(cfg.first_h * 3.6e9)
    late = RediscoverySchedule(cfg, next_us=6 * hour_us, gap_us=2 * hour_us)
    late.confirm_soon(4 * hour_us)
    assert late.next_us == 4 * hour_us + hour_us // 2
    early = RediscoverySchedule(cfg, next_us=40 * 60_000_000, gap_us=first_us)
    early.confirm_soon(30 * 60_000_000)
    assert early.next_us == 30 * 60_000_000 + first_us  # first_h: not sooner than a slot
    soon = RediscoverySchedule(cfg, next_us=hour_us + 1, gap_us=2 * hour_us)
    soon.confirm_soon(hour_us)
    assert soon.next_us == hour_us + 1


def test_a_node_keeps_the_detail_of_its_newest_runs_only() -> None:
    """A daemon runs discovery 18 times a day for months: the runs it keeps for its summary
    are bounded (the newest RUNS_KEPT), nothing grows with time."""
    from recal.node.rediscovery import RUNS_KEPT

    sink = _Capture()
    node = CalibrationNode(NodeSettings("s", PipelineSection(), MODEL, None, RATE_HZ), sink)
    runs = node.discovery.runs
    for i in range(RUNS_KEPT + 5):  # bounded
        runs.append({"t_us": i})
    assert len(runs) == RUNS_KEPT and runs[0]["t_us"] == 5
