"""Batch use of the core: a recording's windows as arrays (`core.window_means`), the calibration
with hindsight (`core.hindsight`), and the shortcuts they rely on (`SensorModel.affine`,
`triaxial.per_axis`), against the live pipeline and the simulator's truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from recal.core import hindsight
from recal.core.batch_windows import Windowing, window_means
from recal.core.effects import Covariates, Gain, Nonlinearity, Offset, Ratiometric
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.refit import fresh_windows
from recal.core.triaxial import per_axis
from recal.samples import RawBatch, batch_groups, rebatch
from recal.sim.wearer import SensorSpec, WearerSpec, error_1s_mg, simulate

RATE = 50.0
FIELDS = ("v", "aux", "t_us", "n", "var")


def _batches(raw: RawBatch, size: int) -> list[RawBatch]:
    return [raw[i:i + size] for i in range(0, len(raw), size)]


def _live_windows(batches: list[RawBatch], cfg: PipelineConfig, s0: float):
    """What the live pipeline commits, stepped as it runs: no norm gate, no update."""
    collect = replace(cfg, norm_tol_g=float("inf"), update_every=2**62)
    model = SensorModel.diagonal(s0)
    pipe = Pipeline(collect, model, Prior.default(model), batches[0].aux_names)
    for b in batches:
        pipe.step(b)
    return fresh_windows(pipe.fresh, len(pipe.aux_names))


def _awkward_recording() -> RawBatch:
    """Lost samples, stretches below min_fill, 1 ms jitter (steps that go back: run breaks),
    and NaN readings: every way a run or a window can end early."""
    rng = np.random.default_rng(8)
    r = simulate(0.3, RATE, 8, SensorSpec.random(rng, offset_mg=50, gain_pct=3))
    i = np.arange(len(r.raw))
    keep = rng.random(len(i)) > 0.02
    for s0 in rng.integers(0, len(i), 40):
        keep[(i >= s0) & (i < s0 + 150) & (i % 3 == 1)] = False
    raw = r.raw[keep]
    raw = replace(raw, t_us=raw.t_us + rng.integers(-1000, 1000, len(raw)))
    v = raw.v.copy()
    v[rng.integers(0, len(v), 20)] = np.nan
    return replace(raw, v=v)


def _windowed(batches: list[RawBatch], cfg: PipelineConfig, s0: float):
    """`Windowing` fed exactly these batches (`window_means` joins small ones first)."""
    w = Windowing(cfg, SensorModel.diagonal(s0), s0)
    for b in batches:
        w.add(b)
    return w.kept().means()[0]


def test_windows_as_arrays_are_the_live_pipelines_bit_for_bit_in_any_batches() -> None:
    raw = _awkward_recording()
    cfg = PipelineConfig(rate_hz=RATE)
    ref = _live_windows([raw], cfg, 1024.0)
    assert len(ref) > 300
    for size in (7, 333, len(raw)):
        w = _windowed(_batches(raw, size), cfg, 1024.0)
        for f in FIELDS:
            assert np.array_equal(getattr(w, f), getattr(ref, f)), (size, f)
    # the live pipeline in the same batches agrees too (a window cut by a batch end)
    live = _live_windows(_batches(raw, 333), cfg, 1024.0)
    w = _windowed(_batches(raw, 333), cfg, 1024.0)
    assert all(np.array_equal(getattr(w, f), getattr(live, f)) for f in FIELDS)
    # and window_means, which joins a recording's small batches (`rebatch`) before its work
    w, names, t0 = window_means(_batches(raw, 7), cfg, 1024.0)
    assert names == raw.aux_names and t0 == int(raw.t_us[0])
    assert all(np.array_equal(getattr(w, f), getattr(ref, f)) for f in FIELDS)


def test_windows_of_readings_in_g_agree_with_the_live_pipelines_to_the_last_bit() -> None:
    """Readings that are not integers (a CSV in g): sums are no longer exact, so a window a
    batch end cuts may differ in its last bit (module doc of core.window_means), never more; in
    one batch nothing is cut and the windows are the pipeline's bit for bit."""
    raw = _awkward_recording()
    raw = replace(raw, v=raw.v / 1000.3)
    cfg = PipelineConfig(rate_hz=RATE)
    whole = _live_windows([raw], cfg, 1.0)
    assert all(np.array_equal(getattr(_windowed([raw], cfg, 1.0), f), getattr(whole, f))
               for f in FIELDS)
    for size in (7, 333):
        w = _windowed(_batches(raw, size), cfg, 1.0)
        for ref in (_live_windows(_batches(raw, size), cfg, 1.0), whole):
            for f in ("t_us", "n"):
                assert np.array_equal(getattr(w, f), getattr(ref, f)), (size, f)
            assert np.allclose(w.v, ref.v, rtol=1e-14, atol=0), size
            assert np.allclose(w.var, ref.var, rtol=1e-9, atol=1e-20), size


def test_rebatch_joins_small_batches_in_order_and_starts_anew_where_channels_change() -> None:
    rng = np.random.default_rng(3)

    def batch(n: int, names: tuple[str, ...] = ()) -> RawBatch:
        return RawBatch(np.arange(n) + rng.integers(0, 10**9), rng.normal(size=(n, 3)),
                        rng.normal(size=(n, len(names))), names)

    small = [batch(1000) for _ in range(10)]
    big = batch(70_000)
    other = [batch(500, ("vdd_v",)) for _ in range(3)]
    parts = [*small, big, *other]
    out = list(rebatch(parts, 3000))
    assert [len(b) for b in out] == [3000, 3000, 3000, 71_000, 1500]
    assert [b.aux_names for b in out] == [()] * 4 + [("vdd_v",)]
    joined = RawBatch.concat(out[:4])
    assert np.array_equal(joined.t_us, np.concatenate([b.t_us for b in [*small, big]]))
    assert np.array_equal(joined.v, np.concatenate([b.v for b in [*small, big]]))
    assert np.array_equal(out[4].aux, np.concatenate([b.aux for b in other]))
    assert next(rebatch([big], 3000)) is big  # big enough: passed on as it is, no copy
    # the pairs behind it keep what came with each batch, in order
    groups = list(batch_groups(((b, i) for i, b in enumerate(parts)), 3000))
    assert [[i for _, i in g] for g in groups] == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10],
                                                   [11, 12, 13]]


def test_windowing_keeps_a_window_once_its_run_went_on_guard_s_past_it() -> None:
    """2 s windows, a 1 s guard, min_fill 0.8, at 50 Hz: window 1 of a still run (2-4 s
    into it) is kept when the run lasts 5.1 s, not when it stops at 4.9 s; window 0 holding
    two samples in three (67 of 100) is dropped."""
    n = 20 * int(RATE)
    t = (np.arange(n) * 1e6 / RATE).astype(np.int64)
    v = np.tile([0.0, 0.0, 1.0], (n, 1)) + np.random.default_rng(0).normal(0, 1e-4, (n, 3))
    cfg = PipelineConfig(rate_hz=RATE)

    def kept(m: np.ndarray):
        w = Windowing(cfg, SensorModel.diagonal(1.0), 1.0)
        w.add(RawBatch(t[m], v[m], np.zeros((int(m.sum()), 0))))
        return w.kept()

    rs = int(kept(np.ones(n, bool)).run_start_us[0])  # the detector settles, then the run
    assert kept(t < rs + 5_100_000).k.tolist() == [0, 1]
    assert kept(t < rs + 4_900_000).k.tolist() == [0]
    holes = (t < rs + 4_900_000) & ~((t < rs + 2_000_000) & (np.arange(n) % 3 == 1))
    assert len(kept(holes)) == 0


def _wearer(seed: int, wearer: WearerSpec | None = None, **sensor):
    rng = np.random.default_rng(seed)
    spec = replace(SensorSpec.random(rng, offset_mg=50, gain_pct=3, **sensor),
                   counts_per_g=1024.0)
    return simulate(2.0, RATE, seed, spec, wearer or WearerSpec())


@pytest.mark.parametrize(("name", "model", "sensor"), [
    ("plain", SensorModel.diagonal(1024.0), {}),
    ("cross-axis", SensorModel.full(1024.0), {"cross_axis_deg": 1.5}),
    ("supply", SensorModel.diagonal(1024.0).with_effect(Ratiometric("vdd_v", 3.3), 0.5),
     {"ratiometric_per_v": 0.05}),
])
def test_hindsight_reaches_the_noise_floor_on_the_whole_recording(name, model, sensor) -> None:
    """One fit, every sample corrected with it: no warm-up, the first minute as good as the
    last. The floor is the error of the true parameters (the sensor's noise, ~1 mg at 1 s)."""
    r = _wearer(21, **sensor)
    batches = _batches(r.raw, 10_000)
    fit = hindsight.calibrate(lambda: batches, model, PipelineConfig(rate_hz=RATE))
    out = np.concatenate([fit.correct(b) for b in batches])
    err = error_1s_mg(out, r.truth.a_true_g, RATE, True)
    raw_err = error_1s_mg(r.raw.v / 1024.0, r.truth.a_true_g, RATE, True)
    assert raw_err > 20.0
    assert err < 1.3, (name, err)
    assert fit.windows > 1000 and not fit.held
    assert fit.residual_rms_mg < 3.0


def test_hindsight_without_the_effect_is_worse_and_says_what_it_could_not_see() -> None:
    """The diagonal model on a cross-axis sensor leaves tens of mg; an upright wearer (never
    lying down: -z unseen) gets s_z held at its start and reported."""
    r = _wearer(22, cross_axis_deg=1.5)
    fit = hindsight.calibrate(lambda: [r.raw], SensorModel.diagonal(1024.0),
                              PipelineConfig(rate_hz=RATE))
    assert error_1s_mg(fit.correct(r.raw), r.truth.a_true_g, RATE, True) > 5.0
    up = _wearer(23, WearerSpec(upright_only=True))
    fit = hindsight.calibrate(lambda: [up.raw], SensorModel.diagonal(1024.0),
                              PipelineConfig(rate_hz=RATE))
    assert "s_z" in fit.held
    before = error_1s_mg(up.raw.v / 1024.0, up.truth.a_true_g, RATE, True)
    assert error_1s_mg(fit.correct(up.raw), up.truth.a_true_g, RATE, True) < before / 3


@pytest.mark.parametrize("model", [
    SensorModel.full(1024.0),
    SensorModel.diagonal(1024.0).with_effect(Ratiometric("vdd_v", 3.3), 0.5),
    SensorModel.diagonal(1024.0).with_effect(Gain("vdd_v", 3.3), 0.5)])
def test_hindsight_corrects_into_an_output_array_as_it_returns(model) -> None:
    """The shortcut (full model; diagonal after a supply channel's divisor) and the chain
    (a gain linear in the supply) alike."""
    r = _wearer(24, ratiometric_per_v=0.05)
    fit = hindsight.calibrate(lambda: [r.raw], model, PipelineConfig(rate_hz=RATE))
    out = np.full_like(r.raw.v, np.nan)
    for i in range(0, len(r.raw), 7000):
        fit.correct(r.raw[i:i + 7000], out[i:i + 7000])
    assert np.allclose(out, fit.correct(r.raw), rtol=0, atol=1e-15)  # any batches
    cov = Covariates.from_samples(r.raw.t_us, r.raw.aux, r.raw.aux_names, fit.t0_us)
    assert np.allclose(out, model.correct(fit.p, r.raw.v, cov), rtol=0, atol=1e-12)


def test_hindsight_refuses_a_recording_without_a_still_window() -> None:
    t = (np.arange(500) * 2e4).astype(np.int64)
    v = np.random.default_rng(1).normal(0, 1.0, (500, 3))  # shaking: never quasi-static
    with pytest.raises(ValueError, match="no quasi-static window"):
        hindsight.calibrate(lambda: [RawBatch(t, v, np.zeros((500, 0)))],
                            SensorModel.diagonal(1.0), PipelineConfig(rate_hz=RATE))
    with pytest.raises(ValueError, match="needs samples"):
        hindsight.calibrate(lambda: [], SensorModel.diagonal(1.0), PipelineConfig(rate_hz=RATE))


def test_an_affine_model_is_one_matrix_product_and_others_are_not() -> None:
    """Offsets, scales, cross-axis terms, also after a ratiometric stage (a per-sample
    divisor): one 3x3 product to rounding. A stage that reads a channel after the first
    affine one, or a nonlinear one: no shortcut."""
    rng = np.random.default_rng(3)
    n = 1000
    v = rng.normal(0, 1024.0, (n, 3))
    cov = Covariates(rng.uniform(0, 2, n), rng.uniform(3.6, 4.1, (n, 1)), ("vdd",))
    for model in (SensorModel.full(1024.0),
                  SensorModel.full(1024.0).with_effect(Ratiometric("vdd", 3.3), 0.5)):
        p = model.nominal() + rng.normal(0, 0.02, model.size) * (np.abs(model.nominal()) + 1)
        aff = model.affine(p)
        assert aff is not None and len(aff.divisors) == model.has("ratiometric", "vdd")
        want = model.correct(p, v, cov)
        assert np.allclose(aff(v, cov), want, rtol=0, atol=1e-12)
        out = np.empty_like(v)
        assert aff(v, cov, out) is out and np.allclose(out, want, rtol=0, atol=1e-12)
    for model in (SensorModel.diagonal(1.0).with_effect(Offset("vdd", 3.3)),
                  SensorModel.diagonal(1.0).with_effect(Nonlinearity())):
        assert model.affine(model.nominal()) is None


@pytest.mark.parametrize("n", [1, 5, 255, 256, 10_000])
def test_per_axis_arithmetic_is_the_broadcast_bit_for_bit(n: int) -> None:
    rng = np.random.default_rng(n)
    x = rng.normal(0, 1000, (n, 3))
    theta = rng.normal(0, 10, 3)
    for op in (np.subtract, np.divide, np.multiply):
        assert np.array_equal(per_axis(op, x, theta), op(x, theta))


# --- the command ---------------------------------------------------------------------------
def _recording(path, sensors: dict[str, RawBatch]) -> None:
    from recal.io.recording_writer import RecordingWriter

    with RecordingWriter(path, overwrite=True) as w:
        for sid, raw in sensors.items():
            for i in range(0, len(raw), 1000):
                w.write_raw(sid, raw[i:i + 1000], int(raw.t_us[i]) * 1000 + 1)


def test_cli_hindsight_writes_every_sample_calibrated_and_the_fit(tmp_path, capsys) -> None:
    """A full model from a file on a cross-axis recording in counts: the MCAP out holds the
    raw messages copied, every sample calibrated (read back with the mcap reader) to the
    noise floor, and the fit; the CSV out the same samples."""
    import json

    from recal import cli
    from recal.io import recording as rec

    r = _wearer(31, cross_axis_deg=1.5)
    mcap, out, fit_json = tmp_path / "in.mcap", tmp_path / "out.mcap", tmp_path / "fit.json"
    _recording(mcap, {"wrist": r.raw})
    model_file = tmp_path / "model.json"
    model_file.write_text(json.dumps(SensorModel.full(1024.0).to_dict()))
    assert cli.main(["hindsight", str(mcap), "--out", str(out), "--model", str(model_file),
                     "--json", str(fit_json), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "calibrated 360000 samples of wrist" in said and "cross_axis" in said
    cal = rec.read_all_calibrated(out, "wrist")
    assert np.array_equal(cal.t_us, r.raw.t_us)
    assert cal.t_dev is not None and np.array_equal(cal.t_dev, r.raw.t_us)  # joins the raw
    # corrected some 65 000 samples at a time, logged in messages of at most 16384 samples,
    # each sample as one correction of the whole recording gives it (as logged: to 0.5 ug)
    sizes = [len(b) for _, b, _ in rec.iter_calibrated(out, "wrist")]
    assert sum(sizes) == len(r.raw) and max(sizes) <= 16384
    whole = hindsight.calibrate(lambda: [r.raw], SensorModel.full(1024.0),
                                PipelineConfig(rate_hz=RATE))
    assert np.max(np.abs(cal.a_g - whole.correct(r.raw))) <= 0.5e-6 + 1e-12
    assert error_1s_mg(cal.a_g, r.truth.a_true_g, RATE, True) < 1.3
    assert cal.quasi_static.mean() > 0.5  # the detector's gate, as the live node writes it
    assert sum(len(b) for _, b, _ in rec.iter_raw(out, "wrist")) == len(r.raw)
    fit = [o for _, o, _ in rec.iter_json([out], "/wrist/calibration")]
    assert len(fit) == 1 and fit[0]["hindsight"] and set(fit[0]["params"]) >= {"c_xy", "s_z"}
    assert json.loads(fit_json.read_text())["windows"] > 1000

    csv = tmp_path / "out.csv"
    assert cli.main(["hindsight", str(mcap), "--out", str(csv), "--model", str(model_file),
                     "--quiet"]) == 0
    assert csv.read_text().split("\n", 1)[0] == "t_us,x_g,y_g,z_g,status,sigma_mg"
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert np.array_equal(rows[:, 0].astype(np.int64), r.raw.t_us)
    # both the same values to the micro-g (the CSV's decimals, the log's fixed point)
    assert np.allclose(rows[:, 1:4], cal.a_g, rtol=0, atol=1e-6 + 1e-12)
    assert np.array_equal(rows[:, 4], cal.status)  # sigma: logged in 1 % steps
    assert np.allclose(rows[:, 5], cal.sigma_mg, rtol=0.005 + 1e-5, atol=0.5e-3 + 1e-9)

    # a CSV in (the raw samples in counts), an MCAP out in messages of at most 16384 samples
    raw_csv, from_csv = tmp_path / "raw.csv", tmp_path / "from_csv.mcap"
    assert cli.main(["export", str(mcap), "--csv", str(raw_csv), "--topic", "raw"]) == 0
    assert cli.main(["hindsight", str(raw_csv), "--units", "counts", "--out", str(from_csv),
                     "--model", str(model_file), "--quiet"]) == 0
    again = rec.read_all_calibrated(from_csv, raw_csv.stem)
    assert np.array_equal(again.t_us, r.raw.t_us)
    assert np.allclose(again.a_g, cal.a_g, rtol=0, atol=1e-9)
    sizes = [len(b) for _, b, _ in rec.iter_calibrated(from_csv, raw_csv.stem)]
    assert max(sizes) <= 16384 and sum(sizes) == len(r.raw)


def test_cli_hindsight_bad_input_is_one_line_and_nothing_is_overwritten(tmp_path,
                                                                          capsys) -> None:
    import json

    from recal import cli

    r = _wearer(32)
    mcap = tmp_path / "two.mcap"
    _recording(mcap, {"a": r.raw[:20_000], "b": r.raw[:20_000]})
    one = tmp_path / "one.mcap"
    _recording(one, {"a": r.raw[:1]})
    out = tmp_path / "out.mcap"
    out.write_bytes(b"keep me")
    supply = tmp_path / "supply.json"
    supply.write_text(json.dumps(SensorModel.diagonal(1024.0)
                                 .with_effect(Ratiometric("vdd_v", 3.3)).to_dict()))
    cases = [
        (["hindsight", str(mcap), "--out", str(tmp_path / "o.mcap")], "several sensors"),
        (["hindsight", str(mcap), "--out", str(tmp_path / "o.mcap"), "--sensor-id", "a",
          "--model", str(supply)], "needs channels ['vdd_v']"),
        (["hindsight", str(mcap), "--out", str(tmp_path / "o.mcap"), "--sensor-id", "c"],
         "no sensor 'c'"),
        (["hindsight", str(mcap), "--out", str(out), "--sensor-id", "a"], "--overwrite"),
        (["hindsight", str(mcap), "--out", str(mcap), "--sensor-id", "a", "--overwrite"],
         "input"),
        (["hindsight", str(tmp_path / "none.mcap"), "--out", str(tmp_path / "o.mcap")],
         "none.mcap"),
        (["hindsight", str(one), "--out", str(tmp_path / "o.mcap")], "at least two samples"),
    ]
    for argv, words in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err and "Traceback" not in err, err
    assert out.read_bytes() == b"keep me"
    assert not (tmp_path / "o.mcap").exists()


def test_hindsight_on_the_measured_xsens_recording_needs_its_cross_axis_terms() -> None:
    """../shared/data/real: an Xsens IMU in raw counts turned through lab poses. Offsets and
    gains leave ~3.4 mg on its still windows; with the cross-axis terms (the effect recal
    discover finds there) ~0.14 mg, every parameter determined by the poses."""
    from pathlib import Path

    from recal.core.discovery_data import rate_and_scale

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / \
        "xsens_imutk_multipos.npz"
    assert path.is_file(), f"measured data missing: {path} (the tests need ../shared/data)"
    with np.load(path) as z:
        v = z["acc_counts"].astype(np.float64) - 32768.0  # unsigned 16-bit, 0 g mid-scale
        t_us = np.round(z["t"] * 1e6).astype(np.int64)
    raw = RawBatch(t_us, v, np.zeros((len(v), 0)))
    rate, s0 = rate_and_scale([raw])
    cfg = PipelineConfig(rate_hz=rate)
    plain = hindsight.calibrate(lambda: [raw], SensorModel.diagonal(s0), cfg)
    full = hindsight.calibrate(lambda: [raw], SensorModel.full(s0), cfg)
    assert full.windows == plain.windows > 100 and not full.held
    assert plain.residual_rms_mg > 2.0
    assert full.residual_rms_mg < 0.3
