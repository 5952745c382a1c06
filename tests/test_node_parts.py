"""The node in parts: each part works on its own (alignment requests, the checkpoint document),
the node holds them within the house limits, and the checkpoint errors are user-facing errors.

Real parts throughout: a real node on simulated wear, its real sink kept in memory.
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from memory_sink import MemorySink
from recal.config import AlignmentConfig, PipelineSection, SensorConfig, model_and_prior
from recal.core import alignment as al
from recal.core.pipeline import Pipeline
from recal.daemon.checkpoint_store import Checkpoints, checkpoint_path, lock_sensor
from recal.errors import CheckpointError, RecalError, SensorLockedError
from recal.node.alignment import Aligner
from recal.node.checkpoint_doc import parse_document, restore_document
from recal.node.events import NodeEvents
from recal.node.node import CalibrationNode, NodeSettings, make_node
from recal.samples import RawBatch
from recal.sim import wearer as sim

PACKAGE = Path(__file__).resolve().parents[1] / "service" / "recal"
RATE_HZ = 50.0
SID = "wrist"
#: the house limits (the project's guide): lines per module, attributes per class
MAX_LINES = 600
MAX_ATTRIBUTES = 20


def _settings() -> NodeSettings:
    sensor = SensorConfig(SID, rate_hz=RATE_HZ)
    pipeline = PipelineSection()
    model, prior = model_and_prior(sensor, pipeline)
    return NodeSettings(SID, pipeline, model, prior, RATE_HZ, None, AlignmentConfig())


def _self_attributes(path: Path, cls: str) -> set[str]:
    """The attributes assigned on self anywhere in class ``cls`` of the module at ``path``."""
    tree = ast.parse(path.read_text())
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls)
    found = set()
    for sub in ast.walk(node):
        targets = (sub.targets if isinstance(sub, ast.Assign)
                   else [sub.target] if isinstance(sub, (ast.AnnAssign, ast.AugAssign)) else [])
        for t in targets:
            for el in t.elts if isinstance(t, ast.Tuple) else [t]:
                if (isinstance(el, ast.Attribute) and isinstance(el.value, ast.Name)
                        and el.value.id == "self"):
                    found.add(el.attr)
    return found


@pytest.mark.parametrize(("module", "cls"), [("node/node.py", "CalibrationNode"),
                                             ("daemon/gateway.py", "Gateway")])
def test_node_and_gateway_hold_at_most_twenty_attributes(module: str, cls: str) -> None:
    attrs = _self_attributes(PACKAGE / module, cls)
    assert 5 < len(attrs) <= MAX_ATTRIBUTES, sorted(attrs)


def test_node_and_daemon_modules_are_at_most_600_lines() -> None:
    paths = [*sorted((PACKAGE / "node").glob("*.py")), *sorted((PACKAGE / "daemon").glob("*.py"))]
    long = {p.name: n for p in paths if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_checkpoint_errors_are_user_errors_and_keep_their_old_kinds(tmp_path: Path) -> None:
    assert issubclass(CheckpointError, RecalError) and issubclass(CheckpointError, ValueError)
    lock = lock_sensor(tmp_path, SID)
    try:
        with pytest.raises(SensorLockedError) as info:
            lock_sensor(tmp_path, SID)
    finally:
        lock.release()
    assert isinstance(info.value, RecalError) and isinstance(info.value, RuntimeError)
    assert f"sensor {SID!r} is already calibrated by process" in str(info.value)
    with pytest.raises(CheckpointError, match="not a strict JSON"):
        parse_document(b'{"format": 1, "x": NaN}', "here")


def test_alignment_requests_are_rate_limited_by_the_component_alone() -> None:
    """The aligner without a node: the first request arms the next still run (no tracker yet:
    nothing to align on), the next ones within the interval are refused and said once."""
    sink = MemorySink()
    aligner = Aligner(AlignmentConfig(request_interval_s=60.0), 2.0, NodeEvents(SID, sink))
    first = aligner.request(None, 0, 100.0)
    assert first["status"] == "armed" and aligner.requested
    replies = [aligner.request(None, 0, 100.0 + dt) for dt in (1.0, 30.0, 59.0)]
    assert [r["status"] for r in replies] == ["refused"] * 3
    assert replies[0]["retry_after_s"] == pytest.approx(59.0) and aligner.refused == 3
    assert aligner.request(None, 0, 160.0)["status"] == "armed"
    kinds = [e["kind"] for e in sink.events]
    assert kinds == ["align_request", "align_refused", "align_request"], kinds
    assert sink.events[-1]["detail"]["refused_before"] == 3


def test_the_checkpoint_document_round_trips_through_the_store(tmp_path: Path) -> None:
    """A node's document, saved by the daemon's store and restored beside the node, gives
    back its state: the same mounting and time base, and the pipeline doubted (another device
    may be under the id now) but otherwise the same, byte for byte in JSON."""
    raw = sim.simulate(10 / 60, RATE_HZ, 4, sim.SensorSpec()).raw
    node = CalibrationNode(_settings(), MemorySink())
    for i in range(0, len(raw), 250):
        node.process(raw[i:i + 250], int(raw.t_us[i]) * 1000)
    node.aligner.alignment = al.estimate_alignment(np.array([0.1, 0.0, 1.0]), 7.0, 10, 5)
    doc = node.checkpoint()
    assert doc is not None and doc["sensor_id"] == SID
    store = Checkpoints(tmp_path, 60.0, out=lambda _line: None)
    store.save({SID: node})
    assert checkpoint_path(tmp_path, SID).exists()
    again = make_node(_settings(), MemorySink(), store)
    assert again.start == "checkpoint"
    back = again.checkpoint()
    assert back is not None
    for part in ("alignment", "timebase"):
        assert json.dumps(back[part]) == json.dumps(doc[part]), part
    doubted = Pipeline.from_state_dict(doc["pipeline"])
    doubted.doubt()
    assert json.dumps(back["pipeline"]) == json.dumps(doubted.state_dict())
    assert json.dumps(back["pipeline"]) != json.dumps(doc["pipeline"])
    with pytest.raises(ValueError, match="is for sensor"):
        restore_document(doc, "hip", (node.settings.model, node.settings.prior),
                         node.settings.rediscovery)


def test_a_node_that_never_started_has_no_document() -> None:
    node = CalibrationNode(_settings(), MemorySink())
    node.process(RawBatch(np.arange(3, dtype=np.int64) * 20_000, np.zeros((3, 3)),
                          np.empty((3, 0)), ()), 0)
    assert node.pipeline is None and node.checkpoint() is None
