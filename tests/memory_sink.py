"""A node's sink that keeps what it is given in memory, per topic (a real Sink, not a mock):
the tests that watch a `recal.node.node.CalibrationNode` share it."""

from __future__ import annotations

from typing import Any

import numpy as np

from recal.io import messages
from recal.samples import CalibratedBatch, RawBatch


class MemorySink:
    """Keeps the calibrated and body batches, the events, calibration states and setup
    messages a node produces (raw and plot are dropped). ``wire``: each calibrated batch is
    kept as a subscriber gets it, encoded for the bus and decoded again."""

    def __init__(self, wire: bool = False) -> None:
        self.wire = wire
        self.cal: list[CalibratedBatch] = []
        self.body: list[CalibratedBatch] = []
        self.events: list[dict[str, Any]] = []
        self.states: list[dict[str, Any]] = []
        self.setup: list[dict[str, Any]] = []

    def raw(self, sensor_id: str, batch: RawBatch, log_time_ns: int) -> None:
        pass

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        if suffix == "calibrated":
            if self.wire:  # the bytes a subscriber gets, read back
                batch = messages.decode_calibrated(messages.encode_calibrated(sensor_id,
                                                                              batch))[1]
            self.cal.append(batch)
        elif suffix == "body":
            self.body.append(batch)

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        pass

    def json(self, sensor_id: str, suffix: str, obj: dict[str, Any], log_time_ns: int) -> None:
        kept = {"events": self.events, "calibration": self.states, "setup": self.setup}
        if suffix in kept:
            kept[suffix].append(obj)

    def kinds(self) -> list[str]:
        """The events' kinds, in order."""
        return [e["kind"] for e in self.events]

    def all(self) -> CalibratedBatch:
        """The calibrated batches joined."""
        return CalibratedBatch.concat(self.cal)

    def joined(self) -> tuple[np.ndarray, np.ndarray]:
        """(t_us, a_g) of the calibrated batches joined."""
        return (np.concatenate([c.t_us for c in self.cal]),
                np.concatenate([c.a_g for c in self.cal]))
