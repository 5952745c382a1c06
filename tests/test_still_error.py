"""GGIR's still-window error batch by batch (`core.still_error`) is the same as on the whole
recording at once, however the recording is cut into batches."""

from __future__ import annotations

import numpy as np
import pytest

from recal.core import still_error as se

RATE_HZ = 50.0


def _whole(t_us: np.ndarray, raw: np.ndarray, cal: np.ndarray) -> tuple[int, float, float]:
    """The metric on all samples at once, as written in its definition (module doc)."""
    index = (t_us - t_us[0]) // se.WINDOW_US
    stills, before, after = 0, [], []
    for w in np.unique(index):
        m = index == w
        if m.sum() < se.MIN_FILL * RATE_HZ * 10 or np.any(raw[m].std(0, ddof=1) >= se.STILL_SD_G):
            continue
        stills += 1
        before.append(abs(np.linalg.norm(raw[m].mean(0)) - 1))
        after.append(abs(np.linalg.norm(cal[m].mean(0)) - 1))
    return stills, 1e3 * float(np.mean(before)), 1e3 * float(np.mean(after))


def _recording(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """5 min: still poses (noise 3 mg) and movement (0.2 g), an offset of 30 mg, a gap."""
    n = int(300 * RATE_HZ)
    t_us = np.arange(n, dtype=np.int64) * int(1e6 / RATE_HZ)
    t_us = np.delete(t_us, np.s_[4000:4400])
    pose = rng.normal(size=(len(t_us) // 1000 + 1, 3))
    pose /= np.linalg.norm(pose, axis=1)[:, None]
    cal = np.repeat(pose, 1000, axis=0)[:len(t_us)] + rng.normal(0, 0.003, (len(t_us), 3))
    moving = (t_us // 20_000_000) % 3 == 2
    cal[moving] += rng.normal(0, 0.2, (int(moving.sum()), 3))
    return t_us, cal + np.array([0.03, -0.02, 0.01]), cal


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_batches_give_the_whole_recordings_figures(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t_us, raw, cal = _recording(rng)
    cuts = np.sort(rng.choice(np.arange(1, len(t_us)), 25, replace=False))
    ref = raw[0]
    parts = [se.batch_sums(t, r, c, int(t_us[0]), ref) for t, r, c in
             zip(np.split(t_us, cuts), np.split(raw, cuts), np.split(cal, cuts), strict=True)]
    got = se.result(parts, ref, RATE_HZ)
    stills, before, after = _whole(t_us, raw, cal)
    assert got.still == stills > 0
    assert got.before_mg == pytest.approx(before, rel=1e-9)
    assert got.after_mg == pytest.approx(after, rel=1e-9)
    assert got.after_mg < got.before_mg


def test_no_still_window_is_none() -> None:
    rng = np.random.default_rng(4)
    t_us = np.arange(3000, dtype=np.int64) * 20_000
    v = rng.normal(0, 0.3, (3000, 3))
    got = se.result([se.batch_sums(t_us, v, v, 0, v[0])], v[0], RATE_HZ)
    assert (got.still, got.before_mg, got.after_mg) == (0, None, None)
    assert got.windows == 6


def test_a_clock_that_jumps_ahead_costs_only_the_windows_it_touches() -> None:
    """A damaged file's stamp 20 years ahead: two windows kept, not the 63 million between."""
    t_us = np.array([0, 20 * 365 * 86_400 * 10**6], np.int64)
    v = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    part = se.batch_sums(t_us, v, v, 0, v[0])
    assert len(part.n) == 2 and part.index.tolist() == [0, t_us[1] // se.WINDOW_US]
    got = se.result([part, se.batch_sums(t_us[1:] + 1, v[1:], v[1:], 0, v[0])], v[0], RATE_HZ)
    assert (got.windows, got.still) == (2, 0)
