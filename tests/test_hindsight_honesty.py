"""Hindsight and discover say when the fit is poor: on a recording with an effect the model
lacks, hindsight's sigma carries the still windows' residual beyond the noise (local in time),
the samples where that is large are suspect, and the console names the next step; on a clean
recording nothing changes. Measured by the honesty metric of bench/honesty_cases.py (1 s
windows marked calibrated, error against sigma_eff = sqrt(sigma^2 + n^2))."""

from __future__ import annotations

from functools import cache

import numpy as np

from bench_modules import load_bench
from recal.commands.discover import format_table
from recal.commands.hindsight import Corrected, fit_summary, summary_lines
from recal.core import hindsight
from recal.core.batch_windows import window_means
from recal.core.discovery import DiscoveryConfig, discover
from recal.core.discovery_data import data_from_windows, rate_and_scale
from recal.core.effects import Covariates
from recal.core.pipeline_config import PipelineConfig
from recal.core.residuals import misfit
from recal.core.status import Status, predicted_sigma_mg
from recal.samples import rebatch
from recal.sim.wearer import error_1s_mg

hc = load_bench("honesty_cases")
CASE = ({c.lacks: c for c in hc.CASES if c.lacks} | {"clean": hc.CASES[0]}  # clean digital
        | {"upright": next(c for c in hc.CASES if c.wearer.get("upright_only"))})


@cache
def _hindsight(kind: str, seed: int = 1):
    """A 2 h recording of the case through what `recal hindsight` runs: fit, then every
    sample corrected (`Corrected`); also sigma from the parameters' covariance alone."""
    case = CASE[kind]
    r = case.simulate(seed)
    raw = r.raw
    rate_hz, median_norm = rate_and_scale([raw])
    cfg = PipelineConfig(rate_hz=rate_hz)
    fit = hindsight.calibrate(lambda: [raw], case.model(median_norm), cfg)
    corrected = Corrected(fit, cfg)
    outs = [corrected(b) for b in rebatch([raw])]
    cal = np.concatenate([o.a_g for o in outs])
    sigma = np.concatenate([o.sigma_mg for o in outs])
    status = np.concatenate([o.status for o in outs])
    cov = Covariates.from_samples(raw.t_us, raw.aux, raw.aux_names, fit.t0_us)
    sigma_p = predicted_sigma_mg(fit.model, fit.p, fit.cov, raw.v, cov)
    return r, fit, corrected, cal, sigma, status, sigma_p


def _score(kind: str) -> tuple[dict, dict]:
    r, _, _, cal, sigma, status, sigma_p = _hindsight(kind)
    noise = float(r.truth.params["sensor"]["noise_g"])
    before = hc.honesty(cal, r.truth.a_true_g, sigma_p, np.full(len(cal), Status.CALIBRATED),
                        50.0, noise)
    return before, hc.honesty(cal, r.truth.a_true_g, sigma, status, 50.0, noise)


def test_temperature_on_offsets_widens_sigma_where_the_residual_is() -> None:
    before, after = _score("offset[temp]")
    assert before["beyond_3"] > 0.2  # the parameters' covariance alone: far too sure
    assert after["calibrated"] > 0.5 * after["windows"]
    assert after["beyond_3"] <= 0.01 and after["beyond_10"] == 0.0
    _, fit, *_ = _hindsight("offset[temp]")
    assert fit.misfit is not None and fit.misfit.well_above_noise
    # local in time: the excess differs along the recording (the temperature wanders)
    assert fit.misfit.max_excess_g > 1.5 * fit.misfit.overall_g


def test_cross_axis_under_a_diagonal_model_is_suspect_or_honest() -> None:
    before, after = _score("cross_axis")
    assert before["beyond_10"] > 0.05
    assert after["beyond_3"] <= 0.01 and after["beyond_10"] == 0.0
    assert 0 < after["calibrated"] < after["windows"]  # some marked suspect, not all


def test_analog_part_on_a_sagging_supply_is_marked_suspect_and_says_what_next() -> None:
    """The analog part's recording: 12-bit analog part, ratiometric output, supply 3.3 -> 2.9 V,
    no prior: a residual of tens of mg. No sample calibrated with a sigma of 0.1 mg."""
    r, fit, corrected, cal, sigma, _, _ = _hindsight("ratiometric[vdd]")
    before, after = _score("ratiometric[vdd]")
    assert before["beyond_10"] > 0.5
    assert after["calibrated"] == 0 or (after["beyond_3"] <= 0.01
                                        and after["beyond_10"] == 0.0)
    assert fit.poor and corrected.samples_suspect > 0.5 * len(cal)
    err = 1e3 * np.linalg.norm(cal - r.truth.a_true_g, axis=1)
    assert np.median(sigma) > 0.1 * np.median(err)
    # sigma itself covers the error, whatever the status (before: 87 mg against 299 mg)
    every = hc.honesty(cal, r.truth.a_true_g, sigma, np.full(len(cal), Status.CALIBRATED),
                       50.0, float(r.truth.params["sensor"]["noise_g"]))
    assert every["over"] > 1.0 and every["beyond_10"] == 0.0 and every["beyond_3"] < 0.1
    s = {"samples": len(cal), "sensor_id": "s", "seconds": 1.0, "out": "o.mcap",
         "in": "in.mcap", "samples_suspect": corrected.samples_suspect, **fit_summary(fit)}
    text = "\n".join(summary_lines(s))
    # a fit of a model given: the way on is hindsight without --model (it selects effects)
    assert "poor fit" in text and "`recal hindsight in.mcap` without --model" in text
    # after discovery ran and found nothing: where to look
    ran = {"effects_found": [], "heldout_error_mg": {"base": 30.0, "final": 30.0},
           "windows": fit.windows}
    text = "\n".join(summary_lines({**s, "discovery": ran}))
    assert "No candidate effect explained it: `recal discover in.mcap --json`" in text


def test_clean_recording_keeps_its_accuracy_and_a_sigma_within_3x() -> None:
    r, fit, corrected, cal, *_ = _hindsight("clean")
    _, after = _score("clean")
    assert after["calibrated"] == after["windows"] and corrected.samples_suspect == 0
    assert after["beyond_3"] <= 0.01 and 1 / 3 <= after["over"] <= 3
    assert error_1s_mg(cal, r.truth.a_true_g, 50.0, True) < 1.3
    assert fit.misfit is not None and not fit.misfit.well_above_noise
    s = {"samples": len(cal), "sensor_id": "s", "seconds": 1.0, "out": "o.mcap",
         "in": "in.mcap", "samples_suspect": 0, **fit_summary(fit)}
    assert "poor fit" not in "\n".join(summary_lines(s))


def test_misfit_pools_the_residual_beyond_the_noise_around_each_window() -> None:
    """Residual 0.4 mg of pure noise for an hour, then 5 mg more: the excess is ~0 in the
    first half, ~5 mg in the second, the chi-square between."""
    rng = np.random.default_rng(0)
    t = np.arange(3600) * 2_000_000  # a window every 2 s for 2 h
    noise = np.full(len(t), 0.0004**2)
    xi = rng.normal(0, 0.0004, len(t))
    late = t > 3600e6
    xi[late] += rng.choice([-1, 1], late.sum()) * 0.005
    m = misfit(xi, noise, t)
    assert np.all(m.at(np.array([600e6, 3000e6])) < 0.0005)
    assert np.all(np.abs(m.at(np.array([4500e6, 7000e6])) - 0.005) < 0.0005)
    assert m.well_above_noise and m.chi2 > 10


def test_discover_says_when_even_the_best_model_leaves_a_residual() -> None:
    """A cross-axis sensor offered only a nonlinearity: the best model discover finds
    leaves tens of times the noise, and its table says so."""
    r, *_ = _hindsight("cross_axis")
    cfg = PipelineConfig(rate_hz=50.0)
    w, names, t0 = window_means([r.raw], cfg, 1024.0)
    data = data_from_windows(w, names, t0)
    res = discover(data, CASE["cross_axis"].model(data.s0), None,
                   DiscoveryConfig(kinds=("nonlinearity",), time=False, bootstrap=200))
    mis = res.misfit()
    assert mis is not None and mis.well_above_noise
    assert "beyond the sensor noise" in format_table(res)


def test_the_honesty_metric_counts_calibrated_1s_windows_against_sigma_eff() -> None:
    """Four 1 s windows at 10 Hz, noise n = 1e3 * 0.001 * sqrt(3 / 10) = 0.548 mg: errors 1,
    5, 30 mg with sigma 1 mg (sigma_eff 1.14 mg), and one window (500 mg off) not calibrated."""
    # errors along gravity, in four directions: no rotation (the metric's alignment) helps
    truth = np.repeat(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0]]), 10, 0)
    cal = truth * (1 + np.repeat([0.001, 0.005, 0.030, 0.5], 10))[:, None]
    status = np.full(40, Status.CALIBRATED)
    status[35] = Status.SUSPECT
    m = hc.honesty(cal, truth, np.full(40, 1.0), status, 10.0, 0.001)
    assert m["windows"] == 4 and m["calibrated"] == 3
    assert m["beyond_3"] == 2 / 3 and m["beyond_10"] == 1 / 3
    assert abs(m["error_rms_mg"] - np.sqrt((1 + 25 + 900) / 3)) < 1e-6


def test_an_axis_the_recording_never_shows_from_both_sides_holds_every_sample() -> None:
    """A wearer who never lies down: hindsight cannot determine s_z (held at nominal, the
    prior's ~46 mg), so no sample is calibrated (7200 windows at sigma 53 mg were, before);
    the summary and the console name it."""
    _, fit, corrected, _, _, status, _ = _hindsight("upright")
    assert corrected.status == Status.HELD and np.all(status == Status.HELD)
    s = fit_summary(fit)
    assert "s_z" in s["unsettled"]
    lines = summary_lines({**s, "in": "x.mcap", "out": "y.mcap", "sensor_id": "hip",
                           "samples": len(status), "seconds": 1.0, "samples_suspect": 0})
    assert any("every sample held" in line and "s_z" in line for line in lines)
    # the clean recording, every parameter known to 5 mg: calibrated as before
    assert _hindsight("clean")[2].status == Status.CALIBRATED
