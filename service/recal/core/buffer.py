"""Rolling, orientation-balanced store of quasi-static window means.

The estimator fits window means (not raw samples: averaging a 2 s window divides the noise by
sqrt(100) at 50 Hz). Windows are binned by the direction of gravity in the sensor frame into the
cells of a cube-face grid (6 faces x n x n). Each cell keeps at most `per_cell` windows and
replaces its oldest, so hours of sitting upright renew the upright cells but cannot crowd out the
one time the wearer lay down (Georgieva et al. found near-duplicate positions bias the fit).
Memory is fixed at construction: cells x per_cell rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BufferConfig", "Coverage", "WindowBuffer", "Windows", "cell_of"]


@dataclass(frozen=True)
class BufferConfig:
    """grid: n for an n x n grid per cube face; per_cell: windows kept per cell."""

    grid: int = 3
    per_cell: int = 6

    @property
    def cells(self) -> int:
        return 6 * self.grid * self.grid


@dataclass(frozen=True, eq=False)
class Windows:
    """Window means: raw v (M,3), aux (M,K), mid time t_us (M,), sample count n (M,),
    and the mean per-axis variance of the raw samples inside each window (M,)."""

    v: np.ndarray
    aux: np.ndarray
    t_us: np.ndarray
    n: np.ndarray
    var: np.ndarray

    def __len__(self) -> int:
        return len(self.t_us)


@dataclass(frozen=True)
class Coverage:
    """Which half-axes gravity has been seen on beyond `level_g`, and how many cells hold data."""

    seen_pos: tuple[bool, bool, bool]
    seen_neg: tuple[bool, bool, bool]
    cells_filled: int
    cells_total: int
    windows: int
    level_g: float = 0.3

    @property
    def axes_covered(self) -> tuple[bool, bool, bool]:
        return tuple(p and n for p, n in zip(self.seen_pos, self.seen_neg, strict=True))

    @property
    def full(self) -> bool:
        return all(self.axes_covered)

    def to_dict(self) -> dict:
        return {"seen_pos": list(self.seen_pos), "seen_neg": list(self.seen_neg),
                "axes_covered": list(self.axes_covered), "cells_filled": self.cells_filled,
                "cells_total": self.cells_total, "windows": self.windows, "level_g": self.level_g}


def cell_of(u: np.ndarray, grid: int) -> np.ndarray:
    """Cube-face grid cell of each direction u (M,3): face = signed dominant axis, then an
    n x n grid over the other two coordinates divided by the dominant one."""
    u = np.asarray(u, np.float64).reshape(-1, 3)
    ax = np.argmax(np.abs(u), axis=1)
    rows = np.arange(len(u))
    dom = u[rows, ax]
    face = 2 * ax + (dom < 0)
    others = np.stack([u[rows, (ax + 1) % 3], u[rows, (ax + 2) % 3]], axis=1)
    uv = others / np.maximum(np.abs(dom), 1e-12)[:, None]  # in [-1, 1]
    ij = np.clip(((uv + 1.0) * 0.5 * grid).astype(np.int64), 0, grid - 1)
    return face * grid * grid + ij[:, 0] * grid + ij[:, 1]


class WindowBuffer:
    """Fixed-size arrays; `add` places a window in its direction cell, evicting the cell's oldest.

    Mutable by design (it is the one large piece of pipeline state); `copy()` for snapshots.
    """

    def __init__(self, cfg: BufferConfig, n_aux: int) -> None:
        self.cfg = cfg
        size = cfg.cells * cfg.per_cell
        self.v = np.zeros((size, 3))
        self.aux = np.zeros((size, n_aux))
        self.t_us = np.zeros(size, np.int64)
        self.n = np.zeros(size, np.int64)
        self.var = np.zeros(size)
        self.dir = np.zeros((size, 3))
        self.filled = np.zeros(size, bool)
        self.added = 0

    def add(self, v: np.ndarray, aux: np.ndarray, t_us: int, n: int, var: float,
            direction: np.ndarray) -> int:
        """Store one window mean; `direction` is gravity's direction (unit, sensor frame)."""
        cell = int(cell_of(direction, self.cfg.grid)[0])
        base = cell * self.cfg.per_cell
        slots = slice(base, base + self.cfg.per_cell)
        free = np.flatnonzero(~self.filled[slots])
        slot = base + (int(free[0]) if len(free) else int(np.argmin(self.t_us[slots])))
        self.v[slot], self.aux[slot], self.t_us[slot] = v, aux, t_us
        self.n[slot], self.var[slot], self.dir[slot] = n, var, direction
        self.filled[slot] = True
        self.added += 1
        return cell

    def windows(self) -> Windows:
        m = self.filled
        order = np.argsort(self.t_us[m], kind="stable")
        return Windows(self.v[m][order], self.aux[m][order], self.t_us[m][order],
                       self.n[m][order], self.var[m][order])

    def __len__(self) -> int:
        return int(self.filled.sum())

    def coverage(self, level_g: float = 0.3) -> Coverage:
        d = self.dir[self.filled]
        cells = np.unique(cell_of(d, self.cfg.grid)) if len(d) else np.zeros(0)
        pos = tuple(bool(np.any(d[:, i] > level_g)) for i in range(3))
        neg = tuple(bool(np.any(d[:, i] < -level_g)) for i in range(3))
        return Coverage(pos, neg, len(cells), self.cfg.cells, len(d), level_g)

    def redirect(self, directions: np.ndarray) -> None:
        """Replace the stored gravity directions (after a recalibration changed them)."""
        self.dir[self.filled] = directions

    def copy(self) -> WindowBuffer:
        new = WindowBuffer(self.cfg, self.aux.shape[1])
        for name in ("v", "aux", "t_us", "n", "var", "dir", "filled"):
            setattr(new, name, getattr(self, name).copy())
        new.added = self.added
        return new

    def state_dict(self) -> dict:
        return {"grid": self.cfg.grid, "per_cell": self.cfg.per_cell, "added": self.added,
                **{k: getattr(self, k).tolist() for k in
                   ("v", "aux", "t_us", "n", "var", "dir", "filled")}}

    @classmethod
    def from_state_dict(cls, d: dict) -> WindowBuffer:
        cfg = BufferConfig(int(d["grid"]), int(d["per_cell"]))
        aux = np.asarray(d["aux"], np.float64)
        buf = cls(cfg, aux.shape[1] if aux.ndim == 2 else 0)
        if buf.v.shape != np.asarray(d["v"]).shape:
            raise ValueError("buffer checkpoint does not match its grid")
        buf.v = np.asarray(d["v"], np.float64)
        buf.aux = aux.reshape(len(buf.v), -1)
        buf.t_us = np.asarray(d["t_us"], np.int64)
        buf.n = np.asarray(d["n"], np.int64)
        buf.var = np.asarray(d["var"], np.float64)
        buf.dir = np.asarray(d["dir"], np.float64)
        buf.filled = np.asarray(d["filled"], bool)
        buf.added = int(d["added"])
        return buf
