"""When the pipeline re-fits: the estimator update is the core's main cost, and most of a day's
windows repeat what the buffer already says.

Before the bootstrap, every window that passes the norm gate is a try (the bootstrap decides).
After it, every update_every-th committed window is a try, and a try re-fits only if a re-fit
can tell anything new: the estimate has not settled (the last update moved it), the buffer
covers a new cell or half-axis since the last update, max_update_interval_s of device time
passed since the last accepted update, or the windows since then disagree with the estimate
(`estimator.consistent`: a knock, a drift). The state (`RefitState`) is what the last update
saw and the consistency tests run since; see docs/design.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from recal.core.buffer import Window, Windows, cell_of
from recal.core.effects import Covariates
from recal.core.estimator import Estimate, EstimatorConfig, consistent_many, innovations
from recal.core.model import SensorModel
from recal.core.triaxial import norm3

__all__ = ["SETTLED_SD_FRACTION", "RefitState", "WindowChunk", "after_update", "fresh_windows",
           "must_update", "next_update", "settled", "tries"]

#: An update that moved no parameter by more than this fraction of its standard deviation
#: leaves the estimate settled: later windows that agree with it need no re-fit (the value
#: trades re-fits against drift tracking; see docs/design.md, "Figures behind choices").
SETTLED_SD_FRACTION = 0.25

CovariatesOf = Callable[[np.ndarray, np.ndarray], Covariates]


@dataclass(frozen=True)
class RefitState:
    """What the last update saw, to skip re-fits that would not move it.

    Attributes:
        settled: the last update was accepted and moved no parameter by more than
            SETTLED_SD_FRACTION of its standard deviation.
        coverage_at_update: the buffer's `cells_opened` at the last update (None: none yet).
        tested: fresh windows tested so far since the last update, and the sums of their
            normalized innovations (squared, plain): (m, s2, s1).
    """

    settled: bool = False
    coverage_at_update: int | None = None
    tested: tuple[int, float, float] = (0, 0.0, 0.0)

    def restarted(self) -> RefitState:
        """After a reset of the estimate: nothing settled, nothing tested."""
        return replace(self, settled=False, tested=(0, 0.0, 0.0))

    def to_dict(self) -> dict:
        """The checkpoint's keys, in its order."""
        return {"settled": self.settled, "coverage_at_update": self.coverage_at_update,
                "tested": list(self.tested)}

    @classmethod
    def from_dict(cls, d: dict) -> RefitState:
        cov_key = d.get("coverage_at_update")
        m, s2, s1 = d.get("tested", (0, 0.0, 0.0))
        return cls(bool(d.get("settled", False)), int(cov_key) if cov_key is not None else None,
                   (int(m), float(s2), float(s1)))


def settled(before: Estimate, after: Estimate) -> bool:
    """Whether an update from ``before`` to ``after`` moved no parameter by more than
    SETTLED_SD_FRACTION of its standard deviation."""
    sd = np.sqrt(np.clip(np.diag(after.cov), 1e-300, None))
    return bool(np.all(np.abs(after.p - before.p) <= SETTLED_SD_FRACTION * sd))


def after_update(before: Estimate, after: Estimate, accepted: bool,
                 cells_opened: int) -> RefitState:
    """The state after an update (accepted or not) with the buffer at ``cells_opened``."""
    return RefitState(accepted and settled(before, after), cells_opened)


def fresh_windows(rows: list[Window], n_aux: int) -> Windows:
    """Committed windows kept one by one (the pipeline's since the last update, which the
    consistency tests read), as arrays."""
    m = len(rows)
    return Windows(np.array([f.v for f in rows]).reshape(m, 3),
                   np.array([f.aux for f in rows]).reshape(m, n_aux),
                   np.array([f.t_us for f in rows], np.int64),
                   np.array([f.n for f in rows], np.int64),
                   np.array([f.var for f in rows], float))


def must_update(state: RefitState, estimate: Estimate | None,
                max_update_interval_s: float) -> bool:
    """An update runs at the next try, whatever the windows say."""
    return (max_update_interval_s <= 0 or estimate is None or estimate.t_us is None
            or not state.settled)


@dataclass(eq=False)
class WindowChunk:
    """Windows lo..lo+len of a batch's committing windows under the parameters in force: their
    norm gate, gravity directions and cells, worked out at once. Most end early, at an update
    that changes the parameters, so the pipeline takes them in chunks that double (64, 128,
    ...) while the parameters hold; `rows` hands the buffer, which takes windows one at a
    time, those it reaches as Python numbers. The innovations of the windows that pass the
    gate are computed when a consistency test first asks (`next_update`)."""

    lo: int
    w: Windows
    ok: np.ndarray
    dirs: np.ndarray
    runs: np.ndarray
    cells: np.ndarray
    norm: np.ndarray | None = None  # calibrated norms (g), for the self-watch
    sigma_mg: np.ndarray | None = None  # their predicted error, when the self-watch asks
    z: np.ndarray | None = None
    _norm_l: list[float] | None = None
    _sigma_l: list[float] | None = None

    @classmethod
    def of(cls, model: SensorModel, p: np.ndarray, covariates: CovariatesOf,
           norm_tol_g: float | None, grid: int, w: Windows, runs: np.ndarray, lo: int,
           hi: int) -> WindowChunk:
        """norm_tol_g None: no norm gate (before the bootstrap)."""
        s = slice(lo, hi)
        mine = Windows(w.v[s], w.aux[s], w.t_us[s], w.n[s], w.var[s])
        a = model.correct(p, mine.v, covariates(mine.t_us, mine.aux))
        norm = norm3(a)
        ok = (np.abs(norm - 1.0) <= norm_tol_g if norm_tol_g is not None
              else np.ones(len(a), bool))
        with np.errstate(invalid="ignore", divide="ignore"):
            dirs = np.where((norm > 0)[:, None], a / norm[:, None], [0.0, 0.0, 1.0])
        return cls(lo, mine, ok, dirs, runs[s], cell_of(dirs, grid), norm)

    def __len__(self) -> int:
        return len(self.ok)

    def norm_at(self, i: int) -> float:
        """norm[i] as a Python float (lists made once per chunk: the self-watch reads one
        window at a time, and indexing numpy per window costs more than the list)."""
        if self._norm_l is None:
            self._norm_l = self.norm.tolist()
        return self._norm_l[i]

    def sigma_at(self, i: int) -> float:
        """sigma_mg[i] as a Python float (as `norm_at`)."""
        if self._sigma_l is None:
            self._sigma_l = self.sigma_mg.tolist()
        return self._sigma_l[i]

    def rows(self, c0: int, c1: int) -> list[tuple]:
        """(ok, v, aux, t_us, n, var, dir, run, cell) of the batch's windows c0..c1."""
        s, w = slice(c0 - self.lo, c1 - self.lo), self.w
        return list(zip(self.ok[s].tolist(), w.v[s].tolist(), w.aux[s].tolist(),
                        w.t_us[s].tolist(), w.n[s].tolist(), w.var[s].tolist(),
                        self.dirs[s].tolist(), self.runs[s].tolist(), self.cells[s].tolist(),
                        strict=True))

    def innovations(self, model: SensorModel, estimate: Estimate, covariates: CovariatesOf,
                    cfg: EstimatorConfig) -> np.ndarray:
        """`estimator.innovations` of the chunk's windows that pass the gate, in order."""
        if self.z is None:
            w = self.w
            self.z = innovations(model, estimate, w, covariates(w.t_us, w.aux), cfg)[self.ok]
        return self.z


def tries(chunk: WindowChunk, c0: int, windows: int, update_every: int
          ) -> tuple[np.ndarray, np.ndarray]:
    """The tries among the chunk's windows from c0 (positions from c0): every update_every-th
    committed window that passes the norm gate (windows: committed so far); and how many of
    them from c0 pass, up to each."""
    ok = chunk.ok[c0 - chunk.lo:]
    cum = np.cumsum(ok)
    return np.flatnonzero(ok & ((windows + cum) % update_every == 0)), cum


def next_update(state: RefitState, chunk: WindowChunk, c0: int, checks: np.ndarray,
                cum: np.ndarray, *, n_fresh: int, late: Callable[[np.ndarray], np.ndarray],
                z_fresh: Callable[[int, int], np.ndarray],
                z_chunk: Callable[[], np.ndarray]) -> tuple[int | None, RefitState]:
    """After the bootstrap, when no update must run (`must_update`): the first try (`tries`:
    checks, cum) after which an update runs, as a window of the batch (None: none in the
    chunk), and the state with the consistency tests run on the way.

    n_fresh: windows committed since the last update (those of the chunk before c0
    included); late(checks): whether those tries come max_update_interval_s after the last
    accepted update; z_fresh(m0, m1): the innovations of fresh windows m0..m1; z_chunk(): the
    chunk's (`WindowChunk.innovations`). A new cell is the caller's reason (the buffer places
    each window)."""
    i0 = c0 - chunk.lo
    n_before = int(np.count_nonzero(chunk.ok[:i0]))  # the chunk's windows already entered
    in_fresh = n_fresh - n_before  # fresh windows from before the chunk
    is_late = late(checks)
    first_late = int(np.argmax(is_late)) if is_late.any() else len(checks)  # no test there
    upto = n_before + cum[checks]  # the chunk's windows that passed, up to each check
    first, state = _test_until(state, in_fresh, upto, first_late, z_fresh, z_chunk)
    return (int(checks[first]) + c0 if first < len(checks) else None), state


def _test_until(state: RefitState, in_fresh: int, upto: np.ndarray, stop: int,
                z_fresh: Callable[[int, int], np.ndarray],
                z_chunk: Callable[[], np.ndarray]) -> tuple[int, RefitState]:
    """The consistency tests (`consistent`: a re-fit would not move the estimate) at the
    first `stop` checks, check j testing the fresh windows through the chunk's upto[j]-th
    window that passed the gate (in_fresh came before the chunk): the first that fails
    (or stop). The tests up to it are recorded in the state's `tested`, as if run one by
    one: each check's sums are added to the running ones in order."""
    if stop == 0:
        return 0, state
    m, s2, s1 = state.tested
    before = max(in_fresh - m, 0)  # untested windows from before the chunk
    tested = max(m - in_fresh, 0)  # the chunk's windows tested already
    z = []
    if before:  # tested with the chunk's own
        z.append(z_fresh(m, in_fresh))
    z.append(z_chunk()[tested:int(upto[stop - 1])])
    zz = np.concatenate(z)
    ends = before + upto[:stop] - tested  # each check's last window in zz, plus one
    starts = np.concatenate(([0], ends[:-1]))
    # each check's windows summed in order, then the checks one after another
    ms = m + ends
    s2s = np.cumsum(np.concatenate(([s2], np.add.reduceat(zz * zz, starts))))[1:]
    s1s = np.cumsum(np.concatenate(([s1], np.add.reduceat(zz, starts))))[1:]
    ok = consistent_many(ms, s2s, s1s)
    j = int(np.argmin(ok)) if not ok.all() else stop - 1
    state = RefitState(state.settled, state.coverage_at_update,
                       (int(ms[j]), float(s2s[j]), float(s1s[j])))
    return (j if not ok[j] else stop), state
