"""Keeping strangers out: which sensors a node serves, rate-limited re-alignment, and the
shipped fleet configuration (Zenoh mutual TLS and access control) end to end on loopback.

Real parts only: certificates made by configs/fleet/make-certs.sh with /usr/bin/openssl, the
shipped configs/fleet/router.json5 run by ``recal.io.router`` in a child process, Zenoh
client sessions, ``run_node`` in a thread, checkpoints and MCAP files read back. Every wait
is bounded; sessions are closed in ``finally``.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from polling import wait_for
from recal.commands.demo import free_port
from recal.config import ConfigError, load_config, parse_config
from recal.daemon.checkpoint_store import load_checkpoint
from recal.daemon.remote_node import REJECT_IDS_KEPT, REJECT_REPORT_S, SensorGate, run_node
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_json, encode_raw
from recal.io.router import RouterProcess, run_router, security_summary
from recal.node.alignment import align_handler
from recal.node.node import CalibrationNode, NodeSettings, node_settings
from recal.node.sinks import EventSink
from recal.samples import RawBatch

REPO = Path(__file__).resolve().parents[1]
FLEET = REPO / "configs" / "fleet"
RATE_HZ = 50.0
COUNTS_PER_G = 1024.0
NAMES = ("gw-a", "gw-b", "node-1", "operator-1")

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")


# --------------------------------------------------------------------------- helpers

def still_raw(n: int, t0_us: int = 0, offset_counts: float = 20.0, seed: int = 0) -> RawBatch:
    """A sensor lying still, z up: n samples at RATE_HZ in counts (1024 per g)."""
    rng = np.random.default_rng(seed)
    t_us = t0_us + np.arange(n, dtype=np.int64) * round(1e6 / RATE_HZ)
    v = np.array([0.0, 0.0, COUNTS_PER_G]) + offset_counts + rng.normal(0, 2.0, (n, 3))
    return RawBatch(t_us, np.round(v), np.empty((n, 0)), ())


def node_config(tmp: Path, sensors: tuple[str, ...], **over: Any) -> Any:
    doc: dict[str, Any] = {
        "zenoh": {"mode": "client", "connect": [], "listen": []},
        "checkpoint": {"dir": str(tmp / "ck"), "interval_s": 60.0},
        "mcap": {"flush_interval_s": 0.05},
        "sensors": [{"id": s, "rate_hz": RATE_HZ, "aux_names": [],
                     "prior": {"counts_per_g": COUNTS_PER_G}} for s in sensors],
    }
    doc.update(over)
    return parse_config(doc, tmp, "node-test")


class NodeThread:
    """run_node on a given bus in a thread; its console lines kept."""

    def __init__(self, cfg: Any, bus: Bus | None, mcap: Path, **kw: Any) -> None:
        self.stop = threading.Event()
        self.lines: list[str] = []
        self.rc: list[int] = []
        self.thread = threading.Thread(target=lambda: self.rc.append(run_node(
            cfg, mcap_out=mcap, stop_event=self.stop, bus=bus, out=self.lines.append, **kw)),
            daemon=True)
        self.thread.start()
        assert wait_for(lambda: any(x.startswith("recal node ready") for x in self.lines)
                        or not self.thread.is_alive(), 10), self.lines

    def close(self) -> int:
        self.stop.set()
        self.thread.join(20)
        assert not self.thread.is_alive()
        return self.rc[0]


def publish_raw(bus: Bus, key_sensor: str, batch: RawBatch, payload_sensor: str | None = None,
                wait_s: float = 5.0) -> bool:
    """Put one raw message on recal/<key_sensor>/raw once a subscriber matches."""
    pub = bus.publisher(key(key_sensor, "raw"))
    if not pub.wait_for_subscribers(wait_s):
        return False
    return pub.put(encode_raw(payload_sensor or key_sensor, batch))


def status_of(bus: Bus, sid: str) -> dict[str, Any] | None:
    for _k, data in bus.get(key(sid, "status"), timeout_s=1.0):
        doc = decode_json(data)
        if "node" in doc:
            return doc
    return None


# --------------------------------------------------------------------------- certificates

@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("fleet-certs")
    subprocess.run([str(FLEET / "make-certs.sh"), str(d), "localhost", *NAMES], check=True,
                   capture_output=True, timeout=60)
    return d


@pytest.fixture(scope="module")
def stranger_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Another CA, with a client certificate that claims to be gw-a."""
    d = tmp_path_factory.mktemp("stranger-certs")
    subprocess.run([str(FLEET / "make-certs.sh"), str(d), "localhost", "gw-a"], check=True,
                   capture_output=True, timeout=60)
    return d


@pytest.fixture(scope="module")
def fleet_router(certs: Path, tmp_path_factory: pytest.TempPathFactory
                 ) -> Iterator[tuple[RouterProcess, str, Path]]:
    """The shipped router.json5 with the test's certificate paths and a free port."""
    port = free_port()
    text = (FLEET / "router.json5").read_text()
    assert "/etc/recal/fleet/" in text and "tls/localhost:7447" in text
    text = text.replace("/etc/recal/fleet/", f"{certs}/").replace(
        "tls/localhost:7447", f"tls/localhost:{port}")
    path = tmp_path_factory.mktemp("router") / "router.json5"
    path.write_text(text)
    proc = RouterProcess([], path).start()
    try:
        yield proc, f"tls/localhost:{port}", path
    finally:
        proc.stop()


def tls_client(endpoint: str, ca_dir: Path, name: str | None) -> Bus:
    """A client with the shipped client.json5's TLS settings and ``name``'s certificate."""
    tls: dict[str, Any] = {"root_ca_certificate": str(ca_dir / "ca.pem")}
    if name is not None:
        tls.update(connect_certificate=str(ca_dir / f"{name}.pem"),
                   connect_private_key=str(ca_dir / f"{name}-key.pem"), enable_mtls=True)
    cfg = zenoh_config(config_file=FLEET / "client.json5", connect=[endpoint],
                       overrides={"transport/link/tls": tls, "connect/timeout_ms": 1500})
    return Bus(cfg)


@pytest.fixture()
def fleet(fleet_router: tuple[RouterProcess, str, Path], certs: Path
          ) -> Iterator[Callable[[str], Bus]]:
    """Opens clients of the fleet router by certificate name; closes them all at the end."""
    opened: list[Bus] = []

    def open_as(name: str) -> Bus:
        bus = tls_client(fleet_router[1], certs, name)
        opened.append(bus)
        return bus

    try:
        yield open_as
    finally:
        for bus in opened:
            bus.close()


def drain(rx: Any, timeout_s: float) -> list[tuple[str, bytes]]:
    out = []
    deadline = time.monotonic() + timeout_s
    while (m := rx.recv(max(0.0, deadline - time.monotonic()))) is not None:
        out.append((m.key, m.payload))
    return out


# --------------------------------------------------------------------------- TLS + ACL

def test_fleet_router_refuses_clients_without_a_fleet_certificate(
        fleet_router: tuple[RouterProcess, str, Path], certs: Path, stranger_certs: Path
) -> None:
    proc, endpoint, config_path = fleet_router
    assert "tls=mtls acl=on" in proc.output and "warning" not in proc.output
    with pytest.raises(zenoh.ZError):  # no client certificate at all
        tls_client(endpoint, certs, None).close()
    with pytest.raises(zenoh.ZError):  # "gw-a", but signed by another CA
        tls_client(endpoint, stranger_certs, "gw-a").close()
    with pytest.raises(zenoh.ZError):  # plain TCP on the TLS port
        Bus(zenoh_config("client", [], [endpoint.replace("tls/localhost", "tcp/127.0.0.1")],
                         overrides={"connect/timeout_ms": 1500})).close()
    ok = tls_client(endpoint, certs, "operator-1")  # the control: a fleet member gets in
    try:
        assert ok.routers() == [proc.zid]
    finally:
        ok.close()
    # the config accepts TLS links only: a plain TCP listener added by mistake is refused
    stopped = threading.Event()
    stopped.set()
    with pytest.raises(zenoh.ZError, match="tcp"):
        run_router([f"tcp/127.0.0.1:{free_port()}"], config_path, stopped, out=lambda _: None)


def test_router_says_what_protects_it() -> None:
    assert security_summary(zenoh_config("router")) == ("off", "off", [])
    exposed = zenoh_config("router", listen=["tcp/192.168.1.10:7447"])
    assert security_summary(exposed) == ("off", "off", ["tcp/192.168.1.10:7447"])
    shipped = zenoh.Config.from_file(str(FLEET / "router.json5"))
    shipped.insert_json5("listen/endpoints", '["tls/router.example:7447"]')
    assert security_summary(shipped) == ("mtls", "on", ["tls/router.example:7447"])
    lines: list[str] = []
    stop = threading.Event()
    th = threading.Thread(target=run_router, args=([f"tcp/127.0.0.1:{free_port()}"],),
                          kwargs={"stop_event": stop, "out": lines.append}, daemon=True)
    th.start()
    try:
        assert wait_for(lambda: bool(lines), 10)
        assert "tls=off acl=off" in lines[0]
        assert not [x for x in lines if "warning" in x]  # loopback only: no warning
    finally:
        stop.set()
        th.join(10)


def test_gateway_puts_only_its_own_sensors_keys(fleet: Callable[[str], Bus]) -> None:
    gw_a, gw_b, node, operator = (fleet(n) for n in NAMES)
    node_rx = node.receiver("recal/*/raw")
    op_rx = operator.receiver("recal/**")
    batch = still_raw(10)
    # gw-a on hip's key (gw-b's sensor) and on an unconfigured id, then the allowed puts
    assert publish_raw(gw_a, "hip", batch)
    gw_a.publisher(key("stranger", "raw")).put(encode_raw("stranger", batch))
    gw_a.publish(key("hip", "calibrated"), b"forged")
    assert publish_raw(gw_a, "wrist", batch)
    assert publish_raw(gw_b, "hip", batch)
    got_node = drain(node_rx, 1.5)
    got_op = drain(op_rx, 0.5)
    assert sorted(k for k, _ in got_node) == ["recal/hip/raw", "recal/wrist/raw"]
    assert sorted(k for k, _ in got_op) == ["recal/hip/raw", "recal/wrist/raw"]
    hip = next(p for k, p in got_node if k == "recal/hip/raw")
    assert hip == encode_raw("hip", batch)  # gw-b's, not gw-a's (same bytes, one message)
    assert sum(k == "recal/hip/raw" for k, _ in got_node) == 1


def test_only_operators_query_align_and_only_the_owner_answers(
        fleet: Callable[[str], Bus]) -> None:
    gw_a, gw_b, node, operator = (fleet(n) for n in NAMES)
    asked: list[str] = []

    def answer(k: str, _p: bytes | None) -> bytes:
        asked.append(k)
        return b"gw-a aligned wrist"

    gw_a.queryable(key("wrist", "align"), answer)
    gw_a.queryable(key("wrist", "status"), lambda _k, _p: b"gw-a status")
    assert wait_for(lambda: bool(operator.get(key("wrist", "status"), timeout_s=0.5)), SETTLE_S)
    for who in (gw_b, node):  # neither a gateway nor a node may ask for a re-alignment
        assert who.get(key("wrist", "align"), timeout_s=0.7) == []
    assert gw_b.get(key("wrist", "status"), timeout_s=0.7) == []
    assert asked == []
    # gw-b answering for wrist (its own session would hear itself; the router must not)
    gw_b.queryable(key("wrist", "align"), lambda _k, _p: b"gw-b impersonates wrist")
    time.sleep(0.3)
    replies = operator.get(key("wrist", "align"), timeout_s=1.0)
    assert replies == [(key("wrist", "align"), b"gw-a aligned wrist")]  # not gw-b's
    assert asked == [key("wrist", "align")]


def fleet_node_toml(tmp: Path, certs: Path, endpoint: str) -> Path:
    """The shipped node.toml and client.json5 with the test's certificates, router port and
    folders: the node opens its own session from them, as `recal node --config` does."""
    client = (FLEET / "client.json5").read_text()
    client = client.replace("/etc/recal/fleet/client", f"{certs}/node-1").replace(
        "/etc/recal/fleet/", f"{certs}/").replace("tls/localhost:7447", endpoint)
    (tmp / "client.json5").write_text(client)
    node = (FLEET / "node.toml").read_text().replace(
        "../sensor-priors.toml", str(REPO / "configs" / "sensor-priors.toml")).replace(
        "/var/lib/recal/checkpoints", str(tmp / "ck"))
    assert str(tmp / "ck") in node
    (tmp / "node.toml").write_text(node)
    return tmp / "node.toml"


def test_node_behind_the_fleet_router_calibrates_only_the_owners_stream(
        fleet: Callable[[str], Bus], fleet_router: tuple[RouterProcess, str, Path],
        certs: Path, tmp_path: Path) -> None:
    """gw-b injects a plausible stream on wrist's key (offset 60 counts instead of 20): the
    router drops it, so the node's wrist state and checkpoint hold gw-a's samples only."""
    gw_a, gw_b, operator = fleet("gw-a"), fleet("gw-b"), fleet("operator-1")
    cfg = load_config(fleet_node_toml(tmp_path, certs, fleet_router[1]))
    nt = NodeThread(cfg, None, tmp_path / "node.mcap")
    try:
        sent = 0
        for i in range(4):
            legit = still_raw(100, t0_us=i * 2_000_000, offset_counts=20.0, seed=i)
            forged = still_raw(100, t0_us=i * 2_000_000 + 1000, offset_counts=60.0, seed=9)
            assert publish_raw(gw_b, "wrist", forged)
            assert publish_raw(gw_a, "wrist", legit)
            sent += len(legit)
        assert wait_for(lambda: (status_of(operator, "wrist") or {}).get(
            "node", {}).get("samples") == sent, 10)
    finally:
        assert nt.close() == 0
    doc = load_checkpoint(tmp_path / "ck" / "wrist.json")
    assert doc is not None and doc["pipeline"]["counts"]["samples"] == sent
    raw = rec.read_all_raw(tmp_path / "node.mcap", "wrist")
    assert len(raw) == sent and float(np.max(raw.v[:, 0])) < 40  # none of the 60-count stream


# --------------------------------------------------------------------------- node admission

#: A generous bound for what a node under load does in a moment (the tests poll, so they take
#: this long only when it fails)
SETTLE_S = 30.0


def _reason_total(lines: list[str], reason: str) -> int:
    """Messages turned away for ``reason`` over all of the node's "ignored ..." lines."""
    return sum(int(m) for x in lines for m in re.findall(rf"\b{reason} (\d+)", x)
               if "ignored" in x)


def plain_client(endpoint: str) -> Bus:
    return Bus(zenoh_config("client", [], [endpoint], overrides={"connect/timeout_ms": 3000}))


def test_rogue_gateway_ids_leave_no_trace_in_the_node(plain_router: str,
                                                      tmp_path: Path) -> None:
    node_bus, gw, rogue = (plain_client(plain_router) for _ in range(3))
    cfg = node_config(tmp_path, ("wrist",))
    try:
        nt = NodeThread(cfg, node_bus, tmp_path / "node.mcap")
        try:
            fake = [f"fake{i:03d}" for i in range(40)]
            for sid in fake:  # enough samples each to start a pipeline and a checkpoint
                assert publish_raw(rogue, sid, still_raw(60, offset_counts=60.0))
            # a payload naming wrist under another key, and another sensor under wrist's key
            assert publish_raw(rogue, "fake999", still_raw(60), payload_sensor="wrist")
            assert publish_raw(rogue, "wrist", still_raw(60), payload_sensor="fake998")
            legit = still_raw(200)
            started = time.monotonic()
            assert publish_raw(gw, "wrist", legit)
            assert wait_for(lambda: (status_of(gw, "wrist") or {}).get("node", {}).get(
                "samples") == len(legit), SETTLE_S)
            assert wait_for(lambda: any("ignored" in x for x in nt.lines), SETTLE_S), nt.lines
            assert status_of(gw, "fake000") is None  # no queryable for a stranger
        finally:
            assert nt.close() == 0
    finally:
        for b in (node_bus, gw, rogue):
            b.close()
    assert (tmp_path / "ck" / "wrist.json").is_file()  # no file (checkpoint, lock) of a rogue id
    assert {p.name.split(".")[0] for p in (tmp_path / "ck").iterdir()} == {"wrist"}
    assert rec.sensors(tmp_path / "node.mcap") == ["wrist"]
    assert not [m.topic for m in rec.iter_messages(tmp_path / "node.mcap", "*fake*")]
    events = [obj for _, obj, _ in rec.iter_json(tmp_path / "node.mcap", "/gateway/events")]
    ignored = [e for e in events if e["kind"] == "sensors_ignored"]
    assert ignored
    by_reason: dict[str, int] = {}
    for e in ignored:
        for k, v in e["detail"]["by_reason"].items():
            by_reason[k] = by_reason.get(k, 0) + v
        assert len(e["detail"]["sensor_ids"]) <= REJECT_IDS_KEPT
    assert by_reason == {"not_served": 40, "key_mismatch": 2}
    lines = [x for x in nt.lines if "ignored" in x]
    # rate-limited, not one per message: one report now, then at most one per REJECT_REPORT_S
    # (and one at the close), however long a loaded machine made this take
    most = 2 + int((time.monotonic() - started) / REJECT_REPORT_S)
    assert len(lines) == len(ignored) <= most


def test_accept_any_serves_strangers_only_up_to_the_cap(plain_router: str,
                                                        tmp_path: Path) -> None:
    node_bus, gw = plain_client(plain_router), plain_client(plain_router)
    cfg = node_config(tmp_path, ())
    try:
        lines: list[str] = []
        assert run_node(cfg, bus=node_bus, out=lines.append) == 2  # nothing named: refused
        assert "accept_any" in lines[0]
        nt = NodeThread(cfg, node_bus, tmp_path / "node.mcap", accept_any=True, max_sensors=3)
        try:
            for i in range(5):  # one session: delivered in this order, first come first served
                assert publish_raw(gw, f"s{i}", still_raw(60))
            assert wait_for(lambda: all((status_of(gw, f"s{i}") or {}).get("node", {}).get(
                "samples") == 60 for i in range(3)), SETTLE_S)
            # the two turned away may land in two rounds, and then in two reports
            # REJECT_REPORT_S apart: wait for their sum, not for one line saying 2
            assert wait_for(lambda: _reason_total(nt.lines, "over_cap") == 2,
                            REJECT_REPORT_S + SETTLE_S), nt.lines
        finally:
            assert nt.close() == 0
    finally:
        node_bus.close()
        gw.close()
    assert sorted(p.name for p in (tmp_path / "ck").glob("*.json")) == [
        "s0.json", "s1.json", "s2.json"]
    assert {p.name.split(".")[0] for p in (tmp_path / "ck").iterdir()} == {"s0", "s1", "s2"}


def test_sensor_gate_memory_is_bounded() -> None:
    gate = SensorGate(["wrist"])
    for i in range(5000):
        assert not gate.admit(f"x{i}")
    assert gate.admit("wrist") and gate.served == {"wrist"}
    report = gate.take_report()
    assert report is not None
    assert report["messages"] == 5000 and len(report["sensor_ids"]) == REJECT_IDS_KEPT
    assert gate.take_report() is None
    assert gate.rejected["not_served"] == 5000


# --------------------------------------------------------------------------- align rate limit


def align_node(interval_s: float) -> tuple[CalibrationNode, EventSink]:
    cfg = node_config(Path("."), ("wrist",), alignment={"request_interval_s": interval_s})
    settings: NodeSettings = node_settings(cfg.sensors[0], cfg)
    sink = EventSink()
    node = CalibrationNode(settings, sink)
    node.process(still_raw(100), 0)
    return node, sink


def test_align_requests_are_rate_limited_and_logged() -> None:
    node, sink = align_node(60.0)
    first = node.request_alignment(now_s=1000.0)
    assert first["status"] in ("armed", "aligned")
    refused = [node.request_alignment(now_s=1000.0 + dt) for dt in (1.0, 2.0, 30.0)]
    assert [r["status"] for r in refused] == ["refused"] * 3
    assert refused[0]["retry_after_s"] == pytest.approx(59.0)
    assert node.status()["node"]["align_refused"] == 3
    kinds = [e["kind"] for e in sink.events]
    assert kinds.count("align_request") == 1 and kinds.count("align_refused") == 1
    again = node.request_alignment(now_s=1060.0)
    assert again["status"] != "refused"
    last = [e for e in sink.events if e["kind"] == "align_request"][-1]
    assert last["detail"]["refused_before"] == 3


def test_align_query_flood_gives_one_refusal_line(tmp_path: Path) -> None:
    node, sink = align_node(60.0)
    lines: list[str] = []
    handle = align_handler(node, lines.append)
    replies = [decode_json(handle("recal/wrist/align", None)) for _ in range(50)]
    assert replies[0]["status"] != "refused"
    assert all(r["status"] == "refused" for r in replies[1:])
    assert len(lines) == 2 and "refused" in lines[1]
    assert [e["kind"] for e in sink.events].count("align_refused") == 1


# --------------------------------------------------------------------------- configuration

def test_node_table_and_fleet_files_load(tmp_path: Path) -> None:
    cfg = parse_config({"node": {"accept_any": True, "max_sensors": 4}})
    assert cfg.node.accept_any and cfg.node.max_sensors == 4
    for bad in ({"node": {"max_sensors": 0}}, {"node": {"accept_any": "yes"}},
                {"node": {"open": True}}, {"alignment": {"request_interval_s": -1}}):
        with pytest.raises(ConfigError):
            parse_config(bad)
    node = load_config(FLEET / "node.toml")
    assert [s.id for s in node.sensors] == ["wrist", "hip"] and not node.node.accept_any
    gw = load_config(FLEET / "gateway.toml")
    assert [s.id for s in gw.sensors] == ["wrist"] and not gw.run_nodes
    for name in ("router.json5", "client.json5"):
        conf = zenoh.Config.from_file(str(FLEET / name))
        assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
    acl = json.loads(zenoh.Config.from_file(str(FLEET / "router.json5")).get_json(
        "access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert not list(FLEET.glob("*key*.pem"))  # no private key is shipped


@pytest.mark.parametrize(("args", "message"), [
    ([], "name them in [[sensors]] or with --sensor-id"),
    (["--accept-any", "--max-sensors", "0"], "--max-sensors: expected an integer >= 1"),
    (["--sensor-id", "a/b"], "--sensor-id"),
])
def test_recal_node_without_sensors_to_serve_is_a_usage_error(
        tmp_path: Path, args: list[str], message: str) -> None:
    cfg = tmp_path / "node.toml"
    cfg.write_text('[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:0"]\nconnect = []\n')
    done = subprocess.run([sys.executable, "-m", "recal", "node", "--config", str(cfg), *args],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stdout + done.stderr
    assert message in done.stderr and "Traceback" not in done.stderr
