"""Per-window scalar paths of the streaming core give the numbers of the numpy code they stand
in for, bit for bit: the running misfit's variance (`RunningMisfit.q_g2` against
`misfit.excess_g2`) and a window chunk's norms and sigmas read one at a time
(`WindowChunk.norm_at`, `sigma_at`)."""

from __future__ import annotations

import math

import numpy as np

from recal.core.buffer import Windows
from recal.core.effects import Covariates
from recal.core.misfit import chance, excess_g2
from recal.core.model import SensorModel
from recal.core.refit import WindowChunk
from recal.core.status import MISFIT_CHANCE, RunningMisfit


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
