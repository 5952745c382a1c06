"""Effect discovery on a live node's evidence, apart from the node, on a schedule.

A :class:`recal.node.node.CalibrationNode` keeps every committed window in its evidence store
(`recal.core.evidence`) and reruns effect discovery (`recal.core.discovery`) on a copy of it
now and then, from the configured model (the user's ``--model`` or model file: an effect an
earlier run adopted is selected again, or dropped, on the larger evidence). The run takes
seconds, so it goes to a thread (or a process, ``executor``) and the node takes its result
``adopt_after_s`` device seconds later. The core is pure, so the run shares nothing with the
node's pipeline. The schedule and the method: docs/design.md (effect discovery).
"""

from __future__ import annotations

import logging
import multiprocessing
import threading
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

import numpy as np

from recal.config.settings import RediscoveryConfig
from recal.core.estimator import Estimate
from recal.core.evidence import EvidenceConfig, EvidenceStore
from recal.core.model import SensorModel
from recal.core.outputs import StepOutput
from recal.core.pending import PendingCandidate
from recal.core.pipeline import Pipeline
from recal.node.events import NodeEvents
from recal.node.state_message import model_name

__all__ = ["NodeDiscovery", "Rediscovery", "RediscoverySchedule", "in_a_process"]

log = logging.getLogger(__name__)

#: Effects whose terms only orientations tell apart (they act along the gravity direction):
#: tried once the evidence holds MIN_CELLS cube-face cells (`EvidenceStore.cells`). With a few
#: upright postures a cross-axis and a nonlinearity term together fit the postures' own
#: scatter and pass the held-out test (seen on a clean, upright wearer at 3 cells).
ORIENTED_KINDS = ("cross_axis", "nonlinearity")
MIN_CELLS = 10
#: Slots every first_h before the schedule's gap starts doubling (the first hour at 10 min).
FIRST_SLOTS = 6


#: Where every node of this process runs discovery while `in_a_process` holds (None: a thread
#: per run).
_EXECUTOR: Executor | None = None


@contextmanager
def in_a_process(on: bool = True) -> Iterator[None]:
    """While in the block, every node's discovery runs go to one worker process of their own
    (the daemons: a run of seconds in a thread holds the interpreter the arrivals need; a
    tick of 1 ms beside a run saw a p99 of 26 ms against 3 ms without, docs/performance.md).
    Spawned, not forked: a fork of a threaded daemon may copy a held lock."""
    global _EXECUTOR
    if not on:
        yield
        return
    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
    _EXECUTOR = pool
    try:
        yield
    finally:
        _EXECUTOR = None
        pool.shutdown(wait=False, cancel_futures=True)


def _discover(*args: Any) -> tuple[Any, float | None]:
    """`discovery.discover_pipeline` on all but the last argument, and the held-out RMS (mg)
    of the last, the live (model, p) (None: none), on the same windows, blocks and scored
    windows: whether the selection predicts better than what is in force."""
    # imported here, not at the top: a node that never reaches a run (a short stream, a
    # replay of minutes) does not load discovery's modules (~15 ms)
    from recal.core import discovery
    from recal.core.model_fit import score_heldout

    *run_args, live = args
    res = discovery.discover_pipeline(*run_args)
    if live is None:
        return res, None
    model, p = live
    n = int(res.blocks.max()) + 1
    sc = score_heldout(model, res.data, res.blocks, [p] * n, p, res.config.fit())
    xi = sc.heldout_xi[res.scored]
    return res, 1e3 * float(np.sqrt(np.mean(xi**2))) if len(xi) else None


class Rediscovery:
    """One effect-discovery run on a copy of a node's evidence, in a daemon thread or in
    ``executor`` (a process pool: a run then never holds the node's interpreter); `result`
    waits for it. ``model_names``: the parameters of the live model when it started."""

    def __init__(self, started_us: int, due_us: int, model_names: tuple[str, ...]) -> None:
        self.started_us = started_us
        self.due_us = due_us
        self.model_names = model_names
        self._done = threading.Event()
        self._result: Any = None
        self._future: Any = None

    @classmethod
    def start(cls, sensor_id: str, args: tuple, started_us: int, due_us: int,
              model_names: tuple[str, ...], executor: Executor | None = None) -> Rediscovery:
        run = cls(started_us, due_us, model_names)
        if executor is not None:
            run._future = executor.submit(_discover, *args)
            return run

        def work() -> None:
            try:
                run._result = _discover(*args)
            except Exception as exc:  # reported as discovery_failed: the waiter must wake
                run._result = _failed(sensor_id, exc)
            finally:
                run._done.set()

        threading.Thread(target=work, name=f"recal-discover-{sensor_id}", daemon=True).start()
        return run

    def result(self) -> Any:
        """The `DiscoveryResult`, or the exception the run raised."""
        if self._future is not None:
            try:
                return self._future.result()
            except Exception as exc:
                return _failed("", exc)
        self._done.wait()
        return self._result


def _failed(sensor_id: str, exc: Exception) -> Exception:
    if not isinstance(exc, (ValueError, np.linalg.LinAlgError)):
        log.error("rediscovery of %s failed: %s: %s", sensor_id, type(exc).__name__, exc)
    return exc


class RediscoverySchedule:
    """When a node reruns discovery (`RediscoveryConfig`): a slot every ``first_h`` after the
    stream's origin for FIRST_SLOTS slots (the first hour at the defaults), then each time the
    evidence has doubled in time, the gap at most ``every_h``; at a slot a run starts if the
    evidence holds ``min_windows`` (else the slot passes; without an estimate, a bootstrap
    that has not found one, the run starts from the windows alone); one run at
    a time, its result taken ``adopt_after_s`` device seconds after it started. Only device
    times decide: a replay starts and adopts each run at the same sample as the live node.

    ``next_us``: the device time of the next slot (None: from the stream's origin);
    ``gap_us``: the gap that led to it.
    """

    def __init__(self, cfg: RediscoveryConfig, next_us: int | None = None,
                 gap_us: int | None = None, executor: Executor | None = None) -> None:
        self.cfg = cfg
        self.next_us = next_us
        self.gap_us = gap_us if gap_us is not None else round(cfg.first_h * 3.6e9)
        self.executor = executor
        self.run: Rediscovery | None = None  # a run going on

    @property
    def due_us(self) -> int | None:
        """The next slot as a checkpoint keeps it: a run still going is not saved, it is due
        again at once on restart (its slot's time)."""
        return self.run.started_us if self.run is not None else self.next_us

    def stop_us(self) -> int | None:
        """The next device time at which the schedule may change the pipeline or start a
        run (a pending run's adoption, else the next slot): a joined step ends there."""
        if not self.cfg.active:
            return None
        return self.run.due_us if self.run is not None else self.next_us

    def start_at(self, origin_us: int) -> None:
        """The first slot, from the stream's origin, unless a checkpoint gave one."""
        if self.next_us is None:
            self.next_us = origin_us + round(self.cfg.first_h * 3.6e9)

    def confirm_soon(self, t_us: int) -> None:
        """A selection waits for the next run's word: that run comes a quarter of the gap
        after ``t_us`` (at least first_h), not a whole doubled gap later (hours, while sigma
        carries the doubt); the evidence has grown by then, and only device time decides."""
        if self.next_us is None:
            return
        soon = t_us + max(round(self.cfg.first_h * 3.6e9), self.gap_us // 4)
        self.next_us = min(self.next_us, soon)

    def poll(self, sensor_id: str, last_t_us: int, evidence: EvidenceStore,
             start: tuple[SensorModel, SensorModel, Estimate | None, tuple[str, ...], int]
             ) -> Rediscovery | None:
        """After a batch ending at ``last_t_us``: start a run when a slot has come (on a copy
        of ``evidence``; ``start``: the configured model, the model in force, the estimate in
        force, the aux channels and the time origin); the run whose result is to be adopted
        now, else None."""
        cfg = self.cfg
        if not cfg.active or self.next_us is None:
            return None
        base, model, estimate, aux_names, origin_us = start
        if self.run is not None:
            if last_t_us >= self.run.due_us:
                run, self.run = self.run, None
                return run
            return None  # one run at a time
        if last_t_us < self.next_us:
            return None
        every_us, first_us = round(cfg.every_h * 3.6e9), round(cfg.first_h * 3.6e9)
        # every first_h for the first hour (FIRST_SLOTS of them), then as the evidence
        # doubles in time, the gap at most every_h
        age = self.next_us - origin_us
        self.gap_us = min(first_us if age < FIRST_SLOTS * first_us else max(age, first_us),
                          every_us)
        self.next_us = max(self.next_us + self.gap_us, last_t_us + 1)
        if len(evidence) < cfg.min_windows:
            return None
        self.run = Rediscovery.start(sensor_id, _run_args(evidence, base, model, estimate,
                                                          aux_names, origin_us, cfg.blocks),
                                     last_t_us, last_t_us + round(cfg.adopt_after_s * 1e6),
                                     model.names, self.executor or _EXECUTOR)
        if cfg.adopt_after_s <= 0:
            run, self.run = self.run, None
            return run
        return None


def _run_args(evidence: EvidenceStore, base: SensorModel, model: SensorModel,
              estimate: Estimate | None, aux_names: tuple[str, ...], t0_us: int, blocks: int
              ) -> tuple:
    """`discovery.discover_pipeline`'s arguments: the evidence's windows, the configured
    model at the live scale, its values carried from the estimate in force (none: the
    bootstrap's own start from the windows, `model_fit.start_params`)."""
    from recal.core.candidates import KIND_ORDER
    from recal.core.discovery import DiscoveryConfig
    from recal.core.model_fit import carry_params

    start = SensorModel(base.effects, model.s0, base.spreads)
    p = (None if estimate is None
         else carry_params(model, np.asarray(estimate.p, np.float64), start))
    kinds = KIND_ORDER if evidence.cells() >= MIN_CELLS else tuple(
        k for k in KIND_ORDER if k not in ORIENTED_KINDS)
    live = (None if estimate is None
            else (model, np.asarray(estimate.p, np.float64).copy()))
    return (evidence.windows(), aux_names, t0_us, start, p,
            DiscoveryConfig(blocks=blocks, kinds=kinds), live)


#: Runs whose detail a node keeps for its summary (18 a day at the defaults: four weeks); a
#: daemon that runs for months keeps the newest, nothing grows with time.
RUNS_KEPT = 512


class NodeDiscovery:
    """A node's discovery part: the evidence (`core.evidence`, from the pipeline's start while
    discovery is on), the schedule, and what each run gave (``runs``: its event's detail and
    device time, the newest RUNS_KEPT). The node calls `step` after each batch; it adopts a
    run's model into the pipeline and says so (event "discovery", a console note)."""

    def __init__(self, cfg: RediscoveryConfig, events: NodeEvents,
                 executor: Executor | None = None) -> None:
        self.schedule = RediscoverySchedule(cfg, executor=executor)
        self.events = events
        self.evidence: EvidenceStore | None = None
        self.runs: deque[dict[str, Any]] = deque(maxlen=RUNS_KEPT)
        #: the effects the last run selected beyond the configured model, while they differ
        #: from those in force: the next run must select them again to have them adopted
        self.pending: tuple[str, ...] | None = None

    def start(self, pipe: Pipeline) -> None:
        cfg = self.schedule.cfg
        if cfg.active and self.evidence is None:
            self.evidence = EvidenceStore(EvidenceConfig(cfg.capacity), len(pipe.aux_names))

    def state(self) -> dict[str, Any] | None:
        """What the checkpoint keeps: the schedule's gap and the evidence."""
        if self.evidence is None:
            return None
        return {"gap_us": self.schedule.gap_us, "evidence": self.evidence.to_dict(),
                "pending": None if self.pending is None else list(self.pending)}

    def restore(self, next_us: int | None, gap_us: int | None,
                evidence: EvidenceStore | None, pending: tuple[str, ...] | None = None
                ) -> None:
        self.pending = pending
        self.schedule.next_us = next_us
        if gap_us is not None:
            self.schedule.gap_us = gap_us
        if evidence is not None and self.evidence is not None:
            self.evidence = evidence

    def resume(self, doc: dict[str, Any]) -> None:
        """Continue from a setup message's ``discovery_json`` (`state` and ``next_us``); what
        does not read leaves the part as it is (a replay then starts its evidence anew)."""
        try:
            ev = doc.get("evidence")
            evidence = EvidenceStore.from_dict(ev) if isinstance(ev, dict) else None
            if (evidence is not None and self.evidence is not None
                    and evidence.aux.shape[1] != self.evidence.aux.shape[1]):
                raise ValueError("its evidence has other channels than the stream")
            pending = doc.get("pending")
            nxt, gap = doc.get("next_us"), doc.get("gap_us")
            self.restore(int(nxt) if isinstance(nxt, int) else None,
                         int(gap) if isinstance(gap, int) and gap > 0 else None, evidence,
                         tuple(map(str, pending)) if isinstance(pending, list) else None)
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("a setup's discovery state does not read: %s", exc)

    def stop_us(self, pipe: Pipeline) -> int | None:
        """Where a joined step must end (`RediscoverySchedule.stop_us`; None: anywhere)."""
        if self.evidence is None or pipe.t0_us is None:
            return None
        self.schedule.start_at(pipe.t0_us)
        return self.schedule.stop_us()

    def step(self, pipe: Pipeline, out: StepOutput, base: SensorModel, t_us: int,
             log_ns: int) -> bool:
        """After a batch ending at ``t_us``: its windows into the evidence, a run started or
        taken on when due. True when the pipeline took on another model."""
        evidence = self.evidence
        if evidence is None:
            return False
        if out.windows is not None:
            evidence.add(out.windows)
        if pipe.t0_us is None:
            return False
        self.schedule.start_at(pipe.t0_us)
        model = out.model if out.model is not None else pipe.model
        run = self.schedule.poll(self.events.sensor_id, t_us, evidence,
                                 (base, model, out.estimate, pipe.aux_names, pipe.t0_us))
        return run is not None and self._take(pipe, run, t_us, log_ns)

    def _take(self, pipe: Pipeline, run: Rediscovery, t_us: int, log_ns: int) -> bool:
        """A run's result: the model it selected from the configured one becomes the live one
        (its fitted values the estimate) when its effects differ from those in force and
        the run before selected the same effects (two runs on growing evidence agree: an
        effect one run's few windows favour by chance, or a form a few postures cannot tell
        from another, is not taken on); an event "discovery" either way (the effects it
        would add and drop, whether it was adopted, the held-out error before and after), a
        console note when adopted."""
        got = run.result()  # waits if it is still running (a replay gets here sooner)
        if isinstance(got, Exception):
            res = got
        else:
            res, live_mg = got
        if isinstance(res, Exception):
            self.events.event("discovery_failed", t_us, log_ns,
                              {"error": str(res), "started_t_us": run.started_us})
            return False
        now = {e.label: e.key for e in pipe.model.effects}
        found = {e.label: e.key for e in res.model.effects}
        added = [lb for lb, k in found.items() if k not in now.values()]
        dropped = [lb for lb, k in now.items() if k not in found.values()]
        # a selection the model in force predicts as well on the same held-out windows is no
        # reason to change (a run's search from the configured model can end elsewhere)
        worse = live_mg is not None and (added or dropped) and (
            res.heldout_final_mg >= live_mg)
        if worse:
            added, dropped = [], []
        chosen = tuple(sorted(found))
        agreed = self.pending == chosen
        self.pending = chosen if (added or dropped) else None
        adopt = bool(added or dropped) and agreed and pipe.model.names == run.model_names
        detail = {
            "effects_selected": [e.label for e in res.selected],
            "added": added, "dropped": dropped, "adopted": adopt,
            "pending": bool(added or dropped) and not adopt,
            "steps": [f"{s.action} {s.effect.label}" for s in res.steps],
            "heldout_error_mg": {"base": res.heldout_base_mg, "final": res.heldout_final_mg},
            "heldout_live_mg": live_mg, "not_better": bool(worse),
            "windows": len(res.data), "started_t_us": run.started_us,
            "model": model_name(res.model)}
        self.events.event("discovery", t_us, log_ns, detail)
        self.runs.append({"t_us": t_us, **detail})
        if not adopt:
            # a selection waiting for the next run's word widens sigma where it disagrees
            # with the model in force (`core.pending`); none: nothing waits
            waits = (added or dropped) and res.model.s0 == pipe.model.s0
            pipe.set_pending(PendingCandidate(res.model, np.asarray(res.p, np.float64),
                                              np.asarray(res.cov, np.float64),
                                              "+".join(added)) if waits else None)
            if waits:
                self.schedule.confirm_soon(t_us)
            return False
        self.pending = None
        pipe.adopt(res.model, res.prior, res.cov, self.evidence.windows())
        what = ", ".join([f"added {lb}" for lb in added] + [f"dropped {lb}" for lb in dropped])
        self.events.note(f"discovery: {what} (held-out error {res.heldout_base_mg:.2f} -> "
                         f"{res.heldout_final_mg:.2f} mg on {len(res.data)} windows)")
        return True
