"""Mounting alignment (Zheng et al. sec. II.B/C): the pure tilt math and the still tracker."""

from __future__ import annotations

import numpy as np
import pytest

from recal.core import alignment as al

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


def test_alarm_above_the_limit_and_not_below() -> None:
    def at(deg_x: float, deg_y: float, limit: float = al.DEFAULT_TILT_LIMIT_DEG) -> al.Alignment:
        g = np.array([np.sin(np.radians(deg_x)), np.sin(np.radians(deg_y)), 0.0])
        g[2] = np.sqrt(1 - g[0] ** 2 - g[1] ** 2)
        return al.estimate_alignment(g, limit)

    assert al.DEFAULT_TILT_LIMIT_DEG == 7.0
    assert not at(6.9, 0.0).alarm
    assert not at(-5.0, 6.5).alarm
    assert at(7.1, 0.0).alarm
    assert at(0.0, -7.5).alarm
    assert at(3.0, 3.0, limit=2.0).alarm  # configurable
    assert not at(8.0, 0.0, limit=10.0).alarm


def test_alignment_round_trips_through_dict() -> None:
    ali = al.estimate_alignment(np.array([0.05, 0.1, 0.99]), 7.0, n=500, t_us=123)
    back = al.Alignment.from_dict(ali.to_dict())
    np.testing.assert_array_equal(back.rotation, ali.rotation)
    assert (back.theta_x_deg, back.alarm, back.n, back.t_us) == (ali.theta_x_deg, ali.alarm,
                                                                 500, 123)


def test_bad_gravity_is_rejected() -> None:
    with pytest.raises(ValueError):
        al.estimate_alignment(np.zeros(3))
    with pytest.raises(ValueError):
        al.estimate_alignment(np.array([np.nan, 0.0, 1.0]))


def _feed_in_batches(tr: al.StillTracker, t: np.ndarray, a: np.ndarray, gate: np.ndarray,
                     size: int, armed: bool = True) -> list[tuple]:
    hits = []
    for i in range(0, len(t), size):
        hit = tr.feed(t[i:i + size], a[i:i + size], gate[i:i + size], armed)
        if hit is not None:
            hits.append(hit)
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
    mean, count, t_hit = hits[0]
    assert t_hit == t[520 + 1000]  # exactly 10 s after the run began
    assert count == 1001
    np.testing.assert_allclose(mean, [0.0, 0.2, 0.98])


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
    assert len(hits) == 1 and hits[0][2] == t[800]  # fires as soon as it is armed
    tr2.rearm()
    assert len(_feed_in_batches(tr2, t[900:950], a[900:950], gate[900:950], 50)) == 1
