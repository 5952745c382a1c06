"""The gateway daemon end to end: real pseudo-terminals, real Zenoh sessions on 127.0.0.1, real
MCAP files, real processes (kill -9 and restart). Every wait is bounded in count and time."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gateway_process import GatewayProcess, write_config
from polling import wait_for
from recal.commands.demo import free_port
from recal.commands.replay import replay
from recal.config import ServiceConfig, model_and_prior, parse_config
from recal.core.pipeline import Pipeline
from recal.core.status import REOPEN_PROBATION_WINDOWS
from recal.daemon.checkpoint_store import load_checkpoint
from recal.daemon.gateway import NOTE_PREFIX, Gateway, run_gateway
from recal.daemon.remote_node import run_node
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_calibrated, decode_json
from recal.io.repair import repair
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from recal.sim.wearer import SensorSpec, WearerSpec, simulate

RATE_HZ = 100.0
SID = "s1"
GARBAGE = [b"\x00\x01junk\n", b"1,2,3\n", b"12,abc,1,2\n", b"13,nan,1,2\n", b"\xff\xfe\n",
           b"-5,1,2,3\n"]  # one parse error each


def sim_raw(minutes: float, seed: int = 11) -> RawBatch:
    spec = SensorSpec.random(np.random.default_rng(seed), offset_mg=40.0, gain_pct=3.0)
    wearer = WearerSpec(still_s=(8.0, 20.0), move_s=(2.0, 5.0))
    return simulate(minutes / 60.0, RATE_HZ, seed, spec, wearer).raw


def stream(dev: PtyDevice, raw: RawBatch, samples_per_s: float, chunk: int = 20,
           garbage_every: int = 0, stop_after_s: float | None = None) -> tuple[int, int]:
    """Write ``raw`` chunk by chunk at a steady pace (one writer: lines never interleave).

    Returns (samples written, garbage lines written)."""
    start = time.monotonic()
    sent = bad = 0
    for k, i in enumerate(range(0, len(raw), chunk)):
        wait = start + i / samples_per_s - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, 1.0))
        part = raw[i:i + chunk]
        dev.write_batch(part)
        sent += len(part)
        if garbage_every and k % garbage_every == garbage_every // 2:
            dev.write_garbage(GARBAGE[bad % len(GARBAGE)])
            bad += 1
        if stop_after_s is not None and time.monotonic() - start >= stop_after_s:
            break
    return sent, bad


def service_config(tmp: Path, port: str, zenoh_port: int | None, **over: Any) -> ServiceConfig:
    doc: dict[str, Any] = {
        "zenoh": ({"mode": "peer", "listen": [f"tcp/127.0.0.1:{zenoh_port}"], "connect": []}
                  if zenoh_port is not None else {"enabled": False}),
        "mcap": {"flush_interval_s": 0.05},
        "checkpoint": {"dir": str(tmp / "ck"), "interval_s": 0.5},
        "sensors": [{"id": SID, "port": port, "aux_names": [], "rate_hz": RATE_HZ,
                     "prior": {"counts_per_g": 1024.0}}],
    }
    doc.update(over)
    return parse_config(doc, tmp, "test")


class LiveGateway:
    """run_gateway in a thread of this process, stopped through its stop event."""

    def __init__(self, cfg: ServiceConfig, mcap: Path, batch_s: float | None = None) -> None:
        self.stop = threading.Event()
        self.ready: list[Gateway] = []
        self.lines: list[str] = []
        self.rc: list[int] = []
        self.thread = threading.Thread(target=lambda: self.rc.append(run_gateway(
            cfg, mcap_out=mcap, stop_event=self.stop, on_ready=self.ready.append,
            out=self.lines.append, batch_s=batch_s)), daemon=True)
        self.thread.start()
        try:
            assert wait_for(lambda: bool(self.ready) or not self.thread.is_alive(), 20), \
                self.lines
            assert self.ready, self.lines
            self.gw = self.ready[0]
            assert wait_for(lambda: all(p.is_open for p in self.gw.ports.values()), 10), \
                "port never opened"
        except AssertionError:
            self.stop.set()
            self.thread.join(30)
            raise

    def close(self) -> int:
        self.stop.set()
        self.thread.join(30)
        assert not self.thread.is_alive()
        return self.rc[0]


def peer(endpoint_port: int) -> Bus:
    return Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{endpoint_port}"]))


def get_json(bus: Bus, key_expr: str, want: Callable[[dict], bool] = lambda d: True,
             tries: int = 20) -> dict:
    for _ in range(tries):
        for _k, payload in bus.get(key_expr, timeout_s=1.0):
            d = decode_json(payload)
            if want(d):
                return d
        time.sleep(0.05)
    raise AssertionError(f"no reply on {key_expr}")


def direct_pipeline(cfg: ServiceConfig) -> Pipeline:
    sensor = cfg.sensors[0]
    model, prior = model_and_prior(sensor, cfg.pipeline)
    return Pipeline(cfg.pipeline.pipeline_config(RATE_HZ), model, prior, ())


# ---------------------------------------------------------------------------------------------


def test_end_to_end_exactly_once_matches_pipeline_and_replay(tmp_path: Path) -> None:
    raw = sim_raw(3.0)
    zport = free_port()
    link = str(tmp_path / "tty0")
    cfg = service_config(tmp_path, link, zport)
    mcap = tmp_path / "live.mcap"
    with PtyDevice(link) as dev:
        live = LiveGateway(cfg, mcap)
        bus = peer(zport)
        got: list[int] = []
        payloads: list[bytes] = []
        try:
            bus.subscribe(key(SID, "calibrated"), lambda m: (
                payloads.append(m.payload), got.append(len(decode_calibrated(m.payload)[1]))))
            pub = live.gw.bus.publisher(key(SID, "calibrated"))
            assert pub.wait_for_subscribers(10)
            sent, bad = stream(dev, raw, 3000.0, garbage_every=25)
            assert sent == len(raw) and bad > 20 and dev.bytes_dropped == 0

            def caught_up() -> bool:
                st = get_json(bus, key(SID, "status"))
                return st["node"]["samples"] == sent and st["gateway"]["samples_logged"] == sent
            assert wait_for(caught_up, 20, 0.1)
            status = get_json(bus, key(SID, "status"))
            assert status["sensor_id"] == SID and status["model"] == "diagonal"
            assert set(status["params"]) == {"o_x", "o_y", "o_z", "s_x", "s_y", "s_z"}
            assert status["node"]["accepted_updates"] >= 1
            assert status["gateway"]["parse_errors_total"] == bad
            assert status["gateway"]["open"] is True
            align = get_json(bus, key(SID, "align"))
            assert align["status"] in ("aligned", "armed") and align["sensor_id"] == SID
            assert wait_for(lambda: sum(got) == sent, 10), (sum(got), sent)
        finally:
            bus.close()
            assert live.close() == 0

    # every valid sample exactly once, in order, bit for bit
    logged = rec.read_all_raw(mcap, SID)
    np.testing.assert_array_equal(logged.t_us, raw.t_us)
    np.testing.assert_array_equal(logged.v, raw.v)
    # the live calibration is Pipeline.step on the same samples (any batching)
    cal = rec.read_all_calibrated(mcap, SID)
    # what was published (each batch as it came, float64) is what was logged (batches joined
    # per flush, to the micro-g)
    published = type(cal).concat([decode_calibrated(p)[1] for p in payloads])
    np.testing.assert_array_equal(published.t_us, cal.t_us)
    np.testing.assert_array_equal(published.status, cal.status)
    assert np.max(np.abs(published.a_g - cal.a_g)) <= 0.5e-6 + 1e-12
    pipe = direct_pipeline(cfg)
    direct = [pipe.step(logged[i:i + 997]).calibrated for i in range(0, len(logged), 997)]
    ref = type(cal).concat(direct)
    np.testing.assert_array_equal(cal.t_us, ref.t_us)
    np.testing.assert_array_equal(cal.quasi_static, ref.quasi_static)
    assert np.max(np.abs(cal.a_g - ref.a_g)) <= 0.5e-6 + 1e-9  # (logged to the micro-g)
    assert pipe.counts["updates"] >= 1
    # parse errors were counted and logged
    events = [obj for _, obj, _ in rec.iter_json(mcap, f"/{SID}/events")]
    kinds = [e["kind"] for e in events]
    assert "port_opened" in kinds and "node_started" in kinds
    perr = [e for e in events if e["kind"] == "parse_errors"]
    assert perr and sum(perr[-1]["detail"]["total"].values()) == bad
    # ... and the operator got one line for them, not one a second (PARSE_NOTE_S)
    noted = [ln for ln in live.lines if ln.startswith(f"{NOTE_PREFIX} {SID}: skipped bad input")]
    assert len(noted) == 1 and noted[0].endswith("; valid samples kept"), live.lines
    gw_events = [obj["kind"] for _, obj, _ in rec.iter_json(mcap, "/gateway/events")]
    assert gw_events[0] == "start" and gw_events[-1] == "stop"
    states = [obj for _, obj, _ in rec.iter_json(mcap, f"/{SID}/calibration")]
    assert states[0]["reason"] == "start" and len(states) >= 2
    assert any(obj for _, obj, _ in rec.iter_plot(mcap, SID))
    # the recording replays to the same calibration, with no Zenoh
    out = replay(mcap, tmp_path / "replay.mcap", progress=False)
    assert out["sensors"][SID]["start"] == "recording" and out["samples"] == len(raw)
    again = rec.read_all_calibrated(tmp_path / "replay.mcap", SID)
    np.testing.assert_array_equal(again.t_us, cal.t_us)
    assert np.max(np.abs(again.a_g - cal.a_g)) <= 1e-9
    body_live = rec.read_all_calibrated(mcap, SID, "body")
    body_replay = rec.read_all_calibrated(tmp_path / "replay.mcap", SID, "body")
    np.testing.assert_array_equal(body_live.t_us, body_replay.t_us)


def test_unplug_and_replug_reconnects(tmp_path: Path) -> None:
    raw = sim_raw(0.5, seed=3)
    link = str(tmp_path / "tty0")
    cfg = service_config(tmp_path, link, None)
    mcap = tmp_path / "plug.mcap"
    half = len(raw) // 2
    with PtyDevice(link) as dev:
        live = LiveGateway(cfg, mcap)
        p = live.gw.ports[SID]
        try:
            stream(dev, raw[:half], 3000.0)
            assert wait_for(lambda: p.samples_logged == half, 10)
            assert p.node is not None and p.node.pipeline is not None
            assert p.node.pipeline.watch.probation == 0  # no doubt so far
            dev.unplug()
            assert wait_for(lambda: not p.is_open, 10), "unplug not noticed"
            time.sleep(0.2)  # stays away a little while
            dev.replug()
            assert wait_for(lambda: p.is_open, 10), "replug not noticed"
            # another device may be plugged in now: its first still window must agree
            assert p.node.pipeline.watch.probation == REOPEN_PROBATION_WINDOWS
            stream(dev, raw[half:], 3000.0)
            assert wait_for(lambda: p.samples_logged == len(raw), 10), p.samples_logged
            assert live.gw.status(SID)["gateway"]["lost_count"] == 1
        finally:
            assert live.close() == 0
    logged = rec.read_all_raw(mcap, SID)
    np.testing.assert_array_equal(logged.t_us, raw.t_us)  # samples after the replug are there
    assert len(rec.read_all_calibrated(mcap, SID)) == len(raw)  # and calibrated
    kinds = [obj["kind"] for _, obj, _ in rec.iter_json(mcap, f"/{SID}/events")]
    assert kinds.index("port_lost") < kinds.index("port_found")
    assert kinds.count("port_lost") == 1  # the stop's last read is no hang-up
    # the operator sees the outage on stdout (the journal under systemd), in order
    head = f"{NOTE_PREFIX} {SID}: port "
    noted = [ln[len(head):].split()[0] for ln in live.lines if ln.startswith(head)]
    # (a retry while the device was away adds "missing" between lost and found)
    assert [k for k in noted if k != "missing"] == ["opened", "lost", "found"], live.lines


def test_kill9_repair_then_restart_resumes_from_checkpoint(tmp_path: Path,
                                                          children: list) -> None:
    raw = sim_raw(4.0, seed=5)
    zport = free_port()
    link = str(tmp_path / "tty0")
    zenoh = f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zport}"]\nconnect = []\n'
    config = write_config(tmp_path, link, zenoh, 0.02, SID, RATE_HZ)
    ckpt = tmp_path / "ck" / f"{SID}.json"
    run1, run2 = tmp_path / "run1.mcap", tmp_path / "run2.mcap"
    with PtyDevice(link) as dev:
        gp = GatewayProcess(config, run1)
        children.append(gp)
        bus = peer(zport)
        try:
            assert wait_for(lambda: get_json(bus, key(SID, "status"))["gateway"]["open"], 10)
            # stream ~6 s, killing the daemon mid-stream once a checkpoint holds an update
            first, _ = stream(dev, raw[:8000], 2000.0)

            def updated_checkpoint() -> bool:
                doc = load_checkpoint(ckpt) if ckpt.exists() else None
                return bool(doc) and doc["pipeline"]["counts"]["updates"] >= 1
            assert wait_for(updated_checkpoint, 10)
            more, _ = stream(dev, raw[first:24000], 2000.0, stop_after_s=2.0)
            sent = first + more
            # the daemon has read what was written (on a loaded machine it may lag behind the
            # writer, and what it has not read would be the restart's, not the repair's)
            assert wait_for(lambda: get_json(bus, key(SID, "status"))["node"]["samples"]
                            >= sent, 30)
            os.kill(gp.proc.pid, signal.SIGKILL)  # no clean close: the file is cut mid-run
            gp.kill()
        finally:
            bus.close()
        # repair recovers what was written: at least 99 % of the samples sent before the kill
        report = repair(run1, tmp_path / "run1-fixed.mcap")
        assert report.truncated
        got = rec.read_all_raw(tmp_path / "run1-fixed.mcap", SID)
        assert len(got) >= 0.99 * sent, (len(got), sent)
        np.testing.assert_array_equal(got.t_us, raw.t_us[:len(got)])  # exactly once, in order
        saved = load_checkpoint(ckpt)
        assert saved is not None and saved["pipeline"]["counts"]["updates"] >= 1

        # restart: it resumes from the checkpoint, then stops cleanly on SIGTERM
        gp2 = GatewayProcess(config, run2)
        children.append(gp2)
        bus = peer(zport)
        try:
            st = get_json(bus, key(SID, "status"), lambda d: d["gateway"]["open"])
            assert st["node"]["start"] == "checkpoint"
            dev.write_header(())  # the device re-announces: the first line read is whole
            later, _ = stream(dev, raw[sent + 1000:sent + 3000], 2000.0)
            # (plus what the killed run left unread in the kernel: the port is opened unflushed)
            assert wait_for(lambda: get_json(bus, key(SID, "status"))["node"]["samples"]
                            >= later, 10)
        finally:
            bus.close()
        gp2.proc.send_signal(signal.SIGTERM)
        assert gp2.proc.wait(20) == 0, gp2.lines
    got2 = rec.read_all_raw(run2, SID)
    left = len(got2) - later  # sent before the kill, read by nobody until the restart
    assert 0 <= left <= 0.01 * sent, (left, sent)
    np.testing.assert_array_equal(got2.t_us, np.concatenate(
        [raw.t_us[sent - left:sent], raw.t_us[sent + 1000:sent + 3000]]))
    states = [obj for _, obj, _ in rec.iter_json(run2, f"/{SID}/calibration")]  # indexed file
    first_state = states[0]
    assert first_state["reason"] == "restored"
    names = first_state["param_names"]
    p_ckpt = np.asarray(saved["pipeline"]["estimate"]["p"])
    p_first = np.array([first_state["params"][n] for n in names])
    np.testing.assert_allclose(p_first, p_ckpt, rtol=0, atol=1e-9)
    prior_mean = np.asarray(saved["pipeline"]["prior"]["mean"])
    assert np.max(np.abs(p_first - prior_mean)) > 1e-3  # the checkpoint, not the prior
    final = load_checkpoint(ckpt)  # written at stop
    assert final is not None
    assert (final["pipeline"]["counts"]["samples"]
            == saved["pipeline"]["counts"]["samples"] + len(got2))
    kinds = [obj["kind"] for _, obj, _ in rec.iter_json(run2, "/gateway/events")]
    assert kinds[-1] == "stop"


def test_remote_node_calibrates_raw_from_the_bus(tmp_path: Path) -> None:
    raw = sim_raw(0.5, seed=9)
    zport = free_port()
    link = str(tmp_path / "tty0")
    cfg = service_config(tmp_path, link, zport, run_nodes=False,
                         checkpoint={"dir": "", "interval_s": 1.0})
    with PtyDevice(link) as dev:
        live = LiveGateway(cfg, tmp_path / "gw.mcap")
        node_bus = peer(zport)
        stop = threading.Event()
        th = threading.Thread(target=run_node, args=(cfg,), daemon=True, kwargs={
            "mcap_out": tmp_path / "node.mcap", "stop_event": stop, "bus": node_bus,
            "out": lambda s: None})
        try:
            th.start()
            assert live.gw.bus.publisher(key(SID, "raw")).wait_for_subscribers(10)
            sent, _ = stream(dev, raw, 3000.0)
            is_node = lambda d: "node" in d  # noqa: E731 - the gateway answers too, without it
            assert wait_for(lambda: get_json(node_bus, key(SID, "status"), is_node)
                            ["node"]["samples"] == sent, 15)
        finally:
            stop.set()
            th.join(20)
            node_bus.close()
            assert live.close() == 0
    assert len(rec.read_all_calibrated(tmp_path / "node.mcap", SID)) == sent
    assert len(rec.read_all_calibrated(tmp_path / "gw.mcap", SID)) == 0  # not calibrated twice
    states = [obj for _, obj, _ in rec.iter_json(tmp_path / "node.mcap", f"/{SID}/calibration")]
    assert states and states[0]["sensor_id"] == SID


def test_bad_config_is_one_line_and_exit_code_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[pipeline]\nthreshold_g = "high"\n')
    lines: list[str] = []
    stopped = threading.Event()
    stopped.set()  # should the config pass after all, the daemon stops at once
    assert run_gateway(bad, ports=["/dev/null"], out=lines.append, stop_event=stopped) == 2
    assert len(lines) == 1 and "threshold_g" in lines[0] and "bad.toml" in lines[0]
    bad.write_text("[[sensors]]\nid = 'a/b'\nport = 'x'\n")
    lines.clear()
    assert run_gateway(bad, out=lines.append, stop_event=stopped) == 2
    assert "invalid sensor id" in lines[0]


@pytest.mark.parametrize("doc", [json.loads('{"mcap": {"chunk_size": 0}}'),
                                 json.loads('{"sensors": [{"id": "a", "format": "csv"}]}'),
                                 json.loads('{"pipeline": {"window_s": 0.5, "guard_s": 1.0}}'),
                                 json.loads('{"zenoh": {"mode": "p2p"}}'),
                                 json.loads('{"sensors": [{"id": "a", "prior": "nope"}]}'),
                                 json.loads('{"tresholds": 1}'),
                                 json.loads('{"batch_ms": -5}')])
def test_config_errors_name_the_key(doc: dict) -> None:
    from recal.config.settings import ConfigError

    with pytest.raises(ConfigError) as err:
        parse_config(doc, ".", "x.toml")
    assert str(err.value).startswith("x.toml: ") and "\n" not in str(err.value)


def test_shipped_configs_load() -> None:
    from recal.config import load_config

    root = Path(__file__).resolve().parents[1] / "configs"
    cfg = load_config(root / "gateway.toml")
    assert [s.id for s in cfg.sensors] == ["wrist", "hip"]
    assert cfg.discovery.active  # effect discovery on, as by default
    for s in cfg.sensors:
        model, prior = model_and_prior(s, cfg.pipeline)
        assert prior is not None and model.s0 == s.prior.counts_per_g


# --------------------------------------------------------------------------- many ports


def multi_config(tmp: Path, links: list[str], batch_ms: float = 0.0,
                 idle_batch_ms: float = 0.0) -> ServiceConfig:
    """`service_config` without Zenoh for sensors m0, m1, ... on these ports."""
    return service_config(
        tmp, links[0], None, batch_ms=batch_ms, idle_batch_ms=idle_batch_ms,
        checkpoint={"dir": str(tmp / "ck"), "interval_s": 60.0},
        sensors=[{"id": f"m{i}", "port": link, "aux_names": [], "rate_hz": RATE_HZ,
                  "prior": {"counts_per_g": 1024.0}} for i, link in enumerate(links)])


@pytest.mark.parametrize("batch_s", [0.0, 0.05])
def test_one_io_thread_serves_many_ports_every_sample_once(tmp_path: Path,
                                                          batch_s: float) -> None:
    n_ports, n = 6, 1500
    raws = [sim_raw(n / RATE_HZ / 60.0, seed=20 + i) for i in range(n_ports)]
    links = [str(tmp_path / f"tty{i}") for i in range(n_ports)]
    mcap = tmp_path / "many.mcap"
    devices = [PtyDevice(link) for link in links]
    try:
        live = LiveGateway(multi_config(tmp_path, links, idle_batch_ms=0.0), mcap, batch_s)
        try:
            names = [t.name for t in threading.enumerate()]
            assert names.count("recal-io") == 1
            assert not any(x.startswith(("recal-read", "recal-node")) for x in names)
            for dev in devices:
                dev.write_header(())  # ends the resync of the freshly opened port
            start = time.monotonic()
            for i in range(n):  # one sample per write, the ports interleaved, 2000/s each
                for dev, raw in zip(devices, raws, strict=True):
                    dev.write_batch(raw[i:i + 1])
                if i % 20 == 19:
                    time.sleep(max(0.0, start + i / 2000.0 - time.monotonic()))
            ports = list(live.gw.ports.values())
            assert wait_for(lambda: all(p.samples_logged == n for p in ports), 20), \
                [p.samples_logged for p in ports]
            if batch_s > 0:  # a 50 ms tick gathers ~100 samples of a port per batch
                assert all(p.batches_logged <= n / 5 for p in ports), \
                    [p.batches_logged for p in ports]
        finally:
            live.close()
    finally:
        for dev in devices:
            dev.close()
    for i, raw in enumerate(raws):
        logged = rec.read_all_raw(mcap, f"m{i}")
        np.testing.assert_array_equal(logged.t_us, raw.t_us)
        np.testing.assert_array_equal(logged.v, raw.v)
        assert len(rec.read_all_calibrated(mcap, f"m{i}")) == n


def test_stop_logs_and_calibrates_what_the_ports_still_hold(tmp_path: Path) -> None:
    raw = sim_raw(0.1, seed=31)[:100]  # a pty nobody reads holds ~4 kB: 100 lines fit
    link = str(tmp_path / "tty0")
    mcap = tmp_path / "held.mcap"
    with PtyDevice(link) as dev:
        # a 10 s tick (from the config): whatever is written now is still in the pty when the
        # stop comes
        live = LiveGateway(multi_config(tmp_path, [link], batch_ms=10_000), mcap)
        try:
            dev.write_header(())
            dev.write_batch(raw)
            assert dev.bytes_dropped == 0 and live.gw.ports["m0"].samples_logged == 0
        finally:
            live.close()
    logged = rec.read_all_raw(mcap, "m0")
    np.testing.assert_array_equal(logged.t_us, raw.t_us)
    assert len(rec.read_all_calibrated(mcap, "m0")) == len(raw)
    start = next(obj for _, obj, _ in rec.iter_json(mcap, "/gateway/events"))
    assert start["kind"] == "start" and start["detail"]["batch_s"] == 10.0


def test_negative_batch_is_one_line_and_exit_code_2() -> None:
    lines: list[str] = []
    stopped = threading.Event()
    stopped.set()
    assert run_gateway(None, ports=["/dev/null"], out=lines.append, stop_event=stopped,
                       batch_s=-0.01) == 2
    assert len(lines) == 1 and "--batch-ms" in lines[0]


def test_latency_on_demand_ticks_until_someone_subscribes(tmp_path: Path) -> None:
    raw = sim_raw(0.5, seed=41)
    zport = free_port()
    link = str(tmp_path / "tty0")
    cfg = service_config(tmp_path, link, zport, idle_batch_ms=200.0)  # off by default
    with PtyDevice(link) as dev:
        live = LiveGateway(cfg, tmp_path / "demand.mcap")
        p = live.gw.ports[SID]
        bus = None
        try:
            dev.write_header(())
            # nobody subscribes: 500 samples written one by one over ~1 s go in ~5 ticks
            sent, _ = stream(dev, raw[:500], 500.0, chunk=1)
            assert wait_for(lambda: p.samples_logged == sent, 10)
            assert p.batches_logged <= 25, p.batches_logged
            bus = peer(zport)
            got: list[int] = []
            bus.subscribe(key(SID, "calibrated"), lambda m: got.append(1))
            assert wait_for(lambda: live.gw.loop.tick_s() == 0.0, 10), "subscriber not noticed"
            before = p.batches_logged
            more, _ = stream(dev, raw[500:700], 100.0, chunk=1)  # 10 ms apart, each at once
            assert wait_for(lambda: p.samples_logged == sent + more, 10)
            assert p.batches_logged - before >= more / 2, p.batches_logged - before
            assert wait_for(lambda: len(got) >= 100, 10)
        finally:
            if bus is not None:
                bus.close()
            assert live.close() == 0


def test_checkpoints_are_spread_over_the_interval() -> None:
    from recal.daemon.checkpoint_store import CheckpointSchedule

    now = [0.0]
    schedule = CheckpointSchedule(60.0, clock=lambda: now[0])
    sensors = [f"s{i}" for i in range(200)]
    for sid in sensors:
        schedule.add(sid)
    taken: list[tuple[float, list[str]]] = []
    for step in range(1, 1201):  # two intervals, 0.1 s apart
        now[0] = step * 0.1
        due = schedule.take_due()
        if due:
            taken.append((now[0], due))
    counts = [len(due) for _, due in taken]
    assert max(counts) <= 3  # never all at once: 200 sensors over 600 wake-ups
    first = [sid for t, due in taken if t <= 60.0 for sid in due]
    assert sorted(first) == sorted(sensors)  # each once per interval
    second = [sid for t, due in taken if 60.0 < t <= 120.0 for sid in due]
    assert sorted(second) == sorted(sensors)
    assert 0.0 <= schedule.next_due_s() <= 60.0
