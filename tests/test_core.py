"""The numerical core: model algebra, detector, buffer, estimator, bootstrap, static fits, and
the accuracy targets on simulated wearers (2 h at 50 Hz, compared against the simulator's truth).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from recal.core import detector as det
from recal.core.bootstrap import fit_ellipsoid
from recal.core.buffer import BufferConfig, WindowBuffer
from recal.core.candidates import proposals
from recal.core.channels import check_channels
from recal.core.effects import EFFECT_KINDS, Covariates, Offset, Ratiometric
from recal.core.estimator import EstimatorConfig, Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Lifecycle, Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.static import fit_known_orientations, fit_unknown_orientations
from recal.core.status import Status
from recal.core.triaxial import all3, any3, norm3
from recal.errors import ModelError, RecalError
from recal.sim.wearer import SensorSpec, WearerSpec, error_1s_mg, simulate

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _run(raw, model, prior, batch=1000, cfg=None):
    pipe = Pipeline(cfg or PipelineConfig(rate_hz=50), model, prior, raw.aux_names)
    out = [pipe.step(raw[i:i + batch]).calibrated.a_g for i in range(0, len(raw), batch)]
    return np.concatenate(out), pipe


def _err_1s_mg(cal, truth, t_us, after_s=1800.0, align=False):
    """`sim.error_1s_mg` (50 Hz) after `after_s`."""
    m = t_us >= after_s * 1e6
    return error_1s_mg(cal[m], truth[m], 50.0, align)


# --- model -----------------------------------------------------------------------------------
#: channels (reference, spread) and time for the registry's proposals (`candidates.proposals`)
_CHANNELS = {"temp": (25.0, 10.0), "vdd": (3.3, 0.5)}
_TIME = (0.0, 1.0)


def _every_effect_at_once() -> SensorModel:
    """The full model grown by the registry's first proposal until none is left: every kind
    of `EFFECT_KINDS` that discovery proposes, in as many forms as fit in one model."""
    m = SensorModel.full(1000.0)
    for _ in range(50):  # bounded: each round adds one effect the model lacked
        todo = proposals(m, _CHANNELS, _TIME)
        if not todo:
            return m
        m = m.with_effect(*todo[0])
    raise AssertionError("the proposals did not run out")


_MODELS = {"every effect": _every_effect_at_once} | {
    f"full+{e.label}": (lambda e=e, sp=sp: SensorModel.full(1000.0).with_effect(e, sp))
    for e, sp in proposals(SensorModel.full(1000.0), _CHANNELS, _TIME)}


def test_the_jacobian_models_cover_every_proposed_kind() -> None:
    kinds = {e.kind for e in _every_effect_at_once().effects}
    assert kinds == {k for k, cls in EFFECT_KINDS.items() if cls.proposed} | {"scale"}
    assert "full+ratiometric[temp,vdd]" in _MODELS  # the pair form, which cannot join the rest


@pytest.mark.parametrize("name", sorted(_MODELS))
def test_chain_rule_jacobian_matches_finite_differences(name: str) -> None:
    rng = np.random.default_rng(0)
    m = _MODELS[name]()
    p = m.nominal() + rng.normal(0, 0.01, m.size) * (np.abs(m.nominal()) + 1)
    n = 40
    v = rng.normal(0, 1000, (n, 3))
    aux = rng.normal(0, 1, (n, 2)) + np.array([25, 3.3])
    cov = Covariates(rng.uniform(0, 2, n), aux, ("temp", "vdd"))
    _, B = m.residual_jacobian(p, v, cov)
    for k in range(m.size):
        h = 1e-6 * max(1.0, abs(p[k]))
        dp = np.zeros(m.size)
        dp[k] = h
        num = -(m.residual_jacobian(p + dp, v, cov)[0] - m.residual_jacobian(p - dp, v, cov)[0])
        assert np.allclose(B[:, k], num / (2 * h), rtol=1e-5, atol=1e-9 * np.abs(B).max())


def test_model_round_trips_through_dict_and_keeps_names():
    m = SensorModel.full(512.0).with_effect(Offset("board_temp", 30.0), 5.0)
    m2 = SensorModel.from_dict(json.loads(json.dumps(m.to_dict())))
    assert m2.names == m.names and m2.s0 == 512.0
    assert "o_board_temp_x" in m2.names


# --- detector --------------------------------------------------------------------------------
def test_detector_is_batch_invariant_bit_for_bit():
    raw = simulate(0.05, 50, 1).raw
    cfg = det.DetectorConfig(rate_hz=50, s0=1024.0)
    _, whole = det.detect(cfg, det.init_state(cfg), raw.v)
    st, parts = det.init_state(cfg), []
    for i in range(len(raw)):
        st, o = det.detect(cfg, st, raw.v[i:i + 1])
        parts.append((o.detector_g, o.flat))
    assert np.array_equal(np.concatenate([p[0] for p in parts]), whole.detector_g)
    assert np.array_equal(np.concatenate([p[1] for p in parts]), whole.flat)


def test_flat_runs_count_the_repeats_before_each_sample_across_batches():
    rng = np.random.default_rng(11)
    for _ in range(200):
        n = int(rng.integers(1, 60))
        v = rng.integers(0, 2, (n, 1)).repeat(3, axis=1).astype(float)  # long runs of repeats
        v[rng.random(n) < 0.1, 0] = 7.0  # and breaks in one axis only
        last = v[0].copy() if rng.random() < 0.5 else np.full(3, np.nan)
        run0 = int(rng.integers(0, 5))
        expect, prev, count = [], last, run0
        for row in v:  # the definition, sample by sample
            count = count + 1 if np.array_equal(row, prev) else 0
            expect.append(count)
            prev = row
        assert det._flat_runs(v, last, run0).tolist() == expect


def test_flat_marks_the_runs_at_or_past_the_threshold_and_carries_the_last():
    """`_flat` (the detector's: the repeats alone) against the count of every sample, with
    one threshold or one per sample (the step still being learned), 0 and 1 included."""
    rng = np.random.default_rng(13)
    for _ in range(300):
        n = int(rng.integers(1, 60))
        v = rng.integers(0, 2, (n, 1)).repeat(3, axis=1).astype(float)
        v[rng.random(n) < 0.1, 1] = 7.0
        last = v[0].copy() if rng.random() < 0.5 else np.full(3, np.nan)
        run0 = int(rng.integers(0, 5))
        runs = det._flat_runs(v, last, run0)
        for flat_n in (int(rng.integers(0, 8)), rng.integers(0, 8, n)):
            flat, run = det._flat(v, last, run0, flat_n)
            assert flat.tolist() == (runs >= np.asarray(flat_n) - 1).tolist()
            assert run == runs[-1]


def test_flat_runs_one_sample_at_a_time_equal_the_whole_batch():
    rng = np.random.default_rng(12)
    v = rng.integers(0, 2, (300, 1)).repeat(3, axis=1).astype(float)  # long runs of repeats
    v[rng.random(300) < 0.1, 2] = 7.0  # breaks in one axis only
    v[::37, 1] = np.nan  # NaN never repeats
    whole = det._flat_runs(v, np.full(3, np.nan), 3)
    last, run, parts = np.full(3, np.nan), 3, []
    for i in range(len(v)):
        part = det._flat_runs(v[i:i + 1], last, run)
        last, run = v[i], int(part[-1])
        parts.append(part)
    assert np.concatenate(parts).dtype == whole.dtype
    assert np.array_equal(np.concatenate(parts), whole)
    assert whole.max() > 5  # the data did have long runs


def test_row_reductions_equal_numpys_to_the_bit():
    rng = np.random.default_rng(5)
    v = rng.normal(0, 1e3, (5000, 3)) * rng.choice([1e-300, 1.0, 1e200], (5000, 3))
    v[::7, 1] = np.nan
    v[::11, 2] = -np.inf
    v[::13] = v[::13].round()  # ties, and whole rows equal to the previous one below
    v[1::13] = v[::13][: len(v[1::13])]
    with np.errstate(over="ignore", invalid="ignore"):
        assert np.array_equal(norm3(v), np.linalg.norm(v, axis=1), equal_nan=True)
    for m in (np.isfinite(v), v[1:] == v[:-1], np.abs(v) > 1e3):
        assert np.array_equal(all3(m), m.all(axis=1))
        assert np.array_equal(any3(m), m.any(axis=1))


def test_detector_separates_still_from_walking_and_rejects_flat_and_clipped():
    r = simulate(0.2, 50, 2)
    cfg = det.DetectorConfig(rate_hz=50, s0=1024.0, clip_raw=1.5 * 1024)
    _, o = det.detect(cfg, det.init_state(cfg), r.raw.v)
    still, moving = r.truth.still, r.truth.posture_id < 0
    assert o.gate[still].mean() > 0.9
    assert o.gate[moving].mean() < 0.5
    v = np.repeat(r.raw.v[:1], 200, axis=0)  # a device repeating its last sample
    _, flat = det.detect(cfg, det.init_state(cfg), v)
    assert flat.flat[60:].all() and not flat.gate[60:].any()
    v = np.full((100, 3), [0.0, 0.0, 2.0 * 1024])  # pinned at full scale
    _, clip = det.detect(cfg, det.init_state(cfg), v)
    assert clip.clipped.all() and not clip.gate.any()


# --- buffer ----------------------------------------------------------------------------------
def test_buffer_is_bounded_and_keeps_the_rare_orientation():
    buf = WindowBuffer(BufferConfig(grid=3, per_cell=4), n_aux=0)
    buf.add(np.zeros(3), np.zeros(0), 0, 100, 1.0, np.array([1.0, 0, 0]))  # lay down once
    for i in range(1, 10_000):  # then hours upright
        buf.add(np.zeros(3), np.zeros(0), i, 100, 1.0, np.array([0.01, 0.0, 1.0]))
    assert len(buf) == 5 and buf.v.shape[0] == 6 * 9 * 4
    assert 0 in buf.t_us[buf.filled]  # the lying window survived
    cov = buf.coverage()
    assert cov.seen_pos == (True, False, True) and cov.cells_filled == 2


def test_buffer_merges_a_still_run_into_slots_and_nothing_else():
    cfg = BufferConfig(grid=3, per_cell=2, merge_max=3, merge_deg=1.0)
    buf = WindowBuffer(cfg, n_aux=1)
    up = np.array([0.0, 0.0, 1.0])
    for i in range(7):  # one still run: 7 windows, 3 per slot, a cell keeps 2 slots
        buf.add(np.array([0.0, 0.0, 1000.0 + i]), np.array([float(i)]), 10 * i, 100, 4.0, up,
                run=1)
    w = buf.windows()
    assert len(w) == 2 and list(w.merged) == [3, 1]  # slots of windows 3-5 and 6
    assert np.allclose(w.v[0], [0, 0, 1004.0]) and w.t_us[0] == 40 and w.n[0] == 300
    tilted = np.array([np.sin(np.radians(2.0)), 0.0, np.cos(np.radians(2.0))])
    buf.add(np.zeros(3), np.zeros(1), 100, 100, 4.0, tilted, run=1)  # 2 deg away: new slot
    buf.add(np.zeros(3), np.zeros(1), 110, 100, 4.0, tilted, run=2)  # another run: new slot
    assert list(buf.windows().merged) == [1, 1]  # the cell's two newest slots
    restored = WindowBuffer.from_dict(json.loads(json.dumps(buf.to_dict())))
    restored.add(np.zeros(3), np.zeros(1), 120, 100, 4.0, tilted, run=2)
    assert list(restored.windows().merged) == [1, 2]  # the checkpoint resumes the merge


def test_buffer_arrays_read_between_merges_are_current_and_copies_stay_apart():
    """A merge updates its slot in Python numbers and writes it back only when the arrays are
    read: every read (attributes, windows, coverage, state, copy) must see every merge."""
    buf = WindowBuffer(BufferConfig(grid=3, per_cell=2, merge_max=10, merge_deg=1.0), n_aux=1)
    up = np.array([0.0, 0.0, 1.0])
    v = np.array([[0.0, 1.0, 1000.0], [0.0, 3.0, 1002.0], [0.0, 2.0, 1007.0]])
    n = np.array([100, 50, 150])
    for i in range(3):
        buf.add(v[i], np.array([10.0 * i]), 1000 * i, int(n[i]), 4.0 + i, up, run=7)
        slot = int(np.flatnonzero(buf.filled)[0])
        mean = (v[:i + 1] * n[:i + 1, None]).sum(0) / n[:i + 1].sum()
        assert np.allclose(buf.v[slot], mean, rtol=0, atol=1e-9) and buf.k[slot] == i + 1
        assert buf.n[slot] == n[:i + 1].sum() and np.allclose(buf.windows().v[0], mean)
        assert buf.to_dict()["k"][slot] == i + 1
    snap = buf.copy()
    buf.add(np.array([0.0, 0.0, 900.0]), np.array([0.0]), 4000, 100, 4.0, up, run=7)
    assert snap.k[slot] == 3 and buf.k[slot] == 4  # the copy does not see later merges
    assert np.allclose(snap.windows().v[0], mean)


# --- estimator -------------------------------------------------------------------------------
def test_consistency_tests_at_once_agree_with_one_by_one_and_the_chi_square_quantile():
    from scipy.stats import chi2, norm

    from recal.core.estimator import CONSISTENT_ALPHA, consistent, consistent_many

    rng = np.random.default_rng(4)
    m = rng.integers(0, 400, 2000)
    s2 = rng.chisquare(np.maximum(m, 1)) * rng.choice([0.5, 1.0, 2.0], len(m))
    s1 = rng.normal(0, 1.5, len(m)) * np.sqrt(np.maximum(m, 1))
    many = consistent_many(m, s2, s1)
    assert many.tolist() == [consistent(int(a), float(b), float(c))
                             for a, b, c in zip(m, s2, s1, strict=True)]
    assert 0.05 < many.mean() < 0.95 and many[m == 0].all()
    for k, tol in ((3, 0.02), (10, 0.01), (100, 0.01), (1000, 0.01)):  # quantiles at alpha
        q, z = chi2.ppf(1 - CONSISTENT_ALPHA, k), norm.ppf(1 - CONSISTENT_ALPHA / 2)
        assert consistent_many([k], [(1 - tol) * q], [0.0])[0]
        assert not consistent_many([k], [(1 + tol) * q], [0.0])[0]
        assert consistent_many([k], [0.0], [0.999 * z * k**0.5])[0]
        assert not consistent_many([k], [0.0], [1.001 * z * k**0.5])[0]


# --- bootstrap and static --------------------------------------------------------------------
def test_ellipsoid_fit_recovers_offsets_and_triangular_sensitivity():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(100, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    K = np.array([[1000, 20, -10], [0, 1030, 15], [0, 0, 980.0]])
    o, U = fit_ellipsoid(a @ K.T + [30, -50, 20])
    assert np.allclose(o, [30, -50, 20], atol=1e-6)
    assert np.allclose(np.linalg.norm((a @ K.T) @ U.T, axis=1), 1.0, atol=1e-9)


@pytest.mark.parametrize(("phone", "paper_pct", "ours_max_pct"),
                         [(1, 0.21, 0.26), (2, 0.45, 0.45), (3, 0.26, 0.26)])
def test_static_tables_of_georgieva(phone, paper_pct, ours_max_pct):
    """Fit rows 1-20, worst relative norm error over all rows. Phones 2 and 3 meet the paper;
    phone 1 reaches 0.258 % (see the next test for why the paper's 0.21 % is not comparable)."""
    path = SHARED / "static_positions" / f"phone{phone}.csv"
    v = np.loadtxt(path, delimiter=",", skiprows=1)[:, 1:]
    rows = np.zeros(len(v), bool)
    rows[:20] = True
    fit = fit_unknown_orientations(v, rows, 9.81)
    assert 100 * fit.rel_norm_error.max() <= ours_max_pct
    raw = np.abs(np.linalg.norm(v, axis=1) / 9.81 - 1).max()
    assert fit.rel_norm_error.max() < raw / 5


def _georgieva_eq16(v, s, b, angles):
    """Georgieva et al. eq. 16 with their published parameters: a = T_orth T_bar (v - s) / b,
    T_bar the inverse Gram matrix of the axes (eq. 5/8), T_orth eq. 12. (The shift is taken
    from the raw reading before the scaling: the reading of eq. 16 that reproduces them.)"""
    phi, psi, theta = angles
    c = np.cos
    gram = np.array([[1, c(phi), c(psi)], [c(phi), 1, c(theta)], [c(psi), c(theta), 1]])
    root = np.sqrt(1 - c(phi)**2 - c(psi)**2 - c(theta)**2 + 2 * c(phi) * c(psi) * c(theta))
    t_orth = np.array([[1, c(phi), c(psi)],
                       [0, np.sin(phi), (c(theta) - c(phi) * c(psi)) / np.sin(phi)],
                       [0, 0, root / np.sin(phi)]])
    return ((t_orth @ np.linalg.inv(gram)) @ ((v - s) / b).T).T


def test_phone1_figure_of_the_paper_holds_on_its_fit_rows_only():
    """Why phone 1 stays above the paper's 0.21 %: the paper's own parameters (fit on rows 1-20,
    sec. 2.4) give 0.195 % on rows 1-20 but 0.36 % over all 27 rows, so its figure describes
    the fitted rows. Ours is better on both (0.135 % and 0.258 %), and no 9-parameter affine
    calibration does better than 0.138 % over all rows even when fitted on all of them."""
    v = np.loadtxt(SHARED / "static_positions" / "phone1.csv", delimiter=",", skiprows=1)[:, 1:]
    a = _georgieva_eq16(v, [0.304496, 0.321482, -1.08995], [-1.00457, -1.00147, -0.989292],
                        [1.57646, 1.57096, 1.57301])
    paper = 100 * np.abs(np.linalg.norm(a, axis=1) / 9.81 - 1)
    assert paper[:20].max() < 0.21 < paper.max()
    rows = np.arange(len(v)) < 20
    ours = 100 * fit_unknown_orientations(v, rows, 9.81).rel_norm_error
    assert ours[:20].max() < paper[:20].max() and ours.max() < paper.max()
    best = 100 * fit_unknown_orientations(v, np.ones(len(v), bool), 9.81).rel_norm_error.max()
    assert best < ours.max()  # the gap is the 7 held-out rows, not the model


def test_known_orientations_reproduce_bragge_fit_of_phone1():
    v = np.loadtxt(SHARED / "static_positions" / "phone1.csv", delimiter=",", skiprows=1)[:, 1:]
    rows = np.zeros(len(v), bool)
    rows[:6] = True
    fit = fit_known_orientations(v, rows, 9.81)
    # Georgieva et al. sec. 3.5.1: worst norm error over all rows 3.15 % (raw 12.2 %)
    assert abs(100 * fit.rel_norm_error.max() - 3.15) < 0.01


# --- in-use accuracy on simulated wearers ----------------------------------------------------
@pytest.fixture(scope="module")
def wearer_2h():
    rng = np.random.default_rng(1)
    return simulate(2.0, 50, 1, SensorSpec.random(rng, offset_mg=50, gain_pct=3))


def test_diagonal_model_reaches_1p5_mg_after_30_min(wearer_2h):
    model = SensorModel.diagonal(1024.0)
    cal, pipe = _run(wearer_2h.raw, model, Prior.default(model))
    err = _err_1s_mg(cal, wearer_2h.truth.a_true_g, wearer_2h.raw.t_us)
    assert err <= 1.5, err
    assert pipe.counts["updates_rejected"] == 0


def _cross_axis_wearer(seed):
    rng = np.random.default_rng(seed)
    sensor = SensorSpec.random(rng, offset_mg=50, gain_pct=3, cross_axis_deg=1.5)
    return simulate(2.0, 50, seed, sensor)


def test_full_model_with_cross_axis_reaches_1p5_mg_after_30_min():
    r = _cross_axis_wearer(2)
    model = SensorModel.full(1024.0)
    cal, pipe = _run(r.raw, model, Prior.default(model))
    assert _err_1s_mg(cal, r.truth.a_true_g, r.raw.t_us, align=True) <= 1.5
    assert pipe.counts["updates_rejected"] == 0
    diag = SensorModel.diagonal(1024.0)
    cal_d, _ = _run(r.raw, diag, Prior.default(diag))  # Lötters' model cannot do this
    assert _err_1s_mg(cal_d, r.truth.a_true_g, r.raw.t_us, align=True) > 3.0


def test_full_model_converges_on_a_wearer_who_shows_minus_z_late():
    """Regression, seed 5: no posture with gravity below -0.3 g on z until minute 47. The first
    estimator held the cross-axis terms of z (and s_z) fixed until z had been seen from both
    sides and updated recursively from linearizations taken far from the truth, so the offsets
    absorbed 1.4 deg of misalignment: 35 mg errors until minute 55, 12.6 mg over 30-120 min.
    Re-fitting the buffer, with parameters freed by what the data inform, follows the data."""
    r = _cross_axis_wearer(5)
    z = r.truth.posture_up[:, 2]
    first_minus_z_min = r.raw.t_us[np.argmax(np.isin(r.truth.posture_id,
                                                     np.flatnonzero(z < -0.3)))] / 60e6
    assert first_minus_z_min > 45  # the scenario: z seen from below only late
    model = SensorModel.full(1024.0)
    cal, pipe = _run(r.raw, model, Prior.default(model))
    assert _err_1s_mg(cal, r.truth.a_true_g, r.raw.t_us, align=True) <= 1.5
    assert pipe.counts["updates_rejected"] == 0
    m = (r.raw.t_us >= 30 * 60e6) & (r.raw.t_us < 50 * 60e6)  # before -z: no worse than later
    assert _err_1s_mg(cal[m], r.truth.a_true_g[m], r.raw.t_us[m], after_s=0, align=True) <= 2.0


def test_no_prior_bootstraps_to_1p5_mg(wearer_2h):
    model = SensorModel.diagonal()
    cal, pipe = _run(wearer_2h.raw, model, None)
    assert pipe.bootstrapped
    assert _err_1s_mg(cal, wearer_2h.truth.a_true_g, wearer_2h.raw.t_us) <= 1.5


def test_upright_only_keeps_unobservable_gain_at_prior_and_says_so():
    rng = np.random.default_rng(3)
    sensor = SensorSpec.random(rng, offset_mg=50, gain_pct=3)
    r = simulate(2.0, 50, 3, sensor, WearerSpec(upright_only=True))
    model = SensorModel.diagonal(1024.0)
    cal, pipe = _run(r.raw, model, Prior.default(model))
    assert np.all(np.isfinite(cal))
    p = pipe.params
    assert p[model.index("s_z")] == 1024.0  # never seen from below: stays at the prior
    obs = pipe.last_report.observable
    assert obs[model.index("s_z")] is False and obs[model.index("o_x")] is True
    o_true = 1024 * np.array(sensor.offset_g)
    assert np.all(np.abs(p[:2] - o_true[:2]) < 3.0)  # x, y offsets converge (counts ~ mg)
    lo, hi = model.bounds()
    assert np.all((p >= lo) & (p <= hi))


def test_offset_drift_is_tracked_to_2_mg():
    """15 mg/h drift, nothing in the model for it: the in-use estimate follows it (the
    estimator's offset rate, a nuisance of the fit; the model's parameters are the offsets now)
    to <= 2 mg after 30 min. Without the rate (random walk only) it lags: > 2 mg."""
    rng = np.random.default_rng(4)
    sensor = replace(SensorSpec.random(rng, offset_mg=50, gain_pct=3),
                     offset_drift_g_per_h=(0.015, -0.015, 0.015))
    r = simulate(2.0, 50, 4, sensor)
    model = SensorModel.diagonal(1024.0)
    cal, pipe = _run(r.raw, model, Prior.default(model))
    err = _err_1s_mg(cal, r.truth.a_true_g, r.raw.t_us)
    assert err <= 2.0, err
    o_end = 1024 * (np.array(sensor.offset_g) + 2.0 * np.array(sensor.offset_drift_g_per_h))
    assert np.all(np.abs(pipe.params[:3] - o_end) < 1.5)  # 30 mg of drift followed to < 1.5
    rate_g_per_h = pipe.estimate.rate / 1024
    assert np.allclose(rate_g_per_h, sensor.offset_drift_g_per_h, atol=0.003)
    no_rate = PipelineConfig(rate_hz=50, estimator=EstimatorConfig(offset_rate_sd_g_per_h=0))
    cal_rw, _ = _run(r.raw, model, Prior.default(model), cfg=no_rate)
    assert _err_1s_mg(cal_rw, r.truth.a_true_g, r.raw.t_us) > 2.0


def test_windows_are_the_same_in_any_batches_with_gaps_jitter_and_short_windows():
    """Long runs are scheduled at once (`Pipeline._tail`) and short or broken ones window by
    window: both must give what one sample at a time gives, counts included."""
    rng = np.random.default_rng(8)
    r = simulate(0.3, 50, 8, SensorSpec.random(rng, offset_mg=50, gain_pct=3))
    i = np.arange(len(r.raw))
    keep = rng.random(len(i)) > 0.02  # lost samples, and stretches missing 1 of every 3:
    for s0 in rng.integers(0, len(i), 40):  # windows below min_fill inside still runs
        keep[(i >= s0) & (i < s0 + 150) & (i % 3 == 1)] = False
    raw = r.raw[keep]
    raw = replace(raw, t_us=raw.t_us + rng.integers(-1000, 1000, len(raw)))  # 1 ms jitter
    raw = raw[np.r_[True, np.diff(raw.t_us) > 0]]
    model = SensorModel.diagonal(1024.0)
    ref, pipe = _run(raw, model, Prior.default(model), batch=len(raw))
    assert pipe.counts["windows_rejected"] > 0 and pipe.counts["updates"] > 5
    for bs in (1, 333, 5000):
        out, p = _run(raw, model, Prior.default(model), batch=bs)
        assert p.counts == pipe.counts
        assert np.array_equal(out, ref)


def test_batches_of_1_10_1000_give_the_same_output_and_checkpoints_resume_exactly():
    rng = np.random.default_rng(5)
    r = simulate(0.4, 50, 5, SensorSpec.random(rng, offset_mg=50, gain_pct=3))
    model = SensorModel.diagonal(1024.0)
    ref, pipe = _run(r.raw, model, Prior.default(model), batch=1000)
    assert pipe.counts["updates"] > 10
    for bs in (1, 10):
        out, _ = _run(r.raw, model, Prior.default(model), batch=bs)
        assert np.max(np.abs(out - ref)) <= 1e-9
    p = Pipeline(PipelineConfig(rate_hz=50), model, Prior.default(model), r.raw.aux_names)
    outs = [p.step(r.raw[:7777]).calibrated.a_g]
    p = Pipeline.from_state_dict(json.loads(json.dumps(p.state_dict())))
    outs.append(p.step(r.raw[7777:]).calibrated.a_g)
    assert np.max(np.abs(np.concatenate(outs) - ref)) <= 1e-9


def test_lifecycle_follows_the_state_and_keeps_the_summary_strings() -> None:
    """Awaiting a scale (no prior, no sample), bootstrapping, tracking; with a prior, tracking
    from the start; suspect while the self-watch objects. The summary's phase and status
    strings are those they always were."""
    r = simulate(0.5, 50.0, 3)
    model = SensorModel.diagonal(1024.0)
    p = Pipeline(PipelineConfig(rate_hz=50.0), model, None, r.raw.aux_names)
    assert p.lifecycle is Lifecycle.AWAITING_SCALE and p.status is Status.UNCALIBRATED
    p.step(r.raw[:100])
    assert p.lifecycle is Lifecycle.BOOTSTRAPPING and p.summary()["phase"] == "provisional"
    for i in range(100, len(r.raw), 500):
        p.step(r.raw[i:i + 500])
    assert p.lifecycle is Lifecycle.TRACKING
    assert (p.summary()["phase"], p.summary()["status"]) == ("bootstrap", "calibrated")
    q = Pipeline(PipelineConfig(rate_hz=50.0), model, Prior.default(model), r.raw.aux_names)
    assert q.lifecycle is Lifecycle.TRACKING
    assert (q.summary()["phase"], q.summary()["status"]) == ("prior", "held")
    q.watch.suspect = True
    assert q.lifecycle is Lifecycle.SUSPECT and q.summary()["status"] == "suspect"


def test_a_model_reading_a_channel_the_input_lacks_is_a_model_error() -> None:
    model = SensorModel.diagonal(1024.0).with_effect(Ratiometric("vdd", 3.3), 0.5)
    with pytest.raises(ModelError, match="vdd") as e:
        check_channels(model, ("temp",))
    assert isinstance(e.value, RecalError) and isinstance(e.value, ValueError)
    with pytest.raises(ModelError):
        Pipeline(PipelineConfig(), model, None, ())
