"""Quasi-static moments detector (Lötters 1998, eq. 1-2), streaming.

    v_in  = |v| / s0                     eq. 1, the vector norm, here in g
    v_out = LPF(REC(HPF(v_in)))          eq. 2, 0.5 Hz high-pass, rectifier, 0.5 Hz low-pass

A sample is quasi-static when v_out is below the threshold T (Lötters' T_v, here in g) and it
is neither clipped (near full scale) nor part of a flat-lined stretch (a device that repeats its
last sample while idle: zero variance is not stillness, it is no data).

Streaming in the manner of scipy.signal.sosfilt: the filter state travels in `DetectorState`, so a
recording fed in one batch or sample by sample gives the same gates to the last bit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import signal

__all__ = ["DetectorConfig", "DetectorOutput", "DetectorState", "detect", "init_state"]

#: Default threshold on the detector output, in g. Chosen from data: on the Xsens multi-position
#: recording (../shared/data/real, 100 Hz) the output stays below 6 mg inside the hand-held
#: still poses and rises above 30 mg within 0.2 s of any rotation; on simulated 4 mg-noise still
#: postures it sits at 3-4 mg, and walking drives it to 100-300 mg. 15 mg keeps all still
#: postures of both and rejects even slow turning; `bench/detector_threshold.py` reproduces it.
DEFAULT_THRESHOLD_G = 0.015


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings.

    Attributes:
        rate_hz: sample rate the filters are designed for.
        threshold_g: T, the largest detector output still called quasi-static.
        hp_hz, lp_hz: the high- and low-pass corner frequencies (Lötters: 0.5 Hz each).
        order: Butterworth order of each filter.
        s0: nominal raw units per g, so that the norm and threshold are in g.
        clip_raw: |v| on any axis at or above this (raw units) counts as clipped; None = off.
        flat_s: this long of bit-identical samples is a flat line, not stillness.
    """

    rate_hz: float
    threshold_g: float = DEFAULT_THRESHOLD_G
    hp_hz: float = 0.5
    lp_hz: float = 0.5
    order: int = 2
    s0: float = 1.0
    clip_raw: float | None = None
    flat_s: float = 1.0

    def sos(self) -> tuple[np.ndarray, np.ndarray]:
        hp = signal.butter(self.order, self.hp_hz, "highpass", fs=self.rate_hz, output="sos")
        lp = signal.butter(self.order, self.lp_hz, "lowpass", fs=self.rate_hz, output="sos")
        return hp, lp

    @property
    def flat_n(self) -> int:
        return max(2, round(self.flat_s * self.rate_hz))


@dataclass(frozen=True, eq=False)
class DetectorState:
    """Filter states (sosfilt zi) and the flat-line run carried between batches."""

    zi_hp: np.ndarray
    zi_lp: np.ndarray
    last_v: np.ndarray
    same_run: int
    started: bool


@dataclass(frozen=True, eq=False)
class DetectorOutput:
    """Per sample: detector output (g), and the reasons a sample is not quasi-static."""

    detector_g: np.ndarray
    below_threshold: np.ndarray
    clipped: np.ndarray
    flat: np.ndarray

    @property
    def gate(self) -> np.ndarray:
        return self.below_threshold & ~self.clipped & ~self.flat


def init_state(cfg: DetectorConfig) -> DetectorState:
    hp, lp = cfg.sos()
    return DetectorState(np.zeros((hp.shape[0], 2)), np.zeros((lp.shape[0], 2)),
                         np.full(3, np.nan), 0, False)


def _start(cfg: DetectorConfig, state: DetectorState, x0_g: float) -> DetectorState:
    """Start the filters in steady state for the first sample; the low-pass starts *above*
    threshold, so a recording is not called still before the detector has seen a second of it."""
    hp, lp = cfg.sos()
    return replace(state, zi_hp=signal.sosfilt_zi(hp) * x0_g,
                   zi_lp=signal.sosfilt_zi(lp) * (2.0 * cfg.threshold_g), started=True)


def _flat_runs(v: np.ndarray, last_v: np.ndarray, run0: int) -> np.ndarray:
    """For each sample, how many samples before it were bit-identical in a row (carried)."""
    prev = np.vstack([last_v[None, :], v[:-1]])
    same = np.all(v == prev, axis=1)
    idx = np.arange(len(v))
    last_reset = np.maximum.accumulate(np.where(same, -1, idx))
    return np.where(last_reset >= 0, idx - last_reset, run0 + 1 + idx)


def detect(cfg: DetectorConfig, state: DetectorState,
           v: np.ndarray) -> tuple[DetectorState, DetectorOutput]:
    """Run the detector on raw samples v (N,3); returns the new state and per-sample output."""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    if len(v) == 0:
        empty = np.zeros(0, bool)
        return state, DetectorOutput(np.zeros(0), empty, empty, empty)
    v_in = np.linalg.norm(v, axis=1) / cfg.s0  # eq. 1
    if not state.started:
        state = _start(cfg, state, float(v_in[0]))
    hp, lp = cfg.sos()
    y_hp, zi_hp = signal.sosfilt(hp, v_in, zi=state.zi_hp)
    v_out, zi_lp = signal.sosfilt(lp, np.abs(y_hp), zi=state.zi_lp)  # eq. 2
    runs = _flat_runs(v, state.last_v, state.same_run)
    clipped = (np.any(np.abs(v) >= cfg.clip_raw, axis=1) if cfg.clip_raw is not None
               else np.zeros(len(v), bool))
    out = DetectorOutput(v_out, v_out < cfg.threshold_g, clipped, runs >= cfg.flat_n - 1)
    return DetectorState(zi_hp, zi_lp, v[-1].copy(), int(runs[-1]), True), out
