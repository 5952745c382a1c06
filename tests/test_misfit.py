"""The factor by which the calibrated vector's error can exceed what the norm residual shows
(`core.misfit.across_factor`): its derivation's bound holds for any unmodelled offset or
symmetric off-diagonal term, it is 5 on the whole sphere, and a posture seen alone bounds
nothing; and the shared excess beyond noise and chance leaves 0 for pure noise."""

from __future__ import annotations

import numpy as np

from bench_modules import load_bench
from recal.core.misfit import (
    ACROSS_MAX,
    ACROSS_SPHERE,
    _unseen_cov,
    across_factor,
    chance,
    direction_sums,
    excess_g2,
    unseen_cross_form,
    unseen_cross_g2,
)
from recal.core.residuals import misfit
from recal.core.status import RunningMisfit


def _sphere(rng: np.random.Generator, n: int) -> np.ndarray:
    u = rng.normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


def _absorbable(u: np.ndarray) -> np.ndarray:
    """The columns a diagonal model's fit absorbs of a norm residual: offsets (u), scales
    (u_k^2)."""
    return np.hstack([u, u * u])


def test_across_factor_is_five_on_the_sphere_and_capped_for_one_posture() -> None:
    rng = np.random.default_rng(0)
    k = across_factor(direction_sums(_sphere(rng, 20000)), 20000)
    assert abs(k - ACROSS_SPHERE) < 0.3, k
    one = np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.01, (200, 3))  # upright, swaying
    assert across_factor(direction_sums(one), len(one)) == ACROSS_MAX
    assert across_factor(direction_sums(one[:2]), 2) == ACROSS_MAX


def test_the_vector_error_stays_within_kappa_times_the_norm_residual() -> None:
    """For direction sets from the sphere to a cap, and random unmodelled terms: the worst
    |e(u)|^2 at any orientation is at most kappa x the mean square of the residual the fit
    leaves (what the fit's columns do not absorb)."""
    rng = np.random.default_rng(1)
    probe = _sphere(rng, 4000)
    for trial in range(40):  # bounded
        n = 60
        u = _sphere(rng, n)
        if trial % 2:  # a cap: postures within ~60 degrees of upright
            u = u[u[:, 1] < -0.3] if np.count_nonzero(u[:, 1] < -0.3) > 12 else u
        k = across_factor(direction_sums(u), len(u))
        a = _absorbable(u)
        d = rng.normal(size=3)
        D = np.array([[0, d[0], d[1]], [d[0], 0, d[2]], [d[1], d[2], 0]])
        r = np.einsum("ni,ij,nj->n", u, D, u)
        r = r - a @ np.linalg.lstsq(a, r, rcond=None)[0]
        worst = float(np.max(np.sum((probe @ D) ** 2, axis=1)))
        assert worst <= k * np.mean(r ** 2) * (1 + 1e-9) or k == ACROSS_MAX, (trial, k)
        o = rng.normal(size=3)
        assert o @ o <= k * np.mean((u @ o) ** 2) * (1 + 1e-9) or k == ACROSS_MAX


def test_the_excess_is_zero_for_noise_and_what_lies_beyond_it() -> None:
    assert excess_g2(1.0, 1.0) == 0.0 and excess_g2(2.0, 1.0) == 1.0
    assert excess_g2(1.2, 1.0, chance(100)) == 0.0  # 1.2 is within 3 sd of a mean of 100
    rng = np.random.default_rng(2)
    t = np.arange(3600) * 2_000_000
    clean = misfit(rng.normal(0, 4e-4, len(t)), np.full(len(t), 4e-4 ** 2), t)
    assert np.mean(clean.excess_g == 0.0) > 0.95 and clean.overall_g == 0.0


def test_a_diagonal_model_on_a_sagging_supply_or_cross_axis_terms_is_honest_streaming() -> None:
    """The streaming bench's wearers (60 min at 25 Hz through the core pipeline) where the
    fit's residual shows what the model lacks: with the misfit's vector factor no calibrated
    second beyond 10 sigma_eff and few beyond 3 (before it: 6.1 % on the supply wearer, 23 %
    on the cross-axis one)."""
    sh = load_bench("sigma_honesty")
    supply = sh.run("supply", sh.CASES["analog 12-bit, sagging supply (ratiometric), diagonal"],
                    60.0, 1)
    assert supply["cal_pct"] > 10 and supply["beyond3_pct"] <= 1.0
    assert supply["beyond10_pct"] == 0.0
    # wearer 1 keeps postures near the axes for 20 min, where no residual shows the cross-axis
    # terms: the floor for what such postures leave unseen covers it (15.2 % before it)
    cross = sh.run("cross", sh.CASES["cross-axis 1.5 deg, diagonal (lacks it)"], 60.0, 1)
    assert cross["cal_pct"] > 50 and cross["beyond3_pct"] <= 1.0 and cross["beyond10_pct"] == 0.0


def test_where_the_model_fits_sigma_is_within_3x_of_the_error_streaming() -> None:
    """The clean digital wearers: no calibrated second beyond 3 sigma_eff and sigma not
    uselessly wide (real/pred >= 1/3): the first minutes, whose sigma reached 46 mg at an
    error of 1-8 mg, are held until every offset and scale is known to 5 mg (real/pred 0.22
    before), and the cross-axis floor stays within that."""
    sh = load_bench("sigma_honesty")
    for seed in (1, 2):
        r = sh.run("clean", sh.CASES["digital, diagonal model (fits)"], 60.0, seed)
        assert r["cal_pct"] > 60 and r["beyond3_pct"] == 0.0
        assert r["real_pred"] >= 1 / 3, (seed, r["real_pred"])


def test_the_unseen_cross_axis_floor_is_the_prior_at_the_axes_and_shrinks_with_coverage() -> None:
    """`unseen_cross_g2`: directions near the axes show no symmetric cross-axis term, so the
    floor is the prior's (2 sd^2 at most); directions over the whole sphere show it in the
    residual, and the floor falls well below; it bounds the mean square of D u over random
    terms whose residual stays within the detection threshold."""
    rng = np.random.default_rng(5)
    sd, detect = 0.003, 0.3e-6
    axes = np.eye(3)[rng.integers(0, 3, 500)] * rng.choice([-1.0, 1.0], (500, 1))
    axes += 0.01 * rng.normal(size=(500, 3))
    near = unseen_cross_g2(direction_sums(axes), 500, detect, sd)
    assert 0.8 * 2 * sd**2 <= near <= 2 * sd**2
    sphere = rng.normal(size=(500, 3))
    wide = unseen_cross_g2(direction_sums(sphere), 500, detect, sd)
    assert wide < 0.25 * near
    assert unseen_cross_g2(direction_sums(sphere[:2]), 2, detect, sd) == 2 * sd**2
    # the bound: terms drawn from the posterior's scale err at most that much on average
    u = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    for _ in range(20):
        d = rng.normal(0, sd, 3)
        D = np.array([[0, d[0], d[1]], [d[0], 0, d[2]], [d[1], d[2], 0]])
        assert float(np.max(np.sum((u @ D) ** 2, axis=1))) <= 4 / 3 * d @ d * (1 + 1e-9)


def test_the_floor_is_per_sample_not_in_the_gross_test_and_is_checkpointed() -> None:
    """The unseen floor lies across gravity: it is sigma's per sample (a^T W a, not in the
    misfit every sample shares), not the norm's gross test's; it survives a checkpoint; a
    checkpoint with the older single figure u loads it as u at every vector of 1 g, and one
    from before any floor without it."""
    m = RunningMisfit()
    m.fitted(1e-4, 1e-7, 40.0, 9e-6)
    assert not m.restate() and m.extra_mg2 == 0.0 and m.norm_mg2 == 0.0
    assert abs(m.unseen_g2 - 9e-6) < 1e-18
    assert RunningMisfit.from_dict(m.to_dict()) == m
    older = {k: v for k, v in m.to_dict().items() if k != "unseen_w"}
    assert RunningMisfit.from_dict({**older, "unseen_g2": 9e-6}) == m
    assert RunningMisfit.from_dict(older).unseen_g2 == 0.0


def test_the_floor_at_a_vector_is_the_expected_error_of_the_terms_left_unseen() -> None:
    """`unseen_cross_form`: a^T W a is E|D a|^2 over the terms' covariance the directions
    leave (drawn), at most the every-orientation bound `unseen_cross_g2` at 1 g, and least
    where the terms the postures showed act: a wearer turning in the x-y plane (lying, on
    every side) shows d_xy, not d_xz and d_yz, and the vector along z carries both of those."""
    rng = np.random.default_rng(5)
    phi = rng.uniform(0, 2 * np.pi, 300)
    lying = np.column_stack([np.cos(phi), np.sin(phi), rng.normal(0, 0.02, 300)])
    sums, sd, detect = direction_sums(lying), 0.003, 1e-7
    w = unseen_cross_form(sums, 300, detect, sd)
    bound = unseen_cross_g2(sums, 300, detect, sd)
    d = rng.normal(size=(20000, 3)) @ np.linalg.cholesky(_unseen_cov(sums, 300, detect, sd)).T
    for a in (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]),
              np.array([0.6, 0.0, 0.8]), np.array([0.577, 0.577, 0.577])):
        e = np.column_stack([d[:, 0] * a[1] + d[:, 1] * a[2], d[:, 0] * a[0] + d[:, 2] * a[2],
                             d[:, 1] * a[0] + d[:, 2] * a[1]])  # D a, D symmetric
        assert abs(a @ w @ a / np.mean(np.sum(e * e, axis=1)) - 1.0) < 0.05
        assert a @ w @ a <= bound * (a @ a) * (1 + 1e-9)
    z, x = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    assert x @ w @ x < 0.6 * (z @ w @ z)


def test_the_running_misfit_keeps_kappa_in_the_checkpoint_and_reads_old_ones() -> None:
    """kappa is part of the state (an update's, applied until the next); a checkpoint from
    before it loads with the whole sphere's."""
    m = RunningMisfit()
    m.fitted(2e-3, 1e-7, 40.0)
    assert m.across == 40.0
    assert abs(m.extra_mg2 - 1e6 * 40.0 * m.fit_g2) < 1e-9
    assert RunningMisfit.from_dict(m.to_dict()) == m
    old = {k: v for k, v in m.to_dict().items() if k != "across"}
    assert RunningMisfit.from_dict(old).across == ACROSS_SPHERE


def test_hindsight_pools_kappa_over_the_minutes_around_each_window() -> None:
    """An hour upright (one posture: kappa capped), then an hour of postures all round (kappa
    near the sphere's): each window's kappa is its own span's, the recording's that of all."""
    rng = np.random.default_rng(3)
    t = np.arange(3600) * 2_000_000  # a window every 2 s
    a = np.where((t < 3600e6)[:, None], np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.01, (3600, 3)),
                 _sphere(rng, 3600))
    m = misfit(rng.normal(0, 4e-4, len(t)), np.full(len(t), 4e-4 ** 2), t, a=a)
    assert m.across is not None
    assert np.all(m.across[t < 3000e6] == ACROSS_MAX)
    assert np.all(m.across[t > 4200e6] < 8.0)
    assert m.across_all < 12.0  # half the windows all round: ~2 x the sphere's 5
