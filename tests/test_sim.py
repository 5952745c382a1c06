"""Tests of the seeded wearer / sensor simulator (recal.sim.wearer)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from recal.sim.wearer import (
    POSTURE_KINDS,
    SensorSpec,
    SimResult,
    WearerSpec,
    forward_model,
    inverse_model,
    load_truth,
    misalignment_matrix,
    save_truth,
    sensing_axis_angles_deg,
    simulate,
    with_sensor,
)

IDEAL = SensorSpec(counts_per_g=None, full_scale_g=None, noise_g=0.0)


def _sim(hours: float = 0.25, rate_hz: float = 10.0, seed: int = 1,
         sensor: SensorSpec | None = None, wearer: WearerSpec | None = None,
         **kw: object) -> SimResult:
    return simulate(hours, rate_hz, seed, sensor or SensorSpec(), wearer or WearerSpec(), **kw)


def _same(a: SimResult, b: SimResult) -> bool:
    ra, rb, ta, tb = a.raw, b.raw, a.truth, b.truth
    return (np.array_equal(ra.t_us, rb.t_us) and np.array_equal(ra.v, rb.v)
            and np.array_equal(ra.aux, rb.aux) and ra.aux_names == rb.aux_names
            and np.array_equal(ta.a_true_g, tb.a_true_g) and np.array_equal(ta.still, tb.still)
            and np.array_equal(ta.posture_id, tb.posture_id)
            and ta.posture_kind == tb.posture_kind
            and np.array_equal(ta.posture_up, tb.posture_up) and ta.params == tb.params)


def _slope(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y on [1, x]."""
    design = np.column_stack([np.ones_like(x), x])
    return float(np.linalg.lstsq(design, y, rcond=None)[0][1])


# --- determinism, shapes ---------------------------------------------------------------------

def test_same_seed_is_bit_identical_and_seeds_differ() -> None:
    sensor = SensorSpec.random(np.random.default_rng(0), gain_tc_per_c=(1e-3, 0, 0),
                               ratiometric_per_v=0.05)
    a, b = _sim(seed=5, sensor=sensor), _sim(seed=5, sensor=sensor)
    assert _same(a, b)
    c = _sim(seed=6, sensor=sensor)
    assert not np.array_equal(a.truth.a_true_g, c.truth.a_true_g)
    assert not np.array_equal(a.raw.aux, c.raw.aux)


def test_shapes_dtypes_and_params() -> None:
    r = _sim(hours=0.1, rate_hz=25.0, start_us=1_000_000,
             wearer=WearerSpec(always_aux=True))
    n = round(0.1 * 3600 * 25)
    assert len(r.raw) == n
    assert r.raw.t_us.dtype == np.int64 and r.raw.t_us[0] == 1_000_000
    assert np.all(np.diff(r.raw.t_us) == 40_000)
    assert r.raw.v.shape == (n, 3) and r.raw.v.dtype == np.float64
    assert r.raw.aux.shape == (n, 2) and r.raw.aux_names == ("temp_c", "vdd_v")
    t = r.truth
    assert t.a_true_g.shape == (n, 3) and t.still.dtype == bool and t.still.shape == (n,)
    assert t.posture_id.shape == (n,) and np.issubdtype(t.posture_id.dtype, np.integer)
    assert len(t.posture_kind) == len(t.posture_up) == t.params["n_postures"]
    assert set(t.posture_kind) <= set(POSTURE_KINDS)
    assert t.posture_id.max() < len(t.posture_kind)
    assert json.loads(json.dumps(t.params)) == t.params
    assert t.sensor == SensorSpec()


def test_posture_bookkeeping() -> None:
    r = _sim(hours=0.5, rate_hz=10.0, wearer=WearerSpec(sway_g=0.0))
    t = r.truth
    assert np.all(t.posture_id[t.still] >= 0)
    assert 0.5 < t.still.mean() < 0.98
    # margins: a still posture's first and last 0.5 s (5 samples) are not `still`
    starts = np.flatnonzero(np.diff(t.posture_id) != 0) + 1
    for i in starts[(t.posture_id[starts] >= 0) & (starts < len(t.still) - 10)]:
        assert not t.still[i:i + 5].any() and t.still[i + 5]
    # within a posture with sway 0 the reading is constant and equals its up vector
    for k in np.unique(t.posture_id[t.posture_id >= 0]):
        np.testing.assert_allclose(t.a_true_g[t.posture_id == k], t.posture_up[k][None, :].repeat(
            np.sum(t.posture_id == k), axis=0), atol=1e-12)


def test_still_norm_is_one_g() -> None:
    swaying = _sim(hours=0.5, sensor=replace(IDEAL)).truth
    dev = np.abs(np.linalg.norm(swaying.a_true_g[swaying.still], axis=1) - 1.0)
    assert dev.max() < 1e-3
    # the sway is there: the reading moves by a few mg within postures
    k = swaying.posture_id == 0
    assert np.ptp(swaying.a_true_g[k & swaying.still], axis=0).max() > 1e-3
    exact = _sim(hours=0.5, wearer=WearerSpec(sway_g=0.0)).truth
    np.testing.assert_allclose(np.linalg.norm(exact.a_true_g[exact.still], axis=1), 1.0,
                               atol=1e-12)


def test_motion_is_continuous_and_walking_like() -> None:
    t = _sim(hours=0.5, rate_hz=50.0).truth
    assert np.abs(np.diff(t.a_true_g, axis=0)).max() < 0.3  # no jumps at segment joins
    norm = np.linalg.norm(t.a_true_g[t.posture_id < 0], axis=1)
    assert norm.max() > 1.2 and norm.min() < 0.8  # steps of 0.15-0.35 g with harmonics


def test_changing_the_sensor_keeps_the_wearer() -> None:
    a = _sim(seed=3)
    b = _sim(seed=3, sensor=SensorSpec.random(np.random.default_rng(1), offset_tc_g_per_c=(
        1e-3, 0, 0)))
    assert np.array_equal(a.truth.a_true_g, b.truth.a_true_g)
    assert a.truth.posture_kind == b.truth.posture_kind


def test_with_sensor_matches_simulate() -> None:
    w = WearerSpec(always_aux=True)
    s2 = SensorSpec.random(np.random.default_rng(2), cross_axis_deg=1.0, ratiometric_per_v=0.1,
                           offset_drift_g_per_h=(0.01, 0, 0))
    direct = _sim(seed=4, sensor=s2, wearer=w)
    swapped = with_sensor(_sim(seed=4, wearer=w), s2)
    assert _same(direct, swapped)


# --- the sensor forward model ----------------------------------------------------------------

def test_ideal_sensor_returns_a_true_exactly() -> None:
    r = _sim(sensor=IDEAL)
    assert np.array_equal(r.raw.v, r.truth.a_true_g)
    assert r.raw.aux.shape[1] == 0


def test_quantization_and_clipping() -> None:
    r = _sim(sensor=SensorSpec(full_scale_g=1.2))
    v = r.raw.v
    assert np.array_equal(v, np.rint(v))
    lim = math.floor(1.2 * 1024)
    assert np.abs(v).max() == lim  # walking exceeds 1.2 g: clipped, at a whole count
    inside = np.abs(r.truth.a_true_g).max(axis=1) < 1.1
    np.testing.assert_allclose(v[inside] / 1024, r.truth.a_true_g[inside], atol=0.03)


def test_inverse_model_undoes_every_effect() -> None:
    sensor = SensorSpec.random(
        np.random.default_rng(3), cross_axis_deg=2.0, counts_per_g=512.0, full_scale_g=None,
        noise_g=0.0, q_per_g=(0.01, -0.02, 0.005), gain_tc_per_c=(1e-3, -5e-4, 2e-4),
        offset_tc_g_per_c=(1e-3, 2e-3, -1e-3), offset_drift_g_per_h=(0.01, -0.02, 0.0),
        ratiometric_per_v=0.08, temp_channel="board_temp", supply_channel="vbat")
    r = _sim(sensor=sensor)
    assert r.raw.aux_names == ("board_temp", "vbat")
    a = inverse_model(r.raw.v, sensor, temp_c=r.raw.channel("board_temp"),
                      vdd_v=r.raw.channel("vbat"), t_h=(r.raw.t_us - r.raw.t_us[0]) / 3.6e9)
    # quantization at 512 counts/g is the only loss: ±0.5 count, divided by gains ≈ 1
    np.testing.assert_allclose(a, r.truth.a_true_g, atol=0.6 / 512)
    exact = replace(sensor, counts_per_g=None)
    v = forward_model(r.truth.a_true_g, exact, temp_c=r.raw.channel("board_temp"),
                      vdd_v=r.raw.channel("vbat"), t_h=np.arange(len(r.raw)) / 36000)
    a = inverse_model(v, exact, temp_c=r.raw.channel("board_temp"), vdd_v=r.raw.channel("vbat"),
                      t_h=np.arange(len(r.raw)) / 36000)
    np.testing.assert_allclose(a, r.truth.a_true_g, atol=1e-12)


def test_forward_model_needs_its_covariates_and_rng() -> None:
    a = np.tile([0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(ValueError, match="temperature"):
        forward_model(a, SensorSpec(noise_g=0.0, offset_tc_g_per_c=(1e-3, 0, 0)))
    with pytest.raises(ValueError, match="rng"):
        forward_model(a, SensorSpec())


EFFECTS = {
    "offset": ({"offset_g": (0.04, -0.03, 0.02)}, None),
    "gain": ({"gain": (0.03, -0.02, 0.01)}, None),
    "offset_tc": ({"offset_tc_g_per_c": (2e-3, -1e-3, 5e-4)}, "temp"),
    "gain_tc": ({"gain_tc_per_c": (1e-3, -2e-3, 5e-4)}, "temp"),
    "drift": ({"offset_drift_g_per_h": (0.02, -0.01, 0.03)}, "time"),
    "ratiometric": ({"ratiometric_per_v": 0.1}, "supply"),
    "nonlinearity": ({"q_per_g": (0.02, -0.03, 0.01)}, None),
}


@pytest.mark.parametrize("effect", EFFECTS)
def test_each_effect_shows_up_in_the_still_samples(effect: str) -> None:
    """Regress the raw-minus-truth residual of still samples on the effect's regressor."""
    fields, covariate = EFFECTS[effect]
    sensor = SensorSpec(temp_channel="board_temp", supply_channel="vbat", **fields)
    r = _sim(hours=1.0, rate_hz=5.0, seed=11, sensor=sensor)
    st = r.truth.still
    a = r.truth.a_true_g[st]
    resid = r.raw.v[st] / 1024 - a
    cov = {"temp": lambda: r.raw.channel("board_temp")[st] - 25.0,
           "supply": lambda: r.raw.channel("vbat")[st] - 3.3,
           "time": lambda: (r.raw.t_us[st] - r.raw.t_us[0]) / 3.6e9}
    for j in range(3):
        if effect == "offset":
            est, want = resid[:, j].mean(), fields["offset_g"][j]
        elif effect == "gain":
            est, want = _slope(a[:, j], resid[:, j]), fields["gain"][j]
        elif effect == "nonlinearity":
            est, want = _slope(a[:, j] ** 2, resid[:, j]), fields["q_per_g"][j]
        elif effect == "offset_tc":
            est, want = _slope(cov["temp"](), resid[:, j]), fields["offset_tc_g_per_c"][j]
        elif effect == "gain_tc":
            est, want = _slope(cov["temp"]() * a[:, j], resid[:, j]), fields["gain_tc_per_c"][j]
        elif effect == "drift":
            est, want = _slope(cov["time"](), resid[:, j]), fields["offset_drift_g_per_h"][j]
        else:
            est, want = _slope(cov["supply"]() * a[:, j], resid[:, j]), fields["ratiometric_per_v"]
        assert est == pytest.approx(want, rel=0.05), (effect, j)
    if covariate in ("temp", "supply"):
        assert r.raw.aux_names == ({"temp": "board_temp", "supply": "vbat"}[covariate],)
    else:
        assert r.raw.aux_names == ()


def test_cross_axis_matrix_and_georgieva_angles() -> None:
    s = misalignment_matrix((0.01, -0.02, 0.015))
    np.testing.assert_allclose(np.linalg.norm(s, axis=1), 1.0)
    assert np.all(np.tril(s, -1) == 0)  # upper-triangular: z axis = frame z, y in y-z plane
    ang = sensing_axis_angles_deg(s)
    assert ang["theta_yz_deg"] == pytest.approx(90 - math.degrees(0.015))
    # first order only: the x-y dot product has a term α_xz·α_yz (here 0.017°)
    assert ang["phi_xy_deg"] == pytest.approx(90 - math.degrees(0.01), abs=0.03)
    assert ang["psi_xz_deg"] == pytest.approx(90 + math.degrees(0.02), abs=0.03)
    for i, name in enumerate(("phi_xy_deg", "psi_xz_deg", "theta_yz_deg")):
        alone = np.zeros(3)
        alone[i] = 0.03
        assert sensing_axis_angles_deg(misalignment_matrix(alone))[name] == pytest.approx(
            90 - math.degrees(0.03))
    sensor = SensorSpec(misalignment_rad=(0.01, -0.02, 0.015), noise_g=0.0, counts_per_g=None)
    r = _sim(sensor=sensor)
    np.testing.assert_allclose(r.raw.v, r.truth.a_true_g @ s.T, atol=1e-12)
    assert r.truth.params["axis_angles_deg"] == ang
    np.testing.assert_allclose(r.truth.params["S"], s)


def test_random_sensor_stays_in_its_ranges() -> None:
    rng = np.random.default_rng(0)
    sensors = [SensorSpec.random(rng, offset_mg=50, gain_pct=3, cross_axis_deg=1.5)
               for _ in range(50)]
    off = np.array([s.offset_g for s in sensors])
    gain = np.array([s.gain for s in sensors])
    ang = np.array([s.misalignment_rad for s in sensors])
    assert np.abs(off).max() <= 0.05 and np.abs(off).max() > 0.04
    assert np.abs(gain).max() <= 0.03 and np.abs(gain).max() > 0.02
    assert np.abs(ang).max() <= math.radians(1.5)
    assert SensorSpec.random(rng, noise_g=0.0).noise_g == 0.0
    assert SensorSpec.random(rng).misalignment_rad == (0.0, 0.0, 0.0)


# --- wearer and aux channels -----------------------------------------------------------------

def test_posture_kind_distribution() -> None:
    kinds = np.array(_sim(hours=40.0, rate_hz=0.5, seed=2, sensor=IDEAL).truth.posture_kind)
    assert len(kinds) > 1000
    for kind, p in zip(POSTURE_KINDS, (0.6, 0.25, 0.15), strict=True):
        assert np.mean(kinds == kind) == pytest.approx(p, abs=0.05)
    lying = np.array(_sim(hours=10.0, rate_hz=0.5, sensor=IDEAL, wearer=WearerSpec(
        p_upright=0.0, p_lying=1.0, p_any=0.0)).truth.posture_up)
    assert np.abs(np.degrees(np.arcsin(lying[:, 2]))).max() <= 30.0


def test_upright_only_keeps_the_tilt() -> None:
    w = WearerSpec(upright_only=True, upright_tilt_deg=20.0, step_vertical_g=(0.0, 0.0))
    t = _sim(hours=1.0, rate_hz=10.0, sensor=IDEAL, wearer=w).truth
    assert set(t.posture_kind) == {"upright"}
    assert np.degrees(np.arccos(t.posture_up[:, 2])).max() <= 20.0
    a = t.a_true_g / np.linalg.norm(t.a_true_g, axis=1, keepdims=True)
    tilt = np.degrees(np.arccos(np.clip(a[:, 2], -1, 1)))
    assert tilt[t.still].max() <= 20.5  # sway adds a fraction of a degree
    # movements slerp between upright postures: only the step wobble adds tilt
    assert tilt.max() <= 20.0 + math.sqrt(2) * w.steps.wobble_deg + 0.5


def test_aux_channels_vary_realistically() -> None:
    r = _sim(hours=1.0, rate_hz=5.0, seed=7, wearer=WearerSpec(always_aux=True))
    temp, vdd = r.raw.channel("temp_c"), r.raw.channel("vdd_v")
    assert 21.5 < temp.min() and temp.max() < 36.5 and np.ptp(temp) > 2.0
    np.testing.assert_allclose(temp * 100, np.round(temp * 100), atol=1e-6)  # 0.01 °C steps
    assert vdd[:100].mean() == pytest.approx(4.1, abs=0.05)
    assert vdd[-100:].mean() == pytest.approx(3.6, abs=0.05)
    t = np.arange(len(vdd), dtype=float)
    for x in (temp, vdd):  # fluctuations keep them from being collinear with time
        resid = x - np.polyval(np.polyfit(t, x, 1), t)
        assert resid.std() > 0.005
    # load dips: tens of mV below the local level for seconds
    assert np.min(vdd - np.convolve(vdd, np.ones(301) / 301, mode="same")[:len(vdd)]
                  ) < -0.025


def test_no_aux_unless_needed() -> None:
    assert _sim().raw.aux_names == ()
    r = _sim(sensor=SensorSpec(ratiometric_per_v=0.1, supply_channel="vbat"))
    assert r.raw.aux_names == ("vbat",)


def test_save_load_round_trip(tmp_path) -> None:
    r = _sim(sensor=SensorSpec(offset_tc_g_per_c=(1e-3, 0, 0), temp_channel="board_temp"))
    path = tmp_path / "rec.sim"
    save_truth(path, r)
    back = load_truth(path)
    assert _same(r, back)
    assert back.truth.sensor == r.truth.sensor
    assert WearerSpec.from_dict(back.truth.params["wearer"]) == WearerSpec()


def test_wearer_keywords_land_in_their_groups() -> None:
    """A group's field given to WearerSpec itself changes that group alone; the flat table of
    ``to_dict`` (the truth file's params["wearer"]) reads back to the same spec."""
    w = WearerSpec(upright_tilt_deg=2.0, still_s=(20.0, 60.0), temp_wander_c=0.5,
                   vdd_end_v=3.0, wobble_deg=1.0, always_aux=True)
    assert (w.postures.upright_tilt_deg, w.postures.still_s) == (2.0, (20.0, 60.0))
    assert (w.temperature.temp_wander_c, w.supply.vdd_end_v, w.steps.wobble_deg) == (0.5, 3.0, 1.0)
    assert w.postures.move_s == WearerSpec().postures.move_s and w.always_aux
    flat = w.to_dict()
    assert flat["still_s"] == [20.0, 60.0] and "postures" not in flat
    assert WearerSpec.from_dict(json.loads(json.dumps(flat))) == w
    assert WearerSpec(postures=w.postures, sway_g=0.0).postures.upright_tilt_deg == 2.0
    assert replace(w, vdd_end_v=3.5).supply.vdd_end_v == 3.5
    assert replace(w, vdd_end_v=3.5).temperature == w.temperature
    with pytest.raises(TypeError, match="stil_s"):
        WearerSpec(stil_s=(1.0, 2.0))
