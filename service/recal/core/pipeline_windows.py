"""The pipeline's window path (`core.pipeline`): the gated runs cut into windows
(`core.windower`), each finished window committed in order (the norm gate, the self-watch, the
buffer), and the windows after which a re-fit runs (`core.refit`). Functions of the pipeline
they change; the one-sample path returns at once when no window finished.
"""

from __future__ import annotations

import bisect
from typing import TYPE_CHECKING

import numpy as np

from recal.core.buffer import Window, Windows
from recal.core.effects import Scale
from recal.core.estimator import innovations
from recal.core.outputs import UpdateEvent
from recal.core.pipeline_fit import try_bootstrap, update_at
from recal.core.pipeline_watch import contradicts, reset_estimate, watch_window
from recal.core.refit import WindowChunk, fresh_windows, must_update, next_update, tries
from recal.core.status import Status
from recal.core.windower import cut
from recal.samples import RawBatch

if TYPE_CHECKING:
    from recal.core.pipeline_state import PipelineParts

__all__ = ["windows"]


def windows(pipe: PipelineParts, b: RawBatch, gate: np.ndarray
            ) -> tuple[list[UpdateEvent], list[int], Windows | None]:
    """Cut the gated runs into windows (`core.windower`) and commit the finished ones; the
    updates, the commit sample of each window and the windows committed (None: none), every
    one whether the norm gate kept it or not (discovery's evidence, `core.evidence`).

    Which windows finish and when they commit depends on the gates and times alone, so it
    is worked out first for the whole batch; committing them then depends on the
    parameters, which change only at updates (`_commit_all`)."""
    before = pipe.windower
    c, pipe.windower = cut(pipe.cfg.windows, before, b.t_us, b.v, b.aux, gate)
    means = c.sums.means() if c.sums is not None else None
    events, at = _commit_all(pipe, b, c.due, means)
    restart = pipe._work.restart_at
    if restart is not None and restart + 1 < len(b):
        # the detector restarts after sample `restart` (`pipeline_fit._relocate`): the step
        # ends there (`Pipeline._step`), the windows still open then as the samples up to
        # it leave them; the rest of the batch is cut anew under the new detector
        h = restart + 1
        _, pipe.windower = cut(pipe.cfg.windows, before, b.t_us[:h], b.v[:h], b.aux[:h],
                               gate[:h])
    if means is None:
        return events, at, None
    w = means[0]
    if len(at) < len(w):  # the windows committed before the step ended
        k = len(at)
        w = Windows(w.v[:k], w.aux[:k], w.t_us[:k], w.n[:k], w.var[:k])
    return events, at, w


def _commit_all(pipe: PipelineParts, b: RawBatch, due: list[tuple[int, bool]],
                means: tuple[Windows, np.ndarray] | None
                ) -> tuple[list[UpdateEvent], list[int]]:
    """Commit the scheduled windows in order. Between updates the parameters hold, so the
    norm gate, directions and cells of the windows are worked out a chunk at a time
    (`refit.WindowChunk`), and `_scan` finds the next window after which an update runs from the
    chunk's arrays; the windows before it only enter the buffer (`_enter`)."""
    if not due:  # no window finished (most arrivals of a live sensor): nothing to do
        return [], []
    events: list[UpdateEvent] = []
    at = [idx for idx, window in due if window]  # commit sample of each window
    slot = [k for k, (_, window) in enumerate(due) if window]  # its place in due
    done = 0  # due entries handled
    if means is not None:
        w, runs = means
        c, size, chunk = 0, 0, None
        while c < len(w):
            restart = pipe._work.restart_at
            if restart is not None and at[c] > restart:
                # the detector restarts after that sample: what comes after is stepped anew
                # (`Pipeline._step`), as it would be had the batch ended there
                at = at[:c]
                break
            if chunk is None or c >= chunk.lo + len(chunk):
                size = min(len(w) - c, max(64, 2 * size))
                chunk = WindowChunk.of(
                    pipe.model, pipe.params, pipe.covariates,
                    pipe.cfg.norm_tol_g if pipe.bootstrapped else None,
                    pipe.cfg.buffer.grid, w, runs, c, c + size)
            e = _scan(pipe, chunk, c, b.t_us, at)
            stop = chunk.lo + len(chunk) if e is None else e + 1
            done, opened = _enter(pipe, chunk, c, stop, due, slot, done)
            e = opened if opened is not None else e
            c = stop if e is None else e + 1
            if e is None:
                continue
            idx = at[e]
            now = int(b.t_us[idx])
            evs: list[UpdateEvent | None] = []
            if pipe._work.reset_due is None:  # (else the self-watch fired at this window)
                evs.append(try_bootstrap(pipe, idx, now) if not pipe.bootstrapped
                           else update_at(pipe, idx, now))
            reset = pipe._work.reset_due is not None  # fired, or the update found a jump again
            if reset:
                evs.append(reset_estimate(pipe, idx, now))
            events += [ev for ev in evs if ev is not None]
            if reset or evs[-1] is not None:
                pipe._work.segs.append(pipe._segment(idx))
                if pipe._work.marks is not None:
                    pipe._work.marks.dirty = True
                chunk, size = None, 0  # the parameters changed: a new first chunk
    restart = pipe._work.restart_at  # due entries after it: the step's tail (`Pipeline._step`)
    end = len(due) if restart is None else bisect.bisect_right([i for i, _ in due], restart)
    _reject_short(pipe, due, done, end)
    return events, at


def _enter(pipe: PipelineParts, chunk: WindowChunk, c0: int, c1: int, due: list[tuple[int, bool]],
           slot: list[int], done: int) -> tuple[int, int | None]:
    """Windows c0..c1 of the batch enter the buffer (or count as rejected by their norm),
    each after the short windows scheduled before it. Returns the due entries handled,
    and the window at which an update must run because the buffer covers a cell it did
    not at the last update (`_scan`'s other reason; whether a window opens a cell or
    merges into the latest slot is the buffer's call, one window at a time)."""
    marks, ue, watch = pipe._work.marks, pipe.cfg.update_every, pipe.bootstrapped
    add, fresh, buf, counts = pipe.buffer.add, pipe.fresh, pipe.buffer, pipe.counts
    lo = chunk.lo
    for c, row in zip(range(c0, c1), chunk.rows(c0, c1), strict=True):
        k = slot[c]
        if k > done:  # short windows scheduled before this one
            done = _reject_short(pipe, due, done, k)
        idx = due[k][0]
        if marks is not None:
            pipe._reach(idx)
        ok, v, aux, t_mid, n, var, direction, run, cell = row
        done = k + 1
        if watch:
            window = Window(v, aux, t_mid, n, var)
            if watch_window(pipe, not ok, window, idx,
                            contradicts(pipe, chunk, c - lo, ok, n, var), cell):
                if ok:  # in the buffer it is about to replace: counted as the others
                    counts["windows"] += 1
                else:
                    counts["windows_rejected"] += 1
                return done, c  # a reset (`reset_estimate`) at this window
        if not ok:
            counts["windows_rejected"] += 1
            continue
        opened = buf.cells_opened
        add(v, aux, t_mid, n, var, direction, run, cell)
        if watch and buf.cells_opened != opened and _axis_newly_covered(pipe):
            fresh.append(window)
            counts["windows"] += 1
            return done, c  # a gain the last update could not see now can be: update
        if watch:  # before the bootstrap nothing tests them (and they would pile up)
            fresh.append(window)
        counts["windows"] += 1
        if not watch and pipe._work.segs and pipe._work.segs[-1].status is Status.UNCALIBRATED:
            pipe._work.segs.append(pipe._segment(idx))  # now bootstrapping
        if (watch and counts["windows"] % ue == 0
                and buf.cells_opened != pipe.refit.coverage_at_update):
            return done, c
    return done, None


def _axis_newly_covered(pipe: PipelineParts) -> bool:
    """An axis the buffer now sees from both sides whose scale the last update could not
    observe (a sphere fitted to five half-axes, then the sixth): worth an update at once,
    whatever the window count (a six-pose stream ends right after its last pose)."""
    rep = pipe.last_report
    if (rep is None or not pipe.model.has("scale") or not rep.observable
            or len(rep.observable) != len(pipe.model.names)):  # (of a model since replaced)
        return False
    sl = pipe.model.slice(Scale())
    seen = rep.observable[sl.start:sl.stop]
    covered = pipe.buffer.coverage().axes_covered
    return any(c and not o for c, o in zip(covered, seen, strict=True))


def _reject_short(pipe: PipelineParts, due: list[tuple[int, bool]], done: int, stop: int) -> int:
    """Due entries done..stop are windows too short to keep (`_finish`): counted."""
    if stop <= done:
        return done
    if pipe._work.marks is not None:
        for idx, _ in due[done:stop]:
            pipe._reach(idx)
            pipe.counts["windows_rejected"] += 1
    else:
        pipe.counts["windows_rejected"] += max(stop - done, 0)
    return max(done, stop)


def _scan(pipe: PipelineParts, chunk: WindowChunk, c0: int, t_us: np.ndarray,
          at: list[int]) -> int | None:
    """The first window from c0 in the chunk after which an update runs (`core.refit`).
    None: none in it. Before the bootstrap: every window that passes the norm gate."""
    if not pipe.bootstrapped:
        hits = np.flatnonzero(chunk.ok[c0 - chunk.lo:])
        return int(hits[0]) + c0 if len(hits) else None
    est, cfg = pipe.estimate, pipe.cfg
    assert est is not None
    checks, cum = tries(chunk, c0, pipe.counts["windows"], cfg.update_every)
    if not len(checks):
        return None
    if must_update(pipe.refit, est, cfg.max_update_interval_s):
        return int(checks[0]) + c0

    def late(checks: np.ndarray) -> np.ndarray:
        return (t_us[np.asarray(at[c0:c0 + len(chunk) - (c0 - chunk.lo)])[checks]]
                - est.t_us >= cfg.max_update_interval_s * 1e6)

    def z_fresh(m0: int, m1: int) -> np.ndarray:
        w = fresh_windows(pipe.fresh[m0:m1], len(pipe.aux_names))
        return innovations(pipe.model, est, w, pipe.covariates(w.t_us, w.aux), cfg.estimator)

    e, pipe.refit = next_update(
        pipe.refit, chunk, c0, checks, cum, n_fresh=len(pipe.fresh), late=late,
        z_fresh=z_fresh,
        z_chunk=lambda: chunk.innovations(pipe.model, est, pipe.covariates, cfg.estimator))
    return e
