"""The simulated wearer's slow aux channels: board temperature and supply voltage, each from a
seeded random stream of its own (`recal.sim.wearer.simulate`). Pure numpy/scipy."""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from recal.sim.wearer_spec import SupplySpec, TemperatureSpec

__all__ = ["supply", "temperature"]

_AUX_GRID_S = 1.0  # slow aux processes are simulated on this grid, then interpolated


def _ou(n: int, dt_s: float, tau_s: float, sd: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary Ornstein-Uhlenbeck process (n,) with standard deviation sd."""
    phi = math.exp(-dt_s / tau_s)
    w = rng.standard_normal(n) * sd * math.sqrt(1.0 - phi * phi)
    x0 = rng.standard_normal() * sd
    return lfilter([1.0], [1.0, -phi], w, zi=[phi * x0])[0]


def _boxes(n: int, starts: np.ndarray, stops: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Sum of rectangles [start, stop) (indices) of given heights, via a difference array."""
    d = np.zeros(n + 1)
    np.add.at(d, np.clip(starts, 0, n), heights)
    np.add.at(d, np.clip(stops, 0, n), -heights)
    return np.cumsum(d[:n])


def temperature(t_s: np.ndarray, w: TemperatureSpec, rng: np.random.Generator) -> np.ndarray:
    """Board temperature channel (°C): wander + excursions, lagged, clipped, noisy, quantized."""
    total_s = float(t_s[-1]) if len(t_s) else 0.0
    n_grid = int(total_s / _AUX_GRID_S) + 2
    grid = np.arange(n_grid) * _AUX_GRID_S
    target = w.temp_mean_c + _ou(n_grid, _AUX_GRID_S, 60 * w.temp_wander_tau_min,
                                 w.temp_wander_c, rng)
    # going outdoors (cold, mostly) or into the sun: the ambient steps for tens of minutes
    n_exc = max(1, int(rng.poisson(total_s / 3600 / w.temp_excursion_every_h)))
    dur = 60 * rng.uniform(*w.temp_excursion_min, n_exc)
    start = rng.uniform(0.0, max(total_s - dur.min() / 2, 0.0), n_exc)
    size = rng.uniform(*w.temp_excursion_c, n_exc) * np.where(rng.random(n_exc) < 0.7, -1, 1)
    i0 = (start / _AUX_GRID_S).astype(np.int64)
    target += _boxes(n_grid, i0, i0 + (dur / _AUX_GRID_S).astype(np.int64), size)
    # thermal inertia of skin and board: first-order lag, starting at equilibrium
    phi = math.exp(-_AUX_GRID_S / (60 * w.temp_lag_min))
    board = lfilter([1.0 - phi], [1.0, -phi], target, zi=[phi * target[0]])[0]
    board = np.clip(board, *w.temp_range_c)
    temp = np.interp(t_s, grid, board) + w.temp_noise_c * rng.standard_normal(len(t_s))
    return _quantize(temp, w.temp_resolution_c)


def supply(t_s: np.ndarray, rate_hz: float, w: SupplySpec,
           rng: np.random.Generator) -> np.ndarray:
    """Supply channel (V): battery discharge + slow wander + load dips, noisy, quantized."""
    n = len(t_s)
    total_s = float(t_s[-1]) if n else 0.0
    # the slow parts live on the coarse grid: fewer full-length temporaries
    n_grid = int(total_s / _AUX_GRID_S) + 2
    grid = np.arange(n_grid) * _AUX_GRID_S
    x = grid / max(total_s, 1e-9)
    # Li-ion shape: quick initial drop, long slope, knee at the end; 0 at x=0, 1 at x=1
    shape = 0.25 * (1 - np.exp(-x / 0.08)) + 0.55 * x + 0.2 * x**6
    shape /= 0.25 * (1 - math.exp(-1 / 0.08)) + 0.75
    slow = w.vdd_start_v + (w.vdd_end_v - w.vdd_start_v) * shape
    slow += _ou(n_grid, _AUX_GRID_S, 300.0, w.vdd_wander_v, rng)
    vdd = np.interp(t_s, grid, slow)
    # radio / motor load dips: seconds long, tens of mV deep
    n_dip = int(rng.poisson(total_s / w.vdd_dip_every_s))
    start = rng.uniform(0.0, total_s, n_dip)
    dur = rng.uniform(*w.vdd_dip_s, n_dip)
    depth = rng.uniform(*w.vdd_dip_v, n_dip)
    i0 = np.floor(start * rate_hz).astype(np.int64)
    i1 = i0 + np.maximum(1, np.round(dur * rate_hz)).astype(np.int64)
    vdd -= _boxes(n, i0, i1, depth)
    vdd += w.vdd_noise_v * rng.standard_normal(n)
    return _quantize(vdd, w.vdd_resolution_v)


def _quantize(x: np.ndarray, step: float) -> np.ndarray:
    if step > 0:
        # round to the step, then to the nearest decimal float so the values print cleanly
        decimals = max(0, -math.floor(math.log10(step)) + 1)
        x = np.round(np.round(x / step) * step, decimals)
    return x
