"""What a node's output is worth right after live discovery adopted a model: the estimator
goes on from what the discovery fit learnt (its buffer refilled from the evidence, the new
terms' prior narrowed to the fit's sd), so the status is calibrated at the next still window,
with a sigma that covers the error. Before, the estimator re-fitted a buffer the old model's
misfit had kept resetting, and held the output minutes until the new model's scales were
known to 5 mg again."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench_modules import load_bench
from recal.config import PipelineSection
from recal.core.buffer import Windows
from recal.core.effects import make_effect
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline, learnt_prior
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import Status
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import CalibratedBatch
from recal.sim import wearer as sim
from recal.sim.sensor import sensor_type
from test_discovery import RATE_HZ, SEED, WEARER, _Capture

hc = load_bench("honesty_cases")


class _Keep(_Capture):
    """`_Capture`, and the calibrated batches whole (status and sigma)."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: list[CalibratedBatch] = []

    def calibrated(self, sensor_id: str, cal: CalibratedBatch, log_time_ns: int,
                   topic: str = "calibrated") -> None:
        super().calibrated(sensor_id, cal, log_time_ns, topic)
        if topic == "calibrated":
            self.batches.append(cal)


def _supply_case() -> tuple[sim.SimResult, sim.SensorSpec]:
    """An analog 12-bit part whose output scales with its supply, which sags 3.3 -> 2.9 V
    over the half hour: nothing declares it."""
    spec = sensor_type("adxl335-adc12", np.random.default_rng(1), ratiometric_per_v=1 / 3.3,
                       v_ref_v=3.3)
    wearer = replace(WEARER, vdd_start_v=3.3, vdd_end_v=2.9)
    return sim.simulate(0.5, RATE_HZ, SEED, spec, wearer), spec


@pytest.mark.slow
@pytest.mark.float_sensitive
def test_after_adoption_the_status_is_calibrated_at_once_and_sigma_covers_the_error() -> None:
    res, spec = _supply_case()
    raw = res.raw
    model = SensorModel.diagonal(float(spec.counts_per_g))
    p0 = model.nominal()
    p0[model.slice(("offset", None))] = spec.zero_g_counts
    sink = _Keep()
    node = CalibrationNode(NodeSettings("s1", PipelineSection(), model,
                                        Prior.default(model, p0), RATE_HZ), sink)
    for i in range(0, len(raw), 500):  # bounded: one pass, a message at a time
        node.process(raw[i:i + 500], 0)
    adopted = [o for s, o in sink.json_messages if s == "events" and o["kind"] == "discovery"
               and o["detail"]["adopted"]]
    assert len(adopted) == 1 and adopted[0]["detail"]["added"] == ["ratiometric[vdd_v]"]
    cal = CalibratedBatch.concat(sink.batches)
    after = cal.t_us > adopted[0]["t_us"]
    assert after.sum() > 5 * 60 * RATE_HZ  # minutes of output after it
    status = cal.status[after]
    calibrated = status == Status.CALIBRATED
    # calibrated within the first 30 s (the next still window), and stays so (the estimator
    # restarted from the prior held it 3 minutes, 64 % calibrated after adoption)
    assert calibrated.any() and int(np.argmax(calibrated)) < 30 * RATE_HZ
    assert calibrated.mean() > 0.95
    # sigma covers the error of the calibrated seconds, and is not many times it
    h = hc.honesty(cal.a_g[after], res.truth.a_true_g[after], cal.sigma_mg[after], status,
                   RATE_HZ, spec.noise_g)
    assert h["calibrated"] > 0.9 * h["windows"]
    assert h["beyond_3"] <= 0.01 and h["beyond_10"] == 0.0
    assert h["sigma_median_mg"] <= 3 * h["error_median_mg"] + 0.5


def test_the_adopted_prior_narrows_the_new_terms_only() -> None:
    base = SensorModel.diagonal(1024.0)
    model = base.with_effect(make_effect("offset", "temp_c", 0.0), 1.0)
    prior = Prior.default(model)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(model.size, model.size))
    cov = 1e-6 * (a @ a.T) + np.diag(np.full(model.size, 1e-4))  # tighter than every default
    got = learnt_prior(model, prior, cov)
    np.testing.assert_array_equal(got.mean, prior.mean)
    terms = model.slice(("offset", "temp_c"))
    core = np.ones(model.size, bool)
    core[terms] = False
    np.testing.assert_allclose(got.sd[core], prior.sd[core])  # offsets and scales as before
    np.testing.assert_allclose(got.sd[terms], np.sqrt(np.diag(cov))[terms])  # the fit's sd
    wide = learnt_prior(model, prior, np.diag(np.full(model.size, 1e12)))
    np.testing.assert_allclose(wide.sd, prior.sd)  # never wider than the default


def test_adopting_with_the_evidence_refills_the_buffer_from_it() -> None:
    model = SensorModel.diagonal(1024.0)
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model))
    rng = np.random.default_rng(4)
    u = rng.normal(size=(200, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = Windows(1024.0 * u, np.zeros((200, 0)), np.arange(200, dtype=np.int64) * 30_000_000,
                np.full(200, 50, np.int64), np.full(200, 1.0))
    assert len(pipe.buffer) == 0
    pipe.adopt(model, Prior.default(model), np.diag(np.full(model.size, 1.0)), w)
    assert len(pipe.buffer) > 50  # spread over the sphere: many cells, up to 6 windows each
    far = Windows(w.v * 1.5, w.aux, w.t_us, w.n, w.var)  # 0.5 g off: the norm gate drops them
    pipe.adopt(model, Prior.default(model), np.diag(np.full(model.size, 1.0)), far)
    assert len(pipe.buffer) == 0
