"""What a pipeline step gives back for a batch (`StepOutput`), with the estimator updates
(`UpdateEvent`) and the self-watch's events (`WatchEvent`) in it; and a step over batches
joined into one, split back per batch (`JoinedStep`, `Pipeline.step_many`).
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from recal.core.buffer import Windows
from recal.core.estimator import Estimate, UpdateReport
from recal.core.model import SensorModel
from recal.samples import CalibratedBatch

__all__ = ["JoinedStep", "MarkState", "Marks", "StepOutput", "UpdateEvent", "WatchEvent"]


@dataclass(frozen=True)
class UpdateEvent:
    """An estimator update that happened at sample `index` of the batch (device time t_us);
    what is in force after it: `StepOutput.model` and `estimate`, as of the batch's end."""

    index: int
    t_us: int
    report: UpdateReport
    bootstrap: bool = False


@dataclass(frozen=True)
class WatchEvent:
    """The self-watch at sample `index` of the batch (device time t_us): ``suspect`` (the
    still windows contradicted the estimate for a sustained time: the output is suspect and
    the estimate was reset toward the prior and re-fitted on the recent windows), ``agrees``
    (the windows agree again: suspect no more) or ``reset`` (the estimate was not finite)."""

    index: int
    t_us: int
    kind: str
    detail: dict = field(default_factory=dict, compare=False)


@dataclass(frozen=True, eq=False)
class StepOutput:
    """What one batch produced (`Pipeline.step`, `Pipeline.step_many`): its calibrated samples,
    the updates and the self-watch's events in it (indices into the batch, in order), the
    windows committed in it; and the state as of the batch's end: the model and estimate in
    force, and ``state``, the model and `Pipeline.summary()` then when the batch holds an
    update or a reset (`step_many` only: after `step` the pipeline's own summary is that);
    ``windows``: the window means committed in it, norm gate or not (None: none; what a node
    keeps for discovery, `core.evidence`)."""

    calibrated: CalibratedBatch
    updates: tuple[UpdateEvent, ...]
    windows_committed: int
    watch: tuple[WatchEvent, ...] = ()
    model: SensorModel | None = None
    estimate: Estimate | None = None
    state: tuple[SensorModel, dict] | None = None
    windows: Windows | None = None


@dataclass(frozen=True, eq=False)
class MarkState:
    """The state after a mark's samples (a joined batch's end, `Pipeline.step_many`); summary:
    only when an update or a reset happened since the previous mark."""

    model: SensorModel
    estimate: Estimate | None
    summary: dict | None


@dataclass(eq=False)
class Marks:
    """Sample counts into a joined batch (its batches' ends) at which `Pipeline.step_many`
    wants the state, and the states recorded as the step passes them (`reach`)."""

    todo: list[int]
    gate: np.ndarray
    samples0: int
    quasi_static0: int
    dirty: bool = False  # an update happened since the last mark passed
    at: dict[int, MarkState] = field(default_factory=dict)

    def reach(self, idx: int, model: SensorModel, estimate: Estimate | None,
              summary: Callable[[], dict]) -> None:
        """Called before anything in the state changes at sample ``idx`` of the batch: the
        state now is the state after ``m`` samples for every mark m <= idx not yet passed."""
        while self.todo and self.todo[0] <= idx:
            m = self.todo.pop(0)
            s = None
            if self.dirty:  # an update since the previous mark: the caller publishes this state
                s = summary()
                s["counts"]["samples"] = self.samples0 + m  # counted at the end of the step
                s["counts"]["quasi_static"] = self.quasi_static0 + int(
                    np.count_nonzero(self.gate[:m]))
                self.dirty = False
            self.at[m] = MarkState(model, estimate, s)


@dataclass(eq=False, slots=True)
class JoinedStep:
    """One step's output over a (possibly joined) batch: `StepOutput`'s, with the sample index
    of each committed window and the state at each mark (`Pipeline.step_many` splits it)."""

    calibrated: CalibratedBatch
    updates: tuple[UpdateEvent, ...]
    commits: list[int]
    watch: tuple[WatchEvent, ...]
    marks: dict[int, MarkState]
    windows: Windows | None = None  # one per commit, in order (None: no commit)

    def joined(self, tail: JoinedStep, at: int) -> JoinedStep:
        """This step's output for the first `at` samples, then `tail`'s for the rest."""
        wins = (self.windows if tail.windows is None else tail.windows if self.windows is None
                else _concat(self.windows, tail.windows))
        return JoinedStep(CalibratedBatch.concat([self.calibrated, tail.calibrated]),
                          (*self.updates, *(replace(u, index=u.index + at)
                                            for u in tail.updates)),
                          [*self.commits, *(c + at for c in tail.commits)],
                          (*self.watch, *(replace(w, index=w.index + at) for w in tail.watch)),
                          {**self.marks, **{m + at: v for m, v in tail.marks.items()}}, wins)

    def split(self, lengths: Sequence[int], model: SensorModel,
              estimate: Estimate | None) -> list[StepOutput]:
        """One output per batch joined (of these lengths, in order; a mark at the end of each
        that is not empty), indices local to it; model and estimate: in force before the
        first batch."""
        outs: list[StepOutput] = []
        lo, c, ups, watch, commits = 0, 0, list(self.updates), list(self.watch), self.commits
        for n in lengths:
            if not n:
                outs.append(StepOutput(CalibratedBatch.empty(), (), 0, (), model, estimate))
                continue
            hi = lo + n
            mine = [replace(u, index=u.index - lo) for u in _take_before(ups, hi)]
            seen = [replace(w, index=w.index - lo) for w in _take_before(watch, hi)]
            c1 = bisect.bisect_left(commits, hi, c)
            mark = self.marks[hi]
            model, estimate = mark.model, mark.estimate
            state = (mark.model, mark.summary) if mark.summary is not None else None
            outs.append(StepOutput(self.calibrated[lo:hi], tuple(mine), c1 - c, tuple(seen),
                                   model, estimate, state, _rows(self.windows, c, c1)))
            lo, c = hi, c1
        return outs


def _concat(a: Windows, b: Windows) -> Windows:
    return Windows(*(np.concatenate([x, y]) for x, y in zip(
        (a.v, a.aux, a.t_us, a.n, a.var), (b.v, b.aux, b.t_us, b.n, b.var), strict=True)))


def _rows(w: Windows | None, lo: int, hi: int) -> Windows | None:
    """Windows lo..hi of a step's (None when there are none)."""
    if w is None or hi <= lo:
        return None
    s = slice(lo, hi)
    return Windows(w.v[s], w.aux[s], w.t_us[s], w.n[s], w.var[s])


def _take_before(events: list, hi: int) -> list:
    """The leading events (in index order) with index < hi, taken off the list."""
    k = 0
    while k < len(events) and events[k].index < hi:
        k += 1
    taken, events[:k] = events[:k], []
    return taken
