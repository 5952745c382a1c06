"""A candidate model waiting to be adopted or rejected (`core.pending`): sigma carries how much
its correction of each sample differs from the one in force, where they differ and only
there, through the pipeline (batches and one sample at a time), and a checkpoint keeps it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recal.core.effects import CrossAxis, Offset
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pending import PendingCandidate
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.errors import ModelError
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec

S0 = 1000.0
RATE_HZ = 25.0
#: the candidate's offset per degree (counts/degC): 2 mg/degC at s0
TEMP_COEF = 2.0
REF_C = 25.0


def wearer_pipeline(spec: SensorSpec, raw: RawBatch, upto: int | None = None) -> Pipeline:
    """The diagonal model at the sensor's own zero-g and scale (a datasheet prior) through a
    simulated wearer's raw samples (the first ``upto``), 500 at a time."""
    model = SensorModel.diagonal(float(spec.counts_per_g or 1024.0))
    p0 = model.nominal()
    p0[model.slice(("offset", None))] = spec.zero_g_counts
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model, p0),
                    raw.aux_names)
    end = len(raw) if upto is None else upto
    for i in range(0, end, 500):
        pipe.step(raw[i:min(i + 500, end)])
    return pipe


def _pipe() -> Pipeline:
    """A diagonal model known to 1 count (1 mg) per parameter: sigma ~2 mg before a doubt."""
    model = SensorModel.diagonal(S0)
    return Pipeline(PipelineConfig(rate_hz=RATE_HZ), model,
                    Prior.from_sd(model.nominal(), np.ones(model.size)), ("temp_c",))


def _moving(n: int, temp_c: np.ndarray | float, rng: np.random.Generator,
            direction: np.ndarray | None = None) -> RawBatch:
    """n readings of 1 g, each in a random direction (or ``direction``, each 5 % off in norm
    so no window is still), at temp_c: no still window, so nothing updates the estimate."""
    if direction is None:
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
    else:
        u = np.tile(direction / np.linalg.norm(direction), (n, 1))
        u *= (1.0 + 0.05 * np.sign(np.sin(np.arange(n))))[:, None]
    t_us = np.arange(n, dtype=np.int64) * round(1e6 / RATE_HZ)
    aux = np.broadcast_to(np.asarray(temp_c, np.float64), (n,)).reshape(n, 1).copy()
    return RawBatch(t_us, S0 * u, aux, ("temp_c",))


def _temperature_candidate(pipe: Pipeline) -> PendingCandidate:
    """The model in force plus an offset following temperature (2 mg/degC on x only)."""
    model, q = pipe.model.extend(pipe.params, Offset("temp_c", REF_C), 10.0)
    q[model.index("o_temp_c_x")] = TEMP_COEF
    return PendingCandidate(model, q, np.diag(model.prior_sd() ** 2), "offset[temp_c]")


def _sigma(pipe: Pipeline, batch: RawBatch, one_by_one: bool = False) -> np.ndarray:
    if one_by_one:
        return np.concatenate([pipe.step(batch[i:i + 1]).calibrated.sigma_mg
                               for i in range(len(batch))])
    return pipe.step(batch).calibrated.sigma_mg


def _twins() -> tuple[Pipeline, Pipeline]:
    a = _pipe()
    return a, Pipeline.from_state_dict(json.loads(json.dumps(a.state_dict())))


@pytest.mark.parametrize("one_by_one", [False, True])
def test_a_temperature_candidate_widens_sigma_by_its_disagreement_away_from_its_reference(
        one_by_one: bool) -> None:
    plain, doubting = _twins()
    doubting.set_pending(_temperature_candidate(doubting))
    rng = np.random.default_rng(1)
    temp = np.repeat([REF_C, REF_C + 5.0, REF_C - 10.0], 40)
    batch = _moving(len(temp), temp, rng)
    s0_mg, s1_mg = _sigma(plain, batch, one_by_one), _sigma(doubting, batch, one_by_one)
    assert np.all(np.isfinite(s0_mg)) and np.all(s0_mg > 0)
    # the disagreement: the x offset's 2 mg/degC times the distance from the reference
    d_mg = 1e3 * TEMP_COEF * np.abs(temp - REF_C) / S0
    np.testing.assert_allclose(s1_mg ** 2 - s0_mg ** 2, d_mg ** 2, rtol=1e-6, atol=1e-6)
    at_ref = temp == REF_C
    np.testing.assert_allclose(s1_mg[at_ref], s0_mg[at_ref], rtol=1e-12)  # they agree there
    assert np.all(s1_mg[~at_ref] > s0_mg[~at_ref] + 5.0)


def test_a_cross_axis_candidate_widens_sigma_across_gravity_at_the_orientations_it_bends() -> None:
    """A candidate with one cross-axis term (the y reading into the x output): along x and z
    the two corrections agree, along y they differ by the term across gravity, where no norm
    residual shows it."""
    plain, doubting = _twins()
    model, q = doubting.model.extend(doubting.params, CrossAxis(), 0.01)
    q[model.index("c_xy")] = 0.01
    doubting.set_pending(PendingCandidate(model, q, np.diag(model.prior_sd() ** 2)))
    rng = np.random.default_rng(2)
    for axis, widened in (((0.0, 0.0, 1.0), False), ((1.0, 0.0, 0.0), False),
                          ((0.0, 1.0, 0.0), True)):
        batch = _moving(60, REF_C, rng, np.array(axis))
        s0_mg, s1_mg = _sigma(plain, batch), _sigma(doubting, batch)
        if not widened:
            np.testing.assert_allclose(s1_mg, s0_mg, rtol=1e-12)
        else:  # |d| = c_xy x the reading along y (g): 10 mg at 1 g, 10.5 / 9.5 mg here
            d_mg = 1e3 * 0.01 * np.abs(batch.v[:, 1]) / S0
            np.testing.assert_allclose(s1_mg ** 2 - s0_mg ** 2, d_mg ** 2, rtol=1e-6)


def test_rejecting_or_adopting_ends_the_doubt() -> None:
    plain, doubting = _twins()
    cand = _temperature_candidate(doubting)
    doubting.set_pending(cand)
    assert doubting.pending is cand and doubting.summary()["pending"] == "offset[temp_c]"
    rng = np.random.default_rng(3)
    batch = _moving(20, REF_C + 10.0, rng)
    assert np.all(_sigma(doubting, batch) > _sigma(plain, batch) + 10.0)
    doubting.set_pending(None)  # rejected
    batch = _moving(20, REF_C + 10.0, rng)
    np.testing.assert_allclose(_sigma(doubting, batch), _sigma(plain, batch), rtol=1e-12)
    doubting.set_pending(cand)
    doubting.adopt(cand.model, Prior.default(cand.model, cand.p))
    assert doubting.pending is None and doubting.summary()["pending"] is None


def test_the_candidate_survives_a_checkpoint_and_the_sigmas_continue_alike() -> None:
    pipe = _pipe()
    cand = _temperature_candidate(pipe)
    pipe.set_pending(cand)
    rng = np.random.default_rng(4)
    pipe.step(_moving(30, REF_C + 3.0, rng))
    back = Pipeline.from_state_dict(json.loads(json.dumps(pipe.state_dict())))
    assert back.pending is not None and back.pending.label == cand.label
    assert back.pending.model.to_dict() == cand.model.to_dict()
    np.testing.assert_array_equal(back.pending.p, cand.p)
    np.testing.assert_array_equal(back.pending.cov, cand.cov)
    batch = _moving(30, REF_C - 7.0, rng)
    np.testing.assert_array_equal(back.step(batch).calibrated.sigma_mg,
                                  pipe.step(batch).calibrated.sigma_mg)


def test_a_candidate_in_other_units_or_channels_is_refused() -> None:
    pipe = _pipe()
    other = SensorModel.diagonal(2 * S0)
    with pytest.raises(ModelError):
        pipe.set_pending(PendingCandidate(other, other.nominal(), np.eye(other.size)))
    model, q = pipe.model.extend(pipe.params, Offset("vdd_v", 3.3), 0.1)
    with pytest.raises(ModelError):
        pipe.set_pending(PendingCandidate(model, q, np.eye(model.size)))


@pytest.mark.slow
@pytest.mark.float_sensitive
def test_a_discovery_runs_candidate_widens_sigma_where_the_model_in_force_errs() -> None:
    """The hook as the live node calls it: a discovery run on the buffer of a wearer whose
    offsets follow temperature (which the diagonal model lacks) ends with a candidate; set
    pending, sigma widens most in the seconds whose output (the model in force) errs most
    against the truth, and no second is further beyond 3 sigma than without it."""
    from dataclasses import replace

    from recal.core.discovery import discover_pipeline
    from recal.sim import wearer as sim

    spec = replace(sim.SensorSpec.random(np.random.default_rng(2), 50, 3),
                   offset_tc_g_per_c=(1.5e-3, -1.5e-3, 1.5e-3))
    res = sim.simulate(1.0, RATE_HZ, 2, spec, sim.WearerSpec(temp_excursion_every_h=0.5))
    k = len(res.raw) // 2
    pipe = wearer_pipeline(spec, res.raw, k)
    found = discover_pipeline(pipe.buffer.windows(), pipe.aux_names, pipe.t0_us or 0,
                              pipe.model, pipe.params)
    cand = PendingCandidate.of_result(found)
    assert cand is not None and "temp_c" in cand.label, [s.effect.label for s in found.steps]
    plain = Pipeline.from_state_dict(json.loads(json.dumps(pipe.state_dict())))
    pipe.set_pending(cand)
    rest, truth = res.raw[k:], res.truth.a_true_g[k:]
    without, with_ = plain.step(rest).calibrated, pipe.step(rest).calibrated
    np.testing.assert_array_equal(with_.a_g, without.a_g)  # sigma only
    n = int(RATE_HZ)
    m = len(rest) // n

    def per_s(x: np.ndarray) -> np.ndarray:
        return x[:m * n].reshape(m, n, *x.shape[1:]).mean(axis=1)

    err_mg = 1e3 * np.linalg.norm(per_s(without.a_g - truth), axis=1)
    s0_mg, s1_mg = per_s(without.sigma_mg), per_s(with_.sigma_mg)
    widening = np.sqrt(np.maximum(s1_mg ** 2 - s0_mg ** 2, 0.0))
    assert np.all(s1_mg >= s0_mg)
    assert np.corrcoef(widening, err_mg)[0, 1] > 0.7
    assert np.quantile(widening, 0.9) > 3.0 * np.quantile(widening, 0.1) + 0.5  # not uniform
    assert np.mean(err_mg > 3 * s1_mg) <= np.mean(err_mg > 3 * s0_mg)


def test_adopting_a_model_drops_the_misfit_measured_under_the_one_it_replaces() -> None:
    """An hour of a wearer whose offsets follow temperature under the diagonal model leaves a
    misfit in sigma; adopting the model with the effect starts the misfit again (kappa and the
    unseen floor kept: they are the postures')."""
    from dataclasses import replace

    from recal.sim import wearer as sim

    spec = replace(sim.SensorSpec.random(np.random.default_rng(2), 50, 3),
                   offset_tc_g_per_c=(1.5e-3, -1.5e-3, 1.5e-3))
    res = sim.simulate(0.5, RATE_HZ, 2, spec, sim.WearerSpec(temp_excursion_every_h=0.5))
    pipe = wearer_pipeline(spec, res.raw)
    before = pipe.watch.misfit
    assert pipe.summary()["misfit_mg"] > 1.0 and before.extra_mg2 > 1.0
    new, q = pipe.model.extend(pipe.params, Offset("temp_c", 30.0), 5.0)
    pipe.adopt(new, Prior.default(new, q))
    after = pipe.watch.misfit
    assert pipe.summary()["misfit_mg"] == 0.0 and after.extra_mg2 == 0.0
    assert after.across == before.across and after.unseen_w == before.unseen_w


def test_a_sample_whose_channel_the_candidate_reads_is_missing_keeps_its_sigma() -> None:
    plain, doubting = _twins()
    doubting.set_pending(_temperature_candidate(doubting))
    temp = np.array([REF_C + 10.0, np.nan, REF_C + 10.0, np.nan])
    batch = _moving(4, temp, np.random.default_rng(6))
    for one in (False, True):
        s0_mg, s1_mg = _sigma(plain, batch, one), _sigma(doubting, batch, one)
        assert np.all(np.isfinite(s1_mg))
        np.testing.assert_allclose(s1_mg[1::2], s0_mg[1::2], rtol=1e-12)
        assert np.all(s1_mg[::2] > s0_mg[::2] + 10.0)
