"""Discovery's evidence: a bounded store of quasi-static window means spread over time and over
the covariates' ranges.

The orientation buffer (`core.buffer`) keeps a few windows per gravity cell for the estimator,
and the self-watch empties it while the model is wrong; effect discovery needs the opposite:
the history of temperature, supply and time, and above all the windows that contradict the
model. So a node keeps every committed window here (norm gate or not: a window the wrong model
puts 200 mg off 1 g is exactly the evidence of what it lacks), and nothing but its own bound
removes one. Discovery (`discovery.discover_pipeline`) runs on `EvidenceStore.windows`.

The bound: at most ``capacity`` windows. When it is exceeded, 1/SLACK of them go, one at a
time: from the most crowded bin of (time, each auxiliary channel, gravity face), each cut into
a few equal parts of the range the store holds now, the one of that bin closest in time to the
window before it in the bin (ties: the earliest). Long sitting at one temperature thins out;
the one cold excursion, the one time the wearer lay down and the first minutes stay. Pure
numpy; the node owns the store and saves it in its checkpoint (`to_dict` / `from_dict`). See
docs/design.md
(effect discovery, live).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from recal.core.buffer import Windows, cell_of
from recal.errors import ConfigError, InputError

__all__ = ["EvidenceConfig", "EvidenceStore"]

#: Thinning, once the store is full, drops 1/SLACK of it at once (bins worked out once for
#: them): a window added costs one drop's work, not a new binning of the whole store.
SLACK = 16


@dataclass(frozen=True)
class EvidenceConfig:
    """capacity: windows kept; time_bins / aux_bins: parts of the time span and of each
    auxiliary channel's range the thinning balances over (with the 6 gravity faces)."""

    capacity: int = 2048
    time_bins: int = 8
    aux_bins: int = 4

    def __post_init__(self) -> None:
        if min(self.capacity, self.time_bins, self.aux_bins) < 1:
            raise ConfigError("evidence capacity, time_bins and aux_bins must be at least 1")


class EvidenceStore:
    """Window means for discovery, oldest first: raw v (M,3), aux (M,K), mid time t_us, sample
    count n, per-axis variance var; ``added``: windows ever offered (kept or not).

    Mutable like the buffer (`add` changes it in place); `copy` for a run's own arrays."""

    def __init__(self, cfg: EvidenceConfig, n_aux: int) -> None:
        self.cfg = cfg
        self.v = np.zeros((0, 3))
        self.aux = np.zeros((0, n_aux))
        self.t_us = np.zeros(0, np.int64)
        self.n = np.zeros(0, np.int64)
        self.var = np.zeros(0)
        self.added = 0

    def __len__(self) -> int:
        return len(self.t_us)

    @property
    def nbytes(self) -> int:
        """Memory the arrays hold (bytes)."""
        return sum(a.nbytes for a in (self.v, self.aux, self.t_us, self.n, self.var))

    def add(self, w: Windows) -> None:
        """Keep these windows (in time order, after the ones held), then thin to capacity."""
        if not len(w):
            return
        if w.aux.shape[1] != self.aux.shape[1]:
            raise InputError(f"windows with {w.aux.shape[1]} aux channels, the evidence "
                             f"holds {self.aux.shape[1]}")
        self.v = np.concatenate([self.v, np.asarray(w.v, np.float64)])
        self.aux = np.concatenate([self.aux, np.asarray(w.aux, np.float64)])
        self.t_us = np.concatenate([self.t_us, np.asarray(w.t_us, np.int64)])
        self.n = np.concatenate([self.n, np.asarray(w.n, np.int64)])
        self.var = np.concatenate([self.var, np.asarray(w.var, np.float64)])
        self.added += len(w)
        if len(self) > self.cfg.capacity:
            self._thin(self.cfg.capacity - self.cfg.capacity // SLACK)

    def windows(self) -> Windows:
        """The windows held (fresh arrays: a run may keep them while the store goes on)."""
        return Windows(self.v.copy(), self.aux.copy(), self.t_us.copy(), self.n.copy(),
                       self.var.copy())

    def span_s(self) -> float:
        """Device seconds between the first and the last window held."""
        return float(self.t_us[-1] - self.t_us[0]) / 1e6 if len(self) > 1 else 0.0

    def cells(self, grid: int = 6) -> int:
        """Distinct gravity directions held: cube-face grid cells (`buffer.cell_of`) of the
        readings about their middle (see `_centred`)."""
        if not len(self):
            return 0
        return len(np.unique(cell_of(self._centred(np.arange(len(self))), grid)))

    def copy(self) -> EvidenceStore:
        new = EvidenceStore(self.cfg, self.aux.shape[1])
        new._take(np.ones(len(self), bool), self)
        new.added = self.added
        return new

    def to_dict(self) -> dict[str, Any]:
        c = self.cfg
        return {"capacity": c.capacity, "time_bins": c.time_bins, "aux_bins": c.aux_bins,
                "added": self.added, "n_aux": self.aux.shape[1], "v": _digits(self.v),
                "aux": _digits(self.aux), "t_us": self.t_us.tolist(), "n": self.n.tolist(),
                "var": _digits(self.var)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EvidenceStore:
        """`to_dict` output back (InputError if its arrays do not agree)."""
        cfg = EvidenceConfig(int(d["capacity"]), int(d["time_bins"]), int(d["aux_bins"]))
        n_aux = int(d["n_aux"])
        store = cls(cfg, n_aux)
        m = len(d["t_us"])
        v = np.asarray(d["v"], np.float64).reshape(m, 3)
        aux = np.asarray(d["aux"], np.float64).reshape(m, n_aux)
        t = np.asarray(d["t_us"], np.int64)
        n, var = np.asarray(d["n"], np.int64), np.asarray(d["var"], np.float64)
        if not (len(n) == len(var) == m <= cfg.capacity) or np.any(np.diff(t) < 0):
            raise InputError("evidence arrays disagree, exceed capacity or are not in order")
        store.v, store.aux, store.t_us, store.n, store.var = v, aux, t, n, var
        store.added = max(int(d["added"]), m)
        return store

    # -- thinning -------------------------------------------------------------------------------

    def _take(self, keep: np.ndarray, src: EvidenceStore | None = None) -> None:
        s = self if src is None else src
        self.v, self.aux, self.t_us = s.v[keep], s.aux[keep], s.t_us[keep]
        self.n, self.var = s.n[keep], s.var[keep]

    def _thin(self, target: int) -> None:
        """Drop windows down to ``target``, one at a time: from the most crowded bin (bins
        as of now), the one nearest in time to its predecessor in the bin (see the module
        doc)."""
        _, inv = np.unique(self._bins(np.arange(len(self))), return_inverse=True)
        counts = np.bincount(inv)
        keep = np.ones(len(self), bool)
        t = self.t_us
        for _ in range(len(self) - target):  # bounded: the windows beyond target
            b = int(np.argmax(counts))
            members = np.flatnonzero(keep & (inv == b))
            drop = members[0] if len(members) < 2 else members[1 + int(np.argmin(
                np.diff(t[members])))]
            keep[drop] = False
            counts[b] -= 1
        self._take(keep)

    def _bins(self, idx: np.ndarray) -> np.ndarray:
        """One integer per window: its time part, aux parts and gravity face."""
        cfg = self.cfg
        key = _part(self.t_us[idx].astype(np.float64), cfg.time_bins)
        for j in range(self.aux.shape[1]):
            key = key * (cfg.aux_bins + 1) + 1 + _part(self.aux[idx, j], cfg.aux_bins)
        c = self._centred(idx)
        ax = np.argmax(np.abs(np.nan_to_num(c)), axis=1)
        face = 2 * ax + (c[np.arange(len(c)), ax] < 0)
        return key * 6 + face

    def _centred(self, idx: np.ndarray) -> np.ndarray:
        """The readings about the middle of their range: gravity's direction well enough to
        bin by (an unsigned ADC reads ~2048 counts at 0 g: raw directions all point one way)."""
        v = np.nan_to_num(self.v[idx])
        return v - (v.max(axis=0) + v.min(axis=0)) / 2


#: Significant digits a checkpoint keeps of the window means (relative to the largest value
#: of the array): 1e-9 of full scale, far below any sensor's noise, and half the text of
#: every double's 17 digits.
DIGITS = 9


def _digits(x: np.ndarray) -> list:
    """``x`` rounded to DIGITS significant digits of its largest magnitude, as lists."""
    finite = np.abs(x[np.isfinite(x)])
    if not finite.size or finite.max() == 0:
        return x.tolist()
    decimals = DIGITS - 1 - int(np.floor(np.log10(finite.max())))
    return np.round(x, decimals).tolist()


def _part(x: np.ndarray, bins: int) -> np.ndarray:
    """Which of ``bins`` equal parts of its finite range each value falls in (NaN: -1)."""
    ok = np.isfinite(x)
    if not ok.any():
        return np.full(len(x), -1, np.int64)
    lo, hi = float(x[ok].min()), float(x[ok].max())
    width = (hi - lo) / bins if hi > lo else 1.0
    part = np.clip(np.floor((np.where(ok, x, lo) - lo) / width), 0, bins - 1).astype(np.int64)
    return np.where(ok, part, -1)
