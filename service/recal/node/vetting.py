"""The checks a node runs on every state its pipeline takes on (the restore checks of
`recal.node.checkpoint_doc`), so that it never holds a state it could not save."""

from __future__ import annotations

import copy
from typing import Any

from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.node.checkpoint_doc import estimate_problem
from recal.node.events import NodeEvents, decade_reached

__all__ = ["EstimateVet"]


class EstimateVet:
    """The last state whose model, estimate and prior passed the restore checks, which (by
    identity) were checked last, and how many were refused.

    Args:
        reference: the configured model and prior (the bounds' centre, and the start a
            refusal goes back to when no state passed yet).
        events: where ``estimate_refused`` events and notes go.
    """

    def __init__(self, reference: tuple[SensorModel, Prior | None], events: NodeEvents
                 ) -> None:
        self.reference = reference
        self.events = events
        self._good: Pipeline | None = None
        self._vetted: tuple[Any, Any, Any] | None = None
        self.refused = 0

    def check(self, pipe: Pipeline, t_us: int, log_ns: int) -> Pipeline | None:
        """Whatever the pipeline took on (a bootstrap, a reset, a new zero-g and scale, a
        rediscovered model) must pass the checks its checkpoint meets at the next start
        (`estimate_problem`, bounds around the configured zero-g): a stream no sensor of this
        configuration sends (a crafted one) cannot move the node there. Refused: the pipeline
        to go back to (the last state that passed, else the configured start), an event
        ``estimate_refused`` and a line; None: ``pipe`` may stay. Runs the checks when the
        model, estimate or prior changed (by identity), not per batch."""
        vetted = self._vetted
        if (vetted is not None and pipe.model is vetted[0] and pipe.estimate is vetted[1]
                and pipe.prior is vetted[2]):
            return None  # (every arrival: three identity checks)
        now = (pipe.model, pipe.estimate, pipe.prior)
        model, prior = self.reference
        why = estimate_problem(pipe, self.reference)
        if why is None:
            self._vetted, self._good = now, copy.deepcopy(pipe)
            return None
        back = (copy.deepcopy(self._good) if self._good is not None
                else Pipeline(pipe.cfg, model, prior, pipe.aux_names))
        back.counts = dict(pipe.counts)  # totals of what happened, refused or not
        self._vetted = (back.model, back.estimate, back.prior)
        self.refused += 1
        to = "the last good state" if self._good is not None else "the configured start"
        if decade_reached(self.refused, 1):
            self.events.event("estimate_refused", t_us, log_ns, {
                "reason": why, "back_to": to, "refused": self.refused})
            self.events.note(f"calibration refused ({why}): no sensor of this configuration "
                             f"gives it; back to {to} ({self.refused} refused in all)")
        return back
