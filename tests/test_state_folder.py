"""The state folder is never a way to write elsewhere: a symlink where a sensor's lock,
checkpoint, previous generation, rejected file or temporary file should be is refused with one
console line and left alone (its target untouched), the other sensors keep their checkpoints;
the folder is made private (0700) and a shared one is warned about. Real files, real nodes."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from recal.config.settings import CheckpointConfig, PriorConfig, SensorConfig, ServiceConfig
from recal.daemon.checkpoint_store import (
    CheckpointError,
    Checkpoints,
    SensorLockedError,
    checkpoint_path,
    load_checkpoint,
    lock_sensor,
    previous_path,
)
from recal.node.node import CalibrationNode, make_node, node_settings
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec, simulate
from test_checkpoints import Capture

RATE_HZ = 50.0
VICTIM = "precious: not recal's\n"
STATE_FILES = {"lock": "wrist.lock", "checkpoint": "wrist.json", "prev": "wrist.json.prev",
               "rejected": "wrist.json.rejected", "prev_rejected": "wrist.json.prev.rejected"}


def _raw() -> RawBatch:
    spec = SensorSpec.random(np.random.default_rng(3), offset_mg=20.0, gain_pct=1.0)
    return simulate(2 / 60, RATE_HZ, 3, spec).raw  # two minutes of a wearer


def _node(ck: Path, keeper: Checkpoints, sid: str) -> CalibrationNode:
    sensor = SensorConfig(id=sid, rate_hz=RATE_HZ,
                          prior=PriorConfig(counts_per_g=1024.0, zero_g=(0.0, 0.0, 0.0)))
    settings = node_settings(sensor, ServiceConfig(checkpoint=CheckpointConfig(dir=ck)))
    node = make_node(settings, Capture(), keeper)
    raw = _raw()
    for i in range(0, len(raw), 500):
        node.process(raw[i:i + 500], 0)
    return node


def _victim(tmp: Path) -> Path:
    victim = tmp / "victim.txt"
    victim.write_text(VICTIM)
    return victim


@pytest.mark.parametrize("which", list(STATE_FILES))
def test_a_symlink_for_a_state_file_is_refused_and_the_other_sensor_goes_on(
        tmp_path: Path, which: str) -> None:
    ck = tmp_path / "ck"
    ck.mkdir(mode=0o700)
    victim = _victim(tmp_path)
    link = ck / STATE_FILES[which]
    link.symlink_to(victim)
    lines: list[str] = []
    keeper = Checkpoints(ck, 60.0, out=lines.append, prefix="test:")
    keeper.acquire(["wrist", "ankle"])  # never raises for one sensor's bad file
    assert len(lines) == 1 and "wrist" in lines[0] and str(link) in lines[0], lines
    assert "symlink" in lines[0] and "without checkpoints" in lines[0], lines
    nodes = {sid: _node(ck, keeper, sid) for sid in ("wrist", "ankle")}
    assert nodes["wrist"].start == "prior"
    keeper.save(nodes)
    keeper.release()
    # the target is untouched, the link left as it was, nothing written for wrist
    assert victim.read_text() == VICTIM
    assert link.is_symlink() and os.readlink(link) == str(victim)
    assert not checkpoint_path(ck, "wrist").exists() or which == "checkpoint"
    # the other sensor: locked while held, saved, and it loads
    assert load_checkpoint(checkpoint_path(ck, "ankle"))["sensor_id"] == "ankle"
    assert len(lines) == 1, lines


def test_a_symlink_planted_at_a_temporary_name_is_never_written_through(tmp_path: Path) -> None:
    ck = tmp_path / "ck"
    ck.mkdir(mode=0o700)
    victim = _victim(tmp_path)
    keeper = Checkpoints(ck, 60.0, out=pytest.fail)
    keeper.acquire(["wrist"])
    # the names an earlier version used for its temporaries, for this process
    planted = [ck / f".wrist.json.{os.getpid()}.tmp", ck / f".wrist.json.prev.{os.getpid()}.tmp"]
    for p in planted:
        p.symlink_to(victim)
    node = _node(ck, keeper, "wrist")
    for _ in range(3):  # saves, and rotations into .prev
        keeper.save({"wrist": node})
    keeper.release()
    assert victim.read_text() == VICTIM
    assert all(p.is_symlink() for p in planted)
    for path in (checkpoint_path(ck, "wrist"), previous_path(ck, "wrist")):
        assert stat.S_ISREG(path.lstat().st_mode)
        assert load_checkpoint(path)["sensor_id"] == "wrist"
    # no temporary is left behind
    assert sorted(p.name for p in ck.iterdir() if p.name.startswith(".")) == \
        sorted(p.name for p in planted)


def test_a_symlink_planted_while_running_is_not_followed(tmp_path: Path) -> None:
    """After the start's check: loading refuses a symlink, saving replaces the link itself."""
    ck = tmp_path / "ck"
    victim = _victim(tmp_path)
    keeper = Checkpoints(ck, 60.0, out=lambda _s: None)
    keeper.acquire(["wrist"])
    node = _node(ck, keeper, "wrist")
    keeper.save({"wrist": node})
    keeper.save({"wrist": node})  # and a previous generation
    good = checkpoint_path(ck, "wrist").read_text()
    (ck / "other.json").write_text(good)
    checkpoint_path(ck, "wrist").unlink()
    checkpoint_path(ck, "wrist").symlink_to(ck / "other.json")
    with pytest.raises(CheckpointError, match="symlink"):
        load_checkpoint(checkpoint_path(ck, "wrist"))
    previous_path(ck, "wrist").unlink()
    previous_path(ck, "wrist").symlink_to(victim)
    keeper.save({"wrist": node})
    keeper.release()
    assert victim.read_text() == VICTIM
    assert (ck / "other.json").read_text() == good
    assert json.loads(checkpoint_path(ck, "wrist").read_text())["sensor_id"] == "wrist"


def test_a_symlinked_lock_is_refused_by_lock_sensor(tmp_path: Path) -> None:
    victim = _victim(tmp_path)
    (tmp_path / "wrist.lock").symlink_to(victim)
    with pytest.raises(OSError, match="symlink"):
        lock_sensor(tmp_path, "wrist")
    assert victim.read_text() == VICTIM
    held = lock_sensor(tmp_path, "ankle")
    try:
        with pytest.raises(SensorLockedError):
            lock_sensor(tmp_path, "ankle")
    finally:
        held.release()


def test_the_state_folder_is_private_and_a_shared_one_is_warned_about(tmp_path: Path) -> None:
    ck = tmp_path / "new" / "ck"
    lines: list[str] = []
    keeper = Checkpoints(ck, 60.0, out=lines.append, prefix="test:")
    keeper.acquire(["wrist"])
    keeper.release()
    assert stat.S_IMODE(ck.stat().st_mode) == 0o700 and lines == []
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    keeper = Checkpoints(shared, 60.0, out=lines.append, prefix="test:")
    keeper.acquire(["wrist"])
    keeper.release()
    assert len(lines) == 1 and str(shared) in lines[0] and "writable" in lines[0], lines
    assert stat.S_IMODE(shared.stat().st_mode) == 0o777  # the operator's folder: only a word
