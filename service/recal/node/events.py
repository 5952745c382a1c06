"""Where a node's parts say things: events on the sink's ``events`` topic, one-line notes.

Every part of a :class:`recal.node.node.CalibrationNode` (alignment, device time, the
published samples' guard and status, the estimate checks, the channel layout) reports through
one :class:`NodeEvents`, so the message's shape and the note's destination live here once.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from recal.node.sinks import Sink

__all__ = ["NodeEvents", "decade_reached"]


def decade_reached(total: int, latest: int) -> bool:
    """Whether ``total`` reached 1, 10, 100, ... with its ``latest`` additions."""
    before = total - latest
    return before <= 0 or len(str(total)) > len(str(before))


class NodeEvents:
    """A sensor's events (``sink.json(sensor_id, "events", ...)``) and notes.

    ``on_note``: where the operator's one-line notes go (the gateway's or node's console,
    prefixed with the sensor id): time units, reboots, first calibrated, suspect and back;
    None: the log only (replay).
    """

    def __init__(self, sensor_id: str, sink: Sink) -> None:
        self.sensor_id = sensor_id
        self.sink = sink
        self.on_note: Callable[[str], None] | None = None

    def event(self, kind: str, t_us: int | None, log_ns: int, detail: Any) -> None:
        self.sink.json(self.sensor_id, "events", {"t_us": t_us, "kind": kind,
                                                  "sensor_id": self.sensor_id,
                                                  "detail": detail}, log_ns)

    def note(self, line: str) -> None:
        if self.on_note is not None:
            self.on_note(line)
