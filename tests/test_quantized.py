"""A sensor as it is: whole counts of 1/256 g, little noise, a clock off its nominal rate, a
stretch on a table. The detector learns the step and does not call such a still sensor stuck;
window means carry the rounding their samples' noise does not dither; nothing assumes the
nominal clock."""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from quantized_sensor import COUNTS_PER_G, SENSOR, Quiet, quiet_ax3
from recal.core import detector as det
from recal.core import hindsight
from recal.core.batch_windows import window_means
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.core.quantization import (
    LATTICE_CHANGES,
    coarse,
    mean_floor_g2,
    observe,
    window_noise_g2,
)
from recal.samples import RawBatch

STEP_G = 1.0 / COUNTS_PER_G


@cache
def quiet(counts_per_g: float | None = COUNTS_PER_G) -> Quiet:
    """One hour, 20 min of it on a table (the same recording for several tests)."""
    return quiet_ax3(sensor=replace(SENSOR, counts_per_g=counts_per_g))


def _slices(b: RawBatch, n: int = 20_000) -> list[RawBatch]:
    return [RawBatch(b.t_us[i:i + n], b.v[i:i + n], b.aux[i:i + n], b.aux_names)
            for i in range(0, len(b), n)]


def _detect(v: np.ndarray, cfg: det.DetectorConfig | None = None
            ) -> tuple[det.DetectorState, det.DetectorOutput]:
    cfg = cfg or PipelineConfig(rate_hz=100.0).detector(1.0, None)
    return det.detect(cfg, det.init_state(cfg), v)


# --- the step --------------------------------------------------------------------------------

def test_the_step_is_learned_from_the_readings_and_then_stays() -> None:
    q = quiet_ax3(hours=0.1, table_s=(60.0, 60.0))
    st, _ = _detect(q.batch.v)
    np.testing.assert_allclose(st.step_raw, STEP_G, rtol=1e-9)
    assert coarse(st.step_raw, 1.0)
    assert st.changes == min(LATTICE_CHANGES, int(np.any(np.diff(q.batch.v, axis=0), 1).sum()) + 1)
    # bounded: once LATTICE_CHANGES changes are seen, finer readings teach nothing
    step, changes, _ = observe(st.step_raw, LATTICE_CHANGES, np.array([[0.0, 0.0, 0.0],
                                                                     [1e-6, 0.0, 0.0]]),
                               np.full(3, np.nan))
    assert changes == LATTICE_CHANGES and np.array_equal(step, st.step_raw)


def test_a_sensor_of_continuous_values_has_no_coarse_step() -> None:
    q = quiet_ax3(hours=0.1, table_s=(60.0, 60.0), sensor=replace(SENSOR, counts_per_g=None))
    st, o = _detect(q.batch.v)
    assert np.all(st.step_raw < 1e-5) and not coarse(st.step_raw, 1.0)
    assert not o.flat.any()


def test_learning_the_step_sample_by_sample_gives_the_batchs_gates_and_state() -> None:
    q = quiet_ax3(hours=0.05, table_s=(30.0, 60.0))
    v = q.batch.v[:9000]
    cfg = PipelineConfig(rate_hz=100.0).detector(1.0, None)
    whole_st, whole = det.detect(cfg, det.init_state(cfg), v)
    st, flats, gates = det.init_state(cfg), [], []
    st, first = det.detect(cfg, st, v[:1])
    flats.append(first.flat)
    gates.append(first.gate)
    for i in range(1, len(v)):
        st, o = det.detect(cfg, st, v[i:i + 1])
        flats.append(o.flat)
        gates.append(o.gate)
    assert np.array_equal(np.concatenate(flats), whole.flat)
    assert np.array_equal(np.concatenate(gates), whole.gate)
    assert np.array_equal(st.step_raw, whole_st.step_raw) and st.changes == whole_st.changes


# --- the flat-line rule ----------------------------------------------------------------------

def test_a_still_quantized_sensor_on_a_table_is_quasi_static_not_flat() -> None:
    q = quiet()
    v = q.batch.v
    # the case itself: on the table most readings repeat the one before on every axis
    same = np.all(v[1:] == v[:-1], axis=1)
    assert same[q.table[1:]].mean() > 0.9
    _, o = _detect(v)
    assert o.gate[q.table].mean() >= 0.9
    assert not o.flat.any()
    assert o.gate[q.still].mean() >= 0.9


def test_a_stuck_sensor_is_still_flat() -> None:
    cfg = PipelineConfig(rate_hz=100.0).detector(1.0, None)
    q = quiet_ax3(hours=0.05, table_s=(30.0, 60.0))
    # never seen to change: no step, the 1 s rule (a serial sensor stuck from its start)
    v = np.repeat(q.batch.v[:1], 500, axis=0)
    _, o = _detect(v, cfg)
    assert o.flat[100:].all() and not o.gate[100:].any()
    # a coarse sensor stuck: flat after flat_coarse_s
    cfg = replace(cfg, flat_coarse_s=60.0)
    v = np.concatenate([q.batch.v[:9000], np.repeat(q.batch.v[8999:9000], 9000, axis=0)])
    st, o = _detect(v, cfg)
    assert coarse(st.step_raw, 1.0)
    start = int(np.flatnonzero(np.any(v[1:] != v[:-1], axis=1))[-1]) + 1  # the last change
    assert start <= 9000 and not o.flat[:start + 5998].any()
    assert o.flat[start + 6000:].all() and not o.gate[start + 6000:].any()
    # and a continuous one, as ever: after flat_s
    v = np.concatenate([q.batch.v[:3000] + 1e-7 * np.arange(3000)[:, None],
                        np.repeat(q.batch.v[:1], 300, axis=0)])
    _, o = _detect(v, cfg)
    assert o.flat[3000 + 100:].all()


# --- the noise of a window mean --------------------------------------------------------------

@pytest.mark.parametrize("sd_steps", [0.0, 0.1, 0.2, 0.3, 0.6, 1.0])
def test_a_window_means_noise_counts_what_rounding_leaves_in_it(sd_steps: float) -> None:
    """Means of 200 rounded readings (step 1) of values spread over a step, with noise of
    sd_steps: their error's variance is what window_noise_g2 says from the readings' own
    variance, with no noise and dithered alike, and nothing beyond var / n once dithered."""
    rng = np.random.default_rng(4)
    true = rng.uniform(0, 1, (4000, 1))
    r = np.round(true + sd_steps * rng.standard_normal((4000, 200)))
    err2 = np.mean((r.mean(1) - true[:, 0]) ** 2)
    var = r.var(1, ddof=1)
    said = np.mean(window_noise_g2(var, np.full(len(r), 200), 1.0, np.ones(3)))
    assert 0.6 * said < err2 < 1.6 * said
    if sd_steps >= 0.6:
        assert np.mean(mean_floor_g2(np.ones(3), var)) < 0.01 * np.mean(var / 200)


def test_an_unknown_step_adds_nothing() -> None:
    assert np.all(mean_floor_g2(np.full(3, np.inf), np.array([0.0, 1e-6])) == 0.0)


# --- hindsight and the clock -----------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.float_sensitive
def test_hindsight_on_a_quiet_quantized_sensor_fits_to_its_noise() -> None:
    q = quiet()
    b = q.batch
    rate_hz = 1e6 * (len(b) - 1) / float(b.t_us[-1] - b.t_us[0])
    fit = hindsight.calibrate(lambda: _slices(b), SensorModel.diagonal(1.0),
                              PipelineConfig(rate_hz=rate_hz))
    assert fit.misfit is not None
    assert 0.1 < fit.chi2 < 2.0 and not fit.misfit.well_above_noise and not fit.poor
    assert fit.misfit.noise_g > STEP_G / np.sqrt(12) / 2  # the rounding is in the noise
    err = fit.correct(b) - q.a_true_g
    n = len(b) // 100 * 100
    e1 = err[:n].reshape(-1, 100, 3).mean(1)[q.still[:n].reshape(-1, 100).all(1)]
    assert 1e3 * np.sqrt(np.mean(np.sum(e1 ** 2, 1))) < 2.0


@pytest.mark.slow
@pytest.mark.float_sensitive
def test_hindsight_on_a_continuous_sensor_is_unchanged_by_the_step() -> None:
    q = quiet(None)
    b = q.batch
    rate_hz = 1e6 * (len(b) - 1) / float(b.t_us[-1] - b.t_us[0])
    cfg = PipelineConfig(rate_hz=rate_hz)
    w, names, t0 = window_means(_slices(b), cfg, 1.0)
    model = SensorModel.diagonal(1.0)
    learned = hindsight.calibrate(lambda: _slices(b), model, cfg)
    without = hindsight.fit(w, names, t0, model, cfg.norm_tol_g, None)
    assert learned.chi2 == pytest.approx(without.chi2, rel=1e-6)
    np.testing.assert_allclose(learned.p, without.p, rtol=1e-9, atol=1e-12)


@pytest.mark.slow
def test_windows_do_not_assume_the_nominal_clock() -> None:
    """The device's oscillator 0.3 % fast, its stamps jittered by +-2 ms (a reader's block
    stamps), the pipeline set to the nominal 100 Hz: the same windows, within a few, as at
    the measured rate with clean stamps."""
    q = quiet()
    b = q.batch
    rate_hz = 1e6 * (len(b) - 1) / float(b.t_us[-1] - b.t_us[0])
    assert abs(rate_hz / 100.0 - 1.003) < 1e-4
    jitter = np.random.default_rng(9).integers(-2000, 2001, len(b))
    jittered = RawBatch(b.t_us + jitter, b.v, b.aux, b.aux_names)
    clean, _, _ = window_means(_slices(b), PipelineConfig(rate_hz=rate_hz), 1.0)
    nominal, _, _ = window_means(_slices(jittered), PipelineConfig(rate_hz=100.0), 1.0)
    assert abs(len(nominal) - len(clean)) <= 0.01 * len(clean)
    table = (b.t_us[q.table][0], b.t_us[q.table][-1])
    on_table = (nominal.t_us > table[0]) & (nominal.t_us < table[1])
    assert on_table.sum() >= 0.9 * 1200 / PipelineConfig().window_s - 2
