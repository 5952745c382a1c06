"""The gateway daemon: serial ports -> raw log + bus -> calibration nodes -> log + bus.

Per sensor (one serial port each) two threads:

* a reader: ``SerialSource.read_batch`` in chunks; every parsed batch is written to the MCAP
  log at once (``/<sensor>/raw``) and the same bytes are published on ``recal/<sensor>/raw``,
  then queued for the node. Logging first and in the reader means a sample that reached the
  service is in the log exactly once, whatever happens to the node or the bus; the recording
  writer flushes small chunks every ``flush_interval_s``, so a crash loses at most that much.
* a worker: takes batches from a bounded queue and runs the sensor's
  :class:`recal.node.CalibrationNode` (calibrated, body, calibration state, plot, events to the
  log and the bus). The queue decouples reading from calibration hiccups; when it is full the
  reader waits, so the serial port is the back-pressure point, as with a real UART.

With ``run_nodes = false`` the gateway only logs and publishes raw; a node elsewhere
(``recal.node.run_node``) subscribes to ``recal/*/raw``.

The main thread checkpoints every pipeline atomically (tmp file + os.replace) every
``checkpoint.interval_s`` and at stop, reports aggregated counts (parse errors, dropped
publishes) once a second as events, and waits for SIGINT/SIGTERM or a stop event. Stopping
drains the queues, writes the checkpoints, closes (and indexes) the MCAP and the Zenoh session.
A restart resumes each pipeline from its checkpoint (the checkpoint wins over a changed prior in
the config; delete ``<checkpoint dir>/<sensor>.json`` to start from the prior again, and a
checkpoint whose model kind differs from the config's is ignored with an event).

Queries: ``recal/<sensor>/status`` answers the node's calibration state plus a ``gateway``
section (port, samples logged, parse errors, ...); ``recal/<sensor>/align`` requests a
mounting alignment.

Memory is bounded: per sensor one queue of at most ``QUEUE_BATCHES`` batches, the parser's
partial line, the pipeline's bounded buffer; counters only.
"""

from __future__ import annotations

import argparse
import logging
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any

from recal.config import ConfigError, SensorConfig, ServiceConfig, load_config
from recal.io import messages
from recal.io.frames import make_parser
from recal.io.recording import RecordingWriter
from recal.io.serial_source import SerialSource, SourceEvent
from recal.node import (
    BusSink,
    CalibrationNode,
    MultiSink,
    RecordingSink,
    Sink,
    checkpoint_path,
    make_node,
    node_settings,
    save_checkpoint,
)
from recal.samples import RawBatch

__all__ = [
    "READY_PREFIX",
    "Gateway",
    "install_stop_signals",
    "main",
    "open_bus",
    "open_recording",
    "recording_path",
    "run_gateway",
]

log = logging.getLogger(__name__)

READY_PREFIX = "recal gateway ready"
STOPPED_PREFIX = "recal gateway stopped"
QUEUE_BATCHES = 512  # per sensor; ~5 s of 100 Hz data read in 10 ms chunks
READ_WAIT_S = 0.05  # longest read_batch call: bounds how fast a stop is noticed
REPORT_INTERVAL_S = 1.0  # aggregated events (parse errors, dropped publishes) at most this often
STOP_JOIN_S = 10.0


# ---------------------------------------------------------------------------------------------
# Shared shell helpers (also used by recal.node.run_node and recal.demo)
# ---------------------------------------------------------------------------------------------

def install_stop_signals(stop: threading.Event) -> Callable[[], None]:
    """SIGINT/SIGTERM set ``stop`` (main thread only); returns a function that undoes it."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}

    def restore() -> None:
        for s, old in previous.items():
            signal.signal(s, old)

    return restore


def open_bus(cfg: ServiceConfig) -> Any:
    """A recal.io.bus.Bus from the [zenoh] settings, or None when Zenoh is disabled."""
    if not cfg.zenoh.enabled:
        return None
    from recal.io.bus import Bus, zenoh_config

    z = cfg.zenoh
    return Bus(zenoh_config(z.mode, z.listen, z.connect,
                            config_file=str(z.config_file) if z.config_file else None))


def recording_path(cfg: ServiceConfig, mcap_out: str | Path | None) -> Path:
    """Where to log: ``mcap_out`` (a file, or a directory for an auto-named file), else the
    config's path or dir. An existing file is never overwritten: a time-stamped sibling
    ``<stem>-<UTC>.mcap`` is used instead (e.g. after a crash, for the repair to read)."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    target = Path(mcap_out) if mcap_out is not None else cfg.mcap.path
    if target is None or target.is_dir() or str(target).endswith(("/", "\\")):
        directory = target if target is not None else cfg.mcap.dir
        return Path(directory) / f"recal-{stamp}.mcap"
    if not target.exists():
        return target
    for i in range(1000):
        alt = target.with_name(f"{target.stem}-{stamp}{'' if i == 0 else f'-{i}'}"
                               f"{target.suffix}")
        if not alt.exists():
            return alt
    raise FileExistsError(f"no free name next to {target}")


def open_recording(cfg: ServiceConfig, mcap_out: str | Path | None) -> RecordingWriter:
    """A RecordingWriter with the [mcap] settings at :func:`recording_path`."""
    m = cfg.mcap
    return RecordingWriter(
        recording_path(cfg, mcap_out), chunk_size=m.chunk_size,
        flush_interval_s=m.flush_interval_s,
        rotate_bytes=None if m.rotate_mb is None else int(m.rotate_mb * 1e6),
        rotate_s=None if m.rotate_hours is None else m.rotate_hours * 3600.0,
        compression=m.compression, fsync=m.fsync)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# One sensor's live parts
# ---------------------------------------------------------------------------------------------

@dataclass
class _Port:
    """A sensor's serial source, node, queue, threads and counters."""

    sensor: SensorConfig
    source: SerialSource
    node: CalibrationNode | None
    queue: queue.Queue[tuple[RawBatch, int]]
    reader_done: threading.Event = field(default_factory=threading.Event)
    threads: list[threading.Thread] = field(default_factory=list)
    samples_logged: int = 0
    batches_logged: int = 0
    is_open: bool = False
    ever_opened: bool = False
    lost_count: int = 0
    open_failures: int = 0
    parse_errors: dict[str, int] = field(default_factory=dict)
    parse_reported: dict[str, int] = field(default_factory=dict)
    node_errors: int = 0
    queue_waits: int = 0

    @property
    def sensor_id(self) -> str:
        return self.sensor.id

    def status(self) -> dict[str, Any]:
        return {"port": self.sensor.port, "open": self.is_open, "lost_count": self.lost_count,
                "samples_logged": self.samples_logged, "batches_logged": self.batches_logged,
                "parse_errors": dict(self.parse_errors),
                "parse_errors_total": sum(self.parse_errors.values()),
                "queue": self.queue.qsize(), "queue_waits": self.queue_waits,
                "node_errors": self.node_errors}


class Gateway:
    """The daemon's parts and threads. :meth:`start`, then :meth:`run` until stopped.

    Args:
        cfg: service configuration; its sensors (each with a port) are served.
        writer: the MCAP log.
        bus: a recal.io.bus.Bus, or None to run without Zenoh.
        nodes: node per sensor id (None for every sensor when ``run_nodes`` is off).
        out: where the ready/stopped lines go.
    """

    def __init__(self, cfg: ServiceConfig, writer: RecordingWriter, bus: Any,
                 nodes: dict[str, CalibrationNode | None],
                 out: Callable[[str], None] = print) -> None:
        self.cfg = cfg
        self.writer = writer
        self.bus = bus
        self.out = out
        self._stop_reading = threading.Event()
        self._lock = threading.Lock()  # event counters touched by several threads
        self.ports: dict[str, _Port] = {}
        for s in cfg.sensors:
            assert s.port is not None
            parser = make_parser(s.format, s.aux_names)
            src = SerialSource(s.port, parser, s.baudrate, read_timeout_s=0.02)
            self.ports[s.id] = _Port(s, src, nodes.get(s.id), queue.Queue(QUEUE_BATCHES))
        self._publish_reported = 0
        self._started_s = time.monotonic()

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        now = time.time_ns()
        self._gateway_event("start", now, {
            "sensors": {sid: p.sensor.port for sid, p in self.ports.items()},
            "mcap": str(self.writer.paths[0]), "run_nodes": self.cfg.run_nodes})
        for sid, p in self.ports.items():
            if self.bus is not None:
                self._declare_queries(sid, p)
            reader = threading.Thread(target=self._read_loop, args=(p,),
                                      name=f"recal-read-{sid}", daemon=True)
            p.threads.append(reader)
            if p.node is not None:
                worker = threading.Thread(target=self._work_loop, args=(p,),
                                          name=f"recal-node-{sid}", daemon=True)
                p.threads.append(worker)
            for t in p.threads:
                t.start()

    def run(self, stop: threading.Event) -> None:
        """Checkpoint and report until ``stop`` is set."""
        interval = self.cfg.checkpoint.interval_s
        next_ckpt = time.monotonic() + interval
        next_report = time.monotonic() + REPORT_INTERVAL_S
        while not stop.wait(0.1):
            now = time.monotonic()
            if now >= next_report:
                self._report_counts(time.time_ns())
                next_report = now + REPORT_INTERVAL_S
            if now >= next_ckpt:
                self.checkpoint()
                next_ckpt = now + interval

    def stop(self) -> dict[str, int]:
        """Stop reading, drain the nodes, checkpoint, close the log and the bus.

        Returns samples logged per sensor.
        """
        self._stop_reading.set()
        deadline = time.monotonic() + STOP_JOIN_S
        for p in self.ports.values():
            for t in p.threads:
                t.join(max(0.1, deadline - time.monotonic()))
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
        self.writer.close()
        if self.bus is not None:
            self.bus.close()
        return logged

    # -- threads ------------------------------------------------------------------------------

    def _read_loop(self, p: _Port) -> None:
        try:
            while not self._stop_reading.is_set():
                batch, events = p.source.read_batch(READ_WAIT_S)
                now = time.time_ns()
                for ev in events:
                    self._source_event(p, ev, now)
                if len(batch):
                    self._log_raw(p, batch, now)
        except Exception:  # never let a reader die silently: the sensor would go quiet
            log.exception("reader of %s failed", p.sensor_id)
            self._sensor_event(p.sensor_id, "reader_failed", time.time_ns(), None)
        finally:
            p.reader_done.set()

    def _log_raw(self, p: _Port, batch: RawBatch, log_ns: int) -> None:
        """Log first (nothing lost), then publish the same bytes, then queue for the node."""
        data = self.writer.write_raw(p.sensor_id, batch, log_ns)
        p.samples_logged += len(batch)
        p.batches_logged += 1
        self._publish(p.sensor_id, "raw", data)
        if p.node is None:
            return
        item = (batch, log_ns)
        while True:
            try:
                p.queue.put(item, timeout=0.5)
                return
            except queue.Full:
                p.queue_waits += 1  # the node is behind; waiting back-pressures the port

    def _work_loop(self, p: _Port) -> None:
        assert p.node is not None
        while True:
            try:
                batch, log_ns = p.queue.get(timeout=0.1)
            except queue.Empty:
                if p.reader_done.is_set() and p.queue.empty():
                    return
                continue
            try:
                p.node.process(batch, log_ns)
            except Exception as exc:  # one bad batch must not stop the calibration
                p.node_errors += 1
                if p.node_errors <= 5 or p.node_errors % 1000 == 0:
                    log.exception("node %s failed on a batch", p.sensor_id)
                    self._sensor_event(p.sensor_id, "node_error", log_ns, {
                        "error": f"{type(exc).__name__}: {exc}", "count": p.node_errors})

    # -- events -------------------------------------------------------------------------------

    def _source_event(self, p: _Port, ev: SourceEvent, now: int) -> None:
        if ev.kind == "parse_errors":
            for k, v in ev.detail.items():
                if k != "port":
                    p.parse_errors[k] = p.parse_errors.get(k, 0) + int(v)
            return
        if ev.kind == "open_failed":
            p.open_failures += 1
            if p.open_failures == 1:  # once per outage: retries follow with back-off
                self._sensor_event(p.sensor_id, "port_missing", now, ev.detail)
            return
        if ev.kind in ("port_opened", "port_found"):
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
        dropped = self._publish_dropped()
        if dropped > self._publish_reported:
            new = dropped - self._publish_reported
            self._publish_reported = dropped
            for sid in self.ports:
                self._sensor_event(sid, "publish_dropped", now, {"new": new, "total": dropped},
                                   publish=False)

    def _publish_dropped(self) -> int:
        if self.bus is None:
            return 0
        return int(self.bus.stats().get("publish_failed", 0))

    def _sensor_event(self, sid: str, kind: str, now: int, detail: Any,
                      publish: bool = True) -> None:
        data = self.writer.write_event(kind, now, sensor_id=sid, detail=detail)
        if publish:
            self._publish(sid, "events", data)

    def _gateway_event(self, kind: str, now: int, detail: Any) -> None:
        self.writer.write_event(kind, now, detail=detail)
        # on the bus, every sensor's event stream hears that its gateway started or stopped
        for sid in self.ports:
            self._publish(sid, "events", messages.encode_event(
                f"gateway_{kind}", sensor_id=sid, detail=detail))

    def _publish(self, sid: str, topic: str, data: bytes) -> None:
        if self.bus is None:
            return
        from recal.io.bus import key

        try:
            self.bus.publish(key(sid, topic), data)
        except RuntimeError:
            pass  # bus closed during shutdown; counted by the final stats

    # -- queries and checkpoints --------------------------------------------------------------

    def _declare_queries(self, sid: str, p: _Port) -> None:
        from recal.io.bus import key

        self.bus.queryable(key(sid, "status"),
                           lambda _k, _pl: messages.encode_json(self.status(sid)))
        if p.node is not None:
            node = p.node
            self.bus.queryable(key(sid, "align"),
                               lambda _k, _pl: messages.encode_json(node.request_alignment()))

    def status(self, sid: str) -> dict[str, Any]:
        """The sensor's calibration state (if calibrated here) plus the gateway's counters."""
        p = self.ports[sid]
        state = p.node.status() if p.node is not None else {"sensor_id": sid}
        state["gateway"] = p.status()
        return state

    def checkpoint(self) -> None:
        """Write every node's checkpoint atomically (no-op without a checkpoint dir)."""
        directory = self.cfg.checkpoint.dir
        if directory is None:
            return
        for sid, p in self.ports.items():
            doc = p.node.checkpoint() if p.node is not None else None
            if doc is None:
                continue
            try:
                save_checkpoint(checkpoint_path(directory, sid), doc)
            except OSError as exc:
                self._sensor_event(sid, "checkpoint_failed", time.time_ns(), str(exc))


# ---------------------------------------------------------------------------------------------
# Entry points
# ---------------------------------------------------------------------------------------------

def _sensors(cfg: ServiceConfig, ports: Sequence[str], sensor_ids: Sequence[str]
             ) -> list[SensorConfig]:
    """The sensors to serve: ports from the command line (ids matched to config entries),
    else the configured sensors (limited to ``sensor_ids`` if given)."""
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
            else:
                base = SensorConfig(id=f"sensor{i}")
            chosen.append(replace(base, port=port))
        return chosen
    chosen = [s for s in cfg.sensors if not sensor_ids or s.id in sensor_ids]
    missing = sorted(set(sensor_ids) - {s.id for s in chosen})
    if missing:
        raise ConfigError(f"sensor {missing[0]!r} is not in the configuration")
    without = [s.id for s in chosen if s.port is None]
    if without:
        raise ConfigError(f"sensor {without[0]!r} has no port")
    return chosen


def _nodes(cfg: ServiceConfig, sink: Sink, model_path: str | Path | None,
           problems: list[tuple[str, str, dict]]) -> dict[str, CalibrationNode | None]:
    nodes: dict[str, CalibrationNode | None] = {}
    for s in cfg.sensors:
        if not cfg.run_nodes:
            nodes[s.id] = None
            continue
        settings = node_settings(s, cfg, model_path)
        nodes[s.id] = make_node(settings, sink, cfg.checkpoint.dir,
                                lambda kind, d, sid=s.id: problems.append((sid, kind, d)))
    return nodes


def run_gateway(config: ServiceConfig | str | Path | None, ports: Sequence[str] = (),
                sensor_ids: Sequence[str] = (), mcap_out: str | Path | None = None,
                model_path: str | Path | None = None,
                stop_event: threading.Event | None = None, *,
                out: Callable[[str], None] | None = None,
                on_ready: Callable[[Gateway], None] | None = None) -> int:
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
    Returns 0 on a clean stop, 2 for a configuration error, 1 if the log or bus cannot open.
    """
    emit = out or (lambda s: print(s, flush=True))
    fail = out or (lambda s: print(s, file=sys.stderr, flush=True))
    try:
        cfg = config if isinstance(config, ServiceConfig) else load_config(config)
        cfg = cfg.with_sensors(_sensors(cfg, ports, sensor_ids))
        if not cfg.sensors:
            raise ConfigError("no sensors: give ports, or [[sensors]] with a port in the config")
    except ConfigError as exc:
        fail(f"recal gateway: {exc}")
        return 2
    stop = stop_event or threading.Event()
    restore = install_stop_signals(stop)
    try:
        return _serve(cfg, mcap_out, model_path, stop, emit, fail, on_ready)
    finally:
        restore()


def _serve(cfg: ServiceConfig, mcap_out: str | Path | None, model_path: str | Path | None,
           stop: threading.Event, emit: Callable[[str], None], fail: Callable[[str], None],
           on_ready: Callable[[Gateway], None] | None) -> int:
    try:
        writer = open_recording(cfg, mcap_out)
    except (OSError, ValueError) as exc:
        fail(f"recal gateway: cannot open the recording: {exc}")
        return 1
    try:
        bus = open_bus(cfg)
    except Exception as exc:  # zenoh.ZError: bad endpoint, port in use, router down
        writer.close()
        fail(f"recal gateway: cannot open Zenoh: {exc}")
        return 1
    sink: Sink = RecordingSink(writer) if bus is None else MultiSink(RecordingSink(writer),
                                                                      BusSink(bus))
    problems: list[tuple[str, str, dict]] = []
    try:
        nodes = _nodes(cfg, sink, model_path, problems)
    except ConfigError as exc:
        writer.close()
        if bus is not None:
            bus.close()
        fail(f"recal gateway: {exc}")
        return 2
    gw = Gateway(cfg, writer, bus, nodes, emit)
    gw.start()
    for sid, kind, detail in problems:
        gw._sensor_event(sid, kind, time.time_ns(), detail)
    starts = {sid: (n.start if n is not None else "remote") for sid, n in nodes.items()}
    emit(f"{READY_PREFIX} mcap={gw.writer.paths[0]} sensors={starts}")
    if on_ready is not None:
        on_ready(gw)
    try:
        gw.run(stop)
    finally:
        logged = gw.stop()
    emit(f"{STOPPED_PREFIX} samples={logged}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m recal.gateway --config gateway.toml [--port P --sensor-id ID ...]``."""
    ap = argparse.ArgumentParser(prog="python -m recal.gateway", description=__doc__.split(
        "\n")[0])
    ap.add_argument("--config", help="service TOML (configs/gateway.toml)")
    ap.add_argument("--port", action="append", default=[], help="serial port (repeatable)")
    ap.add_argument("--sensor-id", action="append", default=[], help="id per --port")
    ap.add_argument("--mcap", help="recording file or directory")
    ap.add_argument("--model", help="model file for every sensor")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return run_gateway(args.config, args.port, args.sensor_id, args.mcap, args.model)


if __name__ == "__main__":
    sys.exit(main())
