"""``recal node``: calibration nodes on a machine of their own, fed by gateways over Zenoh.

Gateways that run with ``run_nodes = false`` only log and publish ``recal/<sensor>/raw``; this
process subscribes to ``recal/*/raw``, admits the sensor ids it serves (:class:`SensorGate`:
named ones, and with ``accept_any`` a bounded number of others), runs one
:class:`recal.node.node.CalibrationNode` per admitted sensor, publishes what they derive, answers
the status and align queries, and checkpoints like the gateway. Deployment and access
control: docs/design.md; throughput: docs/performance.md.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from recal.config import SensorConfig, ServiceConfig, load_config
from recal.daemon.checkpoint_store import Checkpoints, SensorLockedError
from recal.daemon.runtime import (
    ERROR_PREFIX,
    console,
    flush_console,
    install_stop_signals,
    open_bus,
    open_recording,
    watch_recording,
)
from recal.errors import ConfigError
from recal.io import bus as _bus
from recal.io import messages
from recal.node import rediscovery
from recal.node.alignment import align_handler
from recal.node.node import CalibrationNode, make_node, node_settings
from recal.node.sinks import Sink, make_sink
from recal.samples import RawBatch, join_by_layout

__all__ = ["NODE_READY_PREFIX", "NOTE_PREFIX", "REJECT_IDS_KEPT", "SensorGate", "run_node"]

log = logging.getLogger(__name__)

NODE_READY_PREFIX = "recal node ready"
RECV_ROUND = 4096  # most raw messages a remote node takes from its receiver per round
# Raw messages a remote node buffers before Zenoh's thread waits (and after its 1 s wait,
# drops): gateways handling every arrival at once send a message per sample, so this must
# hold a second of many sensors (docs/design.md, "Figures behind choices", bench/scale_out.py).
RECV_CAPACITY = 1 << 17
REJECT_REPORT_S = 10.0  # at most one console line and event this often about turned-away ids
REJECT_IDS_KEPT = 16  # example ids named in that line and event (bounded, whatever comes in)
NOTE_PREFIX = "recal node:"


class SensorGate:
    """Which sensor ids a node on the bus serves, and a count of what it turned away.

    Served: the ``named`` ids (config ``[[sensors]]`` or ``--sensor-id``) and, with
    ``accept_any``, up to ``max_sensors`` other ids, first come first served. Anything else
    is counted by reason (``not_served``, ``over_cap``, ``key_mismatch``: the payload names
    another sensor than its key) and dropped before it gets a node, a log channel, a topic or
    a checkpoint. Memory is bounded: counts, and at most ``REJECT_IDS_KEPT`` example ids
    between two reports.
    """

    REASONS = ("not_served", "over_cap", "key_mismatch")

    def __init__(self, named: Iterable[str], accept_any: bool = False,
                 max_sensors: int = 16) -> None:
        self.named = frozenset(named)
        self.accept_any = bool(accept_any)
        self.max_sensors = int(max_sensors)
        self.served: set[str] = set()
        self._extra = 0  # served ids not named (accept_any)
        self.rejected = dict.fromkeys(self.REASONS, 0)  # messages turned away, in all
        self._pending = dict.fromkeys(self.REASONS, 0)  # ... since the last report
        self._ids: set[str] = set()

    def admit(self, sid: str) -> bool:
        """Whether ``sid`` is served (counting it as turned away if not)."""
        if sid in self.served:
            return True
        if sid in self.named:
            self.served.add(sid)
            return True
        if self.accept_any and self._extra < self.max_sensors:
            self._extra += 1
            self.served.add(sid)
            return True
        self.reject(sid, "over_cap" if self.accept_any else "not_served")
        return False

    def reject(self, sid: str, reason: str) -> None:
        self.rejected[reason] += 1
        self._pending[reason] += 1
        if len(self._ids) < REJECT_IDS_KEPT:
            self._ids.add(sid)

    def take_report(self) -> dict[str, Any] | None:
        """What was turned away since the last call (None: nothing)."""
        n = sum(self._pending.values())
        if n == 0:
            return None
        report = {"messages": n, "by_reason": {k: v for k, v in self._pending.items() if v},
                  "sensor_ids": sorted(self._ids), "ids_listed_max": REJECT_IDS_KEPT,
                  "messages_total": sum(self.rejected.values())}
        self._pending = dict.fromkeys(self.REASONS, 0)
        self._ids = set()
        return report

    def describe(self) -> str:
        """One phrase for the console: what this gate lets in."""
        named = ", ".join(sorted(self.named)) or "none named"
        if self.accept_any:
            return f"{named}, and any other sensor up to {self.max_sensors} (accept_any)"
        return named


def run_node(config: ServiceConfig | str | Path | None = None,
             sensor_ids: Sequence[str] = (), mcap_out: str | Path | None = None,
             model_path: str | Path | None = None, stop_event: threading.Event | None = None,
             *, bus: Any = None, out: Callable[[str], None] | None = None,
             accept_any: bool | None = None, max_sensors: int | None = None) -> int:
    """Calibrate the sensors it serves whose raw streams arrive on ``recal/*/raw`` until stopped.

    Serves the sensors ``sensor_ids`` names, else those of the config's ``[[sensors]]``; with
    ``accept_any`` (default: config ``[node] accept_any``) any other sensor as well, at most
    ``max_sensors`` of them (default ``[node] max_sensors``). Other ids are counted and dropped
    (see :class:`SensorGate`), with a console line and a ``sensors_ignored`` event in the
    recording at most every ``REJECT_REPORT_S``. A node with nothing to serve is a
    configuration error. Publishes calibrated, body, calibration and events on the bus,
    answers ``recal/<sensor>/status`` and ``recal/<sensor>/align`` (rate-limited), optionally
    logs everything (raw included) to ``mcap_out``, and checkpoints like the gateway. Stops on
    ``stop_event`` or SIGINT/SIGTERM (main thread). Returns 0, or 2 for a configuration error.
    """
    emit, fail = console(out)
    try:
        cfg = config if isinstance(config, ServiceConfig) else load_config(config)
    except ConfigError as exc:
        fail(f"{ERROR_PREFIX} {exc}")
        return 2
    own_bus = bus is None
    if own_bus and not cfg.zenoh.enabled:
        fail(f"{ERROR_PREFIX} a calibration node takes its samples from Zenoh, but the "
             f"config's [zenoh] enabled = false")
        return 2
    try:
        gate = _gate(cfg, sensor_ids, accept_any, max_sensors)
    except ConfigError as exc:
        fail(f"{ERROR_PREFIX} {exc}")
        return 2
    try:
        bus = open_bus(cfg) if own_bus else bus
    except Exception as exc:  # zenoh.ZError: bad endpoint, port in use, router down
        fail(f"{ERROR_PREFIX} cannot open Zenoh: {exc}")
        return 1
    try:
        writer = open_recording(cfg, mcap_out) if mcap_out is not None else None
    except (OSError, ValueError) as exc:
        if own_bus:
            bus.close()
        fail(f"{ERROR_PREFIX} cannot open the recording: {exc}")
        return 1
    stop = stop_event or threading.Event()
    restore = install_stop_signals(stop)
    runner = _NodeRunner(cfg, bus, writer, gate, model_path, emit)
    emit(f"{NOTE_PREFIX} checkpoints in {cfg.checkpoint.dir or '(none)'}")
    emit(f"{NODE_READY_PREFIX} mcap={writer.paths[0] if writer is not None else None}")
    emit(f"{NOTE_PREFIX} serving {gate.describe()}")
    watch = None if writer is None else watch_recording(writer, emit, cfg.mcap.backlog_mb,
                                                        stop, NOTE_PREFIX)
    try:
        with rediscovery.in_a_process(cfg.discovery.active):
            runner.run(stop)
    finally:
        runner.close()
        if writer is not None:
            writer.close()
        if watch is not None:
            watch.closed()
        if own_bus:
            bus.close()
        restore()
        flush_console(emit)
    return 0


def _gate(cfg: ServiceConfig, sensor_ids: Sequence[str], accept_any: bool | None,
          max_sensors: int | None) -> SensorGate:
    """The node's SensorGate from the arguments and the config (ConfigError if it would
    serve nothing, or for a bad cap)."""
    named = list(sensor_ids) or [s.id for s in cfg.sensors]
    for sid in named:
        try:
            _bus.validate_sensor_id(sid)
        except ValueError as exc:
            raise ConfigError(f"--sensor-id: {exc}") from None
    any_ = cfg.node.accept_any if accept_any is None else accept_any
    cap = cfg.node.max_sensors if max_sensors is None else max_sensors
    if cap < 1:
        raise ConfigError(f"--max-sensors: expected an integer >= 1, got {cap}")
    if not named and not any_:
        raise ConfigError("a calibration node serves only the sensors it is told about: name "
                          "them in [[sensors]] or with --sensor-id, or serve any that "
                          "publishes with [node] accept_any = true (or --accept-any)")
    return SensorGate(named, any_, cap)


class _NodeRunner:
    """The loop of :func:`run_node`: bus messages -> nodes, checkpoints on a timer.

    Messages are taken in rounds of whatever has arrived (up to ``RECV_ROUND``), and each
    sensor's messages of a round are logged and calibrated as one batch (the pipeline is
    batch-size invariant): under load, rounds grow and the per-batch costs are paid less
    often, as in the gateway's read loop. Only the sensors the :class:`SensorGate` admits get
    that far.
    """

    def __init__(self, cfg: ServiceConfig, bus: Any, writer: Any, gate: SensorGate,
                 model_path: str | Path | None, emit: Callable[[str], None]) -> None:
        self.cfg, self.bus, self.writer, self.gate = cfg, bus, writer, gate
        self.model_path, self.emit = model_path, emit
        self.nodes: dict[str, CalibrationNode] = {}
        self.sink: Sink = make_sink(writer, bus)
        self.receiver = bus.receiver(_bus.key_pattern("raw"), capacity=RECV_CAPACITY)
        self.bad_messages = 0
        self.checkpoints = Checkpoints(cfg.checkpoint.dir, cfg.checkpoint.interval_s,
                                       cfg.checkpoint.after_update_s, out=emit,
                                       event=self._sensor_event, prefix=NOTE_PREFIX)
        self.refused: set[str] = set()  # sensors another process calibrates (locked)
        self._drops_reported = 0
        self._next_drop_report_s = 0.0
        self._next_reject_report_s = 0.0
        # key -> sensor id of served sensors only (bounded by the gate): parsing and
        # validating the key cost a tenth of decoding a one-sample message
        self._key_sid: dict[str, str] = {}

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self._handle_round(self.receiver.recv_batch(RECV_ROUND, timeout=0.1))
            self.checkpoints.save_due(self.nodes)  # a few sensors at a time, and after updates
            self._report_drops()
            self._report_rejects()
        while True:  # what already arrived
            msgs = self.receiver.recv_batch(RECV_ROUND, timeout=0.0)
            if not msgs:
                break
            self._handle_round(msgs)
        self._report_rejects(force=True)

    def _report_drops(self) -> None:
        """Say so (at most once a second) when the receive buffer overflowed: samples lost
        here are still in the gateways' logs, but this node's log and calibration miss them
        (it is slower than the gateways; give them a --batch-ms)."""
        dropped = self.receiver.dropped
        if dropped == self._drops_reported or time.monotonic() < self._next_drop_report_s:
            return
        self._next_drop_report_s = time.monotonic() + 1.0
        log.warning("%d raw messages dropped: the node is behind the gateways",
                    dropped - self._drops_reported)
        self.emit(f"recal node: {dropped} raw messages dropped so far (node behind)")
        self._drops_reported = dropped

    def _report_rejects(self, force: bool = False) -> None:
        """At most every REJECT_REPORT_S: one console line and one ``sensors_ignored`` event
        (the recording's service events, ``/gateway/events``; not on the bus, where it would
        need a key of its own) about the raw messages the gate turned away."""
        now = time.monotonic()
        if not force and now < self._next_reject_report_s:
            return
        report = self.gate.take_report()
        if report is None:
            return
        self._next_reject_report_s = now + REJECT_REPORT_S
        why = ", ".join(f"{k} {v}" for k, v in report["by_reason"].items())
        self.emit(f"{NOTE_PREFIX} ignored {report['messages']} raw messages ({why}) from "
                  f"sensor ids it does not serve: {', '.join(report['sensor_ids'])}"
                  f"{' ...' if len(report['sensor_ids']) >= REJECT_IDS_KEPT else ''} "
                  f"(serving {self.gate.describe()})")
        if self.writer is not None:
            self.writer.write_event("sensors_ignored", time.time_ns(), detail=report)

    def _handle_round(self, msgs: list[Any]) -> None:
        """Decode a round of messages and hand each served sensor its samples, in order."""
        by_sensor: dict[str, list[RawBatch]] = {}
        for msg in msgs:
            try:
                key_sid = self._key_sid.get(msg.key) or msg.sensor
                sid, batch = messages.decode_raw(msg.payload)
            except ValueError:
                self.bad_messages += 1
                continue
            if sid and sid != key_sid:
                # the key is what access control checks: a payload naming another sensor
                # would let a gateway allowed on one key write into another sensor's state
                self.gate.reject(key_sid, "key_mismatch")
                continue
            if self.gate.admit(key_sid):
                self._key_sid[msg.key] = key_sid
                by_sensor.setdefault(key_sid, []).append(batch)
        for sid, batches in by_sensor.items():
            for batch in join_by_layout(batches):
                self._handle(sid, batch)

    def _handle(self, sid: str, batch: RawBatch) -> None:
        node = self.nodes.get(sid) or self._add(sid)
        log_ns = time.time_ns()
        if self.writer is not None:
            self.writer.write_raw(sid, batch, log_ns)
        if node is not None:
            node.process(batch, log_ns)

    def _sensor_event(self, sid: str, kind: str, detail: Any) -> None:
        self.sink.json(sid, "events", {"t_us": None, "kind": kind, "sensor_id": sid,
                                       "detail": detail}, time.time_ns())

    def _add(self, sid: str) -> CalibrationNode | None:
        """A node for a sensor first heard; None (said once) when another process holds its
        checkpoint lock in the same state folder: it calibrates that sensor, not this one."""
        if sid in self.refused:
            return None
        try:
            self.checkpoints.acquire([sid])
        except (SensorLockedError, OSError) as exc:
            self.refused.add(sid)
            self.emit(f"{NOTE_PREFIX} not calibrating {sid}: {exc}")
            return None
        sensor = self.cfg.sensor(sid) or SensorConfig(id=sid)
        settings = node_settings(sensor, self.cfg, self.model_path)
        node = make_node(settings, self.sink, self.checkpoints)
        self.nodes[sid] = node
        self.checkpoints.add(sid, node.accepted_updates)
        k = _bus.key
        self.bus.queryable(k(sid, "status"),
                           lambda _k, _p, n=node: messages.encode_json(n.status()))
        self.bus.queryable(k(sid, "align"), align_handler(node, self.emit))
        node.on_note = lambda line, sid=sid: self.emit(f"{NOTE_PREFIX} {sid}: {line}")
        self.emit(f"recal node: calibrating {sid} (start: {node.start})")
        return node

    def checkpoint(self, sensor_ids: Sequence[str] | None = None) -> None:
        """Checkpoint these sensors (default: all); failures are reported, never raised."""
        self.checkpoints.save(self.nodes, sensor_ids)

    def close(self) -> None:
        now = time.time_ns()
        for node in self.nodes.values():
            node.flush(now)
        self.checkpoint()
        self.checkpoints.release()
        self.receiver.close()

