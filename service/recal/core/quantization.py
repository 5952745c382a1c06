"""A sensor's value lattice (its step, per axis) learned from its samples, and what the step
costs a window mean.

Digital accelerometers report whole counts: an AX3, a GENEActiv or an ActiGraph in steps of
1/256 g (3.9 mg). Two things change when the step is coarse against the sensor's own noise:

* a still sensor repeats its reading bit for bit (a still AX3 shows 2-4 distinct values per
  axis in 10 s, often one for seconds), so identical readings are no sign of a stuck sensor
  (`coarse`, used by the detector's flat-line rule);
* the rounding error of a window mean does not average away: without noise to dither it, the
  mean of n readings of the same value is off by the rounding error of that value, uniform
  over one step (variance step^2 / 12 per axis, Sheppard's correction) whatever n. Gaussian
  noise of sd sigma dithers it: the rounding bias of the mean is a Fourier series in the true
  value whose k-th harmonic is damped by exp(-2 pi^2 k^2 sigma^2 / step^2) (Widrow's
  quantization theorem); `mean_floor_g2` damps step^2 / 12 as the first harmonic's variance
  is, by the variance of the readings themselves (what a window has; not Sheppard's
  sigma^2 = var - step^2 / 12, which holds only once dithered): nothing extra once the noise
  is half a step or more, and the mean's whole error within 0.65-1.4x of what it says at
  every noise from none to a step (tests/test_quantized.py).

The step is learned as the smallest non-zero difference between consecutive readings, per
axis, over the first LATTICE_CHANGES samples that differ from the one before (`observe`):
bounded work, state in and state out, the same estimate fed in one batch or sample by sample.
A sensor of continuous values (floats, a fine ADC) ends with a tiny step, which costs nothing.
"""

from __future__ import annotations

import numpy as np

from recal.core.triaxial import any3

__all__ = ["COARSE_STEP_G", "LATTICE_CHANGES", "coarse", "mean_floor_g2", "observe",
           "rounding_g2", "window_noise_g2"]

#: Samples that differ from their predecessor the step is learned on; then it stays.
LATTICE_CHANGES = 20_000
#: A step at least this (g, on every axis) is coarse: a MEMS part still on a table has
#: 0.2-1 mg of noise at 100 Hz, so at 1/256 g (3.9 mg) it reads one value for seconds, at
#: 1/1024 g (1 mg, noise a step or so) it never repeats for long on all three axes.
COARSE_STEP_G = 0.002


def observe(step_raw: np.ndarray, changes: int, v: np.ndarray,
            last_v: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """The step (per axis, raw units; inf: not seen yet) after readings v (N,3) that follow
    last_v (3,), learning from at most LATTICE_CHANGES - changes samples that differ from
    their predecessor. Returns the new step, the new count, and the step after each sample
    (N,3: what `coarse` sees at each, so batches and single samples decide alike)."""
    prev = np.empty_like(v)
    prev[0] = last_v
    prev[1:] = v[:-1]
    changed = any3(v != prev)  # NaN != anything: a first sample counts as a change
    seen = changes + np.cumsum(changed)
    d = np.abs(v - prev)
    d = np.where((d > 0) & (changed & (seen <= LATTICE_CHANGES))[:, None], d, np.inf)
    d[0] = np.minimum(d[0], step_raw)
    steps = np.minimum.accumulate(d, axis=0)
    return steps[-1].copy(), int(min(seen[-1], LATTICE_CHANGES)), steps


def coarse(step_raw: np.ndarray, s0: float) -> np.ndarray:
    """Whether the step is known and coarse on every axis (rows of step_raw: (3,) or (N,3))."""
    s = np.asarray(step_raw, np.float64)
    return np.all(np.isfinite(s) & (s >= COARSE_STEP_G * s0), axis=-1)


def mean_floor_g2(step_g: np.ndarray, var_g2: np.ndarray) -> np.ndarray:
    """What rounding adds to the variance of a window mean along gravity (g^2, the mean over
    the axes), given the step per axis (g; inf or 0: unknown, nothing) and the windows' mean
    per-axis sample variance var_g2 (M,): step^2 / 12 damped by the noise that dithers it,
    exp(-4 pi^2 var / step^2) (module doc)."""
    s = np.asarray(step_g, np.float64)
    s = np.where(np.isfinite(s), s, 0.0)
    v = np.asarray(var_g2, np.float64)[:, None]
    q2 = s * s / 12.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        damp = np.exp(-4.0 * np.pi**2 * v / (s * s))
    return np.mean(np.where(s > 0, q2 * damp, 0.0), axis=1)



def rounding_g2(var_raw2: np.ndarray, s0: float, step_raw: np.ndarray | None) -> np.ndarray:
    """`mean_floor_g2` of windows in raw units (their mean per-axis variance var_raw2, the
    step per axis step_raw; None: unknown, zeros), in g^2: what a window mean's noise adds
    to var / n of its samples (added after it, so a sensor without a step keeps its bits)."""
    var = np.asarray(var_raw2, np.float64).reshape(-1)
    if step_raw is None:
        return np.zeros(len(var))
    return mean_floor_g2(np.asarray(step_raw, np.float64) / s0, var / (s0 * s0))


def window_noise_g2(var_raw2: np.ndarray, n: np.ndarray, s0: float,
                    step_raw: np.ndarray | None) -> np.ndarray:
    """The noise variance (g^2) of window means along gravity: var / n of their samples (mean
    per-axis variance var_raw2, raw units^2), and the rounding no noise averages away
    (`rounding_g2`)."""
    var = np.asarray(var_raw2, np.float64).reshape(-1)
    return var / np.maximum(np.asarray(n).reshape(-1), 1) / (s0 * s0) + rounding_g2(
        var, s0, step_raw)
