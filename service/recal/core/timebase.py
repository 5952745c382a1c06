"""A device's clock -> the service's time base: microseconds that never go backwards.

Devices stamp samples with whatever clock they have: a 32-bit ``micros()`` that wraps every
71.6 min, a ``millis()`` printed under a ``t_us`` header, a 16-bit tick counter, a clock that
restarts at 0 when the device reboots. The pipeline needs one time axis in microseconds that
only goes forwards. This module makes it, and says what it did:

* **Units.** :func:`decide_unit` reads the median step of the first samples: a step that implies
  a rate outside ``[min_rate_hz, max_rate_hz]`` (an accelerometer samples at about 1-5000 Hz)
  in microseconds is tried as milliseconds, then seconds; with a nominal rate known, the unit
  whose implied rate is nearest to it (within 2x) wins. Not microseconds is an event.
* **Wraps.** A step backwards that is one plausible sample step forwards modulo a counter period
  (2^16 or 2^32 device units, the smallest that fits, then the one seen before) is a wrap: the
  period is added from there on, so the output is the unwrapped device time (first value kept).
* **Reboots.** A step backwards to a device time below ``reboot_max_s`` (time restarts near 0)
  that is no wrap is a reboot; the output continues one nominal step after the last one.
* **Anomalies.** Other steps backwards (continued the same way), duplicates (bumped by 1 us so
  the output strictly increases) and forward jumps beyond ``max(jump_s, 50 steps)`` (kept: a
  real gap) are counted.
* **Implausible jumps.** A step forwards or backwards by more than ``implausible_s`` (a day)
  that is no wrap or reboot is no clock a sensor keeps: a corrupted stamp, another device, a
  crafted stream. It is not taken as a new time base for good: the output continues one
  nominal step after the last one (as after a reboot), and a ``time_jump_refused`` event (one
  per batch, with the count) says so.

Pure (no I/O, no clocks): ``state, t_us, events = step(state, t_dev, cfg)``, like
``scipy.signal.sosfilt`` with ``zi``; the state is a small frozen dataclass that round-trips
through a JSON dict (checkpoints). Vectorized: clean batches are two numpy passes; only samples
at an anomaly are looked at one by one (there are a handful per day). See docs/design.md
("Device time").
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

__all__ = ["WRAP_PERIODS", "TimebaseConfig", "TimebaseState", "decide_unit", "start", "step"]

#: Counter periods a wrap is tried with, in device units, smallest first.
WRAP_PERIODS = (2**16, 2**32)
UNIT_NAMES = {1: "us", 1000: "ms", 1_000_000: "s"}


@dataclass(frozen=True)
class TimebaseConfig:
    """How device time is read.

    Attributes:
        rate_hz: nominal sample rate (None: measured from the first samples).
        min_rate_hz, max_rate_hz: rates an accelerometer plausibly samples at.
        jump_s: a forward step longer than this (and than 50 nominal steps) is a jump (counted).
        reboot_max_s: a step back to a device time below this is a reboot, when it is no wrap.
        implausible_s: a step beyond this either way (no wrap, no reboot) is refused as a gap:
            a day, as far as `recal.node.checkpoint_doc` lets a state's times lie past its last
            sample.
    """

    rate_hz: float | None = None
    min_rate_hz: float = 1.0
    max_rate_hz: float = 5000.0
    jump_s: float = 2.0
    reboot_max_s: float = 60.0
    implausible_s: float = 86_400.0


@dataclass(frozen=True)
class TimebaseState:
    """Where a stream's time base stands (JSON-able through :meth:`to_dict`).

    Attributes:
        unit_us: microseconds per device unit (1, 1000 or 1e6).
        step_us: nominal sample step in microseconds.
        offset_us: added to ``device time * unit_us`` (wraps, reboots).
        period: the counter period a wrap showed, device units (None: none seen yet).
        last_dev, last_us: the last sample's device time and output time.
        wraps, reboots, backwards, duplicates, jumps: counts since the stream began;
        refused: implausible jumps either way, not taken as time (`TimebaseConfig`).
    """

    unit_us: int = 1
    step_us: float = 10_000.0
    offset_us: int = 0
    period: int | None = None
    last_dev: int | None = None
    last_us: int | None = None
    wraps: int = 0
    reboots: int = 0
    backwards: int = 0
    duplicates: int = 0
    jumps: int = 0
    refused: int = 0

    @property
    def unit(self) -> str:
        return UNIT_NAMES.get(self.unit_us, f"{self.unit_us} us")

    def counts(self) -> dict[str, int]:
        return {k: getattr(self, k) for k in ("wraps", "reboots", "backwards", "duplicates",
                                              "jumps", "refused")}

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TimebaseState:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


def _median_step(t_dev: np.ndarray) -> float | None:
    d = np.diff(np.asarray(t_dev, np.int64))
    d = d[d > 0]
    return float(np.median(d)) if len(d) else None


def decide_unit(t_dev: np.ndarray, cfg: TimebaseConfig) -> tuple[int, float | None]:
    """(microseconds per device unit, the rate the samples imply in microseconds or None).

    Microseconds unless their implied rate is implausible (or, with a nominal rate, further
    from it than another unit's): then milliseconds or seconds, whichever fits."""
    d = _median_step(t_dev)
    if d is None:
        return 1, None
    rate_as_us = 1e6 / d
    units = tuple(UNIT_NAMES)
    if cfg.rate_hz is not None:
        miss = [abs(np.log(rate_as_us / u / cfg.rate_hz)) for u in units]
        best = int(np.argmin(miss))
        if miss[best] <= np.log(2.0):
            return units[best], rate_as_us
    for u in units:
        if cfg.min_rate_hz <= rate_as_us / u <= cfg.max_rate_hz:
            return u, rate_as_us
    return 1, rate_as_us


def start(t_dev: np.ndarray, cfg: TimebaseConfig) -> tuple[TimebaseState, list[dict[str, Any]]]:
    """A time base for a stream whose first samples are ``t_dev`` (nothing is consumed: pass
    them to :func:`step` next). Events: ``time_units`` when the clock is not in microseconds,
    ``time_implausible`` when no unit gives a plausible rate."""
    unit, rate_as_us = decide_unit(t_dev, cfg)
    d = _median_step(t_dev)
    step_us = (1e6 / cfg.rate_hz if cfg.rate_hz else d * unit if d else 1e6 / 100.0)
    events: list[dict[str, Any]] = []
    if unit != 1:
        events.append({"kind": "time_units", "index": 0, "detail": {
            "unit": UNIT_NAMES[unit], "implied_rate_hz_as_us": rate_as_us,
            "rate_hz": rate_as_us / unit if rate_as_us else None}})
    elif rate_as_us is not None and not cfg.min_rate_hz <= rate_as_us <= cfg.max_rate_hz:
        events.append({"kind": "time_implausible", "index": 0, "detail": {
            "implied_rate_hz": rate_as_us, "min_rate_hz": cfg.min_rate_hz,
            "max_rate_hz": cfg.max_rate_hz}})
    return TimebaseState(unit_us=unit, step_us=float(step_us)), events


def _wrap_period(prev: int, now: int, limit_dev: float, seen: int | None) -> int | None:
    """The counter period that makes prev -> now one plausible step forwards, or None."""
    for p in ((seen,) if seen else ()) + WRAP_PERIODS:
        if prev < p and now < p and 0 < now + p - prev <= limit_dev:
            return p
    return None


def _clean_continuation(state: TimebaseState, t: np.ndarray, limit_dev: float
                        ) -> tuple[TimebaseState, np.ndarray, list[dict[str, Any]]] | None:
    """:func:`step` for the usual batch (every step forwards and short, after the last one):
    a few array operations, no state copies beyond one: a sensor that sends one sample at a
    time takes this path on every call. None otherwise."""
    if state.last_dev is None or state.last_us is None:
        return None
    first = int(t[0]) - state.last_dev
    if not 0 < first <= limit_dev:
        return None
    if len(t) > 1:
        d = t[1:] - t[:-1]
        if not (d.min() > 0 and d.max() <= limit_dev):
            return None
    unit, offset = state.unit_us, state.offset_us
    out = t if unit == 1 and offset == 0 else t * unit + offset
    if int(out[0]) <= state.last_us:  # after bumped duplicates: the general path
        return None
    # `replace(state, last_dev=..., last_us=...)` without the frozen dataclass's field by
    # field __init__ (a one-sample arrival's largest cost here): the fields copied, two set
    s = object.__new__(TimebaseState)
    s.__dict__.update(state.__dict__)
    s.__dict__.update(last_dev=int(t[-1]), last_us=int(out[-1]))
    return s, out, []


def step(state: TimebaseState, t_dev: np.ndarray, cfg: TimebaseConfig
         ) -> tuple[TimebaseState, np.ndarray, list[dict[str, Any]]]:
    """Map one batch of device times to output microseconds.

    Returns (new state, int64 output times strictly after every earlier output, events). An
    event is ``{"kind", "index", "detail"}`` with ``index`` the sample in this batch:
    ``time_wrap`` and ``time_reboot`` one each, implausible jumps in one ``time_jump_refused``
    and other anomalies in one ``time_anomalies`` event per batch.
    """
    t = np.asarray(t_dev, np.int64)
    n = len(t)
    if n == 0:
        return state, np.zeros(0, np.int64), []
    unit = state.unit_us
    limit_dev = max(cfg.jump_s * 1e6, 50.0 * state.step_us) / unit
    clean = _clean_continuation(state, t, limit_dev)
    if clean is not None:
        return clean
    prev0 = state.last_dev if state.last_dev is not None else int(t[0])
    d = np.diff(t, prepend=np.int64(prev0))
    odd = np.flatnonzero((d <= 0) | (d > limit_dev))
    if state.last_dev is None:
        odd = odd[odd > 0]
    events: list[dict[str, Any]] = []
    offsets = [state.offset_us]
    s = state
    before = s.counts()
    implausible_dev = cfg.implausible_s * 1e6 / unit
    refused: list[tuple[int, int, int]] = []  # (index, device before, device after)
    for k in odd.tolist():
        prev = int(t[k - 1]) if k > 0 else int(prev0)
        prev_us = prev * unit + offsets[-1]
        now = int(t[k])
        offset = offsets[-1]
        if now == prev:
            s = replace(s, duplicates=s.duplicates + 1)
        elif now - prev > implausible_dev:  # no clock: continue one step after the last
            offset = prev_us + round(s.step_us) - now * unit
            s = replace(s, refused=s.refused + 1)
            refused.append((k, prev, now))
        elif now > prev:
            s = replace(s, jumps=s.jumps + 1)
        else:
            period = _wrap_period(prev, now, limit_dev, s.period)
            if period is not None:
                offset += period * unit
                s = replace(s, wraps=s.wraps + 1, period=period)
                events.append({"kind": "time_wrap", "index": k, "detail": {
                    "period": period, "unit": s.unit, "device_before": prev,
                    "device_after": now, "wraps": s.wraps}})
            else:
                # no wrap: continue one nominal step after the last output
                offset = prev_us + round(s.step_us) - now * unit
                if now * unit <= cfg.reboot_max_s * 1e6:
                    s = replace(s, reboots=s.reboots + 1)
                    events.append({"kind": "time_reboot", "index": k, "detail": {
                        "device_before": prev, "device_after": now, "unit": s.unit,
                        "reboots": s.reboots}})
                elif prev - now > implausible_dev:
                    s = replace(s, refused=s.refused + 1)
                    refused.append((k, prev, now))
                else:
                    s = replace(s, backwards=s.backwards + 1)
        offsets.append(offset)
    if len(offsets) == 1:
        out = t * unit + offsets[0]
    else:
        lengths = np.diff(np.concatenate(([0], odd, [n])))
        out = t * unit + np.repeat(np.asarray(offsets, np.int64), lengths)
    # strictly increasing, also across batches: out[i] >= out[i-1] + 1 (duplicates, and a
    # step back within a jump limit that was neither wrap nor reboot)
    ramp = np.arange(n, dtype=np.int64)
    y = out - ramp
    if state.last_us is not None:
        y[0] = max(int(y[0]), state.last_us + 1)
    out = np.maximum.accumulate(y) + ramp
    if refused:
        k, prev, now = refused[0]
        events.append({"kind": "time_jump_refused", "index": k, "detail": {
            "device_before": prev, "device_after": now, "unit": s.unit,
            "jump_s": (now - prev) * unit / 1e6, "limit_s": cfg.implausible_s,
            "in_batch": len(refused), "refused": s.refused}})
    after = s.counts()
    extra = {k: after[k] - before[k] for k in ("backwards", "duplicates", "jumps")
             if after[k] != before[k]}
    if extra:
        events.append({"kind": "time_anomalies", "index": int(odd[0]),
                       "detail": {**extra, "total": {k: after[k] for k in extra}}})
    s = replace(s, offset_us=int(offsets[-1]), last_dev=int(t[-1]), last_us=int(out[-1]))
    return s, out, events
