"""The streaming core's fast paths give what the general code gives, to the bit: the
per-axis Jacobian of the correction (`status._unit_jacobian`) against the full chain rule."""

from __future__ import annotations

import numpy as np
import pytest

from recal.core.candidates import proposals
from recal.core.effects import Covariates, CrossAxis, Effect, Gain, Offset, Ratiometric
from recal.core.model import SensorModel
from recal.core.sigma import _chain_jacobian, correction_jacobian, predicted_sigma_mg

S0 = 1024.0
CHANNELS = ("vdd", "temp", "vref")


def _chain_rule(model: SensorModel, p: np.ndarray, v: np.ndarray,
                cov: Covariates) -> np.ndarray:
    """J = da/dp by every stage's full `vjp`, each unit row of da/da in turn, whatever the
    model says of its axes."""
    stages = [(e, model.slice(e)) for e in model.effects]
    xs = [v]
    for e, sl in stages:
        xs.append(e.apply(xs[-1], cov, p[sl]))
    return _chain_jacobian(stages, xs, cov, p, len(v), model.size)


MODELS = {
    "diagonal": lambda: SensorModel.diagonal(S0),
    "ratiometric": lambda: SensorModel.diagonal(S0).with_effect(Ratiometric("vdd", 3.3), 0.5),
    "ratiometric-ref": lambda: SensorModel.diagonal(S0).with_effect(
        Ratiometric("vdd", 3.3, reference="vref", reference_ref=1.2), 0.5),
    "temperature": lambda: SensorModel.diagonal(S0).with_effect(Gain("temp", 20.0), 10.0)
    .with_effect(Offset("temp", 20.0), 10.0),
    "all": lambda: SensorModel.diagonal(S0).with_effect(Ratiometric("vdd", 3.3), 0.5)
    .with_effect(Gain("temp", 20.0), 10.0).with_effect(Offset("time"), 1.0),
}


def _inputs(model: SensorModel, rng: np.random.Generator, n: int
            ) -> tuple[np.ndarray, Covariates, np.ndarray]:
    """n random readings, the three channels around their references, parameters near
    nominal (drawn from ``rng`` in that order)."""
    v = rng.normal(0, S0, (n, 3))
    aux = np.column_stack([3.3 + rng.normal(0, 0.3, n), 20 + rng.normal(0, 5, n),
                           1.2 + rng.normal(0, 0.01, n)])
    cov = Covariates.from_samples(np.arange(n) * 20_000, aux, CHANNELS, 0)
    p = model.nominal() + rng.normal(size=model.size) * model.prior_sd() * 0.3
    return v, cov, p


def _assert_same_bits(J: np.ndarray, ref: np.ndarray) -> None:
    """Equal to the bit, where -0.0 == 0.0 (the full rule's zero columns may be -0.0)."""
    assert np.array_equal(J, ref)
    nonzero = J != 0
    assert np.array_equal(J[nonzero].view(np.uint64), ref[nonzero].view(np.uint64))


@pytest.mark.parametrize("name", sorted(MODELS))
def test_per_axis_jacobian_is_the_chain_rule_to_the_bit(name: str) -> None:
    model = MODELS[name]()
    assert model.axes_apart  # the fast path
    rng = np.random.default_rng(3)
    v, cov, p = _inputs(model, rng, 2000)
    ref = _chain_rule(model, p, v, cov)
    _assert_same_bits(correction_jacobian(model, p, v, cov), ref)
    if not model.covariates:
        return  # its sigma is a quadratic form (`status.sigma_form`), not J sample by sample
    a = rng.normal(size=(model.size, model.size)) * model.prior_sd()
    cov_p = a @ a.T / model.size
    sigma = predicted_sigma_mg(model, p, cov_p, v, cov)
    full = 1e3 * np.sqrt(np.einsum("nip,nip->n", np.matmul(ref, cov_p), ref))
    assert np.array_equal(sigma.view(np.uint64), full.view(np.uint64))


#: every form of every kind the registry proposes, each on the diagonal model
REGISTERED = {e.label: (e, sp) for e, sp in proposals(
    SensorModel.diagonal(S0), {"vdd": (3.3, 0.5), "temp": (20.0, 10.0)}, (0.0, 1.0))}


@pytest.mark.parametrize("label", sorted(REGISTERED))
def test_every_registered_effect_gives_the_chain_rule_to_the_bit(label: str) -> None:
    """Whichever path `correction_jacobian` takes for it (axis by axis or the full rule)."""
    model = SensorModel.diagonal(S0).with_effect(*REGISTERED[label])
    v, cov, p = _inputs(model, np.random.default_rng(6), 500)
    _assert_same_bits(correction_jacobian(model, p, v, cov), _chain_rule(model, p, v, cov))


def test_a_stage_that_mixes_axes_takes_the_chain_rule() -> None:
    model = SensorModel.diagonal(S0).with_effect(Ratiometric("vdd", 3.3), 0.5).with_effect(
        CrossAxis(), 1.0)
    assert type(model.effects[-1]).unit_vjp is Effect.unit_vjp and not model.axes_apart
    rng = np.random.default_rng(4)
    v = rng.normal(0, S0, (500, 3))
    cov = Covariates.from_samples(np.arange(500) * 20_000,
                                  np.column_stack([3.3 + rng.normal(0, 0.3, 500),
                                                   np.zeros(500), np.zeros(500)]), CHANNELS, 0)
    p = model.nominal() + rng.normal(size=model.size) * model.prior_sd() * 0.3
    ref = _chain_rule(model, p, v, cov)
    assert np.array_equal(correction_jacobian(model, p, v, cov).view(np.uint64),
                          ref.view(np.uint64))


def test_the_estimators_median_is_numpys_to_the_bit() -> None:
    """`estimator._median` (a partition) against np.median, odd and even counts, with ties."""
    from recal.core.estimator import _median

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 4, 7, 8, 31, 64, 257):
        for _ in range(20):
            x = np.round(rng.lognormal(size=n), 2) * 1e-7  # ties among the values
            got, want = _median(x), float(np.median(x))
            assert np.float64(got).view(np.uint64) == np.float64(want).view(np.uint64)
    assert np.isnan(_median(np.array([1.0, np.nan, 2.0])))
