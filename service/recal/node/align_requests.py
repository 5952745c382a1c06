"""Alignment on request (``recal/<sensor>/align``), at most one per interval per sensor.

A query on a sensor's align key makes its node align at once on the current still run, or arm
the next one as the mounting reference. Anyone who may query the key could otherwise reset the
reference at will, so requests within ``[alignment] request_interval_s`` of the last accepted
one are refused and counted, with one event and one console line per interval (a flood of
queries floods neither). The tilt math: `recal.core.alignment`; the alarm: docs/design.md.

Alignment (Zheng et al. sec. II.B): the reference posture is the first quasi-static run of
``min_still_s`` (10 s) within ``upright_max_deg`` of +z, after at least one accepted update;
a query on ``recal/<sensor>/align`` aligns at once on the current still run (if it lasted
``request_min_s``) or arms the next run of ``min_still_s`` as the reference. Every later
still run of ``min_still_s`` is checked for a slip of the mounting (``tilt_alarm`` and
``tilt_cleared`` events; the rule is ``recal.core.alignment.SlipWatch``'s).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from recal.core import alignment as al
from recal.io import messages

__all__ = ["ALIGN_NOTE_PREFIX", "AlignmentRequests", "align_handler"]

ALIGN_NOTE_PREFIX = "recal node:"  # the align query's console lines, unless told otherwise


class AlignmentRequests:
    """The request side of a :class:`recal.node.node.CalibrationNode` (a mixin: it uses the node's
    lock, settings, still-run tracker, events and ``_set_alignment``)."""

    sensor_id: str
    settings: Any  # recal.node.node.NodeSettings
    last_t_us: int | None
    _lock: threading.RLock
    _tracker: al.StillTracker | None
    _align_requested: bool
    _last_align_request_s: float | None  # monotonic time of the last accepted
    align_refused: int  # requests refused by the rate limit, in all
    _refused_unreported: int  # ... since the last align_refused event

    def _event(self, kind: str, t_us: int | None, log_ns: int, detail: Any) -> None:
        raise NotImplementedError

    def _set_alignment(self, mean: Any, n: int, t_us: int | None, source: str,
                       log_ns: int) -> al.Alignment:
        raise NotImplementedError

    def request_alignment(self, log_time_ns: int | None = None,
                          now_s: float | None = None) -> dict[str, Any]:
        """Align now on the current still run if it is long enough, else arm the next one.

        Returns ``{"status": "aligned", "alignment": {...}}`` or ``{"status": "armed", ...}``,
        or ``{"status": "refused", "retry_after_s": ...}`` within ``[alignment]
        request_interval_s`` of the last request accepted (``now_s``: a monotonic clock,
        default ``time.monotonic()``). Why: anyone who may query the key could otherwise
        reset the mounting reference at will. Accepted requests are events
        ``align_request``; refusals are counted and reported as ``align_refused`` events, at
        most one per interval (a flood of queries must not flood the log).
        """
        log_ns = time.time_ns() if log_time_ns is None else log_time_ns
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            wait_s = self._align_wait_s(now)
            if wait_s > 0:
                return self._refuse_alignment(wait_s, log_ns)
            self._last_align_request_s = now
            reply = self._accept_alignment(log_ns)
            self._event("align_request", self.last_t_us, log_ns, {
                "status": reply["status"], "refused_before": self._refused_unreported})
            self._refused_unreported = 0
            return reply

    def _align_wait_s(self, now_s: float) -> float:
        """Seconds until an alignment request may be accepted again (0: now)."""
        last = self._last_align_request_s
        if last is None:
            return 0.0
        return max(0.0, last + self.settings.alignment.request_interval_s - now_s)

    def _refuse_alignment(self, wait_s: float, log_ns: int) -> dict[str, Any]:
        self.align_refused += 1
        self._refused_unreported += 1
        if self._refused_unreported == 1:  # the first refusal of this interval
            self._event("align_refused", self.last_t_us, log_ns, {
                "retry_after_s": wait_s,
                "interval_s": self.settings.alignment.request_interval_s,
                "refused_total": self.align_refused})
        return {"status": "refused", "sensor_id": self.sensor_id,
                "retry_after_s": round(wait_s, 3), "refused": self._refused_unreported,
                "detail": f"at most one alignment request per "
                          f"{self.settings.alignment.request_interval_s:g} s"}

    def _accept_alignment(self, log_ns: int) -> dict[str, Any]:
        tr = self._tracker
        if tr is not None and tr.duration_s >= self.settings.request_min_s:
            mean = tr.mean()
            if mean is not None:
                ali = self._set_alignment(mean, tr.n, self.last_t_us, "request", log_ns)
                return {"status": "aligned", "sensor_id": self.sensor_id,
                        "alignment": ali.to_dict()}
        self._align_requested = True
        if tr is not None:
            tr.rearm()
        return {"status": "armed", "sensor_id": self.sensor_id,
                "detail": f"aligns on the next still period of "
                          f"{self.settings.alignment.min_still_s:g} s",
                "still_s": tr.duration_s if tr else 0.0}


def align_handler(node: AlignmentRequests, out: Callable[[str], None],
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
