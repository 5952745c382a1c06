"""Per-window scalar paths of the streaming core give the numbers of the numpy code they stand
in for, bit for bit: the running misfit's variance (`RunningMisfit.q_g2` against
`misfit.excess_g2`) and a window chunk's norms and sigmas read one at a time
(`WindowChunk.norm_at`, `sigma_at`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from recal.core.buffer import Windows
from recal.core.detector import DetectorConfig, detect, init_state
from recal.core.effects import Covariates
from recal.core.estimator import Prior
from recal.core.misfit import chance, excess_g2
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.refit import WindowChunk
from recal.core.status import MISFIT_CHANCE, RunningMisfit
from recal.samples import CalibratedBatch, RawBatch
from recal.sim.wearer import SensorSpec, simulate


def test_q_g2_is_excess_g2_bit_for_bit() -> None:
    rng = np.random.default_rng(7)
    r2 = np.concatenate([rng.uniform(0, 1e-5, 200), [0.0, 1e-300, np.inf, np.nan, 1e-6]])
    e2 = np.concatenate([rng.uniform(0, 1e-5, 200), [0.0, 0.0, 1.0, 1e-6, np.nan]])
    # past the first windows chance is MISFIT_CHANCE; over them, what a mean of n allows
    for n, chance_n in ((1000, MISFIT_CHANCE), (72, MISFIT_CHANCE), (1, float(chance(1))),
                        (5, float(chance(5))), (0, float(chance(1)))):
        for a, b in zip(r2.tolist(), e2.tolist(), strict=True):
            got = RunningMisfit(r2_g2=a, e2_g2=b, n=n).q_g2
            want = float(excess_g2(a, b, chance_n))
            assert type(got) is float
            if math.isnan(want):
                assert math.isnan(got)
            else:
                assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


def test_chunk_reads_one_window_as_the_arrays_hold() -> None:
    rng = np.random.default_rng(3)
    m = 50
    v = rng.normal(size=(m, 3))
    w = Windows(v, np.zeros((m, 0)), np.arange(m, dtype=np.int64) * 1_000_000,
                np.full(m, 50), rng.uniform(0, 1e-4, m))
    model = SensorModel.diagonal(1.0)
    def cov(t_us: np.ndarray, aux: np.ndarray) -> Covariates:
        return Covariates.from_samples(t_us, aux, (), 0)

    chunk = WindowChunk.of(model, model.nominal(), cov, 0.1, 4, w, np.arange(m), 0, m)
    chunk.sigma_mg = rng.uniform(0, 5, m)
    assert [chunk.norm_at(i) for i in range(m)] == [float(x) for x in chunk.norm]
    assert [chunk.sigma_at(i) for i in range(m)] == [float(x) for x in chunk.sigma_mg]


def test_detector_one_sample_at_a_time_is_the_batch_bit_for_bit() -> None:
    """`detect` of one sample (Python floats) against one batch (arrays): outputs, gates and
    the carried state, with a zero-g taken off, clipping, a flat-lined stretch, a NaN and an
    inf among the samples."""
    rng = np.random.default_rng(11)
    n = 1500
    raw = rng.normal(0.0, 10.0, (n, 3)) + np.array([2048.0, 2048.0, 3072.0])
    raw[300:420] += rng.normal(0.0, 300.0, (120, 3))  # movement
    raw[500:540] = raw[499]  # the device repeats itself: flat, not still
    raw[700, 0] = 2048.0 + 2000.0  # near full scale: clipped
    raw[800, 1], raw[900, 2] = np.nan, np.inf
    cfg = DetectorConfig(rate_hz=100.0, s0=1024.0, clip_raw=1900.0, flat_s=0.2,
                         zero_raw=(2048.0, 2048.0, 2048.0))
    end, whole = detect(cfg, init_state(cfg), raw)
    state, outs = init_state(cfg), []
    for i in range(n):
        state, out = detect(cfg, state, raw[i:i + 1])
        outs.append(out)
    for name in ("detector_g", "below_threshold", "clipped", "flat", "gate"):
        got = np.concatenate([getattr(o, name) for o in outs])
        assert np.array_equal(got, getattr(whole, name), equal_nan=name == "detector_g"), name
    assert np.array_equal(state.zi_hp, end.zi_hp) and np.array_equal(state.zi_lp, end.zi_lp)
    assert np.array_equal(state.last_v, end.last_v) and state.same_run == end.same_run
    assert whole.flat.any() and whole.clipped.any() and whole.gate.any()


@pytest.mark.parametrize("with_prior", [True, False])
def test_pipeline_one_sample_per_step_is_the_large_batches_bit_for_bit(with_prior: bool) -> None:
    """The one-sample paths of a step (detector, windower, correction, the batch built from
    checked arrays) against 1000-sample batches: every field of every calibrated sample, and
    the state at the end, bit for bit (integer readings, as a device's ADC counts: window
    sums then do not depend on where batches cut them). Without a prior the stream is
    bootstrapped first (the state is then redone from a snapshot within a batch)."""
    rng = np.random.default_rng(5)
    r = simulate(0.25, 50, 5, SensorSpec.random(rng, offset_mg=50, gain_pct=3))
    raw = RawBatch(r.raw.t_us, np.round(r.raw.v), r.raw.aux, r.raw.aux_names)
    model = SensorModel.diagonal(1024.0)

    def run(size: int) -> tuple[CalibratedBatch, str]:
        pipe = Pipeline(PipelineConfig(rate_hz=50), model,
                        Prior.default(model) if with_prior else None, raw.aux_names)
        outs = [pipe.step(raw[i:i + size]).calibrated for i in range(0, len(raw), size)]
        return CalibratedBatch.concat(outs), json.dumps(pipe.state_dict())

    (one, one_state), (big, big_state) = run(1), run(1000)
    for name in ("t_us", "a_g", "quasi_static", "detector_g", "status", "sigma_mg"):
        a, b = getattr(one, name), getattr(big, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert a.tobytes() == b.tobytes(), name
    assert one_state == big_state
    assert json.loads(big_state)["counts"]["updates"] > 3


@pytest.mark.parametrize("extra_mg2", [0.0, 2.5])
def test_correction_of_one_sample_is_the_batch_bit_for_bit(extra_mg2: float) -> None:
    """`correction.calibrate` of one sample (sigma from the segment's form as lists, the
    misfit's widening on Python floats) against a 400-sample batch (arrays): the same
    corrected values, statuses and sigmas, NaN and inf readings among them."""
    from recal.core.correction import Segment, calibrate
    from recal.core.status import Status, sigma_form

    rng = np.random.default_rng(13)
    model = SensorModel.diagonal(1024.0)
    p = model.nominal() + rng.normal(0.0, 20.0, model.size)
    a = rng.normal(0.0, 1e-3, (model.size, model.size))
    cov_p = a @ a.T + np.diag(np.full(model.size, 1e-2))
    form = sigma_form(model, p, cov_p)
    assert form is not None
    seg = Segment(0, model, p, cov_p, form, Status.HELD, extra_mg2, form.tolist())
    n = 400
    v = rng.normal(0.0, 800.0, (n, 3)) + np.array([0.0, 0.0, 1024.0])
    v[17, 0], v[99, 2], v[123, 1] = np.nan, np.inf, 1e200
    b = RawBatch(np.arange(n, dtype=np.int64) * 10_000, v, np.zeros((n, 0)), ())

    def cov(t_us: np.ndarray, aux: np.ndarray) -> Covariates:
        return Covariates.from_samples(t_us, aux, (), 0)

    whole = calibrate([seg], b, cov)
    ones = [calibrate([seg], b[i:i + 1], cov) for i in range(n)]
    for k, name in enumerate(("a_g", "status", "sigma_mg")):
        got = np.concatenate([o[k] for o in ones])
        assert got.dtype == whole[k].dtype and got.tobytes() == whole[k].tobytes(), name
    assert np.isnan(whole[2]).sum() >= 2 and np.isfinite(whole[2]).sum() > n - 5


@pytest.mark.parametrize("with_form", [True, False])
def test_the_unseen_floor_is_the_same_one_sample_or_in_a_batch(with_form: bool) -> None:
    """The unseen cross-axis floor a^T W a: folded into the form (`sigma.with_floor`) or
    added sample by sample (`sigma.floor_mg2`, a model without a form), one sample at a time
    gives the batch's sigmas to the bit; and the folded form is the per-sample floor's sum."""
    from recal.core.correction import Segment, calibrate
    from recal.core.sigma import floor_mg2, predicted_sigma_mg, sigma_form, with_floor
    from recal.core.status import Status

    rng = np.random.default_rng(14)
    model = SensorModel.diagonal(1024.0)
    p = model.nominal() + rng.normal(0.0, 20.0, model.size)
    cov_p = np.diag(np.full(model.size, 1e-2))
    form = sigma_form(model, p, cov_p)
    assert form is not None
    b = rng.normal(size=(3, 3)) * 3e-3
    w = b @ b.T
    n = 300
    v = rng.normal(0.0, 800.0, (n, 3)) + np.array([0.0, 0.0, 1024.0])
    t = RawBatch(np.arange(n, dtype=np.int64) * 10_000, v, np.zeros((n, 0)), ())

    def cov(t_us: np.ndarray, aux: np.ndarray) -> Covariates:
        return Covariates.from_samples(t_us, aux, (), 0)

    folded = with_floor(model, p, form, w)
    seg = (Segment(0, model, p, cov_p, folded, Status.HELD, 0.0, folded.tolist()) if with_form
           else Segment(0, model, p, cov_p, None, Status.HELD, 0.0, None, None, w))
    whole = calibrate([seg], t, cov)
    ones = np.concatenate([calibrate([seg], t[i:i + 1], cov)[2] for i in range(n)])
    assert ones.tobytes() == whole[2].tobytes()
    plain = predicted_sigma_mg(model, p, cov_p, v, cov(t.t_us, t.aux), form)
    a = model.correct(p, v, cov(t.t_us, t.aux))
    np.testing.assert_allclose(whole[2] ** 2, plain ** 2 + floor_mg2(a, w), rtol=1e-9)
