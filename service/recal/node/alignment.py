"""A node's mounting alignment: the reference posture, the slip alarm, and requests for it.

Alignment (Zheng et al. sec. II.B): the reference posture is the first quasi-static run of
``min_still_s`` (10 s) within ``upright_max_deg`` of +z, after at least one accepted update;
a query on ``recal/<sensor>/align`` aligns at once on the current still run (if it lasted
``request_min_s``) or arms the next run of ``min_still_s`` as the reference. Every later
still run of ``min_still_s`` is checked for a slip of the mounting (``tilt_alarm`` and
``tilt_cleared`` events; the rule is ``recal.core.alignment.SlipWatch``'s).

Requests: anyone who may query the key could otherwise reset the reference at will, so
requests within ``[alignment] request_interval_s`` of the last accepted one are refused and
counted, with one event and one console line per interval (a flood of queries floods
neither). The tilt math: `recal.core.alignment`; the alarm: docs/design.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from recal.config.settings import AlignmentConfig
from recal.core import alignment as al
from recal.core.outputs import StepOutput
from recal.core.pipeline import Pipeline
from recal.io import messages
from recal.node.events import NodeEvents
from recal.samples import CalibratedBatch

__all__ = ["ALIGN_NOTE_PREFIX", "Aligner", "align_handler"]

ALIGN_NOTE_PREFIX = "recal node:"  # the align query's console lines, unless told otherwise


class Aligner:
    """One sensor's mounting: the reference (``alignment``), the still-run tracker that finds
    it, the slip watch, and the rate limit on requests. The node holds one and calls it with
    each calibrated batch (`track`) and each request (`request`, under the node's lock).

    Args:
        cfg: reference-posture and tilt-alarm settings.
        request_min_s: a request uses the current still run if it lasted this long.
        events: where events and notes go.
        alignment: a known mounting (from a checkpoint).
    """

    def __init__(self, cfg: AlignmentConfig, request_min_s: float, events: NodeEvents,
                 alignment: al.Alignment | None = None) -> None:
        self.cfg = cfg
        self.request_min_s = request_min_s
        self.events = events
        self.alignment = alignment
        self.tracker: al.StillTracker | None = None
        self._slip: al.SlipWatch | None = None  # the tilt alarm's check of later periods
        self.requested = False
        self._offsets_known: tuple[Any, Any, bool] | None = None  # model, estimate, answer
        self._last_request_s: float | None = None  # monotonic time of the last accepted
        self.refused = 0  # requests refused by the rate limit, in all
        self._refused_unreported = 0  # ... since the last align_refused event

    def start(self, rate_hz: float) -> None:
        """The pipeline runs at ``rate_hz``: still runs can be tracked."""
        self.tracker = al.StillTracker(self.cfg.min_still_s, round(3e6 / rate_hz))

    @property
    def still_s(self) -> float:
        return self.tracker.duration_s if self.tracker else 0.0

    # -- each batch -----------------------------------------------------------------------------

    def track(self, cal: CalibratedBatch, log_ns: int, out: StepOutput, pipe: Pipeline | None,
              accepted_updates: int) -> None:
        """Feed a calibrated batch to the still-run tracker: a reference taken, or a slip
        checked, at each still run it completes."""
        cfg = self.cfg
        if self.tracker is None or not (cfg.enabled or self.requested):
            return
        if self.requested or self.alignment is None:
            armed = (self.requested or not cfg.require_update
                     or (accepted_updates > 0 and self._tilt_offsets_known(out, pipe)))
        else:
            armed = cfg.enabled  # aligned: every later still period is checked for a slip
        for hit in self.tracker.feed(cal.t_us, cal.a_g, cal.quasi_static, armed):
            if self.requested or self.alignment is None:
                self._take_reference(hit, log_ns)
            elif cfg.enabled:
                self._watch_slip(hit, log_ns)

    def _take_reference(self, hit: al.StillHit, log_ns: int) -> None:
        cfg = self.cfg
        if not self.requested and al.tilt_from_z_deg(hit.mean_g) > cfg.upright_max_deg:
            # not upright (lying, or the sensor worn sideways): not a reference posture
            self.events.event("reference_skipped", hit.t_us, log_ns, {
                "tilt_deg": al.tilt_from_z_deg(hit.mean_g),
                "upright_max_deg": cfg.upright_max_deg})
            return
        source = "request" if self.requested else "reference"
        self._set(hit.mean_g, hit.n, hit.t_us, source, log_ns)

    def _watch_slip(self, hit: al.StillHit, log_ns: int) -> None:
        """The tilt alarm (rule and reason in ``recal.core.alignment``): raised when later
        upright still periods agree that the mounting moved beyond the limit, cleared when
        they agree it is back."""
        ali = self.alignment
        assert ali is not None
        if self._slip is None:  # a new reference, or one restored from a checkpoint
            self._slip = al.SlipWatch(ali.gravity_g, ali.limit_deg, alarmed=ali.alarm,
                                      upright_max_deg=self.cfg.upright_max_deg)
        change = self._slip.observe(hit.mean_g, hit.t_us, hit.gap_s)
        if change is None:
            return
        detail = {**change.to_dict(), "limit_deg": ali.limit_deg}
        if change.kind == "slipped":
            self.alignment = replace(ali, moved_deg=change.moved_deg)
            self.events.event("tilt_alarm", change.t_us, log_ns, {**detail, "detail": (
                f"the mounting moved {change.moved_deg:.1f} deg since the reference (limit "
                f"{ali.limit_deg:g} deg; {change.periods} still periods agree): re-seat the "
                f"sensor, or query recal/{self.events.sensor_id}/align to make this the "
                "reference")})
        else:
            self.alignment = replace(ali, moved_deg=None)
            self.events.event("tilt_cleared", change.t_us, log_ns, {**detail, "detail": (
                f"the mounting is back within {ali.limit_deg:g} deg of the reference")})

    def _tilt_offsets_known(self, out: StepOutput, pipe: Pipeline | None) -> bool:
        """Whether the x/y offsets' posterior sd is below ``max_offset_sd_mg`` (tilt error), as
        of the end of the batch ``out`` is of."""
        if pipe is None:
            return True
        model = out.model if out.model is not None else pipe.model
        estimate = out.estimate if out.model is not None else pipe.estimate
        if estimate is None or not model.has("offset"):
            return True  # nothing to wait for
        # asked every batch until a reference is found; it changes only with the estimate
        known = self._offsets_known
        if known is not None and known[0] is model and known[1] is estimate:
            return known[2]
        sl = model.slice(("offset", None))
        sd_mg = np.sqrt(np.diag(estimate.cov)[sl][:2]) / model.s0 * 1e3
        answer = bool(np.all(sd_mg <= self.cfg.max_offset_sd_mg))
        self._offsets_known = (model, estimate, answer)
        return answer

    def _set(self, mean: np.ndarray, n: int, t_us: int | None, source: str,
             log_ns: int) -> al.Alignment:
        ali = al.estimate_alignment(mean, self.cfg.tilt_limit_deg, n, t_us)
        self.alignment = ali
        self._slip = None  # later periods are checked against this reference
        self.requested = False
        self.events.event("alignment", t_us, log_ns, {**ali.to_dict(), "source": source})
        return ali

    @staticmethod
    def body(cal: CalibratedBatch, ali: al.Alignment) -> CalibratedBatch:
        """``cal`` rotated into the body frame of the mounting ``ali``."""
        # a rotation keeps each sample's status and the length of its error (sigma_mg); the
        # other arrays are the calibrated batch's, checked when it was made
        return CalibratedBatch.of_checked(
            cal.t_us, np.ascontiguousarray(al.to_body(ali.rotation, cal.a_g)), cal.quasi_static,
            cal.detector_g, cal.status, cal.sigma_mg, cal.t_dev)

    # -- requests ---------------------------------------------------------------------------

    def request(self, last_t_us: int | None, log_ns: int, now_s: float) -> dict[str, Any]:
        """`recal.node.node.CalibrationNode.request_alignment` (the node holds its lock)."""
        wait_s = self._wait_s(now_s)
        if wait_s > 0:
            return self._refuse(wait_s, last_t_us, log_ns)
        self._last_request_s = now_s
        reply = self._accept(last_t_us, log_ns)
        self.events.event("align_request", last_t_us, log_ns, {
            "status": reply["status"], "refused_before": self._refused_unreported})
        self._refused_unreported = 0
        return reply

    def _wait_s(self, now_s: float) -> float:
        """Seconds until an alignment request may be accepted again (0: now)."""
        last = self._last_request_s
        if last is None:
            return 0.0
        return max(0.0, last + self.cfg.request_interval_s - now_s)

    def _refuse(self, wait_s: float, last_t_us: int | None, log_ns: int) -> dict[str, Any]:
        self.refused += 1
        self._refused_unreported += 1
        if self._refused_unreported == 1:  # the first refusal of this interval
            self.events.event("align_refused", last_t_us, log_ns, {
                "retry_after_s": wait_s,
                "interval_s": self.cfg.request_interval_s,
                "refused_total": self.refused})
        return {"status": "refused", "sensor_id": self.events.sensor_id,
                "retry_after_s": round(wait_s, 3), "refused": self._refused_unreported,
                "detail": f"at most one alignment request per "
                          f"{self.cfg.request_interval_s:g} s"}

    def _accept(self, last_t_us: int | None, log_ns: int) -> dict[str, Any]:
        tr = self.tracker
        sid = self.events.sensor_id
        if tr is not None and tr.duration_s >= self.request_min_s:
            mean = tr.mean()
            if mean is not None:
                ali = self._set(mean, tr.n, last_t_us, "request", log_ns)
                return {"status": "aligned", "sensor_id": sid, "alignment": ali.to_dict()}
        self.requested = True
        if tr is not None:
            tr.rearm()
        return {"status": "armed", "sensor_id": sid,
                "detail": f"aligns on the next still period of {self.cfg.min_still_s:g} s",
                "still_s": tr.duration_s if tr else 0.0}


class AlignsOnRequest(Protocol):
    """What `align_handler` asks of a node."""

    sensor_id: str
    settings: Any  # recal.node.node.NodeSettings

    def request_alignment(self, log_time_ns: int | None = None,
                          now_s: float | None = None) -> dict[str, Any]: ...


def align_handler(node: AlignsOnRequest, out: Callable[[str], None],
                  prefix: str = ALIGN_NOTE_PREFIX) -> Callable[[str, bytes | None], bytes]:
    """The ``recal/<sensor>/align`` queryable's handler: :meth:`CalibrationNode.
    request_alignment`, and a console line for each accepted request and for the first
    refusal of an interval (a flood of queries gives one line, not one per query)."""
    def handle(_key: str, _payload: bytes | None) -> bytes:
        reply = node.request_alignment()
        sid = node.sensor_id
        if reply["status"] != "refused":
            out(f"{prefix} {sid}: alignment requested on the bus ({reply['status']})")
        elif reply.get("refused") == 1:
            out(f"{prefix} {sid}: alignment request refused: at most one per "
                f"{node.settings.alignment.request_interval_s:g} s (next in "
                f"{reply['retry_after_s']:.0f} s); further refusals are counted in status")
        return messages.encode_json(reply)

    return handle
