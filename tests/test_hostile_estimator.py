"""The in-use calibration (core/pipeline.py Pipeline) under hostile data.

Simulated wearers (sim.py) whose data is made hostile: nothing but movement, a vibration near the
detector's 0.5 Hz corner, clipping at full scale, a device that flat-lines, a sensor knocked
(its offsets jump), one orientation for hours, and samples or auxiliary values that are NaN.
After every batch the outputs, the parameters, the published calibration state and the
checkpoint are checked: finite (the state must serialize as strict JSON), and inside the
physical bounds of core/effects.py. Each case then states what the estimate must do.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
import pytest

from recal.core.effects import Offset
from recal.core.estimator import Prior, UpdateReport
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.samples import RawBatch
from recal.sim.wearer import SensorSpec, SimResult, WearerSpec, forward_model, simulate, with_sensor

RATE_HZ = 50.0
S0 = 1024.0  # counts per g, the simulator's default ADC
BATCH = 500  # 10 s per step


def _sensor(seed: int, **over: object) -> SensorSpec:
    return SensorSpec.random(np.random.default_rng(seed), offset_mg=50, gain_pct=3, **over)


def _truth_params(spec: SensorSpec) -> np.ndarray:
    """Offsets and sensitivities in counts, as the diagonal model names them."""
    return np.concatenate([S0 * np.array(spec.offset_g), S0 * (1 + np.array(spec.gain))])


@dataclass
class Run:
    """A pipeline fed batch by batch, with what every batch gave."""

    pipe: Pipeline
    cal: np.ndarray  # (N, 3) calibrated, g
    gate: np.ndarray  # (N,) quasi-static
    params: np.ndarray  # (batches, P) parameters after each batch
    windows: np.ndarray  # (batches,) windows committed so far, after each batch
    reports: list[UpdateReport]


def _assert_sane(pipe: Pipeline, cal: np.ndarray, detector_g: np.ndarray, raw: RawBatch) -> None:
    """Finite outputs for finite inputs, parameters in bounds, strict-JSON state."""
    used = [raw.aux_names.index(c) for c in pipe.model.covariates if c in raw.aux_names]
    finite_in = np.isfinite(raw.v).all(axis=1) & np.isfinite(raw.aux[:, used]).all(axis=1)
    assert np.isfinite(cal[finite_in]).all(), "calibrated output is not finite"
    assert np.isfinite(detector_g[finite_in]).all(), "detector output is not finite"
    p = pipe.params
    lo, hi = pipe.model.bounds()
    assert np.isfinite(p).all() and np.all((p >= lo) & (p <= hi)), pipe.model.params_dict(p)
    if pipe.estimate is not None:
        assert np.isfinite(pipe.estimate.cov).all()
    # what the node publishes and checkpoints: strict JSON (no NaN/Infinity tokens)
    _strict_json(pipe.summary())
    _strict_json(pipe.state_dict())


def _strict_json(obj: object) -> str:
    """JSON with numpy values converted (as io/messages.py does) but NaN and inf refused
    (io/messages.py would quietly publish them as null)."""
    def default(o: object) -> object:
        if isinstance(o, np.generic | np.ndarray):
            return o.tolist()
        raise TypeError(type(o).__name__)
    return json.dumps(obj, allow_nan=False, default=default)


def run(raw: RawBatch, model: SensorModel | None = None, cfg: PipelineConfig | None = None,
        batch: int = BATCH) -> Run:
    model = model or SensorModel.diagonal(S0)
    pipe = Pipeline(cfg or PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model),
                    raw.aux_names)
    cal, gate, params, windows, reports = [], [], [], [], []
    for i in range(0, len(raw), batch):  # bounded by the recording's length
        part = raw[i:i + batch]
        out = pipe.step(part)
        _assert_sane(pipe, out.calibrated.a_g, out.calibrated.detector_g, part)
        cal.append(out.calibrated.a_g)
        gate.append(out.calibrated.quasi_static)
        params.append(pipe.params.copy())
        windows.append(pipe.counts["windows"])
        reports += [u.report for u in out.updates]
    return Run(pipe, np.concatenate(cal), np.concatenate(gate), np.array(params),
               np.array(windows), reports)


def _with_v(res: SimResult, v: np.ndarray) -> RawBatch:
    return RawBatch(res.raw.t_us, v, res.raw.aux, res.raw.aux_names)


def _err_1s_mg(cal: np.ndarray, truth: np.ndarray, still: np.ndarray) -> np.ndarray:
    """|mean over 1 s of (calibrated - true)| per second, NaN where not still all second."""
    n = int(RATE_HZ)
    m = len(cal) // n
    e = 1e3 * np.linalg.norm((cal - truth)[:m * n].reshape(m, n, 3).mean(axis=1), axis=1)
    return np.where(still[:m * n].reshape(m, n).all(axis=1), e, np.nan)


@cache
def wearer_1h() -> SimResult:
    """One hour of a wearer through all orientations (shared by several cases)."""
    return simulate(1.0, RATE_HZ, 1, _sensor(1))


# --------------------------------------------------------------------------- pure movement


def test_pure_movement_never_moves_the_calibration() -> None:
    """Walking for an hour with never more than 1.5 s of stillness: nothing is a window."""
    spec = _sensor(1)
    res = simulate(1.0, RATE_HZ, 2, spec, WearerSpec(still_s=(1.1, 1.5), move_s=(60.0, 180.0)))
    r = run(res.raw)
    assert r.gate.mean() < 0.05  # the detector sees movement
    assert r.pipe.counts["windows"] == 0 and r.pipe.counts["updates"] == 0
    np.testing.assert_array_equal(r.pipe.params, r.pipe.prior.mean)  # not a hair moved


# --------------------------------------------------------------------------- vibration


def _vibrated(freq_hz: float, amp_g: float) -> RawBatch:
    """The 1 h wearer with a norm vibration amp_g * sin(2 pi f t) along gravity (a vehicle, a
    machine, a boat): the worst case for a detector that looks at the norm only."""
    res = wearer_1h()
    a = res.truth.a_true_g
    t_s = (res.raw.t_us - res.raw.t_us[0]) / 1e6
    shaken = a + amp_g * np.sin(2 * np.pi * freq_hz * t_s)[:, None] * (
        a / np.linalg.norm(a, axis=1, keepdims=True))
    v = forward_model(shaken, res.truth.sensor, rng=np.random.default_rng(5))
    return _with_v(res, v)


@pytest.mark.parametrize(("freq_hz", "amp_g"), [(0.4, 0.01), (0.5, 0.03), (0.7, 0.01),
                                                (1.0, 0.01)])
def test_vibration_near_the_detector_corner_is_gated_or_harmless(freq_hz: float,
                                                                 amp_g: float) -> None:
    """Either the detector rejects the shaking (the calibration stays exactly where it was), or
    the windows it lets through leave offsets within 6 mg and gains within 0.5 % of truth.
    (10 mg at 0.4-2 Hz and 20 mg at 0.5, 1 and 2 Hz pass; 30 mg from 0.5 Hz up is gated.)"""
    raw = _vibrated(freq_hz, amp_g)
    r = run(raw)
    if r.pipe.counts["windows"] == 0:
        np.testing.assert_array_equal(r.pipe.params, r.pipe.prior.mean)
        return
    err = r.pipe.params - _truth_params(wearer_1h().truth.sensor)
    assert np.all(np.abs(err[:3]) / S0 < 0.006), 1e3 * err[:3] / S0  # g
    assert np.all(np.abs(err[3:]) / S0 < 0.005), 100 * err[3:] / S0  # relative


@pytest.mark.parametrize(("freq_hz", "amp_g"), [(0.25, 0.01), (0.4, 0.03)])
def test_vibration_passing_the_detector_does_not_drag_the_estimate(freq_hz: float,
                                                                   amp_g: float) -> None:
    """Window means that follow a slow vibration the detector let through: the estimator's
    C_mu floor rises to how much the merged windows of a slot disagree (core/estimator.py).
    (Was a known failure with the recursive estimator: 145 mg / 15 % at 0.25 Hz.)"""
    raw = _vibrated(freq_hz, amp_g)
    r = run(raw)
    err = r.pipe.params - _truth_params(wearer_1h().truth.sensor)
    assert np.all(np.abs(err[:3]) / S0 < 0.006), 1e3 * err[:3] / S0
    assert np.all(np.abs(err[3:]) / S0 < 0.005), 100 * err[3:] / S0


# --------------------------------------------------------------------------- clipping


def test_clipping_at_full_scale_is_gated_and_does_not_bias() -> None:
    """A +-2 g sensor on a wearer whose steps reach 1.2-2.5 g, plus ten minutes pinned at full
    scale (z stuck high, x and y still noisy): no clipped sample is ever quasi-static, and the
    estimate is as good as on clean data."""
    spec = _sensor(1, full_scale_g=2.0)
    res = simulate(1.0, RATE_HZ, 1, spec, WearerSpec(step_vertical_g=(1.2, 2.5)))
    v = res.raw.v.copy()
    fs = spec.full_scale_counts
    assert fs is not None
    stuck = slice(len(v) // 3, len(v) // 3 + int(600 * RATE_HZ))
    v[stuck, 2] = fs
    clipped = np.any(np.abs(v) >= 0.98 * fs, axis=1)
    assert clipped.mean() > 0.1  # the scenario really clips
    r = run(_with_v(res, v), cfg=PipelineConfig(rate_hz=RATE_HZ, full_scale_g=2.0))
    assert not r.gate[clipped].any()
    assert r.pipe.counts["updates_rejected"] == 0
    err = r.pipe.params - _truth_params(spec)
    assert np.all(np.abs(err[:3]) / S0 < 0.002), 1e3 * err[:3] / S0
    assert np.all(np.abs(err[3:]) / S0 < 0.003), 100 * err[3:] / S0


# --------------------------------------------------------------------------- flat line


@pytest.mark.parametrize("fill", ["repeat_last", "zeros"])
def test_flat_lined_idle_data_is_no_data(fill: str) -> None:
    """Twenty minutes of a device repeating its last sample bit for bit (idle firmware), or of
    zeros (a dead sensor): never quasi-static, no window from it, the calibration unchanged."""
    res = wearer_1h()
    v = res.raw.v.copy()
    a0, a1 = 60 * BATCH, 180 * BATCH  # batch-aligned: 10 min in, 20 min long
    v[a0:a1] = v[a0 - 1] if fill == "repeat_last" else 0.0
    r = run(_with_v(res, v))
    flat_n = int(RATE_HZ)  # the detector's flat_s = 1 s
    assert not r.gate[a0 + flat_n:a1].any()
    # from one batch into the flat stretch (a window of the run before may commit within its
    # guard time) to its end: no window, no update
    b0, b1 = a0 // BATCH + 1, a1 // BATCH - 1
    assert r.windows[b1] == r.windows[b0]
    np.testing.assert_array_equal(r.params[b1], r.params[b0])
    assert r.pipe.counts["updates_rejected"] == 0
    # and it calibrated before and after (most update tries are skipped: the windows agree)
    assert r.pipe.counts["updates"] > 20
    still = res.truth.still.copy()
    still[a0:a1] = False
    err = _err_1s_mg(r.cal, res.truth.a_true_g, still)
    assert np.nanmean(err[-600:] ** 2) ** 0.5 < 2.0  # last 10 min as good as ever


# --------------------------------------------------------------------------- knocked sensor

KNOCK_G = (0.08, -0.06, 0.07)  # an offset jump of 123 mg, at 1 h of a 2 h recording


@cache
def knocked() -> tuple[SimResult, Run, int]:
    spec = _sensor(1)
    res = simulate(2.0, RATE_HZ, 1, spec)
    k = len(res.raw) // 2
    after = with_sensor(res, replace(spec, offset_g=tuple(np.add(spec.offset_g, KNOCK_G))))
    v = np.concatenate([res.raw.v[:k], after.raw.v[k:]])
    return res, run(_with_v(res, v)), k


def _error_per_5_min(res: SimResult, r: Run, k: int) -> dict[int, float]:
    """RMS of the 1 s error over still seconds, per 5 min bin (minutes relative to the knock)."""
    err = _err_1s_mg(r.cal, res.truth.a_true_g, res.truth.still)
    minute = (np.arange(len(err)) - k // int(RATE_HZ)) / 60.0
    return {b: float(np.sqrt(np.nanmean(err[(minute >= b) & (minute < b + 5)] ** 2)))
            for b in range(-10, 60, 5)}


def test_knocked_sensor_recovers_within_15_minutes() -> None:
    """The 1 s error jumps to ~100 mg when the offsets jump by 123 mg; within 15 min it is back
    under 12 mg, and the offsets end within 8 mg of their new values."""
    res, r, k = knocked()
    per_bin = _error_per_5_min(res, r, k)
    assert per_bin[-10] < 2.0 and per_bin[-5] < 2.0, per_bin  # calibrated before the knock
    assert per_bin[0] > 20.0, per_bin  # the knock is seen
    late = {b: e for b, e in per_bin.items() if b >= 15}
    assert max(late.values()) < 12.0, per_bin
    o_new = S0 * (np.array(res.truth.sensor.offset_g) + KNOCK_G)
    assert np.all(np.abs(r.pipe.params[:3] - o_new) / S0 < 0.008), (r.pipe.params[:3] - o_new)
    assert r.pipe.counts["updates_rejected"] == 0


def test_knocked_sensor_returns_to_its_pre_knock_accuracy() -> None:
    """The jump is fitted as a step of the offsets (core/estimator.py): the gains keep what the
    older windows told them. (Was a known failure: 2-12 mg for the hour after the knock.)"""
    res, r, k = knocked()
    per_bin = _error_per_5_min(res, r, k)
    late = {b: e for b, e in per_bin.items() if b >= 20}
    assert max(late.values()) < 2 * per_bin[-10], per_bin


# --------------------------------------------------------------------------- one orientation

ONE_POSE_HOURS = 2.0
ONE_POSE_RATE_HZ = 20.0


@cache
def one_orientation() -> tuple[RawBatch, Run]:
    """Two hours lying still in one tilted orientation (a sensor left on a table)."""
    n = int(ONE_POSE_HOURS * 3600 * ONE_POSE_RATE_HZ)
    up = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    v = forward_model(np.tile(up, (n, 1)), _sensor(1), rng=np.random.default_rng(3))
    raw = RawBatch(np.arange(n, dtype=np.int64) * round(1e6 / ONE_POSE_RATE_HZ), v,
                   np.zeros((n, 0)), ())
    return raw, run(raw, cfg=PipelineConfig(rate_hz=ONE_POSE_RATE_HZ), batch=6000)


def test_single_orientation_for_hours_reports_the_gains_unobservable() -> None:
    """Gains cannot be seen from one orientation: they stay exactly at the pre-calibration and
    every update says so; nothing wanders beyond the pre-calibration's own uncertainty."""
    _, r = one_orientation()
    pipe = r.pipe
    # one try per 10 s of windows; those that agree with the estimate are skipped, but at
    # least one update runs every max_update_interval_s (5 min)
    assert pipe.counts["updates"] > 20 and pipe.counts["updates_rejected"] == 0
    names = pipe.model.names
    gains = [names.index(f"s_{ax}") for ax in "xyz"]
    np.testing.assert_array_equal(r.params[:, gains], np.tile(pipe.prior.mean[gains],
                                                               (len(r.params), 1)))
    for rep in r.reports:
        assert not any(rep.observable[i] or rep.free[i] for i in gains)
    published = pipe.summary()["last_update"]["observable"]
    assert not any(published[f"s_{ax}"] for ax in "xyz")
    assert sum(published.values()) < len(names)
    coverage = pipe.coverage()
    assert coverage.axes_covered == (False, False, False) and coverage.cells_filled == 1
    wander = np.abs(r.params - pipe.prior.mean) / pipe.prior.sd
    assert wander.max() <= 1.0, wander.max(axis=0)


def test_single_orientation_for_hours_keeps_the_norm_at_1_g() -> None:
    """(Was a known failure of the recursive estimator: the norm drifted ~2.6 mg/h.)"""
    _, r = one_orientation()
    half_hour = int(1800 * ONE_POSE_RATE_HZ)
    norm_mg = 1e3 * (np.linalg.norm(r.cal, axis=1) - 1.0)
    blocks = norm_mg[:len(norm_mg) // half_hour * half_hour].reshape(-1, half_hour).mean(axis=1)
    assert np.all(np.abs(blocks) < 3.0), blocks


# --------------------------------------------------------------------------- NaN in the input


def test_nan_and_inf_samples_do_not_poison_the_detector() -> None:
    """A replayed recording or imported table may hold a NaN or inf sample (the serial parsers
    drop them, other sources may not). That sample's output is NaN, but the detector's filters
    must not keep the NaN: the calibration goes on as if the sample were missing."""
    res = wearer_1h()
    v = res.raw.v.copy()
    hit = [1000, 30_000, 30_001, 90_000]
    v[hit] = [[np.nan, 0, 0], [np.inf, 0, 0], [np.nan] * 3, [0, -np.inf, 1]]
    r = run(_with_v(res, v))
    clean = run(res.raw)
    assert not np.isfinite(r.cal[hit]).all(axis=1).any()
    assert not r.gate[hit].any()
    # after the bad samples the detector works as before (its filters held no NaN)
    assert r.gate[hit[-1] + 500:].mean() > 0.5 * clean.gate[hit[-1] + 500:].mean()
    assert r.pipe.counts["updates"] > 0.9 * clean.pipe.counts["updates"]
    err = _err_1s_mg(r.cal, res.truth.a_true_g, res.truth.still)
    assert np.nanmean(err[-600:] ** 2) ** 0.5 < 2.0
    # and still the same for any batching, around the bad samples too
    piece = _with_v(res, v)[28_000:34_000]
    whole, small = run(piece, batch=6000), run(piece, batch=7)
    np.testing.assert_array_equal(small.cal, whole.cal)
    np.testing.assert_array_equal(small.gate, whole.gate)


def test_missing_auxiliary_values_never_reach_the_estimator() -> None:
    """A CSV row may lack its temperature (read as NaN): with a temperature model, samples
    without it are not quasi-static, so no window, update or checkpoint ever holds a NaN (their
    own calibrated output is NaN: there is nothing to correct them with)."""
    spec = _sensor(1, offset_tc_g_per_c=(0.001, -0.001, 0.0005))
    res = simulate(1.0, RATE_HZ, 1, spec)
    aux = res.raw.aux.copy()
    missing = np.zeros(len(aux), bool)
    for start in range(20_000, len(aux), 40_000):  # 4 s gaps every 13 min, in any posture
        missing[start:start + 200] = True
    aux[missing, res.raw.aux_names.index("temp_c")] = np.nan
    raw = RawBatch(res.raw.t_us, res.raw.v, aux, res.raw.aux_names)
    model = SensorModel.diagonal(S0).with_effect(Offset("temp_c", 25.0), 10.0)
    r = run(raw, model=model)
    assert not r.gate[missing].any()
    assert r.pipe.counts["updates"] > 20 and r.pipe.counts["updates_rejected"] == 0
    assert np.isfinite(r.pipe.buffer.aux[r.pipe.buffer.filled]).all()
    assert np.isfinite(r.cal[~missing]).all()
