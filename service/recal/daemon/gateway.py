"""The gateway daemon: serial ports -> raw log + bus -> calibration nodes -> log + bus.

One I/O thread serves every port (one serial port per sensor) from a selector: it reads what
the ready ports hold (never waiting on one device), then, per port, handles all the new
samples as one batch: logged at once (``/<sensor>/raw``), the same bytes published on
``recal/<sensor>/raw``, then calibrated by the sensor's :class:`recal.node.node.CalibrationNode`.
Logging before calibrating means a sample that reached the service is in the log exactly
once, whatever happens to the node or the bus. When calibration takes longer, the next round
finds more bytes waiting, so batches grow with the load; the serial ports' kernel buffers are
the back-pressure point. ``batch_s`` (``--batch-ms``) and ``idle_batch_s`` (config
``idle_batch_ms``: a tick while nobody subscribes live) trade latency for CPU. Why one thread
and what each choice costs: docs/design.md and docs/performance.md. The ports, which sensors
they serve and the I/O thread's loop: `recal.daemon.ports`.

With ``run_nodes = false`` the gateway only logs and publishes raw; a node elsewhere
(`recal.daemon.remote_node`) subscribes to ``recal/*/raw``.

The main thread checkpoints every pipeline (recal.daemon.checkpoint_store), reports aggregated
counts (parse errors, dropped publishes) once a second as events, and waits for SIGINT/SIGTERM or a
stop event. Stopping reads what the ports still hold, calibrates it, writes the checkpoints,
closes (and indexes) the MCAP and the Zenoh session. A restart resumes each pipeline from its
checked checkpoint; each calibrated sensor's lock in the state folder is taken before anything
is opened, so a second daemon for the same sensor id exits with one line naming the holder.
Then every port that exists is opened (exclusively) before the recording: the open decides who
owns a port, so of two daemons started at the same instant on one port the one that lost
exits at once with one line naming the holder; a port taken by another process later (after
an unplug) stops the daemon the same way. A port that does not exist yet is waited for.
A full disk never stops reading, calibrating or publishing (`recal.daemon.runtime.RecordingWatch`).

Queries: ``recal/<sensor>/status`` answers the node's calibration state plus a ``gateway``
section (port, samples logged, parse errors, ...); ``recal/<sensor>/align`` requests a
mounting alignment. Memory is bounded: per sensor at most ``max_batch_bytes`` read per round,
the parser's partial line, the pipeline's bounded buffer; counters only.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from recal.config import (
    ServiceConfig,
    check_model_channels,
    load_config,
)
from recal.config.sensor_options import SensorOptions, with_options
from recal.daemon.checkpoint_store import Checkpoints, SensorLockedError
from recal.daemon.ports import (
    Port,
    PortLoop,
    PortTakenError,
    claim_ports,
    make_source,
    select_sensors,
)
from recal.daemon.runtime import (
    ERROR_PREFIX,
    RecordingWatch,
    console,
    flush_console,
    install_stop_signals,
    open_bus,
    open_recording,
)
from recal.errors import ConfigError
from recal.io import messages
from recal.io.recording_writer import RecordingWriter
from recal.io.serial_source import SerialSource, SourceEvent
from recal.io.wire_formats import wire_format
from recal.node import rediscovery
from recal.node.alignment import align_handler
from recal.node.node import CalibrationNode, make_node, node_settings
from recal.node.sinks import Sink, make_sink
from recal.samples import RawBatch

__all__ = [
    "NOTE_PREFIX",
    "READY_PREFIX",
    "Gateway",
    "run_gateway",
]

log = logging.getLogger(__name__)

READY_PREFIX = "recal gateway ready"
STOPPED_PREFIX = "recal gateway stopped"
REPORT_INTERVAL_S = 1.0  # aggregated events (parse errors, dropped publishes) at most this often
NOTE_PREFIX = "recal gateway:"  # a line for the operator (stdout: the journal under systemd)
NOTE_KINDS = ("port_opened", "port_found", "port_lost", "port_missing", "port_busy")  # a line each
PARSE_NOTE_S = 60.0  # bad input is summed up for the operator at most this often per sensor
# a partial line cut at a (re)connect is expected: an event in the log, no line for the operator
PARSE_NOT_NOTED = frozenset({"resync_dropped", "truncated"})
STOP_JOIN_S = 10.0


# ---------------------------------------------------------------------------------------------
# One sensor's live parts
# ---------------------------------------------------------------------------------------------



class Gateway:
    """The daemon's parts and its I/O thread. :meth:`start`, then :meth:`run` until stopped.

    Args:
        cfg: service configuration; its sensors (each with a port) are served.
        writer: the MCAP log.
        bus: a recal.io.bus.Bus, or None to run without Zenoh.
        nodes: node per sensor id (None for every sensor when ``run_nodes`` is off).
        out: where the ready/stopped lines go.
        batch_s: 0 handles samples as they arrive (lowest latency); a positive value wakes
            every ``batch_s`` and handles what arrived meanwhile as one batch per sensor,
            trading that much latency for fewer, larger batches (less CPU per sample).
        idle_batch_s: with ``batch_s`` = 0, the tick used while nobody subscribes to the
            sensors' live topics (0: always handle arrivals at once).
        sources: the sensors' serial sources if already made (:func:`claim_ports`), else
            made here; ``opened``: what their first opens reported (logged at :meth:`start`).
    """

    def __init__(self, cfg: ServiceConfig, writer: RecordingWriter, bus: Any,
                 nodes: dict[str, CalibrationNode | None],
                 out: Callable[[str], None] = print, *, batch_s: float = 0.0,
                 idle_batch_s: float = 0.0, checkpoints: Checkpoints | None = None,
                 sources: dict[str, SerialSource] | None = None,
                 opened: dict[str, list[SourceEvent]] | None = None) -> None:
        self.ports: dict[str, Port] = {}
        #: the I/O thread's loop over the ports (its tick: ``batch_s``, ``idle_batch_s``)
        self.loop = PortLoop(self.ports, bus, batch_s, idle_batch_s, self._handle,
                             self._source_event, self._gateway_event)
        self.cfg = cfg
        self.writer = writer
        self.bus = bus
        self.out = out
        self._opened = opened or {}
        for s in cfg.sensors:
            src = (sources or {}).get(s.id) or make_source(s)
            node = nodes.get(s.id)
            if node is not None:
                node.on_note = lambda line, sid=s.id: self.out(f"{NOTE_PREFIX} {sid}: {line}")
            self.ports[s.id] = Port(s, src, node)
        #: why the daemon stopped by itself (a sensor that cannot be calibrated), or None
        self.fatal: str | None = None
        self._stop_event: threading.Event | None = None
        self._io_thread: threading.Thread | None = None
        self._publish_reported = 0
        self._started_s = time.monotonic()
        c = cfg.checkpoint
        self.checkpoints = checkpoints or Checkpoints(
            c.dir, c.interval_s, c.after_update_s, out=out, prefix=NOTE_PREFIX)
        self.checkpoints.set_event(
            lambda sid, kind, detail: self._sensor_event(sid, kind, time.time_ns(), detail))
        for sid, p in self.ports.items():
            if p.node is not None:
                self.checkpoints.add(sid, p.node.accepted_updates)
        self._write_watch = RecordingWatch(writer, out, cfg.mcap.backlog_mb, prefix=NOTE_PREFIX)

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        now = time.time_ns()
        self._gateway_event("start", now, {
            "sensors": {sid: p.sensor.port for sid, p in self.ports.items()},
            "mcap": str(self.writer.paths[0]), "run_nodes": self.cfg.run_nodes,
            "batch_s": self.loop.batch_s, "idle_batch_s": self.loop.idle_batch_s})
        for sid, events in self._opened.items():
            for ev in events:
                self._source_event(self.ports[sid], ev, now)
        if self.bus is not None:
            from recal.io.bus import key

            for sid, p in self.ports.items():
                p.keys = {t: key(sid, t) for t in ("raw", "events")}
                p.raw_publisher = self.bus.publisher(p.keys["raw"])
                self._declare_queries(sid, p)
        self._io_thread = threading.Thread(target=self.loop.run, name="recal-io", daemon=True)
        self._io_thread.start()

    def run(self, stop: threading.Event) -> None:
        """Checkpoint (each sensor in its turn, and soon after its accepted updates, see
        recal.daemon.checkpoint_store) and report until ``stop`` is set."""
        self._stop_event = stop
        if self.fatal is not None:
            stop.set()
        nodes = self._nodes()
        next_report = time.monotonic() + REPORT_INTERVAL_S
        while not stop.wait(min(self.checkpoints.next_due_s(),
                                max(0.0, next_report - time.monotonic()))):
            if time.monotonic() >= next_report:
                self._report_counts(time.time_ns())
                self._report_recording(time.time_ns())
                next_report = time.monotonic() + REPORT_INTERVAL_S
            self.checkpoints.save_due(nodes)

    def _nodes(self) -> dict[str, CalibrationNode]:
        return {sid: p.node for sid, p in self.ports.items() if p.node is not None}

    def stop(self) -> dict[str, int]:
        """Stop reading (after a last read of what the ports hold), flush the nodes,
        checkpoint, close the log and the bus.

        Returns samples logged per sensor.
        """
        self.loop.stop_reading.set()
        if self._io_thread is not None:
            self._io_thread.join(STOP_JOIN_S)
        for p in self.ports.values():
            p.source.close()
        now = time.time_ns()
        for p in self.ports.values():
            if p.node is not None:
                p.node.flush(now)
        self.checkpoint()
        self._report_counts(now)
        logged = {sid: p.samples_logged for sid, p in self.ports.items()}
        self._gateway_event("stop", now, {"samples_logged": logged,
                                          "uptime_s": time.monotonic() - self._started_s})
        self._report_recording(now)
        self.writer.close()
        self._write_watch.closed()
        if self.bus is not None:
            self.bus.close()
        return logged

    # -- the I/O thread -----------------------------------------------------------------------


    def _handle(self, p: Port, batch: RawBatch, log_ns: int) -> None:
        """Log first (nothing lost), then publish the same bytes, then calibrate."""
        self.writer.log_raw(p.sensor_id, batch, log_ns)
        p.samples_logged += len(batch)
        p.batches_logged += 1
        if p.raw_publisher is not None and not self.bus.closed:
            # encoded only if someone subscribes; a refusal is counted in the bus stats
            p.raw_publisher.put(partial(messages.encode_raw, p.sensor_id, batch))
        if p.node is None:
            return
        try:
            p.node.process(batch, log_ns)
        except Exception as exc:  # one bad batch must not stop the calibration
            p.node_errors += 1
            if p.node_errors <= 5 or p.node_errors % 1000 == 0:
                log.exception("node %s failed on a batch", p.sensor_id)
                self._sensor_event(p.sensor_id, "node_error", log_ns, {
                    "error": f"{type(exc).__name__}: {exc}", "count": p.node_errors})
        if p.node.failed is not None and self.fatal is None:
            # no batch of this stream can ever be calibrated (a channel the model needs is
            # not in it): a start-up error found at the first batch, so the daemon stops
            # (the log is finished) instead of running on uncalibrated
            self.fatal = f"sensor {p.sensor_id}: {p.node.failed}"
            if self._stop_event is not None:
                self._stop_event.set()

    # -- events -------------------------------------------------------------------------------

    def _source_event(self, p: Port, ev: SourceEvent, now: int) -> None:
        if ev.kind == "parse_errors":
            for k, v in ev.detail.items():
                if k != "port":
                    p.parse_errors[k] = p.parse_errors.get(k, 0) + int(v)
            return
        if ev.kind == "port_busy" and self.fatal is None:
            # another process owns the device now (it won a race for it after an unplug):
            # reading on would take it back from that one at its next unplug
            self.fatal = f"port {p.sensor.port} is {ev.detail.get('error', 'in use')}"
            if self._stop_event is not None:
                self._stop_event.set()
        if ev.kind in ("open_failed", "port_busy"):
            p.open_failures += 1
            if p.open_failures == 1:  # once per outage: retries follow with back-off
                kind = "port_missing" if ev.kind == "open_failed" else "port_busy"
                self._sensor_event(p.sensor_id, kind, now, ev.detail)
            return
        if ev.kind in ("port_opened", "port_found"):
            if p.ever_opened and p.node is not None:  # unplugged and back: another device?
                p.node.port_reopened()
            p.is_open, p.ever_opened, p.open_failures = True, True, 0
        elif ev.kind == "port_lost":
            p.is_open = False
            p.lost_count += 1
        self._sensor_event(p.sensor_id, ev.kind, now, ev.detail)

    def _report_counts(self, now: int) -> None:
        """Parse errors and dropped publishes since the last report, as events."""
        for p in self.ports.values():
            snapshot = dict(p.parse_errors)
            delta = {k: v - p.parse_reported.get(k, 0) for k, v in snapshot.items()
                     if v != p.parse_reported.get(k, 0)}
            if delta:
                p.parse_reported = snapshot
                self._sensor_event(p.sensor_id, "parse_errors", now,
                                   {"new": delta, "total": snapshot})
            self._note_parse_errors(p, snapshot)
        dropped = self._publish_dropped()
        if dropped > self._publish_reported:
            new = dropped - self._publish_reported
            self._publish_reported = dropped
            for sid in self.ports:
                self._sensor_event(sid, "publish_dropped", now, {"new": new, "total": dropped},
                                   publish=False)

    def _note_parse_errors(self, p: Port, snapshot: dict[str, int]) -> None:
        """Bad input skipped since the last such line, for the operator, at most every
        PARSE_NOTE_S per sensor (a device that sends garbage for weeks fills no journal)."""
        now_s = time.monotonic()
        new = {k: v - p.parse_noted.get(k, 0) for k, v in snapshot.items()
               if k not in PARSE_NOT_NOTED and v != p.parse_noted.get(k, 0)}
        if not new or now_s < p.parse_noted_s + PARSE_NOTE_S:
            return
        p.parse_noted, p.parse_noted_s = snapshot, now_s
        what = ", ".join(f"{k} {v}" for k, v in sorted(new.items()))
        hint = ""
        if ("wrong_columns" in new and p.sensor.rate_hz is None
                and wire_format(p.sensor.format).untimed_by_rate):
            hint = " (lines x,y,z[,aux] without a time column need the rate: --rate or rate_hz)"
        self.out(f"{NOTE_PREFIX} {p.sensor_id}: skipped bad input ({what}); valid samples "
                 f"kept{hint}")

    def _report_recording(self, now: int) -> None:
        """Lines and events about the recording's writes (see RecordingWatch)."""
        self._write_watch.check(now, lambda kind, detail: self._gateway_event(kind, now, detail))

    def _publish_dropped(self) -> int:
        if self.bus is None:
            return 0
        return int(self.bus.stats().get("publish_failed", 0))

    def _sensor_event(self, sid: str, kind: str, now: int, detail: Any,
                      publish: bool = True) -> None:
        if kind in NOTE_KINDS:
            why = f": {detail['error']}" if isinstance(detail, dict) and "error" in detail else ""
            port = detail.get("port", "") if isinstance(detail, dict) else ""
            wait = "; waiting for it" if kind == "port_missing" else ""
            self.out(f"{NOTE_PREFIX} {sid}: {kind.replace('_', ' ')} {port}{why}{wait}".rstrip())
        data = self.writer.write_event(kind, now, sensor_id=sid, detail=detail)
        if publish:
            self._publish(sid, "events", data)

    def _gateway_event(self, kind: str, now: int, detail: Any) -> None:
        self.writer.write_event(kind, now, detail=detail)
        # on the bus, every sensor's event stream hears that its gateway started or stopped
        for sid in self.ports:
            self._publish(sid, "events", messages.encode_event(
                f"gateway_{kind}", sensor_id=sid, detail=detail))

    def _publish(self, sid: str, topic: str, data: bytes, key_expr: str | None = None) -> None:
        if self.bus is None:
            return
        from recal.io.bus import key

        try:
            self.bus.publish(key_expr or key(sid, topic), data)
        except RuntimeError:
            pass  # bus closed during shutdown; counted by the final stats

    # -- queries and checkpoints --------------------------------------------------------------

    def _declare_queries(self, sid: str, p: Port) -> None:
        from recal.io.bus import key

        self.bus.queryable(key(sid, "status"),
                           lambda _k, _pl: messages.encode_json(self.status(sid)))
        if p.node is not None:
            self.bus.queryable(key(sid, "align"), align_handler(p.node, self.out, NOTE_PREFIX))

    def status(self, sid: str) -> dict[str, Any]:
        """The sensor's calibration state (if calibrated here) plus the gateway's counters."""
        p = self.ports[sid]
        state = p.node.status() if p.node is not None else {"sensor_id": sid}
        state["gateway"] = p.status()
        h = self.writer.health()
        state["gateway"]["recording"] = {
            "writing": not h.failing, "error": h.error, "waiting_bytes": h.waiting_bytes,
            "dropped_samples": h.dropped_samples, "dropped_messages": h.dropped_messages}
        return state

    def checkpoint(self, sensor_ids: Sequence[str] | None = None) -> None:
        """Write these sensors' (default: every) checkpoints atomically (no-op without a
        checkpoint dir); a failure is an event and a console line (rate-limited), never
        raised."""
        self.checkpoints.save(self._nodes(), sensor_ids)


# ---------------------------------------------------------------------------------------------
# Entry points
# ---------------------------------------------------------------------------------------------



def _nodes(cfg: ServiceConfig, sink: Sink, model_path: str | Path | None,
           checkpoints: Checkpoints) -> dict[str, CalibrationNode | None]:
    nodes: dict[str, CalibrationNode | None] = {}
    for s in cfg.sensors:
        if not cfg.run_nodes:
            nodes[s.id] = None
            continue
        settings = node_settings(s, cfg, model_path)
        nodes[s.id] = make_node(settings, sink, checkpoints)
    return nodes


def _checkpoints(cfg: ServiceConfig, emit: Callable[[str], None]) -> Checkpoints:
    """The sensors' checkpoints (none without nodes here), with their locks taken:
    SensorLockedError or OSError when they cannot be."""
    c = cfg.checkpoint
    keeper = Checkpoints(c.dir if cfg.run_nodes else None, c.interval_s, c.after_update_s,
                         out=emit, prefix=NOTE_PREFIX)
    keeper.acquire(s.id for s in cfg.sensors)
    return keeper


def run_gateway(config: ServiceConfig | str | Path | None, ports: Sequence[str] = (),
                sensor_ids: Sequence[str] = (), mcap_out: str | Path | None = None,
                model_path: str | Path | None = None,
                stop_event: threading.Event | None = None, *,
                out: Callable[[str], None] | None = None,
                on_ready: Callable[[Gateway], None] | None = None,
                batch_s: float | None = None, idle_batch_s: float | None = None,
                sensor_options: SensorOptions | None = None) -> int:
    """Run the daemon until ``stop_event`` is set or SIGINT/SIGTERM arrives.

    Args:
        config: a ServiceConfig, a TOML path, or None for defaults.
        ports, sensor_ids: serve these ports (ids paired by position; ids also pick the
            matching ``[[sensors]]`` entry for format, rate and prior). Without ports: the
            configured sensors (only ``sensor_ids`` if given).
        mcap_out: recording file or directory (default: the config's [mcap]).
        model_path: a model file for every sensor (replaces the priors' model files).
        stop_event: set it to stop (tests, the demo).
        out: where the ready/stopped lines and errors go (default: print).
        on_ready: called with the running Gateway once it is reading (tests, the demo).
        batch_s: handle arrivals every ``batch_s`` seconds instead of at once (see Gateway);
            None: the config's ``batch_ms``.
        idle_batch_s: the tick while nobody subscribes live (see Gateway); None: the config's
            ``idle_batch_ms``.
        sensor_options: the command line's rate, channels and prior for every served sensor
            (`recal.config.settings.with_options`).
    Returns 0 on a clean stop, 2 for a configuration error (also one found at a sensor's first
    batch: a channel its model needs is not in the stream), 1 if the log or bus cannot open.
    """
    emit, fail = console(out)
    try:
        if batch_s is not None and not batch_s >= 0:
            raise ConfigError(f"--batch-ms must be 0 or more, not {batch_s * 1e3:g}")
        cfg = config if isinstance(config, ServiceConfig) else load_config(config)
        cfg = with_options(cfg.with_sensors(select_sensors(cfg, ports, sensor_ids)),
                           sensor_options or SensorOptions())
        if cfg.run_nodes:
            check_model_channels(cfg, model_path)
        batch_s = cfg.batch_ms / 1e3 if batch_s is None else batch_s
        idle_batch_s = cfg.idle_batch_ms / 1e3 if idle_batch_s is None else idle_batch_s
        if not cfg.sensors:
            raise ConfigError("no sensors: give ports, or [[sensors]] with a port in the config")
    except ConfigError as exc:
        fail(f"{ERROR_PREFIX} {exc}")
        return 2
    stop = stop_event or threading.Event()
    restore = install_stop_signals(stop)
    try:
        with rediscovery.in_a_process(cfg.run_nodes and cfg.discovery.active):
            return _serve(cfg, mcap_out, model_path, stop, emit, fail, on_ready, batch_s,
                          idle_batch_s)
    finally:
        restore()


def _serve(cfg: ServiceConfig, mcap_out: str | Path | None, model_path: str | Path | None,
           stop: threading.Event, emit: Callable[[str], None], fail: Callable[[str], None],
           on_ready: Callable[[Gateway], None] | None, batch_s: float = 0.0,
           idle_batch_s: float = 0.0) -> int:
    try:  # before anything is opened: a second daemon for a sensor must not touch its port
        checkpoints = _checkpoints(cfg, emit)
    except SensorLockedError as exc:
        fail(f"{ERROR_PREFIX} {exc}")
        return 1
    except OSError as exc:
        fail(f"{ERROR_PREFIX} cannot use the state folder {cfg.checkpoint.dir}: "
             f"{exc.strerror or exc}")
        return 1
    try:
        try:  # before the recording: a daemon that lost a port must leave no trace
            sources, opened = claim_ports(cfg)
        except PortTakenError as exc:
            fail(f"{ERROR_PREFIX} {exc}")
            return 1
        try:
            return _serve_locked(cfg, mcap_out, model_path, stop, emit, fail, on_ready,
                                 batch_s, idle_batch_s, checkpoints, sources, opened)
        finally:
            for src in sources.values():
                src.close()
    finally:
        checkpoints.release()


def _serve_locked(cfg: ServiceConfig, mcap_out: str | Path | None,
                  model_path: str | Path | None, stop: threading.Event,
                  emit: Callable[[str], None], fail: Callable[[str], None],
                  on_ready: Callable[[Gateway], None] | None, batch_s: float,
                  idle_batch_s: float, checkpoints: Checkpoints,
                  sources: dict[str, SerialSource], opened: dict[str, list[SourceEvent]]
                  ) -> int:
    try:
        writer = open_recording(cfg, mcap_out)
    except (OSError, ValueError) as exc:
        fail(f"{ERROR_PREFIX} cannot open the recording: {exc}")
        return 1
    try:
        bus = open_bus(cfg)
    except Exception as exc:  # zenoh.ZError: bad endpoint, port in use, router down
        writer.close()
        fail(f"{ERROR_PREFIX} cannot open Zenoh: {exc}")
        return 1
    sink: Sink = make_sink(writer, bus)
    problems: list[tuple[str, str, Any]] = []  # until the gateway can log them as events
    checkpoints.set_event(lambda sid, kind, d: problems.append((sid, kind, d)))
    try:
        nodes = _nodes(cfg, sink, model_path, checkpoints)
    except ConfigError as exc:
        writer.close()
        if bus is not None:
            bus.close()
        fail(f"{ERROR_PREFIX} {exc}")
        return 2
    gw = Gateway(cfg, writer, bus, nodes, emit, batch_s=batch_s, idle_batch_s=idle_batch_s,
                 checkpoints=checkpoints, sources=sources, opened=opened)
    gw.start()
    for sid, kind, detail in problems:
        gw._sensor_event(sid, kind, time.time_ns(), detail)
    starts = {sid: (n.start if n is not None else "remote") for sid, n in nodes.items()}
    if checkpoints.enabled:
        emit(f"{NOTE_PREFIX} checkpoints in {checkpoints.directory}")
    emit(f"{READY_PREFIX} mcap={gw.writer.paths[0]} sensors={starts}")
    if on_ready is not None:
        on_ready(gw)
    try:
        gw.run(stop)
    finally:
        logged = gw.stop()
    flush_console(emit)
    emit(f"{STOPPED_PREFIX} samples={logged}")
    if gw.fatal is not None:
        fail(f"{ERROR_PREFIX} {gw.fatal}")
        return 2
    return 0

