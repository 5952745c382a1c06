"""A node's device time: each batch on the time base (`recal.core.timebase`), its events said.

Device time goes through the time base right before ``Pipeline.step`` (unwrapped, units,
reboots; never backwards), where the live node and replay both pass: the raw log keeps the
device's values, the calibrated output has the time base's (docs/design.md, device time).
"""

from __future__ import annotations

from typing import Any

from recal.core import timebase as tb
from recal.core.pipeline import Pipeline
from recal.node.events import NodeEvents, decade_reached
from recal.samples import RawBatch

__all__ = ["ANOMALY_EVENT_US", "DeviceClock"]

ANOMALY_EVENT_US = 60_000_000  # time_anomalies events at most this often (device time)


class DeviceClock:
    """The time base of one device's clock (``state``: None until the rate is known) and the
    rules for saying what it finds (events and notes)."""

    def __init__(self, events: NodeEvents, state: tb.TimebaseState | None = None) -> None:
        self.events = events
        self.state = state
        self._tcfg: tb.TimebaseConfig | None = None  # the time base's, per rate
        self._anomalies_said_us = -ANOMALY_EVENT_US  # device time of the last time_anomalies

    def apply(self, batch: RawBatch, log_ns: int, pipe: Pipeline) -> RawBatch:
        """The batch on the time base, its events reported (a reboot doubts ``pipe``)."""
        assert self.state is not None
        tcfg = self._config(pipe.cfg.rate_hz)
        unit_events: list[dict[str, Any]] = []
        if self.state.last_dev is None:  # the stream's first batch: say how time is read
            first, unit_events = tb.start(batch.t_us, tcfg)
            if first.unit_us != self.state.unit_us:
                unit_events = []
        self.state, t_us, events = tb.step(self.state, batch.t_us, tcfg)
        for ev in [*unit_events, *events]:
            self._time_event(ev, int(t_us[ev["index"]]), log_ns, pipe)
        if t_us is batch.t_us:  # the device's own microseconds (the time base's usual case)
            return batch
        return RawBatch(t_us, batch.v, batch.aux, batch.aux_names)

    def _config(self, rate_hz: float | None) -> tb.TimebaseConfig:
        # made once per rate, not per arrival (a frozen dataclass: building it is most of
        # what a one-sample batch costs the time base)
        cached = self._tcfg
        if cached is None or cached.rate_hz != rate_hz:
            cached = self._tcfg = tb.TimebaseConfig(rate_hz=rate_hz)
        return cached

    def _time_event(self, ev: dict[str, Any], t_us: int, log_ns: int, pipe: Pipeline) -> None:
        if ev["kind"] == "time_anomalies":
            # a millisecond clock above 1 kHz repeats every other stamp: one event a device
            # minute at most, with the totals (so a replay says the same)
            if t_us < self._anomalies_said_us + ANOMALY_EVENT_US:
                return
            self._anomalies_said_us = t_us
        d = ev["detail"]
        if ev["kind"] == "time_jump_refused" and not decade_reached(d["refused"],
                                                                     d["in_batch"]):
            return  # a clock that jumps on every batch: said at 1, 10, 100, ... in all
        self.events.event(ev["kind"], t_us, log_ns, d)
        note = None
        if ev["kind"] == "time_units":
            note = (f"device time is in {d['unit']}, not microseconds (as microseconds it "
                    f"implies {d['implied_rate_hz_as_us']:.0f} Hz; read as {d['unit']}: "
                    f"{d['rate_hz']:.4g} Hz)")
        elif ev["kind"] == "time_implausible":
            note = (f"device time implies {d['implied_rate_hz']:.4g} Hz, outside "
                    f"{d['min_rate_hz']:g}-{d['max_rate_hz']:g} Hz in any unit: check the "
                    "time column")
        elif ev["kind"] == "time_reboot":
            pipe.doubt()  # a reboot, or another device: windows must agree
            note = (f"device time restarted ({d['device_before']} -> {d['device_after']} "
                    f"{d['unit']}): the device rebooted; output time continues")
        elif ev["kind"] == "time_jump_refused":
            note = (f"device time jumped {d['jump_s'] / 86_400:+.4g} days ({d['device_before']}"
                    f" -> {d['device_after']} {d['unit']}), beyond the {d['limit_s'] / 86_400:g}"
                    f" day a clock plausibly does: not taken as time, output time continues "
                    f"({d['refused']} such jump{'s' if d['refused'] > 1 else ''} in all)")
        if note is not None:
            self.events.note(note)
