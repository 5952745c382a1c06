"""What a node publishes per sample: the last guard before the wire, the counts by status, and
the status lines (``status_changed`` events and notes)."""

from __future__ import annotations

import math

import numpy as np

from recal.core.pipeline import Pipeline
from recal.core.status import NOT_FINITE_SIGMA_MG, Status
from recal.node.events import NodeEvents
from recal.samples import CalibratedBatch

__all__ = ["UNSEEN_SAY_UPDATES", "Published"]

#: Updates over which the same parameters stay unobserved before the console says so.
UNSEEN_SAY_UPDATES = 10


def _finite_one(a_g: np.ndarray, sigma_mg: float) -> bool:
    """Whether one sample's three values are finite and its sigma finite or inf (what
    `Published.admit` lets through unchanged), with scalar checks."""
    x, y, z = a_g.tolist()
    s = float(sigma_mg)
    return (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
            and not math.isnan(s))


class Published:
    """The samples a node published: guarded (`admit`), counted per status, and the status
    changes said (`report`)."""

    def __init__(self, events: NodeEvents) -> None:
        self.events = events
        self.samples = 0
        # samples published per status (`core.status.Status`), and those zeroed (not finite)
        self.status_counts = np.zeros(len(Status), np.int64)
        self.samples_not_finite = 0
        self._status: Status | None = None  # of the last sample published
        self._said: Status | None = None  # the status the console last named
        self._unseen: tuple[tuple[str, ...], int, bool] = ((), 0, False)  # `_say_unseen`

    def by_status(self) -> dict[str, int]:
        """Samples published so far per status label (only the statuses seen)."""
        return {Status(i).label: int(n) for i, n in enumerate(self.status_counts.tolist()) if n}

    def admit(self, cal: CalibratedBatch, log_ns: int) -> CalibratedBatch:
        """``cal`` as it may be published (`_guard`), counted."""
        cal = self._guard(cal, log_ns)
        self.samples += len(cal)
        if len(cal) == 1:  # one sample per arrival: a scalar count, no histogram
            self.status_counts[int(cal.status[0])] += 1
        else:
            self.status_counts += np.bincount(cal.status, minlength=len(Status))[:len(Status)]
        return cal

    def _guard(self, cal: CalibratedBatch, log_ns: int) -> CalibratedBatch:
        """The last guard before the wire: a calibrated value that is not finite is never
        published. Its sample goes out as (0, 0, 0) g, status uncalibrated, sigma inf: a
        consumer that reads the status, or weighs by 1/sigma^2, cannot take it for data (NaN
        would be read by many as "missing", zeros alone as a vector). Counted, and said once
        per batch as an event. A non-finite sigma of a finite value is inf."""
        a = cal.a_g
        if len(a) == 1 and _finite_one(a[0], cal.sigma_mg[0]):
            return cal  # one sample per arrival, the usual case: scalar checks, no arrays
        bad = ~(np.isfinite(a[:, 0]) & np.isfinite(a[:, 1]) & np.isfinite(a[:, 2]))
        bad_sigma = ~np.isfinite(cal.sigma_mg) & ~np.isinf(cal.sigma_mg)
        if not bad.any() and not bad_sigma.any():
            return cal
        a, status, sigma = a.copy(), cal.status.copy(), cal.sigma_mg.copy()
        sigma[bad_sigma] = NOT_FINITE_SIGMA_MG
        n = int(bad.sum())
        if n:
            a[bad] = 0.0
            status[bad] = Status.UNCALIBRATED
            sigma[bad] = NOT_FINITE_SIGMA_MG
            self.samples_not_finite += n
            self.events.event("not_finite", int(cal.t_us[np.argmax(bad)]), log_ns, {
                "samples": n, "published_as": "zeros, status uncalibrated, sigma_mg inf",
                "total": self.samples_not_finite})
        return CalibratedBatch(cal.t_us, a, cal.quasi_static, cal.detector_g, status, sigma,
                               cal.t_dev)

    def report(self, cal: CalibratedBatch, log_ns: int, pipe: Pipeline | None) -> None:
        """One line (a note) and an event ``status_changed`` when the status becomes or stops
        being suspect, and when the sensor is calibrated where the last line named another
        status (first, or after a suspect status that cleared to held)."""
        st = cal.status
        first_new = int(st[0]) != self._status
        if len(st) == 1:  # one sample per arrival: nothing within the batch to compare
            points = [0] if first_new else []
        else:
            change = np.flatnonzero(st[1:] != st[:-1]) + 1
            points = ([0] if first_new else []) + change.tolist()
        for i in points:
            old, new = self._status, Status(int(st[i]))
            self._status = new
            first = new == Status.CALIBRATED and self._said != Status.CALIBRATED
            if not (first or new == Status.SUSPECT or old == Status.SUSPECT):
                continue
            self._said = new
            why = (" (the still windows contradict the calibration: re-fitting)"
                   if new == Status.SUSPECT else "")
            self.events.event("status_changed", int(cal.t_us[i]), log_ns, {
                "status": new.label, "was": old.label if old is not None else None})
            self.events.note(f"{new.label}{why}")
        self._say_unseen(pipe)

    def _say_unseen(self, pipe: Pipeline | None) -> None:
        """One line when the data leave the same offsets or scales unobserved over
        UNSEEN_SAY_UPDATES updates (status held for it; a start learns them in fewer)."""
        if pipe is None:
            return
        unseen, updates = pipe.unobserved, int(pipe.counts["updates"])
        if unseen != self._unseen[0]:
            self._unseen = (unseen, updates, False)
        elif (unseen and not self._unseen[2]
              and updates - self._unseen[1] >= UNSEEN_SAY_UPDATES):
            self._unseen = (unseen, self._unseen[1], True)
            self.events.note(f"held: {', '.join(unseen)} not observed by the data (sigma "
                             "carries the prior's uncertainty on it)")
