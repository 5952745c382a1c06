"""bench/device_tools.py's own parts on made-up data: the still windows and GGIR's metric and
the held-out blocks."""

from __future__ import annotations

import numpy as np

from bench_modules import load_bench

dt = load_bench("device_tools")

RATE_HZ = 50.0


def _recording(v_g: np.ndarray) -> object:
    t_us = np.arange(len(v_g), dtype=np.int64) * int(1e6 / RATE_HZ) + 1_700_000_000_000_000
    return dt.Recording("made-up", "none", t_us, v_g, np.zeros((len(v_g), 0)), (), RATE_HZ)


def test_still_windows_and_the_metric_are_ggirs() -> None:
    rng = np.random.default_rng(3)
    n = int(10 * RATE_HZ)  # one 10 s window
    still = np.tile([0.0, 0.0, 1.02], (n, 1)) + rng.normal(0, 0.004, (n, 3))  # |a| 20 mg high
    moving = np.tile([0.0, 0.7, 0.7], (n, 1)) + rng.normal(0, 0.05, (n, 3))  # SD 50 mg
    tilted = np.tile([0.6, 0.0, 0.79], (n, 1)) + rng.normal(0, 0.004, (n, 3))
    rec = _recording(np.concatenate([still, moving, tilted]))
    w = dt.windows(rec)
    assert w.still.tolist() == [True, False, True]
    want = np.mean([abs(np.linalg.norm(still.mean(0)) - 1),
                    abs(np.linalg.norm(tilted.mean(0)) - 1)])
    assert np.isclose(dt.still_error_mg(rec.v_g, w), 1e3 * want)
    # a correction that scales |a| by 1/1.02 takes the first window's error away
    fixed = rec.v_g.copy()
    fixed[:n] /= np.linalg.norm(still.mean(0))
    assert dt.still_error_mg(fixed, w) < dt.still_error_mg(rec.v_g, w) - 5.0


def test_a_window_short_of_samples_is_not_judged() -> None:
    n = int(10 * RATE_HZ)
    v = np.tile([0.0, 0.0, 1.0], (2 * n, 1))
    rec = _recording(v)
    rec.t_us = np.concatenate([rec.t_us[:n], rec.t_us[n:n + n // 2] + 10_000_000_000])
    rec.v_g = v[:n + n // 2]
    assert dt.windows(rec).still.sum() == 1  # the half-filled window after the gap is left out


def test_held_out_blocks_alternate_every_30_min() -> None:
    rec = _recording(np.tile([0.0, 0.0, 1.0], (int(RATE_HZ * 3600 * 1.25), 1)))
    w = dt.windows(rec)
    per_block = int(1800 / 10)
    assert w.block[:per_block].tolist() == [0] * per_block
    assert w.block[per_block:2 * per_block].tolist() == [1] * per_block
    assert w.block[2 * per_block] == 0
