"""Mounting alignment (Zheng et al. sec. II.B/C): the pure tilt math, the still tracker, and
the tilt alarm (a slip of the mounting, not a tilted reference) on simulated wear end to end."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from recal.config.settings import (
    PriorConfig,
    SensorConfig,
    ServiceConfig,
)
from recal.core import alignment as al
from recal.node.node import CalibrationNode, NodeSettings, node_settings
from recal.node.sinks import EventSink
from recal.sim import wearer as sim

Z = np.array([0.0, 0.0, 1.0])


def test_zheng_angles_are_arcsin_of_the_normalized_components() -> None:
    g = np.array([0.1, -0.2, 0.9])
    tx, ty = al.zheng_angles(2.5 * g)  # any unit: only the direction counts
    u = g / np.linalg.norm(g)
    assert tx == pytest.approx(np.arcsin(u[0]))
    assert ty == pytest.approx(np.arcsin(u[1]))


def test_single_axis_tilt_matches_zheng_equations_exactly() -> None:
    # tilt in the x-z plane only: Zheng's theta_x is then exact (eq. 3, 6-7)
    theta = np.radians(5.0)
    g = np.array([np.sin(theta), 0.0, np.cos(theta)])
    ali = al.estimate_alignment(g)
    assert ali.theta_x_deg == pytest.approx(5.0)
    assert ali.theta_y_deg == pytest.approx(0.0, abs=1e-12)
    # eq. 6: a_x = a_x cos - a_z sin; eq. 7: a_z = a_x sin + a_z cos
    a = np.array([[0.3, 0.1, 0.8]])
    want = np.array([[0.3 * np.cos(theta) - 0.8 * np.sin(theta), 0.1,
                      0.3 * np.sin(theta) + 0.8 * np.cos(theta)]])
    np.testing.assert_allclose(al.to_body(ali.rotation, a), want, atol=1e-15)


@pytest.mark.parametrize("seed", range(20))
def test_known_rotation_is_recovered(seed: int) -> None:
    rng = np.random.default_rng(seed)
    theta1, theta_y = rng.uniform(-0.6, 0.6, 2)
    R_true = al.rotation_from_angles(theta1, theta_y)  # sensor -> body
    g_sensor = R_true.T @ Z * rng.uniform(0.95, 1.05)  # what the tilted sensor reads upright
    ali = al.estimate_alignment(g_sensor)
    np.testing.assert_allclose(ali.rotation, R_true, atol=1e-12)
    np.testing.assert_allclose(ali.rotation @ (g_sensor / np.linalg.norm(g_sensor)), Z,
                               atol=1e-12)
    np.testing.assert_allclose(ali.rotation @ ali.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(ali.rotation) == pytest.approx(1.0)
    assert ali.theta_y_deg == pytest.approx(np.degrees(theta_y))
    tilt = np.degrees(np.arccos(g_sensor[2] / np.linalg.norm(g_sensor)))
    assert ali.tilt_deg == pytest.approx(tilt)
    # any acceleration maps like the true rotation would map it
    a = rng.normal(size=(10, 3))
    np.testing.assert_allclose(al.to_body(ali.rotation, a), a @ R_true.T, atol=1e-12)


def test_a_tilted_reference_alone_is_no_alarm_a_confirmed_slip_is() -> None:
    def at(deg_x: float, deg_y: float, limit: float = al.DEFAULT_TILT_LIMIT_DEG) -> al.Alignment:
        g = np.array([np.sin(np.radians(deg_x)), np.sin(np.radians(deg_y)), 0.0])
        g[2] = np.sqrt(1 - g[0] ** 2 - g[1] ** 2)
        return al.estimate_alignment(g, limit)

    assert al.DEFAULT_TILT_LIMIT_DEG == 7.0
    # Zheng alarmed beyond 7 deg on the reference itself; the rotation here is exact at any
    # tilt (test_known_rotation_is_recovered), so a tilted mounting is aligned, not alarmed
    for deg in [(6.9, 0.0), (7.1, 0.0), (0.0, -7.5), (25.0, 10.0)]:
        ali = at(*deg)
        assert not ali.alarm and ali.moved_deg is None
        assert ali.tilt_deg == pytest.approx(np.hypot(*deg), abs=0.6)
    slipped = replace(at(3.0, 0.0), moved_deg=9.5)  # what the node records on a slip
    assert slipped.alarm and slipped.to_dict()["alarm"] is True
    assert slipped.to_dict()["moved_deg"] == 9.5


def test_alignment_round_trips_through_dict() -> None:
    ali = al.estimate_alignment(np.array([0.05, 0.1, 0.99]), 7.0, n=500, t_us=123)
    back = al.Alignment.from_dict(ali.to_dict())
    np.testing.assert_array_equal(back.rotation, ali.rotation)
    assert (back.theta_x_deg, back.alarm, back.n, back.t_us) == (ali.theta_x_deg, ali.alarm,
                                                                 500, 123)
    moved = al.Alignment.from_dict(replace(ali, moved_deg=8.25).to_dict())
    assert moved.alarm and moved.moved_deg == 8.25
    # a checkpoint written before slips were tracked (Zheng's "alarm" key, no moved_deg)
    old = {k: v for k, v in ali.to_dict().items() if k != "moved_deg"} | {"alarm": True}
    assert not al.Alignment.from_dict(old).alarm


def test_bad_gravity_is_rejected() -> None:
    with pytest.raises(ValueError):
        al.estimate_alignment(np.zeros(3))
    with pytest.raises(ValueError):
        al.estimate_alignment(np.array([np.nan, 0.0, 1.0]))


def _feed_in_batches(tr: al.StillTracker, t: np.ndarray, a: np.ndarray, gate: np.ndarray,
                     size: int, armed: bool = True) -> list[tuple]:
    hits = []
    for i in range(0, len(t), size):
        hits += tr.feed(t[i:i + size], a[i:i + size], gate[i:i + size], armed)
    return hits


@pytest.mark.parametrize("size", [1, 7, 100, 5000])
def test_still_tracker_fires_once_when_a_run_reaches_min_s(size: int) -> None:
    rate = 100.0
    n = 4000
    t = (np.arange(n) * 1e6 / rate).astype(np.int64)
    gate = np.ones(n, bool)
    gate[500:520] = False  # a 5 s run first (too short), then a 34.8 s run from sample 520
    a = np.tile([0.1, 0.0, 1.0], (n, 1))
    a[520:] = [0.0, 0.2, 0.98]
    tr = al.StillTracker(10.0, round(3e6 / rate))
    hits = _feed_in_batches(tr, t, a, gate, size)
    assert len(hits) == 1
    mean, count, t_hit, gap_s = hits[0]
    assert t_hit == t[520 + 1000]  # exactly 10 s after the run began
    assert count == 1001
    np.testing.assert_allclose(mean, [0.0, 0.2, 0.98])
    assert gap_s == pytest.approx(0.21)  # from sample 499 to sample 520


@pytest.mark.parametrize("size", [1, 13, 700, 20000])
def test_still_tracker_reports_every_run_whatever_the_batches(size: int) -> None:
    # three runs of 12 s in one batch (when size is large): each is reported, with the
    # stillness gap before it, exactly as when the samples come one at a time
    rate = 50.0
    gate = np.zeros(3000, bool)
    runs = [(100, 700), (760, 1360), (1900, 2500)]  # gaps 1.2 s and 10.8 s
    for i0, i1 in runs:
        gate[i0:i1] = True
    t = (np.arange(3000) * 1e6 / rate).astype(np.int64)
    a = np.tile(Z, (3000, 1))
    for k, (i0, i1) in enumerate(runs):
        a[i0:i1] = [0.01 * (k + 1), 0.0, 1.0]
    hits = _feed_in_batches(al.StillTracker(10.0, round(3e6 / rate)), t, a, gate, size)
    assert [h.t_us for h in hits] == [t[i0 + 500] for i0, _ in runs]
    assert hits[0].gap_s is None  # no run before the first
    assert [h.gap_s for h in hits[1:]] == pytest.approx([1.22, 10.82])
    np.testing.assert_allclose([h.mean_g[0] for h in hits], [0.01, 0.02, 0.03])


def test_still_tracker_breaks_runs_at_time_gaps_and_waits_until_armed() -> None:
    rate = 100.0
    t = (np.arange(3000) * 1e4).astype(np.int64)
    t[1500:] += 10_000_000  # a 10 s hole in the data: the run restarts after it
    a = np.tile(Z, (3000, 1))
    gate = np.ones(3000, bool)
    tr = al.StillTracker(16.0, round(3e6 / rate))
    assert _feed_in_batches(tr, t, a, gate, 50) == []  # two 15 s runs, not one of 35 s
    tr2 = al.StillTracker(5.0, round(3e6 / rate))
    assert _feed_in_batches(tr2, t[:800], a[:800], gate[:800], 50, armed=False) == []
    assert tr2.duration_s == pytest.approx(7.99)
    hits = _feed_in_batches(tr2, t[800:900], a[800:900], gate[800:900], 50, armed=True)
    assert len(hits) == 1 and hits[0].t_us == t[800]  # fires as soon as it is armed
    tr2.rearm()
    assert len(_feed_in_batches(tr2, t[900:950], a[900:950], gate[900:950], 50)) == 1


# -- the tilt alarm: SlipWatch on its own ---------------------------------------------------------

def _tilted(deg: float, azimuth_deg: float = 0.0) -> np.ndarray:
    th, az = np.radians(deg), np.radians(azimuth_deg)
    return np.array([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.cos(th)])


def test_slip_watch_alarms_on_agreeing_periods_beyond_the_limit_and_clears_on_reseat() -> None:
    w = al.SlipWatch(_tilted(2.0), 7.0, periods=3)
    t = itertools.count(0, 60_000_000)
    # the reference's own posture again and again: nothing
    assert [w.observe(_tilted(2.3, 10), next(t), 20.0) for _ in range(4)] == [None] * 4
    # the mounting turns by 10 deg: three upright periods agree -> slipped, once
    got = [w.observe(_tilted(12.0 + 0.5 * k, 2 * k), next(t), 20.0) for k in range(5)]
    assert got[:2] == [None, None] and got[3:] == [None, None]
    s = got[2]
    assert s is not None and s.kind == "slipped" and w.alarmed
    assert s.moved_deg == pytest.approx(10.5, abs=0.3) and s.periods == 3
    assert s.spread_deg < 1.0 and s.first_t_us < s.t_us
    assert s.theta_x_deg == pytest.approx(12.5, abs=0.3)
    # lying down in between says nothing either way
    assert w.observe(_tilted(85.0), next(t), 20.0) is None and w.alarmed
    # re-seated: three upright periods back within the limit -> cleared
    back = [w.observe(_tilted(2.0 + k, 40 * k), next(t), 20.0) for k in range(3)]
    assert back[:2] == [None, None] and back[2] is not None and back[2].kind == "reseated"
    assert not w.alarmed


def test_slip_watch_ignores_postures_that_scatter_or_come_back() -> None:
    w = al.SlipWatch(Z, 7.0, periods=3)
    t = itertools.count(0, 60_000_000)
    # leaning 15-25 deg every which way (a wearer, not a slip): beyond the limit, no agreement
    for k in range(30):
        assert w.observe(_tilted(15.0 + (k % 3) * 5, 137.5 * k), next(t), 20.0) is None
    # two agreeing periods beyond the limit, one near the reference, two more: no streak of 3
    for deg in (10.0, 10.2, 1.0, 10.1, 10.3):
        assert w.observe(_tilted(deg), next(t), 20.0) is None
    assert w.observe(_tilted(10.0), next(t), 20.0) is not None  # the third in a row
    default = al.SlipWatch(Z, 7.0)  # the node's: four in a row
    assert [default.observe(_tilted(10.0), 10**8 * k) is not None for k in range(4)] == [
        False, False, False, True]


def test_slip_watch_needs_movement_between_periods() -> None:
    w = al.SlipWatch(Z, 7.0, periods=3, min_move_s=3.0)
    # one posture whose still run the detector broke twice for a second: one period, not three
    got = [w.observe(_tilted(11.0), 10**7 * k, gap) for k, gap in enumerate((9.0, 1.0, 0.5))]
    assert got == [None, None, None] and not w.alarmed
    assert w.observe(_tilted(11.2), 10**8, 6.0) is None  # the second separate period
    assert w.observe(_tilted(10.8), 2 * 10**8, None) is not None  # gap unknown: counted


# -- the tilt alarm end to end: CalibrationNode on simulated wear -----------------------------

RATE_HZ = 25.0


def _settings() -> NodeSettings:
    """The default service's settings for one sensor at RATE_HZ with a 1024 counts/g prior."""
    sensor = SensorConfig("s", rate_hz=RATE_HZ, prior=PriorConfig(counts_per_g=1024.0))
    return node_settings(sensor, ServiceConfig())


def _wear(seed: int, minutes: float, wearer: sim.WearerSpec, slip: sim.MountSlip | None = None,
          batch: int = 250) -> EventSink:
    """A sensor with offsets +-50 mg and gains +-3 % on a simulated wearer, through a node with
    the default alignment settings (reference after an accepted update, 7 deg limit)."""
    spec = sim.SensorSpec.random(np.random.default_rng(seed), offset_mg=50.0, gain_pct=3.0)
    raw = sim.simulate(minutes / 60, RATE_HZ, seed, spec, wearer, slip=slip).raw
    sink = EventSink()
    node = CalibrationNode(_settings(), sink)
    for i in range(0, len(raw), batch):
        b = raw[i:i + batch]
        node.process(b, int(b.t_us[0]) * 1000)
    return sink


STANDING = sim.WearerSpec(upright_tilt_deg=2.0, still_s=(20.0, 60.0))


@pytest.mark.parametrize("seed", [1, 5, 6])
def test_a_wearer_moving_through_all_orientations_raises_no_alarm(seed: int) -> None:
    sink = _wear(seed, 40.0, sim.WearerSpec())
    refs = sink.of("alignment")
    assert refs, "no reference posture in 40 min"
    d = refs[0]["detail"]
    # the reference was a posture leaning beyond 7 deg: Zheng's rule alarmed here
    assert max(abs(d["theta_x_deg"]), abs(d["theta_y_deg"])) > 7.0
    assert sink.of("tilt_alarm") == []


@pytest.mark.parametrize(("seed", "deg", "over_s"), [(1, 10.0, 0.0), (6, 12.0, 0.0),
                                                     (6, 10.0, 300.0)])
def test_a_mounting_that_slips_beyond_the_limit_is_alarmed_within_minutes(
        seed: int, deg: float, over_s: float) -> None:
    before = _wear(seed, 8.0, STANDING)  # the same wearer until the slip begins
    ref_s = before.of("alignment")[0]["t_us"] / 1e6
    slip = sim.MountSlip(deg, ref_s + 120.0, over_s, azimuth_deg=40.0 * seed)
    sink = _wear(seed, 30.0, STANDING, slip)
    assert sink.of("alignment")[0]["t_us"] / 1e6 == ref_s
    alarms = sink.of("tilt_alarm")
    assert len(alarms) == 1, [(e["kind"], e["t_us"]) for e in sink.events]
    a = alarms[0]
    delay_s = a["t_us"] / 1e6 - (slip.at_s + over_s)
    assert 0 < delay_s < 15 * 60  # four upright periods after the slip
    assert a["detail"]["first_t_us"] / 1e6 >= slip.at_s  # all of its evidence is after it
    # upright postures scatter within 2 deg, the reference's one too
    assert a["detail"]["moved_deg"] == pytest.approx(deg, abs=2.5)
    assert "re-seat" in a["detail"]["detail"]


def test_a_slip_within_the_limit_raises_no_alarm() -> None:
    before = _wear(1, 8.0, STANDING)
    ref_s = before.of("alignment")[0]["t_us"] / 1e6
    sink = _wear(1, 30.0, STANDING, sim.MountSlip(4.0, ref_s + 120.0, azimuth_deg=40.0))
    assert sink.of("alignment") and sink.of("tilt_alarm") == []


def test_the_alarm_does_not_depend_on_the_batch_size() -> None:
    slip = sim.MountSlip(10.0, 240.0, azimuth_deg=40.0)
    runs = [_wear(1, 20.0, STANDING, slip, batch) for batch in (7, 250, 30_000)]
    kinds = ("alignment", "tilt_alarm", "tilt_cleared")
    got = [[(e["kind"], e["t_us"]) for e in s.events if e["kind"] in kinds] for s in runs]
    assert any(k == "tilt_alarm" for k, _ in got[0])
    assert got[1] == got[0] and got[2] == got[0]


def test_sim_mount_slip_turns_only_what_follows_it() -> None:
    w = sim.WearerSpec(still_s=(10.0, 20.0))
    spec = sim.SensorSpec(noise_g=0.0, counts_per_g=None)
    plain = sim.simulate(0.1, RATE_HZ, 3, spec, w)
    slip = sim.MountSlip(9.0, 120.0, 60.0, azimuth_deg=30.0)
    slipped = sim.simulate(0.1, RATE_HZ, 3, spec, w, slip=slip)
    assert "slip" not in plain.truth.params and slipped.truth.params["slip"]["deg"] == 9.0
    t_s = (plain.raw.t_us / 1e6)
    before, ramp, after = t_s < 120.0, (t_s >= 120.0) & (t_s < 180.0), t_s >= 180.0
    a0, a1 = plain.truth.a_true_g, slipped.truth.a_true_g
    np.testing.assert_array_equal(a1[before], a0[before])  # bit for bit until the slip
    np.testing.assert_array_equal(slipped.truth.posture_up, plain.truth.posture_up)
    np.testing.assert_allclose(np.linalg.norm(a1, axis=1), np.linalg.norm(a0, axis=1),
                               rtol=1e-12)  # a rotation: lengths unchanged
    # a turn by θ about the unit axis k moves v by φ with cos φ = cos θ + (1 - cos θ)(k·v/|v|)²;
    # the axis lies at 30 deg in the sensor's x-y plane
    ax = np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0])
    v0, v1 = a0[after][::97], a1[after][::97]
    kv = (v0 @ ax) / np.linalg.norm(v0, axis=1)
    c = np.cos(np.radians(9.0))
    want = np.degrees(np.arccos(c + (1 - c) * kv ** 2))
    got = [al.angle_deg(x, y) for x, y in zip(v0, v1, strict=True)]
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert slip.apply(ax[None, :].copy(), np.array([500.0]))[0] == pytest.approx(ax)
    half = slip.apply(Z[None, :].copy(), np.array([150.0]))[0]  # half way through the ramp
    assert al.angle_deg(half, Z) == pytest.approx(4.5)
    assert np.all(np.isfinite(a1[ramp]))
    np.testing.assert_array_equal(slipped.raw.v[before], plain.raw.v[before])


def test_the_alarm_stands_in_the_state_and_clears_when_the_sensor_is_reseated() -> None:
    seed, minutes = 1, 40.0
    ref_s = _wear(seed, 8.0, STANDING).of("alignment")[0]["t_us"] / 1e6
    slip = sim.MountSlip(10.0, ref_s + 120.0, azimuth_deg=40.0)
    spec = sim.SensorSpec.random(np.random.default_rng(seed), offset_mg=50.0, gain_pct=3.0)
    plain = sim.simulate(minutes / 60, RATE_HZ, seed, spec, STANDING)
    slipped = sim.simulate(minutes / 60, RATE_HZ, seed, spec, STANDING, slip=slip)
    # re-seated 15 min after the slip: the sensor reads as it did before it
    t_s = plain.raw.t_us / 1e6
    a = np.where((t_s >= slip.at_s + 900.0)[:, None], plain.truth.a_true_g,
                 slipped.truth.a_true_g)
    v = sim.forward_model(a, spec, rng=np.random.default_rng(seed + 100))
    raw = replace(plain.raw, v=v)
    sink = EventSink()
    node = CalibrationNode(_settings(), sink)
    standing: list[bool] = []
    for i in range(0, len(raw), 250):
        b = raw[i:i + 250]
        node.process(b, int(b.t_us[0]) * 1000)
        standing.append(node.status()["alignment"]["alarm"] if node.alignment else False)
    kinds = [e["kind"] for e in sink.events if e["kind"].startswith("tilt_")]
    assert kinds == ["tilt_alarm", "tilt_cleared"]
    raised, cleared = sink.of("tilt_alarm")[0], sink.of("tilt_cleared")[0]
    assert slip.at_s < raised["t_us"] / 1e6 < slip.at_s + 900.0 < cleared["t_us"] / 1e6
    assert cleared["detail"]["moved_deg"] < 7.0
    # the alarm stood in the published state from the one event to the other
    at = np.array([int(b.t_us[-1]) for b in (raw[i:i + 250] for i in range(0, len(raw), 250))])
    on = np.array(standing)
    assert on[(at >= raised["t_us"]) & (at < cleared["t_us"])].all()
    assert not on[(at < raised["t_us"]) | (at >= cleared["t_us"])].any()
    assert len(sink.of("alignment")) == 1  # neither event replaced the reference


def test_still_tracker_one_sample_on_scalars_is_the_array_path_bit_for_bit() -> None:
    """`StillTracker._feed_one` (one sample, scalars) against the array path fed the same
    one-sample batches: the same hits and the same state after every sample, to the bit,
    through runs, gaps in time, arming and re-arming, with signed zeros among the values."""
    rng = np.random.default_rng(21)
    n, rate = 6000, 100.0
    t = np.cumsum(np.where(rng.random(n) < 0.0005, 500_000, 10_000)).astype(np.int64)
    gate = np.repeat(rng.random(n // 300 + 1) < 0.7, 300)[:n] & (rng.random(n) > 0.0005)
    a = rng.normal(0.0, 0.3, (n, 3))
    a[rng.random((n, 3)) < 0.05] = -0.0
    armed = np.repeat(rng.random(n // 700 + 1) < 0.6, 700)[:n]
    scalar = al.StillTracker(2.0, round(3e6 / rate))
    arrays = al.StillTracker(2.0, round(3e6 / rate))
    arrays._feed_one = lambda *args: None  # type: ignore[method-assign]  # the array path
    hits = 0
    for i in range(n):
        if i % 1000 == 999:
            scalar.rearm()
            arrays.rearm()
        h1 = scalar.feed(t[i:i + 1], a[i:i + 1], gate[i:i + 1], bool(armed[i]))
        h2 = arrays.feed(t[i:i + 1], a[i:i + 1], gate[i:i + 1], bool(armed[i]))
        assert [(h.mean_g.tobytes(), h.n, h.t_us, h.gap_s) for h in h1] == \
            [(h.mean_g.tobytes(), h.n, h.t_us, h.gap_s) for h in h2]
        hits += len(h1)
        for name in ("start_us", "end_us", "last_us", "last_gate", "n", "fired", "gap_us"):
            assert getattr(scalar, name) == getattr(arrays, name), name
        assert scalar.sum_g.tobytes() == arrays.sum_g.tobytes()
    assert hits >= 3, hits
