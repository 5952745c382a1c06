"""The gateway's ports: which sensors it serves, their serial sources claimed, each one's live
parts (`Port`), and the one I/O thread's loop over all of them (`PortLoop`).

One I/O thread serves every port from a selector: it reads what the ready ports hold (never
waiting on one device), then, per port, hands all the new samples to the gateway as one batch
(`recal.daemon.gateway.Gateway`: logged, published, calibrated). Why one thread and what each
choice costs: docs/design.md and docs/performance.md.
"""

from __future__ import annotations

import contextlib
import logging
import os
import selectors
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from recal.config.settings import SensorConfig, ServiceConfig, default_sensor_id
from recal.errors import ConfigError, RecalError
from recal.io import topics
from recal.io.recording import sensor_topic
from recal.io.serial_source import SerialSource, SourceEvent, port_problem
from recal.io.wire_formats import make_parser
from recal.node.node import CalibrationNode
from recal.samples import RawBatch, join_by_layout

__all__ = [
    "Port",
    "PortLoop",
    "PortTakenError",
    "claim_ports",
    "make_source",
    "select_sensors",
]

log = logging.getLogger(__name__)

READ_WAIT_S = 0.05  # longest selector wait: bounds how fast a stop is noticed
POLL_QUIET_S = 0.25  # an open port that sent nothing is polled this often (unplug check)
SWEEP_S = 0.05  # how often every port is looked at for a due open retry or quiet poll
IO_RETRY_S = 0.1  # pause after a failed I/O round
LISTEN_CHECK_S = 0.5  # how often the loop asks whether anyone subscribes to live data
LIVE_TOPICS = topics.live_topics()  # a subscriber to any of these wants low latency
FINAL_LINE_S = 0.1  # at stop, how long a partial line may take to end


# ---------------------------------------------------------------------------------------------
# One sensor's live parts
# ---------------------------------------------------------------------------------------------

@dataclass
class Port:
    """A sensor's serial source, node and counters (touched by the I/O thread only, except
    reads of the counters for status queries)."""

    sensor: SensorConfig
    source: SerialSource
    node: CalibrationNode | None
    keys: dict[str, str] = field(default_factory=dict)  # topic -> Zenoh key, built once
    raw_publisher: Any = None  # the bus's Publisher of recal/<sensor>/raw, looked up once
    fd: int | None = None  # registered with the selector
    polled_s: float = 0.0  # last poll, for the periodic poll of quiet ports
    pending: list[RawBatch] = field(default_factory=list)  # read this round, not yet handled
    samples_logged: int = 0
    batches_logged: int = 0
    is_open: bool = False
    ever_opened: bool = False
    lost_count: int = 0
    open_failures: int = 0
    parse_errors: dict[str, int] = field(default_factory=dict)
    parse_reported: dict[str, int] = field(default_factory=dict)
    parse_noted: dict[str, int] = field(default_factory=dict)  # as of the last operator line
    parse_noted_s: float = float("-inf")
    node_errors: int = 0

    @property
    def sensor_id(self) -> str:
        return self.sensor.id

    def status(self) -> dict[str, Any]:
        return {"port": self.sensor.port, "open": self.is_open, "lost_count": self.lost_count,
                "samples_logged": self.samples_logged, "batches_logged": self.batches_logged,
                "parse_errors": dict(self.parse_errors),
                "parse_errors_total": sum(self.parse_errors.values()),
                "queue": sum(len(b) for b in list(self.pending)),
                "node_errors": self.node_errors}


# ---------------------------------------------------------------------------------------------
# The I/O thread
# ---------------------------------------------------------------------------------------------

class PortLoop:
    """The I/O thread's loop (`run`) over every port, until `stop_reading` is set.

    Args:
        ports: the gateway's ports, by sensor id.
        bus: a recal.io.bus.Bus (asked whether anyone listens live), or None.
        batch_s, idle_batch_s: the tick (see `recal.daemon.gateway.Gateway`).
        handle: ``handle(port, batch, log_ns)``, what arrived on a port, one batch each.
        source_event: ``source_event(port, event, log_ns)``, what a port's source reports.
        gateway_event: ``gateway_event(kind, log_ns, detail)``, a failed round.
    """

    def __init__(self, ports: dict[str, Port], bus: Any, batch_s: float, idle_batch_s: float,
                 handle: Callable[[Port, RawBatch, int], None],
                 source_event: Callable[[Port, SourceEvent, int], None],
                 gateway_event: Callable[[str, int, Any], None]) -> None:
        if batch_s < 0 or idle_batch_s < 0:
            raise ValueError("batch_s and idle_batch_s must be >= 0")
        self.ports = ports
        self.bus = bus
        self.batch_s = float(batch_s)
        self.idle_batch_s = float(idle_batch_s)
        self.handle = handle
        self.source_event = source_event
        self.gateway_event = gateway_event
        self.stop_reading = threading.Event()
        self._listening = True  # until the first check: start out responsive
        self._next_listen_check_s = 0.0
        self._next_sweep_s = 0.0
        self._io_errors = 0

    def run(self) -> None:
        """Read every port from one selector; log, publish and calibrate what arrived.

        One thread for all ports: a thread per port costs a wake-up and GIL hand-over per
        sample and sensor (docs/design.md, one I/O thread). Reading every ready port
        before handling any batch, and handling all of one port's new samples as one batch,
        makes batches grow by themselves when the loop falls behind, so the per-batch cost
        is paid less often exactly when it matters.
        """
        sel = selectors.DefaultSelector()
        try:
            next_tick = time.monotonic()
            while not self.stop_reading.is_set():
                tick = self.tick_s()
                if tick > 0:  # sleep out the tick, then take what arrived at once
                    delay = next_tick - time.monotonic()
                    if delay > 0 and self.stop_reading.wait(delay):
                        break
                    next_tick = max(next_tick + tick, time.monotonic())
                    ready = sel.select(0)
                else:
                    ready = sel.select(READ_WAIT_S)
                    next_tick = time.monotonic()
                self._guarded_round(sel, [k.data for k, _ in ready])
            # a last read of every port, not as "readable": an empty read then means nothing
            # was left, not that the device hung up (a port_lost at every stop, before)
            self._guarded_round(sel, [], final=True)
            # a line the device was writing as we stopped gets a moment to end: cut here, its
            # rest would start the next run's stream and both halves would be lost
            deadline = time.monotonic() + FINAL_LINE_S
            while (time.monotonic() < deadline
                   and any(p.source.parser.partial
                           for p in self.ports.values() if p.source.is_open)):
                time.sleep(0.005)
                self._guarded_round(sel, [], final=True)
        finally:
            sel.close()

    def tick_s(self) -> float:
        """The loop's tick now: ``batch_s``, else 0 while someone listens live, else
        ``idle_batch_s`` (who listens is asked every ``LISTEN_CHECK_S``)."""
        if self.batch_s > 0 or self.idle_batch_s <= 0:
            return self.batch_s
        now_s = time.monotonic()
        if now_s >= self._next_listen_check_s:
            self._next_listen_check_s = now_s + LISTEN_CHECK_S
            self._listening = self._anyone_listening()
        return 0.0 if self._listening else self.idle_batch_s

    def _anyone_listening(self) -> bool:
        """Whether any subscriber matches a sensor's raw, calibrated or body key."""
        if self.bus is None:
            return False
        from recal.io.bus import key

        try:
            return any(self.bus.publisher(key(sid, topic)).has_subscribers
                       for sid in self.ports for topic in LIVE_TOPICS)
        except RuntimeError:  # the bus closed under us (shutdown)
            return False

    def _guarded_round(self, sel: selectors.BaseSelector, ready: list[Port],
                       final: bool = False) -> None:
        """A round whose failure (a bug; a full disk does not fail a round, the writer keeps
        what the disk refuses) is reported and survived: the loop serves every sensor, so it
        must not end, or all of them would go quiet."""
        try:
            self._read_round(sel, ready, final)
        except Exception as exc:
            self._io_errors += 1
            if self._io_errors <= 5 or self._io_errors % 1000 == 0:
                log.exception("gateway I/O round failed")
                with contextlib.suppress(Exception):  # the log itself may be what fails
                    self.gateway_event("io_error", time.time_ns(), {
                        "error": f"{type(exc).__name__}: {exc}", "count": self._io_errors})
            self.stop_reading.wait(IO_RETRY_S)  # no hot loop on a lasting failure

    def _read_round(self, sel: selectors.BaseSelector, ready: list[Port],
                    final: bool = False) -> None:
        """Poll the ready ports and those due a poll anyway, then handle what they gave."""
        now_s = time.monotonic()
        for p in ready:
            self._poll(sel, p, now_s, readable=True)
        polled = ready
        if final or now_s >= self._next_sweep_s:
            # Closed ports retry opening on their back-off schedule; quiet open ports are
            # polled now and then so that their path check notices an unplug. Looking at
            # every port is O(sensors), so it happens on a timer, not every round.
            self._next_sweep_s = now_s + SWEEP_S
            polled = [*ready, *self._sweep(sel, now_s, {id(p) for p in ready}, final)]
        now_ns = time.time_ns()
        for p in polled:
            if p.pending:
                batches, p.pending = p.pending, []
                for batch in batches if len(batches) == 1 else join_by_layout(batches):
                    self.handle(p, batch, now_ns)

    def _sweep(self, sel: selectors.BaseSelector, now_s: float, skip: set[int],
               final: bool) -> list[Port]:
        swept = []
        for p in self.ports.values():
            if id(p) in skip:
                continue
            due = p.source.next_open_s if p.fd is None else p.polled_s + POLL_QUIET_S
            if final or now_s >= due:
                self._poll(sel, p, now_s)
                swept.append(p)
        return swept

    def _poll(self, sel: selectors.BaseSelector, p: Port, now_s: float,
              readable: bool = False) -> None:
        p.polled_s = now_s
        batch, events = p.source.poll(readable)
        if events:
            now = time.time_ns()
            for ev in events:
                self.source_event(p, ev, now)
        if len(batch):
            p.pending.append(batch)
        fd = p.source.fileno()
        if fd != p.fd:  # opened, lost or reopened: keep the selector in step
            if p.fd is not None:
                with contextlib.suppress(KeyError, ValueError, OSError):
                    sel.unregister(p.fd)
            if fd is not None:
                sel.register(fd, selectors.EVENT_READ, p)
            p.fd = fd


# ---------------------------------------------------------------------------------------------
# Which sensors, their ports claimed
# ---------------------------------------------------------------------------------------------

def select_sensors(cfg: ServiceConfig, ports: Sequence[str], sensor_ids: Sequence[str]
             ) -> list[SensorConfig]:
    """The sensors to serve: ports from the command line (ids matched to config entries),
    else the configured sensors (limited to ``sensor_ids`` if given).

    A device path that does not exist yet is waited for (a deployment may boot before its
    devices appear, a device may be plugged in later), as is any device unplugged later;
    one that can never be a serial port (a regular file, a directory, /dev/null, a URL scheme
    pyserial does not know) is an error now (one another process holds: `claim_ports`)."""
    if ports:
        if sensor_ids and len(sensor_ids) != len(ports):
            raise ConfigError(f"{len(ports)} ports but {len(sensor_ids)} sensor ids")
        chosen = []
        for i, port in enumerate(ports):
            if sensor_ids:
                sid = sensor_ids[i]
                base = cfg.sensor(sid) or SensorConfig(id=sid)
            elif i < len(cfg.sensors):
                base = cfg.sensors[i]
            else:  # the device's own name: two devices never share a calibration
                base = SensorConfig(id=default_sensor_id(port))
            chosen.append(replace(base, port=port))
        return _distinct(chosen)
    chosen = [s for s in cfg.sensors if not sensor_ids or s.id in sensor_ids]
    missing = sorted(set(sensor_ids) - {s.id for s in chosen})
    if missing:
        raise ConfigError(f"sensor {missing[0]!r} is not in the configuration")
    without = [s.id for s in chosen if s.port is None]
    if without:
        raise ConfigError(f"sensor {without[0]!r} has no port")
    return _distinct(chosen)


def _distinct(sensors: list[SensorConfig]) -> list[SensorConfig]:
    """Each sensor a valid id of its own and a device of its own: two readers of one tty split
    its bytes between them and each sees the other's reads as a hang-up."""
    seen_ids: set[str] = set()
    seen_ports: dict[str, str] = {}
    for s in sensors:
        try:  # the config's ids are checked when it is read; --sensor-id ones only here
            sensor_topic(s.id, "raw")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        assert s.port is not None  # the port first: a device given twice gets one id twice
        device = s.port if "://" in s.port else os.path.realpath(s.port)
        if device in seen_ports:
            raise ConfigError(f"port {s.port} is given to two sensors "
                              f"({seen_ports[device]!r} and {s.id!r})")
        seen_ports[device] = s.id
        if s.id in seen_ids:
            raise ConfigError(f"sensor id {s.id!r} is given twice")
        seen_ids.add(s.id)
    for s in sensors:
        assert s.port is not None
        problem = port_problem(s.port)
        if problem is not None:
            raise ConfigError(f"port {problem}")
    return sensors


class PortTakenError(RecalError):
    """A port another process holds (another daemon: it would split the bytes with us)."""


def make_source(s: SensorConfig) -> SerialSource:
    assert s.port is not None
    # a known rate lets records come without a time column where the format allows it
    # (ASCII lines x,y,z[,aux]); make_parser passes it to such formats only
    parser = make_parser(s.format, s.aux_names, rate_hz=s.rate_hz)
    return SerialSource(s.port, parser, s.baudrate, read_timeout_s=0.02)


def claim_ports(cfg: ServiceConfig
                ) -> tuple[dict[str, SerialSource], dict[str, list[SourceEvent]]]:
    """Every sensor's serial source, opened now where its device exists: (sources, what
    their opens reported). The exclusive open itself decides who owns a port, so two daemons
    racing for one cannot both pass; PortTakenError (every source closed) for a port another
    process holds. A port that is missing (``open_failed``) is retried by the I/O thread."""
    sources: dict[str, SerialSource] = {}
    opened: dict[str, list[SourceEvent]] = {}
    for s in cfg.sensors:
        src = sources[s.id] = make_source(s)
        opened[s.id] = events = src.open_now()
        busy = [ev for ev in events if ev.kind == "port_busy"]
        if busy:
            for other in sources.values():
                other.close()
            raise PortTakenError(f"port {s.port} is {busy[0].detail.get('error', 'in use')}")
    return sources, opened
