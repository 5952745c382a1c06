"""The windower (`core.windower`): its two ways of cutting a batch (all runs at once, run by
run) give the same windows bit for bit, whatever the batches, gates and time steps."""

from __future__ import annotations

import json
from itertools import pairwise

import numpy as np
import pytest

from recal.core.windower import WindowConfig, WindowerState, WindowSums, _Cutter, cut

CFG = WindowConfig(rate_hz=50.0, window_s=2.0, guard_s=1.0, min_fill=0.8)


def _stream(seed: int, n: int, n_aux: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                    np.ndarray]:
    """Times with jitter, gaps and steps back; float readings; gates in runs of all lengths."""
    rng = np.random.default_rng(seed)
    dt = np.full(n, 20_000, np.int64) + rng.integers(-3000, 3000, n)
    odd = rng.random(n)
    dt[odd < 0.002] = 200_000  # a gap
    dt[(odd > 0.002) & (odd < 0.003)] = -50_000  # a step back
    sparse = np.repeat(rng.random(n // 500 + 1) < 0.3, 500)[:n]
    dt[sparse & (odd > 0.5)] = 55_000  # stretches of samples far apart: short windows
    t = 1_000_000 + np.cumsum(dt)
    v = rng.normal(0.0, 0.3, (n, 3)) + np.array([0.1, -0.2, 0.97])
    aux = rng.normal(25.0, 1.0, (n, n_aux))
    lengths = rng.choice([1, 5, 30, 80, 101, 150, 400, 2000], size=n)
    gate = np.zeros(n, bool)
    i, on = 0, bool(rng.integers(2))
    while i < n:
        gate[i:i + lengths[i]] = on
        i, on = i + int(lengths[i]), not on
    return t, v, aux, gate


def _sums(w: WindowSums | None) -> list:
    return [] if w is None else [np.asarray(getattr(w, f)).tobytes() for f in
                                 ("run_start_us", "k", "n", "sum_v", "sum_v2", "sum_aux",
                                  "sum_t")]


@pytest.mark.parametrize("seed, n_aux, largest", [(1, 0, 3000), (2, 2, 300), (3, 1, 20000),
                                                  (4, 0, 60)])
def test_all_runs_at_once_and_run_by_run_cut_the_same_windows(seed: int, n_aux: int,
                                                              largest: int) -> None:
    t, v, aux, gate = _stream(seed, 60_000, n_aux)
    rng = np.random.default_rng(seed + 10)
    ends = np.cumsum(rng.integers(1, largest, size=len(t)))
    ends = [0, *ends[ends < len(t)].tolist(), len(t)]
    a = b = WindowerState()
    n_windows = n_due = 0
    for lo, hi in pairwise(ends):
        s = slice(lo, hi)
        ca, a = cut(CFG, a, t[s], v[s], aux[s], gate[s], runs_at_once=1)
        cb, b = cut(CFG, b, t[s], v[s], aux[s], gate[s], runs_at_once=10**9)
        assert ca.due == cb.due
        assert _sums(ca.sums) == _sums(cb.sums)
        assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())
        n_windows += ca.committed
        n_due += len(ca.due)
    assert n_windows > 100 and n_due > n_windows  # windows committed, and short ones


def test_the_state_restores_from_its_dict() -> None:
    t, v, aux, gate = _stream(5, 5000, 1)
    _, st = cut(CFG, WindowerState(), t[:2345], v[:2345], aux[:2345], gate[:2345])
    back = WindowerState.from_dict(json.loads(json.dumps(st.to_dict())))
    assert json.dumps(back.to_dict()) == json.dumps(st.to_dict())
    c1, s1 = cut(CFG, st, t[2345:], v[2345:], aux[2345:], gate[2345:])
    c2, s2 = cut(CFG, back, t[2345:], v[2345:], aux[2345:], gate[2345:])
    assert c1.due == c2.due and _sums(c1.sums) == _sums(c2.sums)
    assert json.dumps(s1.to_dict()) == json.dumps(s2.to_dict())


@pytest.mark.parametrize("seed, n_aux", [(5, 0), (6, 2)])
def test_one_sample_per_call_cuts_the_windows_of_large_batches(seed: int, n_aux: int) -> None:
    """A live sensor's one-sample batches (`windower._cut_one`, scalars) against batches of
    up to 3000 samples (arrays): the same events, the same windows and the same state.
    Integer readings (ADC counts), so that a window's sums do not depend on where batches
    cut it (`core.window_means`)."""
    t, v, aux, gate = _stream(seed, 12_000, n_aux)
    v, aux = np.round(v * 1024.0), np.round(aux * 100.0)
    rng = np.random.default_rng(seed + 10)
    ends = np.cumsum(rng.integers(1, 3000, size=len(t)))
    ends = [0, *ends[ends < len(t)].tolist(), len(t)]

    def run(bounds: list[int]) -> tuple[list, list, str]:
        state, due, sums = WindowerState(), [], []
        for lo, hi in pairwise(bounds):
            c, state = cut(CFG, state, t[lo:hi], v[lo:hi], aux[lo:hi], gate[lo:hi])
            due += [(lo + i, commit) for i, commit in c.due]
            if c.sums is not None:
                sums += [_sums(c.sums.take(np.array([j]))) for j in range(c.committed)]
        return due, sums, json.dumps(state.to_dict())

    one = run(list(range(len(t) + 1)))
    assert one == run(ends)
    assert len(one[1]) > 10 and len(one[0]) > len(one[1])


def _cut_one_by_cutter(state: WindowerState, t: np.ndarray, v: np.ndarray, aux: np.ndarray,
                       gate: np.ndarray) -> tuple[list, list, WindowerState]:
    """One sample cut by `_Cutter.schedule_run` on arrays, as a batch's run is: what the
    scalar `_cut_one` stands in for."""
    t0 = int(t[0])
    if not gate[0]:
        return [], [], WindowerState(None, None, t0, False)
    dt = 1 if state.last_t_us is None else t0 - state.last_t_us
    goes_on = state.last_gate and 0 < dt <= 3.0e6 / CFG.rate_hz
    c = _Cutter(CFG, state.open if goes_on else None, state.pending if goes_on else None,
                [], [])
    c.schedule_run(t, v, aux, 0, 1)
    table = WindowSums.gather(c.table, aux.shape[1]) if c.table else None
    return c.due, _sums(table), WindowerState(c.open, c.pending, t0, True)


@pytest.mark.parametrize("seed, n_aux", [(7, 0), (8, 2)])
def test_one_sample_on_scalars_is_the_run_cutter_bit_for_bit(seed: int, n_aux: int) -> None:
    """`_cut_one`'s scalar sums against `_Cutter.schedule_run` on the same one-sample
    arrays, sample after sample: the same events, window sums and state, to the bit, with
    float readings (sums in any order of addition) and signed zeros among them (a one-row
    numpy sum turns -0.0 into 0.0)."""
    t, v, aux, gate = _stream(seed, 6000, n_aux)
    rng = np.random.default_rng(seed)
    zero = rng.random(v.shape) < 0.05
    v[zero] = np.where(rng.random(int(zero.sum())) < 0.5, -0.0, 0.0)
    aux[rng.random(aux.shape) < 0.05] = -0.0
    a = b = WindowerState()
    commits = 0
    for i in range(len(t)):
        s = slice(i, i + 1)
        ca, a = cut(CFG, a, t[s], v[s], aux[s], gate[s])
        due, sums, b = _cut_one_by_cutter(b, t[s], v[s], aux[s], gate[s])
        assert ca.due == due and _sums(ca.sums) == sums
        for acc_a, acc_b in ((a.open, b.open), (a.pending and a.pending[0],
                                                 b.pending and b.pending[0])):
            assert (acc_a is None) == (acc_b is None)
            if acc_a is not None:
                assert [np.asarray(getattr(acc_a, f)).tobytes() for f in _ACC] == \
                    [np.asarray(getattr(acc_b, f)).tobytes() for f in _ACC]
        assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())
        commits += ca.committed
    assert commits > 10 and ((v == 0) & np.signbit(v))[gate].any()


_ACC = ("run_start_us", "k", "n", "sum_v", "sum_v2", "sum_aux", "sum_t")
