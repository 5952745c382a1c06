"""A sensor without a prior turned through a few clean poses: the lab six-position stream (each
pose held a few seconds, one after another) and data covering only five half-axes. The
bootstrap (core/bootstrap.py, pipeline_fit.try_bootstrap) must calibrate from them to the noise
floor: six poses determine the diagonal model's six parameters exactly, five half-axes a sphere.
"""

from __future__ import annotations

import numpy as np
import pytest

from recal.commands.replay import replay_lines
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import Status
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec, forward_model

RATE_HZ = 50.0
S0 = 1024.0
OFFSETS_COUNTS = np.array([20.0, -15.0, 10.0])
SIX = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


def _poses(dirs: np.ndarray, hold_s: float = 5.0, turn_s: float = 0.0, seed: int = 0,
           gain: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> RawBatch:
    """Poses held hold_s each, one after another (turn_s > 0: a hand turn between them, a
    swing in norm the detector sees; 0: the next pose starts at once, as a stream cut
    together from single-pose recordings), sensed by a 1024 counts/g part with 4 mg noise."""
    rng = np.random.default_rng(seed)
    parts = []
    for i, d in enumerate(dirs):
        parts.append(np.tile(d, (int(hold_s * RATE_HZ), 1)))
        if turn_s and i + 1 < len(dirs):
            s = np.linspace(0.0, 1.0, int(turn_s * RATE_HZ))[:, None]
            mid = (1 - s) * d + s * dirs[i + 1] + np.array([0.3, 0.2, 0.25])
            mid /= np.linalg.norm(mid, axis=1, keepdims=True)
            parts.append(mid * (1 + 0.4 * np.sin(np.pi * s)))  # a hand's push and stop
    a = np.concatenate(parts)
    spec = SensorSpec(counts_per_g=S0, offset_g=OFFSETS_COUNTS / S0, gain=gain, noise_g=0.004)
    v = forward_model(a, spec, rng=rng)
    t = np.arange(len(v), dtype=np.int64) * round(1e6 / RATE_HZ)
    return RawBatch(t, v, np.zeros((len(v), 0)))


def _run(raw: RawBatch, batch: int = 50) -> Pipeline:
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), SensorModel.diagonal(), None)
    for i in range(0, len(raw), batch):
        pipe.step(raw[i:i + batch])
    return pipe


@pytest.mark.parametrize("turn_s", [0.0, 2.0])
@pytest.mark.parametrize("batch", [1, 50, 10_000])
def test_six_clean_poses_without_prior_calibrate_to_the_noise_floor(turn_s: float,
                                                                    batch: int) -> None:
    gain = (0.02, -0.01, 0.015)
    pipe = _run(_poses(SIX, turn_s=turn_s, gain=gain), batch)
    assert pipe.bootstrapped and pipe.status is Status.CALIBRATED
    assert pipe.counts["updates"] >= 1 and pipe.counts["updates_rejected"] == 0
    p = pipe.model.params_dict(pipe.params)
    o = np.array([p["o_x"], p["o_y"], p["o_z"]])
    s = np.array([p["s_x"], p["s_y"], p["s_z"]])
    # 250 samples of 4 mg noise per pose: each mean within ~0.25 mg; an exact fit of six
    # means is as good, give or take a factor of a few
    assert np.all(np.abs(o - OFFSETS_COUNTS) < 2.0), o
    assert np.all(np.abs(s / (S0 * (1 + np.array(gain))) - 1) < 2e-3), s


def test_five_half_axes_without_prior_bootstrap_a_sphere() -> None:
    """No face-down pose: a sphere (offsets and one scale) through five poses and the tilts
    between them; bootstrapped, the offsets across gravity to the noise floor. z never seen
    from below leaves s_z to the sphere's common scale, so the output is held and says which
    parameter the data did not observe (partly observable), not called calibrated."""
    tilt = np.array([[1, 1, 1], [-1, 1, 1], [1, -1, 1], [-1, -1, 1]], float) / np.sqrt(3)
    pipe = _run(_poses(np.vstack([SIX[:5], tilt]), turn_s=2.0))
    assert pipe.bootstrapped and pipe.status is Status.HELD and pipe.unobserved == ("s_z",)
    p = pipe.model.params_dict(pipe.params)
    assert abs(p["o_x"] - OFFSETS_COUNTS[0]) < 2.0 and abs(p["o_y"] - OFFSETS_COUNTS[1]) < 2.0
    assert abs(p["o_z"] - OFFSETS_COUNTS[2]) < 4.0


def test_one_pose_and_its_neighbours_do_not_bootstrap() -> None:
    """Four half-axes (never x- and never z-): nothing pins the scale; no fit, and says so."""
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, -1, 0], [0.7, 0.7, 0], [0.7, -0.7, 0],
                     [0.6, 0, 0.8]])
    pipe = _run(_poses(dirs, turn_s=2.0))
    assert not pipe.bootstrapped and pipe.estimate is None


def _summary(rejected: int, reason: str) -> dict:
    return {"samples": 1500, "seconds": 1.0, "samples_per_s": 1500.0, "out": "x.mcap",
            "sensors": {"s": {"start": "bootstrap", "model": "diagonal", "bootstrapped": False,
                              "counts": {"quasi_static": 1400, "windows": 12,
                                         "updates": rejected, "updates_rejected": rejected},
                              "residual_rms_mg": None, "last_update_reason": reason}}}


def test_replay_summary_names_rejected_updates_not_coverage() -> None:
    lines = "\n".join(replay_lines(_summary(5, "out of bounds: o_z")))
    assert "5 updates rejected" in lines and "out of bounds: o_z" in lines
    assert "orientations" not in lines
    lines = "\n".join(replay_lines(_summary(0, "")))
    assert "orientations" in lines


def test_six_clean_poses_of_an_unsigned_analog_part_without_prior() -> None:
    """An analog part on a 12-bit ADC (zero-g ~2048 counts, 372 counts/g): zero-g and the scale
    come from the six still means too (`bootstrap.locate`), then the fit."""
    rng = np.random.default_rng(0)
    parts = [np.tile(d, (int(5 * RATE_HZ), 1)) for d in SIX]
    a = np.concatenate(parts)
    spec = SensorSpec(counts_per_g=372.0, zero_g_counts=2048.0, adc_bits=12, full_scale_g=None,
                      offset_g=(0.02, -0.015, 0.01), gain=(0.02, -0.01, 0.015), noise_g=0.004)
    v = forward_model(a, spec, rng=rng)
    t = np.arange(len(v), dtype=np.int64) * round(1e6 / RATE_HZ)
    pipe = _run(RawBatch(t, v, np.zeros((len(v), 0))))
    assert pipe.bootstrapped and pipe.status is Status.CALIBRATED
    p = pipe.model.params_dict(pipe.params)
    o = np.array([p["o_x"], p["o_y"], p["o_z"]])
    s = np.array([p["s_x"], p["s_y"], p["s_z"]])
    o_true = 2048.0 + 372.0 * np.array(spec.offset_g)
    assert np.all(np.abs(o - o_true) < 1.5), o  # counts of 2.7 mg
    assert np.all(np.abs(s / (372.0 * (1 + np.array(spec.gain))) - 1) < 4e-3), s
