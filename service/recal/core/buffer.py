"""Rolling, orientation-balanced store of quasi-static window means.

The estimator fits window means (not raw samples: averaging a 2 s window divides the noise by
sqrt(100) at 50 Hz). Windows are binned by the direction of gravity in the sensor frame into the
cells of a cube-face grid (6 faces x n x n). Each cell keeps at most `per_cell` slots and
replaces its oldest, so hours of sitting upright renew the upright cells but cannot crowd out the
one time the wearer lay down (Georgieva et al. found near-duplicate positions bias the fit).
Memory is fixed at construction: cells x per_cell rows.

A slot holds one window, or the merged mean of up to `merge_max` consecutive windows of the same
still run whose directions agree within `merge_deg` (`k` counts them): a two-minute posture then
fills a few slots instead of evicting every older posture of its cell with the same 12 s of
itself. Merging keeps what the windows say (the estimator weighs a slot as its k windows) but not
their number: a buffer of single windows forgets the first half hour of a wearer, merged slots
learn as fast as keeping every window (docs/design.md, "Figures behind choices"). The direction
tolerance bounds the norm bias of averaging directions that differ: the mean of unit vectors
within 1 deg of each other is short by at most 0.15 mg. Why this buffer: docs/design.md ("Why
the buffer bins windows on a cube-face grid").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from recal.errors import ConfigError, InputError

__all__ = ["BufferConfig", "Coverage", "Window", "WindowBuffer", "Windows", "cell_of"]


@dataclass(frozen=True)
class BufferConfig:
    """grid: n for an n x n grid per cube face; per_cell: slots kept per cell; merge_max:
    windows of one still run merged into one slot; merge_deg: how far (deg) a window's direction
    may be from its slot's to merge."""

    grid: int = 6
    per_cell: int = 6
    merge_max: int = 15
    merge_deg: float = 1.0

    def __post_init__(self) -> None:
        if min(self.grid, self.per_cell, self.merge_max) < 1 or not self.merge_deg >= 0:
            raise ConfigError("grid, per_cell and merge_max must be at least 1, merge_deg >= 0")

    @property
    def cells(self) -> int:
        return 6 * self.grid * self.grid


class Window(NamedTuple):
    """One committed window's mean as it travels on its own (the windows since the last
    update, the self-watch's recent ones, a refill): raw v (3,), aux (K,), mid time t_us,
    sample count n, the mean per-axis variance of its raw samples var. `Windows` holds many
    as arrays."""

    v: np.ndarray | list[float]
    aux: np.ndarray | list[float]
    t_us: int
    n: int
    var: float

    def to_list(self) -> list:
        """JSON-able: [v, aux, t_us, n, var]."""
        return [np.asarray(self.v).tolist(), np.asarray(self.aux).tolist(), int(self.t_us),
                int(self.n), float(self.var)]

    @classmethod
    def from_list(cls, w: Sequence) -> Window:
        return cls(np.asarray(w[0], float), np.asarray(w[1], float), int(w[2]), int(w[3]),
                   float(w[4]))


@dataclass(frozen=True, eq=False)
class Windows:
    """Window means: raw v (M,3), aux (M,K), mid time t_us (M,), sample count n (M,),
    the mean per-axis variance of the raw samples inside each window (M,), how many
    windows each row merges (M,; None: one each), and the variance of the merged windows'
    norms |v| between them (M,, raw units squared; 0 below two windows; None: unknown)."""

    v: np.ndarray
    aux: np.ndarray
    t_us: np.ndarray
    n: np.ndarray
    var: np.ndarray
    k: np.ndarray | None = None
    spread: np.ndarray | None = None

    @property
    def merged(self) -> np.ndarray:
        return np.ones(len(self.t_us), np.int64) if self.k is None else self.k

    @property
    def norm_var(self) -> np.ndarray:
        return np.zeros(len(self.t_us)) if self.spread is None else self.spread

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


_NEXT2 = np.array([1, 2])


def cell_of(u: np.ndarray, grid: int) -> np.ndarray:
    """Cube-face grid cell of each direction u (M,3): face = signed dominant axis, then an
    n x n grid over the other two coordinates divided by the dominant one."""
    u = np.asarray(u, np.float64).reshape(-1, 3)
    ax = np.argmax(np.abs(u), axis=1)
    rows = np.arange(len(u))
    dom = u[rows, ax]
    face = 2 * ax + (dom < 0)
    others = u[rows[:, None], (ax[:, None] + _NEXT2) % 3]  # the two other axes, in order
    uv = others / np.maximum(np.abs(dom), 1e-12)[:, None]  # in [-1, 1]
    ij = np.clip(((uv + 1.0) * 0.5 * grid).astype(np.int64), 0, grid - 1)
    return face * grid * grid + ij[:, 0] * grid + ij[:, 1]


def _norm3(x: list[float]) -> float:
    return math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])


def _floats(x: Sequence[float] | np.ndarray) -> list[float]:
    """A window's vector as Python floats (the pipeline passes lists already)."""
    return x if type(x) is list else np.asarray(x, np.float64).tolist()


class _Flushed:
    """A per-slot array of WindowBuffer, brought up to date with the slot being merged into
    (`WindowBuffer._hot`) whenever it is read or replaced."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.attr = "_" + name

    def __get__(self, obj: WindowBuffer | None, objtype: type | None = None) -> np.ndarray:
        if obj is None:
            return self  # type: ignore[return-value]
        obj._flush()
        return getattr(obj, self.attr)

    def __set__(self, obj: WindowBuffer, value: np.ndarray) -> None:
        obj._flush()
        obj._hot = None
        setattr(obj, self.attr, value)


@dataclass(slots=True)
class _Hot:
    """The slot windows are being merged into, in Python numbers: a merge is a few float
    operations, and numpy's per-call overhead made it the buffer's main cost. Written back to
    the arrays (`WindowBuffer._flush`) before anything reads them."""

    slot: int
    cell: int
    v: list[float]
    aux: list[float]
    t_us: int
    var: float
    dir: list[float]
    n: int
    k: int
    nmean: float
    nm2: float
    dirty: bool = False


class WindowBuffer:
    """Fixed-size arrays; `add` places a window in its direction cell, evicting the cell's oldest.

    Mutable by design (it is the one large piece of pipeline state); `copy()` for snapshots.
    """

    v = _Flushed()
    aux = _Flushed()
    t_us = _Flushed()
    n = _Flushed()
    var = _Flushed()
    dir = _Flushed()
    k = _Flushed()  # windows merged into each slot
    nmean = _Flushed()  # mean of the merged windows' norms |v|, raw units
    nm2 = _Flushed()  # their sum of squared deviations (Welford)

    def __init__(self, cfg: BufferConfig, n_aux: int) -> None:
        self.cfg = cfg
        size = cfg.cells * cfg.per_cell
        self._hot: _Hot | None = None
        self._v = np.zeros((size, 3))
        self._aux = np.zeros((size, n_aux))
        self._t_us = np.zeros(size, np.int64)
        self._n = np.zeros(size, np.int64)
        self._var = np.zeros(size)
        self._dir = np.zeros((size, 3))
        self.filled = np.zeros(size, bool)
        self.added = 0
        self.cells_opened = 0  # adds that put a window in an empty cell: new coverage
        self._coverage: dict[float, Coverage] = {}  # until the next add or redirect
        self._cell = np.zeros(size, np.int64)  # cell_of(dir) per slot, kept with dir
        self._k = np.zeros(size, np.int64)
        self._nmean = np.zeros(size)
        self._nm2 = np.zeros(size)
        self.last: tuple[int, int] | None = None  # (slot, run) of the latest add, to merge into
        self._cos_merge = math.cos(math.radians(cfg.merge_deg))

    def _flush(self) -> None:
        h = self._hot
        if h is None or not h.dirty:
            return
        s = h.slot
        self._v[s], self._t_us[s], self._var[s], self._dir[s] = h.v, h.t_us, h.var, h.dir
        if self._aux.shape[1]:
            self._aux[s] = h.aux
        self._n[s], self._k[s], self._nmean[s], self._nm2[s] = h.n, h.k, h.nmean, h.nm2
        h.dirty = False

    def _load(self, slot: int) -> _Hot:
        return _Hot(slot, int(self._cell[slot]), self._v[slot].tolist(), self._aux[slot].tolist(),
                    int(self._t_us[slot]), float(self._var[slot]), self._dir[slot].tolist(),
                    int(self._n[slot]), int(self._k[slot]), float(self._nmean[slot]),
                    float(self._nm2[slot]))

    def add(self, v: Sequence[float], aux: Sequence[float], t_us: int, n: int, var: float,
            direction: Sequence[float], run: int | None = None, cell: int | None = None) -> int:
        """Store one window mean; `direction` is gravity's direction (unit, sensor frame);
        `run` identifies its still run (None: never merge it); `cell`: `cell_of(direction)`
        if the caller has it (the pipeline bins a batch's windows at once)."""
        if cell is None:
            cell = int(cell_of(direction, self.cfg.grid)[0])
        if run is not None and self._merge(v, aux, t_us, n, var, direction, run, cell):
            return cell
        self._flush()
        base = cell * self.cfg.per_cell
        slots = slice(base, base + self.cfg.per_cell)
        filled = self.filled[slots].tolist()  # a few Python bools: cheaper than numpy calls
        if False in filled:  # the first free slot; a cell with none filled is new coverage
            slot = base + filled.index(False)
            self.cells_opened += not any(filled)
        else:  # the cell's oldest
            slot = base + int(np.argmin(self._t_us[slots]))
        self._v[slot], self._aux[slot], self._t_us[slot] = v, aux, t_us
        self._n[slot], self._var[slot], self._dir[slot] = n, var, direction
        self.filled[slot] = True
        self.added += 1
        self._cell[slot] = cell
        self._k[slot] = 1
        self._nmean[slot], self._nm2[slot] = _norm3(_floats(v)), 0.0
        self.last = None if run is None else (slot, int(run))
        self._hot = None
        self._coverage.clear()
        return cell

    def _merge(self, v: Sequence[float], aux: Sequence[float], t_us: int, n: int, var: float,
               direction: Sequence[float], run: int, cell: int) -> bool:
        """Fold the window into the latest slot if it continues that slot's run, in the same
        cell, within merge_deg of its direction and below merge_max windows. (In Python floats,
        written out: it runs for nearly every window, and numpy's per-call cost would
        dominate; each norm is sqrt(x*x + y*y + z*z) as `_norm3` has it.)"""
        last = self.last
        if last is None or last[1] != run:
            return False
        slot = last[0]
        h = self._hot
        if h is None or h.slot != slot:
            if not self.filled[slot] or self._cell[slot] != cell:
                return False
            h = self._hot = self._load(slot)
        elif h.cell != cell:
            return False
        if h.k >= self.cfg.merge_max:
            return False
        ox, oy, oz = h.dir
        ex, ey, ez = direction if type(direction) is list else _floats(direction)
        if ox * ex + oy * ey + oz * ez < self._cos_merge:
            return False
        n0 = h.n
        n1 = int(n)
        w0, w1 = n0 / (n0 + n1), n1 / (n0 + n1)
        vx, vy, vz = v if type(v) is list else _floats(v)
        hx, hy, hz = h.v
        h.v = [w0 * hx + w1 * vx, w0 * hy + w1 * vy, w0 * hz + w1 * vz]
        if h.aux:
            h.aux = [w0 * a + w1 * b for a, b in zip(h.aux, _floats(aux), strict=True)]
        h.t_us = round(w0 * h.t_us + w1 * int(t_us))
        h.var = w0 * h.var + w1 * float(var)  # pooled within-window variance
        dx, dy, dz = w0 * ox + w1 * ex, w0 * oy + w1 * ey, w0 * oz + w1 * ez
        nd = math.sqrt(dx * dx + dy * dy + dz * dz)
        h.dir = [dx / nd, dy / nd, dz / nd]
        h.n = n0 + n1
        k = h.k = h.k + 1
        x = math.sqrt(vx * vx + vy * vy + vz * vz)  # Welford: how much the windows' norms disagree
        mean0 = h.nmean
        mean1 = mean0 + (x - mean0) / k
        h.nm2 += (x - mean0) * (x - mean1)
        h.nmean = mean1
        h.dirty = True
        self.added += 1
        if self._coverage:
            self._coverage.clear()
        return True

    def windows(self) -> Windows:
        self._flush()
        slots = np.flatnonzero(self.filled)
        s = slots[np.argsort(self._t_us[slots], kind="stable")]  # oldest first
        k = self._k[s]
        return Windows(self._v[s], self._aux[s], self._t_us[s], self._n[s], self._var[s], k,
                       self._nm2[s] / np.maximum(k - 1, 1))

    def __len__(self) -> int:
        return int(self.filled.sum())

    def slots(self) -> np.ndarray:
        """The filled slots in the order `windows` returns their windows (oldest first)."""
        self._flush()
        slots = np.flatnonzero(self.filled)
        return slots[np.argsort(self._t_us[slots], kind="stable")]

    def drop(self, slots: np.ndarray) -> None:
        """Empty these slots (windows found not to be still poses once the scale is known)."""
        slots = np.asarray(slots, np.intp)
        if not len(slots):
            return
        self._flush()
        self._hot = None
        self.filled[slots] = False
        self._k[slots] = 0
        if self.last is not None and self.last[0] in set(slots.tolist()):
            self.last = None
        self._coverage.clear()

    def coverage(self, level_g: float = 0.3) -> Coverage:
        known = self._coverage.get(level_g)
        if known is not None:  # updates and state messages ask between the same adds
            return known
        d = self.dir[self.filled]
        # distinct cells of the stored directions (tracked per slot, not recomputed)
        cells = np.count_nonzero(np.bincount(self._cell[self.filled], minlength=1))
        pos = tuple((d > level_g).any(axis=0).tolist())
        neg = tuple((d < -level_g).any(axis=0).tolist())
        cov = Coverage(pos, neg, cells, self.cfg.cells, len(d), level_g)
        self._coverage[level_g] = cov
        return cov

    def redirect(self, directions: np.ndarray, slots: np.ndarray | None = None) -> None:
        """Replace the stored gravity directions (after a recalibration changed them), given
        for the filled slots in slot order, or for ``slots`` in that order (`slots()`)."""
        self._flush()
        self._hot = None
        if slots is None:
            self._dir[self.filled] = directions
        else:
            self._dir[slots] = directions
        self._cell[self.filled] = cell_of(self._dir[self.filled], self.cfg.grid)
        self._coverage.clear()

    def copy(self) -> WindowBuffer:
        new = WindowBuffer(self.cfg, self.aux.shape[1])
        for name in ("v", "aux", "t_us", "n", "var", "dir", "filled", "_cell", "k", "nmean",
                     "nm2"):
            setattr(new, name, getattr(self, name).copy())
        new.added = self.added
        new.cells_opened = self.cells_opened
        new.last = self.last
        return new

    def to_dict(self) -> dict:
        return {"grid": self.cfg.grid, "per_cell": self.cfg.per_cell,
                "merge_max": self.cfg.merge_max, "merge_deg": self.cfg.merge_deg,
                "added": self.added, "cells_opened": self.cells_opened,
                "last": None if self.last is None else list(self.last),
                **{k: getattr(self, k).tolist() for k in
                   ("v", "aux", "t_us", "n", "var", "dir", "filled", "k", "nmean", "nm2")}}

    @classmethod
    def from_dict(cls, d: dict) -> WindowBuffer:
        cfg = BufferConfig(int(d["grid"]), int(d["per_cell"]), int(d.get("merge_max", 1)),
                           float(d.get("merge_deg", 0.0)))
        aux = np.asarray(d["aux"], np.float64)
        buf = cls(cfg, aux.shape[1] if aux.ndim == 2 else 0)
        if buf.v.shape != np.asarray(d["v"]).shape:
            raise InputError("buffer checkpoint does not match its grid")
        buf.v = np.asarray(d["v"], np.float64)
        buf.aux = aux.reshape(len(buf.v), -1)
        buf.t_us = np.asarray(d["t_us"], np.int64)
        buf.n = np.asarray(d["n"], np.int64)
        buf.var = np.asarray(d["var"], np.float64)
        buf.dir = np.asarray(d["dir"], np.float64)
        buf.filled = np.asarray(d["filled"], bool)
        buf.added = int(d["added"])
        buf.cells_opened = int(d.get("cells_opened", 0))
        buf.k = np.asarray(d.get("k", buf.filled.astype(int)), np.int64)
        buf.nmean = np.asarray(d.get("nmean", np.linalg.norm(buf.v, axis=1)), np.float64)
        buf.nm2 = np.asarray(d.get("nm2", np.zeros(len(buf.v))), np.float64)
        buf.last = None if d.get("last") is None else (int(d["last"][0]), int(d["last"][1]))
        buf._cell[buf.filled] = cell_of(buf.dir[buf.filled], cfg.grid)
        return buf
