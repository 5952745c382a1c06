"""Cutting gated samples into windows: the one windower of the streaming pipeline and the batch
windowing (`core.window_means`), so both see the same windows bit for bit for the same batches.

Runs of gated samples without time gaps are cut into windows of window_s from each run's start;
a window is committed only once its run has gone on guard_s past its end (the detector's
low-pass reacts ~0.5 s late to the start of a movement) and if it holds min_fill of its nominal
samples. In the manner of scipy.signal.sosfilt's ``zi``, `cut` takes the state left by the
previous batch (`WindowerState`: the open window's sums, the pending window and its commit
time, the last sample's time and gate) and returns the new one: the windows do not depend on
where the batches end, except in the last bit of a float sum (see docs/design.md).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from recal.core.buffer import Windows

__all__ = ["Cut", "WindowAcc", "WindowConfig", "WindowSums", "WindowerState", "cut"]


@dataclass(frozen=True)
class WindowConfig:
    """The window rules (`PipelineConfig` holds them: rate_hz, window_s, guard_s, min_fill)."""

    rate_hz: float
    window_s: float
    guard_s: float
    min_fill: float

    @property
    def min_samples(self) -> float:
        """A window with fewer samples than this (min_fill of its nominal count) is dropped."""
        return self.min_fill * self.window_s * self.rate_hz

    @property
    def window_us(self) -> int:
        return round(self.window_s * 1e6)

    def commit_us(self, run_start_us: int | np.ndarray, k: int | np.ndarray) -> int | np.ndarray:
        """When window k of a run commits: guard_s after its end (ints or arrays alike)."""
        return run_start_us + (k + 1) * self.window_us + round(self.guard_s * 1e6)


@dataclass(frozen=True, eq=False, slots=True)
class WindowAcc:
    """Running sums of one window (k-th window of a run that started at run_start_us)."""

    run_start_us: int
    k: int
    n: int
    sum_v: np.ndarray
    sum_v2: np.ndarray
    sum_aux: np.ndarray
    sum_t: float

    @classmethod
    def of(cls, run_start_us: int, k: int, v: np.ndarray, aux: np.ndarray,
           t_us: np.ndarray) -> WindowAcc:
        return cls(run_start_us, k, len(v), v.sum(0), (v * v).sum(0), aux.sum(0),
                   float((t_us - run_start_us).sum()))

    def merge(self, other: WindowAcc) -> WindowAcc:
        return WindowAcc(self.run_start_us, self.k, self.n + other.n,
                         self.sum_v + other.sum_v, self.sum_v2 + other.sum_v2,
                         self.sum_aux + other.sum_aux, self.sum_t + other.sum_t)

    def to_dict(self) -> dict:
        return {"run_start_us": self.run_start_us, "k": self.k, "n": self.n,
                "sum_v": self.sum_v.tolist(), "sum_v2": self.sum_v2.tolist(),
                "sum_aux": self.sum_aux.tolist(), "sum_t": self.sum_t}

    @classmethod
    def from_dict(cls, d: dict | None) -> WindowAcc | None:
        if d is None:
            return None
        return cls(int(d["run_start_us"]), int(d["k"]), int(d["n"]),
                   np.asarray(d["sum_v"], float), np.asarray(d["sum_v2"], float),
                   np.asarray(d["sum_aux"], float), float(d["sum_t"]))



@dataclass(frozen=True, eq=False)
class WindowSums:
    """The running sums of many windows, one row each (what an `WindowAcc` holds for one): a long
    run's windows are summed, scheduled and committed as arrays, not one object each."""

    run_start_us: np.ndarray
    k: np.ndarray
    n: np.ndarray
    sum_v: np.ndarray
    sum_v2: np.ndarray
    sum_aux: np.ndarray
    sum_t: np.ndarray

    @classmethod
    def of_run(cls, run_start_us: int | np.ndarray, k: np.ndarray, starts: list[int] | np.ndarray,
               v: np.ndarray, aux: np.ndarray, t_us: np.ndarray) -> WindowSums:
        """Every window of one run (run_start_us: its start) or of several (an array: each
        sample's run start); starts: each window's first sample. One reduction per quantity."""
        idx = np.asarray(starts, np.intp)
        rs = np.broadcast_to(np.asarray(run_start_us, np.int64), t_us.shape)
        saux = (np.add.reduceat(aux, idx, axis=0) if aux.shape[1]
                else np.zeros((len(idx), 0)))
        return cls(rs[idx], k[idx], np.diff(np.append(idx, len(v))),
                   np.add.reduceat(v, idx, axis=0), np.add.reduceat(v * v, idx, axis=0), saux,
                   np.add.reduceat(t_us - rs, idx).astype(np.float64))  # exact

    @classmethod
    def of_accs(cls, accs: list[WindowAcc], n_aux: int) -> WindowSums:
        if len(accs) == 1:  # a live sensor's usual batch: its rows as views of the sums
            a = accs[0]
            return cls(np.array([a.run_start_us], np.int64), np.array([a.k], np.int64),
                       np.array([a.n], np.int64), np.asarray(a.sum_v, np.float64).reshape(1, 3),
                       np.asarray(a.sum_v2, np.float64).reshape(1, 3),
                       np.asarray(a.sum_aux, np.float64).reshape(1, n_aux),
                       np.array([a.sum_t], np.float64))
        return cls(np.array([a.run_start_us for a in accs], np.int64),
                   np.array([a.k for a in accs], np.int64),
                   np.array([a.n for a in accs], np.int64),
                   np.array([a.sum_v for a in accs]).reshape(-1, 3),
                   np.array([a.sum_v2 for a in accs]).reshape(-1, 3),
                   np.array([a.sum_aux for a in accs]).reshape(len(accs), n_aux),
                   np.array([a.sum_t for a in accs], np.float64))

    @classmethod
    def gather(cls, parts: list[WindowAcc | WindowSums], n_aux: int) -> WindowSums:
        """One table of windows given one by one (`WindowAcc`) and in blocks, in that order."""
        blocks: list[WindowSums] = []
        for part in parts:
            if isinstance(part, WindowSums):
                blocks.append(part)
            elif blocks and isinstance(blocks[-1], list):
                blocks[-1].append(part)
            else:
                blocks.append([part])
        return cls.concat([b if isinstance(b, WindowSums) else cls.of_accs(b, n_aux)
                           for b in blocks])

    @classmethod
    def concat(cls, tables: list[WindowSums]) -> WindowSums:
        if len(tables) == 1:
            return tables[0]
        return cls(*(np.concatenate([getattr(t, f.name) for t in tables])
                     for f in fields(cls)))

    @classmethod
    def empty(cls, n_aux: int) -> WindowSums:
        return cls.of_accs([], n_aux)

    def join(self, first: np.ndarray) -> WindowSums:
        """Rows first[j]..first[j+1] summed into one each (pieces of one window, in order)."""
        return WindowSums(self.run_start_us[first], self.k[first],
                          np.add.reduceat(self.n, first), np.add.reduceat(self.sum_v, first, 0),
                          np.add.reduceat(self.sum_v2, first, 0),
                          (np.add.reduceat(self.sum_aux, first, 0) if self.sum_aux.shape[1]
                           else self.sum_aux[first]), np.add.reduceat(self.sum_t, first))

    def __len__(self) -> int:
        return len(self.n)

    def acc(self, j: int) -> WindowAcc:
        return WindowAcc(int(self.run_start_us[j]), int(self.k[j]), int(self.n[j]), self.sum_v[j],
                    self.sum_v2[j], self.sum_aux[j], float(self.sum_t[j]))

    def take(self, rows: np.ndarray) -> WindowSums:
        return WindowSums(*(getattr(self, f.name)[rows] for f in fields(self)))

    def means(self) -> tuple[Windows, np.ndarray]:
        """Window means (and the run each belongs to), all at once."""
        n = self.n
        nf = n[:, None]
        v = self.sum_v / nf
        s2 = np.maximum(self.sum_v2 / nf - v * v, 0.0)
        # the mean per-axis variance, unbiased
        var = (s2[:, 0] + s2[:, 1] + s2[:, 2]) / 3 * n / np.maximum(n - 1, 1)
        t_mid = self.run_start_us + np.rint(self.sum_t / n).astype(np.int64)
        return Windows(v, self.sum_aux / nf, t_mid, n, var), self.run_start_us




class WindowerState(NamedTuple):
    """What the windower carries from one batch to the next (immutable: `cut` returns a new
    one; a tuple, the cheapest such record to make at every step).

    Attributes:
        open: the window being filled (None: no run open at the last batch's end).
        pending: a finished window and the device time it commits at (guard_s past its end).
        last_t_us, last_gate: the last sample's time and gate (a run may continue).
    """

    open: WindowAcc | None = None
    pending: tuple[WindowAcc, int] | None = None
    last_t_us: int | None = None
    last_gate: bool = False

    def to_dict(self) -> dict:
        """The checkpoint's keys, in its order."""
        return {"open": self.open.to_dict() if self.open is not None else None,
                "pending": ([self.pending[0].to_dict(), self.pending[1]]
                            if self.pending is not None else None),
                "last_t_us": self.last_t_us, "last_gate": self.last_gate}

    @classmethod
    def from_dict(cls, d: dict) -> WindowerState:
        pend = d["pending"]
        return cls(WindowAcc.from_dict(d["open"]),
                   (WindowAcc.from_dict(pend[0]), int(pend[1])) if pend is not None else None,
                   d["last_t_us"], bool(d["last_gate"]))


@dataclass(eq=False)
class Cut:
    """One batch's window events in sample order (`due`): (index, True) for a window that
    commits at sample index, (index, False) for one too short to keep; and the committing
    windows' sums, in the same order (None: none commits)."""

    sums: WindowSums | None
    #: the events as a list, or what gives them as (sample index, commits) arrays not yet in
    #: order (the batch windowing never asks)
    events: list[tuple[int, bool]] | Callable[[], tuple[np.ndarray, np.ndarray]]

    @property
    def due(self) -> list[tuple[int, bool]]:
        """The events as a list, in order (worked out at each call: ask once)."""
        if isinstance(self.events, list):
            return self.events
        idx, commits = self.events()  # a short window before a commit at the same sample
        order = np.lexsort((commits, idx))
        return list(zip(idx[order].tolist(), commits[order].tolist(), strict=True))

    @property
    def committed(self) -> int:
        return len(self.sums) if self.sums is not None else 0


#: From this many runs in a batch on, `cut` works on all of them at once (`_cut_all`); fewer
#: (a live sensor's batches) go run by run (`_Cutter`), with fewer numpy calls. Both give the
#: same windows bit for bit (tests/test_windower.py).
RUNS_AT_ONCE = 2


def cut(cfg: WindowConfig, state: WindowerState, t_us: np.ndarray, v: np.ndarray,
        aux: np.ndarray, gate: np.ndarray, runs_at_once: int = RUNS_AT_ONCE
        ) -> tuple[Cut, WindowerState]:
    """The batch's windows (samples t_us, v, aux; `gate`: which may enter one), and the state
    for the next batch. Pure: ``state`` is not changed."""
    if len(t_us) == 1:
        return _cut_one(cfg, state, t_us, v, aux, gate)
    start, forward = _run_starts(t_us, gate, state.last_t_us, state.last_gate, cfg.rate_hz)
    continues = (bool(gate[0]) and not start[0]
                 and (state.open is not None or state.pending is not None))
    start[0] = gate[0]  # a range of this batch all the same
    s_idx = np.flatnonzero(start)
    new_last = (int(t_us[-1]), bool(gate[-1]))
    if len(s_idx) and len(s_idx) >= runs_at_once:
        due, table, open_, pending = _cut_all(cfg, state, t_us, v, aux, gate, start, s_idx,
                                              continues, bool(forward[1:].all()))
        return Cut(table, due), WindowerState(open_, pending, *new_last)
    stops = np.append(np.flatnonzero(~gate | start), len(gate))
    ends = stops[np.searchsorted(stops, s_idx, side="right")]
    c = _Cutter(cfg, state.open, state.pending, [], [])
    c.schedule(t_us, v, aux, len(gate),
               list(zip(s_idx.tolist(), ends.tolist(), strict=True)), continues)
    table = WindowSums.gather(c.table, aux.shape[1]) if c.table else None
    return Cut(table, c.due), WindowerState(c.open, c.pending, *new_last)


def _cut_one(cfg: WindowConfig, state: WindowerState, t_us: np.ndarray, v: np.ndarray,
             aux: np.ndarray, gate: np.ndarray) -> tuple[Cut, WindowerState]:
    """`cut` of one sample (a live sensor's arrival): `_run_starts` and `_Cutter.schedule_run`
    for one sample, worked out on Python scalars and a few 3-element sums, so the same
    windows and state. A one-row sum is the row plus 0.0 (numpy's reduction starts from
    the identity, so -0.0 sums to 0.0): the sample's share is added as that."""
    t0 = int(t_us[0])
    if not gate[0]:  # no run: whatever was open or pending is dropped
        return Cut(None, []), WindowerState(None, None, t0, False)
    dt = 1 if state.last_t_us is None else t0 - state.last_t_us
    if state.last_gate and 0 < dt <= _run_step_us(cfg.rate_hz):  # the run goes on
        open_, pending = state.open, state.pending
    else:
        open_, pending = None, None
    run_start = open_.run_start_us if open_ is not None else (
        pending[0].run_start_us if pending is not None else t0)
    k = (t0 - run_start) // cfg.window_us
    v0 = v[0]
    due: list[tuple[int, bool]] = []
    if open_ is not None and open_.k == k:  # the sample continues the open window (merge)
        # no aux channels: the empty sum as it was (an empty array is never written to)
        sum_aux = open_.sum_aux + (aux[0] + 0.0) if aux.shape[1] else open_.sum_aux
        acc = WindowAcc(run_start, k, open_.n + 1, open_.sum_v + (v0 + 0.0),
                        open_.sum_v2 + v0 * v0, sum_aux, open_.sum_t + float(t0 - run_start))
    else:
        if open_ is not None:  # the open window ended where this one begins (`_finish`)
            if open_.n < cfg.min_samples:
                due.append((0, False))
            else:
                pending = (open_, cfg.commit_us(open_.run_start_us, open_.k))
        acc = WindowAcc(run_start, k, 1, v0 + 0.0, v0 * v0, aux[0] + 0.0,
                        float(t0 - run_start))
    table = None
    if pending is not None and t0 >= pending[1]:  # guard_s past the pending window: commit
        due.append((0, True))
        table = WindowSums.of_accs([pending[0]], aux.shape[1])
        pending = None
    return Cut(table, due), WindowerState(acc, pending, t0, True)


def _run_step_us(rate_hz: float) -> int:
    """The longest step (whole us) between two gated samples of one run: three sample
    periods (integer steps against whole microseconds: the same test as against the float
    bound, without a float copy of the steps)."""
    return math.floor(3.0e6 / rate_hz)


def _cut_all(cfg: WindowConfig, state: WindowerState, t: np.ndarray, v: np.ndarray,
             aux: np.ndarray, gate: np.ndarray, start: np.ndarray, s_idx: np.ndarray,
             continues: bool, rising: bool
             ) -> tuple[Callable[[], tuple[np.ndarray, np.ndarray]], WindowSums | None,
                        WindowAcc | None, tuple[WindowAcc, int] | None]:
    """`cut` for every run of the batch at once: what `_Cutter` does run by run, with the same
    sums (a run's pieces by `np.add.reduceat`, a run of one piece by `ndarray.sum`, a window
    continued from the last batch added to its earlier part). Returns what gives the due
    events, the committing windows' sums, and the open and pending window left at the batch's
    end. rising: t rises through the whole batch."""
    n, R, W = len(t), len(s_idx), cfg.window_us
    carried_open = state.open if continues else None
    carried_pending = state.pending if continues else None
    rs_run = t[s_idx].astype(np.int64)
    if continues:
        rs_run[0] = (carried_open.run_start_us if carried_open is not None
                     else carried_pending[0].run_start_us)  # type: ignore[index]
    # each sample's run start (0 before the first run): repeated over the stretch from each
    # run's start to the next (several times cheaper than a cumulative count and a gather)
    rs = np.repeat(np.concatenate(([0], rs_run)), np.diff(np.concatenate(([0], s_idx, [n]))))
    dt = t - rs
    k = dt // W
    # pieces: a run's windows within the batch; reduceat bounds also after each run's end
    # (those pieces, of samples outside any run, are dropped)
    bounds = start.copy()
    bounds[1:] |= (k[1:] != k[:-1]) & gate[1:] | gate[:-1] & ~gate[1:]
    bounds[0] = True
    bidx = np.flatnonzero(bounds)
    real = gate[bidx]
    p0, p1 = bidx[real], np.append(bidx[1:], n)[real]
    prun, pk, pn = np.searchsorted(s_idx, p0, side="right") - 1, k[p0], p1 - p0
    sv = np.add.reduceat(v, bidx, axis=0)[real]
    vv = v * v
    sv2 = np.add.reduceat(vv, bidx, axis=0)[real]
    saux = (np.add.reduceat(aux, bidx, axis=0)[real] if aux.shape[1]
            else np.zeros((len(p0), 0)))
    st = np.add.reduceat(dt, bidx)[real].astype(np.float64)  # exact
    counts = np.bincount(prun, minlength=R)
    first = np.searchsorted(prun, np.arange(R))  # each run's first piece
    single = first[counts == 1]  # a run's only window in the batch: plain sums (ndarray.sum)
    add, with_aux = np.add.reduce, aux.shape[1] > 0
    for j, a, b in zip(single.tolist(), p0[single].tolist(), p1[single].tolist(), strict=True):
        sv[j], sv2[j] = add(v[a:b], 0), add(vv[a:b], 0)
        if with_aux:
            saux[j] = add(aux[a:b], 0)
    carried: list[WindowAcc] = []  # windows from the last batch that finish at sample 0
    if carried_open is not None and carried_open.k == pk[0]:  # the batch continues it
        o = carried_open
        sv[0], sv2[0], saux[0] = o.sum_v + sv[0], o.sum_v2 + sv2[0], o.sum_aux + saux[0]
        st[0], pn[0] = o.sum_t + st[0], o.n + pn[0]
    elif carried_open is not None:
        carried.append(carried_open)
    last = first + counts - 1  # each run's last piece
    ends = p1[last]  # each run's end
    finishes = np.ones(len(p0), bool)
    finishes[last] = False  # a run's last piece ends with it or stays open
    table = WindowSums(rs_run[prun], pk, pn.astype(np.int64), sv, sv2, saux, st)
    if carried_pending is not None or carried:
        table = WindowSums.concat([WindowSums.of_accs(
            [*([carried_pending[0]] if carried_pending else []), *carried], aux.shape[1]), table])
    m0 = len(table) - len(p0)  # rows before the pieces
    # every finished window in order (the carried pending first, finished at sample 0)
    rows = np.concatenate([np.arange(m0), m0 + np.flatnonzero(finishes)])
    run = np.concatenate([np.zeros(m0, np.int64), prun[finishes]])
    fin = np.concatenate([np.zeros(m0, np.int64), p1[finishes]])
    long = table.n[rows] >= cfg.min_samples
    commit = np.asarray(cfg.commit_us(table.run_start_us[rows], table.k[rows]), np.int64)
    if carried_pending is not None:
        long[0], commit[0] = True, carried_pending[1]
    # a long window is pending until it commits or the next long one of its run finishes
    lr, lf = run[long], fin[long]
    same = np.append(lr[1:] == lr[:-1], False)
    bound = np.where(same, np.append(lf[1:], 0), ends[lr])
    lc = commit[long]
    # t rises within a run: it commits in [lf, bound) if the last sample before bound is late
    found = (bound > lf) & (t[bound - 1] >= lc)

    def due() -> tuple[np.ndarray, np.ndarray]:
        """The short windows' ends and the commits' samples, for `Cut.due`."""
        at = np.maximum(_first_at_or_past(t, gate, s_idx, ends, np.cumsum(start) - 1,
                                          lr[found], lc[found], rising), lf[found])
        short = fin[~long]
        return (np.concatenate([short, at]),
                np.concatenate([np.zeros(len(short), bool), np.ones(len(at), bool)]))

    committed = rows[long][found]
    out = table.take(committed) if len(committed) else None
    if ends[-1] < n:  # the last run ended inside the batch: nothing open or pending
        return due, out, None, None
    open_ = table.acc(m0 + int(last[-1]))
    pending = None
    if len(lr) and lr[-1] == R - 1 and not found[-1]:
        j = int(rows[long][-1])
        pending = (table.acc(j), int(lc[-1]))
    return due, out, open_, pending


def _first_at_or_past(t: np.ndarray, gate: np.ndarray, s_idx: np.ndarray, ends: np.ndarray,
                      local: np.ndarray, run: np.ndarray, t_us: np.ndarray,
                      rising: bool) -> np.ndarray:
    """For each (run, t_us): the first sample of that run at or past t_us, or a sample past
    the run if none (t rises within a run, and usually through the whole batch: then t itself
    is the sorted key; else one is made of every run's times, each past the one before)."""
    if rising:
        return np.searchsorted(t, t_us)
    span = t[ends - 1] - t[s_idx]
    base = np.concatenate(([0], np.cumsum(span + 1)[:-1]))
    g = np.flatnonzero(gate)
    key = base[local[g]] + (t[g] - t[s_idx][local[g]])
    target = base[run] + np.clip(t_us - t[s_idx][run], 0, span[run] + 1)
    return np.append(g, len(t))[np.searchsorted(key, target)]


@dataclass(eq=False)
class _Cutter:
    """`cut`'s working state while it walks the batch's runs."""

    cfg: WindowConfig
    open: WindowAcc | None
    pending: tuple[WindowAcc, int] | None
    due: list[tuple[int, bool]]
    table: list[WindowAcc | WindowSums]

    def schedule(self, t_us: np.ndarray, v: np.ndarray, aux: np.ndarray, n: int,
                 runs: list[tuple[int, int]], continues: bool) -> None:
        """Every run of the batch in turn (`cut`); a run that ended drops its open window."""
        for r, (i0, i1) in enumerate(runs):
            if not (r == 0 and continues):
                self.open, self.pending = None, None
            self.schedule_run(t_us, v, aux, i0, i1)
        if runs and runs[-1][1] < n:  # the last run ended inside this batch
            self.open, self.pending = None, None
        if not runs:
            self.open, self.pending = None, None

    def schedule_run(self, t_us: np.ndarray, v: np.ndarray, aux: np.ndarray, i0: int,
                     i1: int) -> None:
        """`schedule` for the run of gated samples i0..i1 (continuing `self.open` and
        `self.pending` if they are set): windows of window_s from the run's start."""
        W = self.cfg.window_us
        run_start = self.open.run_start_us if self.open is not None else (
            self.pending[0].run_start_us if self.pending is not None else int(t_us[i0]))
        t = t_us[i0:i1]
        k = (t - run_start) // W
        cuts = (np.flatnonzero(k[1:] != k[:-1]) + 1).tolist()  # window boundaries
        if cuts:
            sums = WindowSums.of_run(run_start, k, [0, *cuts], v[i0:i1], aux[i0:i1], t)
            first = sums.acc(0)
        else:  # one window (a live sensor's few samples): plain sums
            first = WindowAcc.of(run_start, int(k[0]), v[i0:i1], aux[i0:i1], t)
        # windows 1.. of a long run at once when none but the last is short (`_tail`)
        fast = len(cuts) > 1 and bool(np.all(sums.n[1:-1] >= self.cfg.min_samples))
        starts, ends = [0, *cuts], [*cuts, len(t)]
        due, table = self.due, self.table
        for j in range(1 if fast else len(starts)):
            g0, g1 = starts[j], ends[j]
            acc = first if j == 0 else sums.acc(j)
            if self.open is not None and self.open.k == acc.k:
                acc = self.open.merge(acc)
            elif self.open is not None:  # the open window ended where this one begins
                self._finish(self.open, i0 + g0)
            self.open = acc
            if self.pending is not None:  # commit once the run is guard_s past the window
                # t rises within a run: the first sample at or past the commit time
                at = bisect.bisect_left(t, self.pending[1], g0, g1) - g0
                if at < g1 - g0:
                    due.append((i0 + g0 + at, True))
                    table.append(self.pending[0])
                    self.pending = None
            if g1 < len(t):  # a later window follows in this run: this one is complete
                self._finish(self.open, i0 + g1)
                self.open = None
        if fast:
            self._tail(sums, cuts, t, i0)

    def _tail(self, sums: WindowSums, cuts: list[int], t: np.ndarray, i0: int) -> None:
        """`schedule_run`'s loop over windows 1.. of a run (samples i0.., times t, window j
        from cuts[j-1]), all at once, when every one but the last is long enough to keep:
        window j is then pending from the start of window j + 1 and commits at its first
        sample guard_s past its end, or stays pending if window j + 1 is the run's last and
        ends before that; the last window stays open."""
        g0 = np.asarray(cuts)
        g1 = np.append(g0[1:], len(t))
        # the window pending in each window 1..: the one before it (the first: as it is)
        commit = np.empty(len(g0), np.int64)
        commit[1:] = self.cfg.commit_us(sums.run_start_us[1:-1], sums.k[1:-1])
        commit[0] = self.pending[1] if self.pending is not None else 0
        at = np.maximum(np.searchsorted(t, commit), g0)
        if self.pending is None:
            at[0] = len(t)  # nothing pending: never found
        found = at < g1
        due, table = self.due, self.table
        due.extend((i0 + a, True) for a in at[found].tolist())
        if found[0]:
            table.append(self.pending[0])
        rows = np.flatnonzero(found[1:]) + 1
        if len(rows):
            table.append(sums.take(rows))
        last = len(g0) - 1
        self.pending = None if found[last] else (sums.acc(last), int(commit[last]))
        self.open = sums.acc(len(sums) - 1)

    def _finish(self, acc: WindowAcc, idx: int) -> None:
        """A window is complete (seen at sample idx, the next window's first); keep it
        pending until the guard time has passed."""
        if acc.n < self.cfg.min_samples:
            self.due.append((idx, False))
            return
        self.pending = (acc, self.cfg.commit_us(acc.run_start_us, acc.k))



def _run_starts(t_us: np.ndarray, gate: np.ndarray, prev_t_us: int | None, prev_gate: bool,
                rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Where a run of gated samples starts: a gated sample after one that was not, or after a
    time step that is no step (<= 0) or a gap (> 3 nominal periods); the batch's first sample
    continues the previous batch's run if that ended gated (prev_gate) one step before it.
    And where time stepped forward (t_us[i] > the time before it)."""
    prev_t = int(t_us[0]) - 1 if prev_t_us is None else prev_t_us
    dt = np.empty(len(t_us), np.int64)  # np.diff(t_us, prepend=prev_t), without np.r_
    dt[0] = int(t_us[0]) - prev_t
    np.subtract(t_us[1:], t_us[:-1], out=dt[1:])
    forward = dt > 0
    ok_dt = forward & (dt <= _run_step_us(rate_hz))
    start = gate.copy()
    start[1:] &= ~(gate[:-1] & ok_dt[1:])
    start[0] &= not (prev_gate and ok_dt[0])
    return start, forward


