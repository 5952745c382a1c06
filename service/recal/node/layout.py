"""A node's stream before the pipeline: samples held until the rate is known, and each
batch fitted to the channel layout the pipeline was built with."""

from __future__ import annotations

from dataclasses import replace

from recal.core import timebase as tb
from recal.core.channels import unnamed_for
from recal.core.model import SensorModel
from recal.core.rate import infer_rate_hz
from recal.node.events import NodeEvents
from recal.samples import RawBatch, conform_channels

__all__ = ["DEFAULT_RATE_HZ", "UNIT_SAMPLES", "ChannelLayout", "RateHold"]

DEFAULT_RATE_HZ = 100.0  # only when a stream ends before its rate could be measured
# samples the clock's unit is read from when the rate is configured: the median of 7 steps
# (a repeated stamp or a wrap among the first two would decide it alone)
UNIT_SAMPLES = 8


class RateHold:
    """Samples kept until the rate and the clock's unit are known (``infer_samples``, or
    ``UNIT_SAMPLES`` with a nominal ``rate_hz``); bounded: time stamps that never advance give
    no rate, and after 20 times ``infer_samples`` the hold stops waiting (`overdue`)."""

    def __init__(self, rate_hz: float | None, infer_samples: int) -> None:
        self.rate_hz = rate_hz
        self.infer_samples = infer_samples
        self._pending: list[RawBatch] = []
        self._n = 0

    def __bool__(self) -> bool:
        return bool(self._pending)

    def add(self, batch: RawBatch) -> bool:
        """Hold ``batch``; whether enough samples are held to measure."""
        self._pending.append(batch)
        self._n += len(batch)
        return self._n >= (self.infer_samples if self.rate_hz is None else UNIT_SAMPLES)

    @property
    def overdue(self) -> bool:
        return self._n >= 20 * self.infer_samples

    def take(self) -> RawBatch:
        """The held samples as one batch in the first one's channel layout (emptied)."""
        names = self._pending[0].aux_names
        parts = [b if b.aux_names == names else conform_channels(b, names, ())
                 for b in self._pending]
        self._pending, self._n = [], 0
        return RawBatch.concat([b for b in parts if isinstance(b, RawBatch)])

    def put_back(self, batch: RawBatch) -> None:
        self._pending, self._n = [batch], len(batch)

    def measure(self, batch: RawBatch, force: bool
                ) -> tuple[float, tb.TimebaseState] | None:
        """The rate and the time base ``batch`` starts (None: its time stamps are all equal;
        ``force``: DEFAULT_RATE_HZ then)."""
        tcfg = tb.TimebaseConfig(rate_hz=self.rate_hz)
        state, _ = tb.start(batch.t_us, tcfg)
        t_out = tb.step(state, batch.t_us, tcfg)[1]  # a look ahead, for the rate only
        rate = self.rate_hz or infer_rate_hz(t_out) or (DEFAULT_RATE_HZ if force else None)
        if rate is None:
            return None
        # the step the nominal rate gives, so that wraps and reboots are judged by it
        return rate, replace(state, step_us=1e6 / rate)


class ChannelLayout:
    """Fits each batch to the pipeline's channel layout, and says when the stream's changes
    (``last_names``: the layout of the last batch seen)."""

    def __init__(self, events: NodeEvents) -> None:
        self.events = events
        self.last_names: tuple[str, ...] | None = None

    def fit(self, batch: RawBatch, names: tuple[str, ...], model: SensorModel,
            log_ns: int) -> RawBatch | None:
        """The batch in the layout ``names``, or None (reported) if it cannot be."""
        if batch.aux_names == names:  # the usual case: nothing to map, nothing to say
            self.last_names = batch.aux_names
            return batch
        if unnamed_for(batch.aux_names, names):
            # a device that prints its header only at boot, heard after a restart: the same
            # count of channels, unnamed, are the ones the state was built with (else each
            # would be missing and its windows NaN)
            if batch.aux_names != self.last_names:
                self.events.event("layout_mapped", int(batch.t_us[0]), log_ns, {
                    "got": list(batch.aux_names), "mapped_to": list(names)})
                self.events.note(f"channels {', '.join(batch.aux_names)} (no header heard) "
                                 f"taken as {', '.join(names)}, as before the restart")
            self.last_names = batch.aux_names
            return RawBatch(batch.t_us, batch.v, batch.aux, names)
        fitted = conform_channels(batch, names, model.covariates)
        if batch.aux_names != self.last_names and batch.aux_names != names:
            self.events.event("layout_changed", int(batch.t_us[0]), log_ns, {
                "expected": list(names), "got": list(batch.aux_names),
                "calibrated": isinstance(fitted, RawBatch)})
        self.last_names = batch.aux_names
        if isinstance(fitted, str):
            return None
        return fitted
