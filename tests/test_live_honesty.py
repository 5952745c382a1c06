"""The sigma-honesty bench's cases through the live node (bench/sigma_honesty.py `run_live`):
a node restored from a checkpoint the way the gateway restores one, the lab's six poses, and
effects with their term in the model, each against the core pipeline's row."""

from __future__ import annotations

from functools import cache
from types import ModuleType

import numpy as np
import pytest

from bench_modules import load_bench
from recal.sim import wearer as sim

MINUTES = 60.0


@cache
def _bench() -> ModuleType:
    return load_bench("sigma_honesty")


def _live_as_core(name: str, seed: int = 1) -> dict:
    """The live row of one case, checked equal to the core pipeline's field by field (but the
    CPU time; by repr, so a "never" (NaN) equals a "never")."""
    sh = _bench()
    live = sh.run_live(name, sh.CASES[name], MINUTES, seed)
    core = sh.run(name, sh.CASES[name], MINUTES, seed)
    assert {k: repr(v) for k, v in live.items() if k != "cpu_s"} == {
        k: repr(v) for k, v in core.items() if k != "cpu_s"}
    return live


@pytest.mark.parametrize("name", ["poisoned checkpoint (offset x +0.39 g)",
                                  "another sensor's checkpoint"])
def test_a_node_restored_from_a_bad_checkpoint_marks_no_second_calibrated_while_off(
        name: str) -> None:
    """The first half's node checkpointed into a state folder, its offset x moved by 0.39 g
    (inside the bounds: the load checks pass it) or another sensor's data after it; the node
    `make_node` restores from it (as the gateway does) doubts: no calibrated second more than
    20 mg off; either suspect at the first still window that contradicts (15-21 s here), or
    the estimate re-fitted right before any second is marked calibrated (the jump test allows
    for what a model misses at a posture: where the restored estimate is wrong at every
    posture of its buffer, the re-fit rather than a jump corrects it); and the node's row is
    the core pipeline's, which restores and doubts by hand."""
    live = _live_as_core(name)
    assert live["cal_over_20mg"] == 0, live
    assert live["to_suspect_s"] <= 30.0 or (live["cal_pct"] > 0 and live["err_mg"] < 2.0), live


def test_the_restored_node_is_the_checkpoints() -> None:
    """`_restored` goes through the state folder: the node starts from the checkpoint (not the
    prior), and the poisoned offset is what it starts with."""
    sh = _bench()
    case = sh.CASES["poisoned checkpoint (offset x +0.39 g)"]
    spec = case.spec(np.random.default_rng(1))
    raw = sim.simulate(0.25, sh.RATE_HZ, 1, spec).raw
    settings = sh._settings(*sh._model_prior(spec, case, raw))
    clean = sh._restored(settings, raw, sh._Kept(), poison=False)
    poisoned = sh._restored(settings, raw, sh._Kept(), poison=True)
    assert clean.start == poisoned.start == "checkpoint"
    assert clean.pipeline is not None and poisoned.pipeline is not None
    moved = poisoned.pipeline.estimate.p - clean.pipeline.estimate.p
    assert moved[0] == pytest.approx(400.0) and not np.any(moved[1:])


def test_six_clean_poses_through_the_node_calibrate_to_the_noise_floor() -> None:
    """The lab stream (six poses held 5 s, twice) through a node without a prior: calibrated
    through the second round at the noise left in a 1 s mean (1.39 mg), none beyond 3
    sigma_eff; the core pipeline's row."""
    live = _live_as_core("six clean poses twice, no prior (lab)")
    assert live["cal_s"] >= 30 and live["err_mg"] < 2.0 and live["beyond3_pct"] == 0.0, live


@pytest.mark.parametrize("name", ["temperature 1.5 mg/degC on offsets, with its term (fits)",
                                  "analog 12-bit, sagging supply, with its term (fits)"])
def test_an_effect_with_its_term_in_the_model_calibrates_live_to_the_noise_floor(
        name: str) -> None:
    """Temperature on the offsets, a sagging supply on a ratiometric part: with the term
    `recal discover` adds, the node calibrates to the noise floor (11.5 and 15.6 mg without
    it, the diagonal rows of the bench), none beyond 3 sigma_eff; the core pipeline's row."""
    live = _live_as_core(name)
    assert live["err_mg"] < 2.0 and live["cal_s"] > 1000, live
    assert live["beyond3_pct"] == 0.0 and live["beyond10_pct"] == 0.0
