"""Tests of the Zenoh adapter (recal.io.bus) and the router process (recal.io.router).

Real Zenoh sessions on 127.0.0.1, no mocks. Every wait is bounded; sessions and router
processes are closed by fixture finalizers even when a test fails.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from polling import wait_for as wait_until
from recal.errors import ConfigError, UsageError
from recal.io.bus import (
    Bus,
    Message,
    Receiver,
    key,
    key_pattern,
    parse_key,
    sensor_of,
    validate_sensor_id,
)
from recal.io.bus_config import loopback_endpoint, zenoh_config
from recal.io.router import READY_PREFIX, RouterProcess, run_router

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
# Short reconnect back-off so a restarted router is found within a fraction of a second
# (Zenoh's default starts at 1 s and grows to 4 s).
FAST_RETRY = {"connect/retry": {"period_init_ms": 50, "period_max_ms": 200}}


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def open_bus() -> Iterator[Callable[[zenoh.Config], Bus]]:
    """Factory of buses that are all closed at teardown, pass or fail."""
    buses: list[Bus] = []

    def factory(config: zenoh.Config) -> Bus:
        bus = Bus(config)
        buses.append(bus)
        return bus

    yield factory
    for bus in reversed(buses):
        bus.close()


@pytest.fixture
def peer_pair(open_bus: Callable[[zenoh.Config], Bus]) -> tuple[Bus, Bus]:
    """Two peer sessions in this process: the first listens, the second connects to it."""
    endpoint = loopback_endpoint(free_port())
    listener = open_bus(zenoh_config(mode="peer", listen=[endpoint]))
    dialer = open_bus(zenoh_config(mode="peer", connect=[endpoint]))
    return listener, dialer


@pytest.fixture
def router() -> Iterator[RouterProcess]:
    """A router child process on a free loopback port, killed at teardown."""
    proc = RouterProcess([loopback_endpoint(free_port())])
    proc.start()
    yield proc
    proc.kill()


# --------------------------------------------------------------------------- keys


@pytest.mark.parametrize("sensor", ["wrist", "imu-01", "left_ankle.2", "Ä7"])
def test_valid_sensor_ids_round_trip_through_keys(sensor: str) -> None:
    for topic in ("raw", "calibrated", "body", "calibration", "status", "events", "align"):
        k = key(sensor, topic)
        assert k == f"recal/{sensor}/{topic}"
        assert parse_key(k) == (sensor, topic)
        assert sensor_of(k) == sensor
        zenoh.KeyExpr(k)  # Zenoh accepts it as a canonical key expression


@pytest.mark.parametrize("sensor", ["", "a/b", "a*", "$x", "q?", "#1", "tab\there", "x" * 129])
def test_invalid_sensor_ids_are_rejected(sensor: str) -> None:
    with pytest.raises(UsageError):
        validate_sensor_id(sensor)
    with pytest.raises(UsageError):
        key(sensor, "raw")


@pytest.mark.parametrize(
    "bad_key", ["recal/s1", "other/s1/raw", "recal/s1/raw/extra", "recal/*/raw", "recal/s1/nope"]
)
def test_parse_key_rejects_keys_outside_the_layout(bad_key: str) -> None:
    with pytest.raises(ValueError):
        parse_key(bad_key)


def test_key_pattern_and_unknown_topic() -> None:
    assert key_pattern("raw") == "recal/*/raw"
    with pytest.raises(ValueError):
        key("s1", "rawdata")


# --------------------------------------------------------------------------- configuration


def _endpoints(config: zenoh.Config, path: str) -> list[str]:
    import json

    return json.loads(config.get_json(path))


@pytest.mark.parametrize("mode", ["peer", "client", "router"])
def test_default_configs_are_loopback_only_without_multicast(mode: str) -> None:
    config = zenoh_config(mode=mode)  # type: ignore[arg-type]
    listen = _endpoints(config, "listen/endpoints")
    assert isinstance(listen, list)  # explicit, not Zenoh's per-mode all-interfaces default
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in listen)
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in _endpoints(config, "connect/endpoints"))
    assert config.get_json("scouting/multicast/enabled") == "false"
    assert config.get_json("mode") == f'"{mode}"'


def test_config_overrides_and_bad_mode() -> None:
    config = zenoh_config(
        mode="client",
        connect=["tcp/127.0.0.1:1234"],
        overrides={"connect/timeout_ms": 250, **FAST_RETRY},
    )
    assert _endpoints(config, "connect/endpoints") == ["tcp/127.0.0.1:1234"]
    assert config.get_json("connect/timeout_ms") == "250"
    with pytest.raises(ConfigError):
        zenoh_config(mode="broker")  # type: ignore[arg-type]
    with pytest.raises(UsageError, match="port out of range"):
        loopback_endpoint(65536)


@pytest.mark.parametrize("name", ["peer", "client", "router"])
def test_example_config_files_load_and_stay_on_loopback(name: str) -> None:
    config = zenoh_config(config_file=CONFIG_DIR / f"zenoh-{name}.json5")
    assert config.get_json("mode") == f'"{name}"'
    endpoints = _endpoints(config, "listen/endpoints") + _endpoints(config, "connect/endpoints")
    assert all(ep.startswith("tcp/127.0.0.1:") for ep in endpoints)
    assert config.get_json("scouting/multicast/enabled") == "false"


def test_config_file_without_listen_gets_loopback_listen(tmp_path: Path) -> None:
    path = tmp_path / "bare.json5"
    path.write_text('{ mode: "peer" }  // nothing else\n')
    config = zenoh_config(config_file=path)
    assert _endpoints(config, "listen/endpoints") == ["tcp/127.0.0.1:0"]
    assert config.get_json("scouting/multicast/enabled") == "false"
    overridden = zenoh_config(config_file=path, mode="router", listen=["tcp/127.0.0.1:7999"])
    assert overridden.get_json("mode") == '"router"'
    assert _endpoints(overridden, "listen/endpoints") == ["tcp/127.0.0.1:7999"]


# --------------------------------------------------------------------------- receiver (no network)


def test_receiver_drop_oldest_keeps_newest_and_counts() -> None:
    rx = Receiver(capacity=3, overflow="drop_oldest")
    for i in range(5):
        rx.push(Message("recal/s/raw", bytes([i])))
    assert rx.dropped == 2 and rx.received == 5 and len(rx) == 3
    assert [m.payload for m in rx.recv_batch(10, timeout=0.1)] == [b"\x02", b"\x03", b"\x04"]
    assert rx.recv(timeout=0.01) is None


def test_receiver_block_gives_up_after_timeout_and_close_wakes_waiters() -> None:
    rx = Receiver(capacity=1, overflow="block", block_timeout_s=0.05)
    assert rx.push(Message("k/a", b"1"))
    t0 = time.monotonic()
    assert not rx.push(Message("k/a", b"2"))  # full for longer than block_timeout_s: dropped
    assert 0.04 < time.monotonic() - t0 < 1.0
    assert rx.dropped == 1
    assert rx.recv(0.1) == Message("k/a", b"1")
    waiter_result: list[Message | None] = []
    waiter = threading.Thread(target=lambda: waiter_result.append(rx.recv(timeout=5.0)))
    waiter.start()
    time.sleep(0.05)
    rx.close()
    waiter.join(2.0)
    assert not waiter.is_alive() and waiter_result == [None]


# --------------------------------------------------------------------------- peer to peer


def test_wildcard_subscription_two_sensors_no_loss(peer_pair: tuple[Bus, Bus]) -> None:
    """2 x 2000 messages through a small blocking buffer: none lost, order kept per sensor."""
    listener, dialer = peer_pair
    n = 2000
    rx = listener.receiver(key_pattern("raw"), capacity=64)  # small: forces back-pressure
    pubs = [dialer.publisher(key(s, "raw")) for s in ("s1", "s2")]
    assert all(p.wait_for_subscribers(5.0) for p in pubs)

    def produce() -> None:
        for i in range(n):
            for pub in pubs:
                pub.put(i.to_bytes(4, "little"), attachment=b"seq")

    producer = threading.Thread(target=produce, daemon=True)
    producer.start()
    got: dict[str, list[int]] = {"s1": [], "s2": []}
    deadline = time.monotonic() + 15.0
    while sum(map(len, got.values())) < 2 * n and time.monotonic() < deadline:
        for msg in rx.recv_batch(256, timeout=0.5):
            got[msg.sensor].append(int.from_bytes(msg.payload, "little"))
            assert msg.attachment == b"seq"
    producer.join(5.0)
    assert got == {"s1": list(range(n)), "s2": list(range(n))}
    assert rx.dropped == 0
    assert all(p.sent == n and p.failed == 0 and p.unmatched == 0 for p in pubs)
    assert listener.stats()["received"] == 2 * n


def test_subscribe_callback_errors_are_counted_not_fatal(peer_pair: tuple[Bus, Bus]) -> None:
    listener, dialer = peer_pair
    seen: list[Message] = []
    done = threading.Event()

    def callback(msg: Message) -> None:
        if msg.payload == b"boom":
            raise RuntimeError("callback failure on purpose")
        seen.append(msg)
        done.set()

    sub = listener.subscribe(key("s1", "events"), callback)
    pub = dialer.publisher(key("s1", "events"))
    assert pub.wait_for_subscribers(5.0)
    pub.put(b"boom")
    pub.put(b"fine")
    assert done.wait(5.0)
    assert [m.payload for m in seen] == [b"fine"]
    assert wait_until(lambda: sub.errors == 1, 30.0)


def test_status_queryable_answers_get(peer_pair: tuple[Bus, Bus]) -> None:
    node, gateway = peer_pair
    asked: list[tuple[str, bytes | None]] = []

    def status(query_key: str, payload: bytes | None) -> bytes:
        asked.append((query_key, payload))
        return b"state-of-s1"

    node.queryable(key("s1", "status"), status)
    node.queryable(key("s2", "status"), lambda _k, _p: b"state-of-s2")

    def failing(_k: str, _p: bytes | None) -> bytes:
        raise ValueError("not aligned")

    node.queryable(key("s1", "align"), failing)
    # Declarations propagate asynchronously; retry the first get within a bounded time.
    assert wait_until(lambda: gateway.get(key("s1", "status"), timeout_s=0.5) != [], 30.0)
    assert gateway.get(key("s1", "status"), payload=b"please") == [
        ("recal/s1/status", b"state-of-s1")
    ]
    assert asked[-1] == ("recal/s1/status", b"please")
    assert sorted(gateway.get(key_pattern("status"))) == [
        ("recal/s1/status", b"state-of-s1"),
        ("recal/s2/status", b"state-of-s2"),
    ]
    t0 = time.monotonic()
    assert gateway.get(key("s1", "align"), timeout_s=3.0) == []  # error reply skipped
    assert time.monotonic() - t0 < 1.0  # finalised at once, not at the timeout
    assert gateway.stats()["query_error_replies"] == 1
    t0 = time.monotonic()
    assert gateway.get(key("nobody", "status"), timeout_s=0.3) == []
    assert time.monotonic() - t0 < 2.0


def test_get_keeps_every_reply_on_the_same_key(peer_pair: tuple[Bus, Bus]) -> None:
    # A gateway and a remote node both answer recal/<sensor>/status; neither may be dropped.
    node, gateway = peer_pair
    node.queryable(key("s1", "status"), lambda _k, _p: b"from-node")
    gateway.queryable(key("s1", "status"), lambda _k, _p: b"from-gateway")
    want = [("recal/s1/status", b"from-gateway"), ("recal/s1/status", b"from-node")]
    for asker in (gateway, node):  # a local and a remote queryable, from both sides
        assert wait_until(lambda a=asker: len(a.get(key("s1", "status"), timeout_s=0.5)) == 2,
                          30.0)
        for _ in range(10):
            assert sorted(asker.get(key("s1", "status"), timeout_s=1.0)) == want


def test_close_is_prompt_with_a_full_blocking_receiver(
    open_bus: Callable[[zenoh.Config], Bus],
) -> None:
    """A consumer that never reads must not make close() (or process exit) hang."""
    endpoint = loopback_endpoint(free_port())
    a = open_bus(zenoh_config(listen=[endpoint]))
    b = Bus(zenoh_config(connect=[endpoint]))
    try:
        rx = b.receiver("recal/**", capacity=2, block_timeout_s=30.0)
        pub = a.publisher(key("s1", "raw"))
        assert pub.wait_for_subscribers(5.0)
        for i in range(20):
            pub.put(bytes([i]))
        assert wait_until(lambda: len(rx) == 2, 30.0)
    finally:
        t0 = time.monotonic()
        b.close()
        assert time.monotonic() - t0 < 5.0
    assert b.closed and rx.closed
    with pytest.raises(RuntimeError):
        b.publish(key("s1", "raw"), b"x")
    b.close()  # idempotent


def test_publish_after_peer_left_is_unmatched_not_an_error(
    open_bus: Callable[[zenoh.Config], Bus],
) -> None:
    endpoint = loopback_endpoint(free_port())
    a = open_bus(zenoh_config(listen=[endpoint]))
    b = Bus(zenoh_config(connect=[endpoint]))
    b.receiver(key_pattern("raw"))
    pub = a.publisher(key("s1", "raw"))
    assert pub.wait_for_subscribers(5.0)
    b.close()
    assert wait_until(lambda: not pub.has_subscribers, 30.0)
    assert pub.put(b"into the void")
    assert pub.unmatched == 1 and pub.failed == 0


def test_a_put_of_what_makes_the_bytes_makes_them_only_for_a_subscriber(
    open_bus: Callable[[zenoh.Config], Bus],
) -> None:
    """The live path hands a publisher what encodes a message, not its bytes: nobody
    subscribed, nothing is encoded (counted unmatched as a put of bytes is); a subscriber
    gets exactly the bytes the encoder made."""
    endpoint = loopback_endpoint(free_port())
    a = open_bus(zenoh_config(listen=[endpoint]))
    pub = a.publisher(key("s1", "calibrated"))
    made: list[bytes] = []

    def encode() -> bytes:
        made.append(b"encoded-%d" % len(made))
        return made[-1]

    assert pub.put(encode)
    assert made == [] and pub.unmatched == 1 and pub.sent == 1
    b = open_bus(zenoh_config(connect=[endpoint]))
    rx = b.receiver(key_pattern("calibrated"))
    assert pub.wait_for_subscribers(5.0)
    assert pub.put(encode) and pub.put(b"plain")
    got = [rx.recv(timeout=5.0), rx.recv(timeout=5.0)]
    assert None not in got
    assert [m.payload for m in got if m is not None] == [b"encoded-0", b"plain"]
    assert made == [b"encoded-0"] and pub.unmatched == 1 and pub.sent == 3


# --------------------------------------------------------------------------- through a router


def _client(open_bus: Callable[[zenoh.Config], Bus], router: RouterProcess) -> Bus:
    return open_bus(
        zenoh_config(mode="client", connect=router.listen_endpoints, overrides=FAST_RETRY)
    )


def _deliver(pub_bus: Bus, rx: Receiver, key_expr: str, payload: bytes, timeout_s: float) -> bool:
    """Publish ``payload`` repeatedly until ``rx`` sees it or ``timeout_s`` elapses."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pub_bus.publish(key_expr, payload)
        msg = rx.recv(timeout=0.05)
        while msg is not None and msg.payload != payload:
            msg = rx.recv(timeout=0.01)
        if msg is not None:
            return True
    return False


def test_clients_through_router_survive_router_restart(
    router: RouterProcess, open_bus: Callable[[zenoh.Config], Bus]
) -> None:
    gateway = _client(open_bus, router)
    node = _client(open_bus, router)
    assert gateway.routers() == [router.zid]
    rx = node.receiver(key_pattern("raw"), capacity=256, overflow="drop_oldest")
    node.queryable(key("s1", "status"), lambda _k, _p: b"ok")
    raw = key("s1", "raw")
    assert _deliver(gateway, rx, raw, b"before", 5.0)
    assert gateway.get(key("s1", "status")) == [("recal/s1/status", b"ok")]

    first_zid = router.zid
    router.kill()  # a crash: no goodbye to the clients
    pub = gateway.publisher(raw)
    pub.put(b"right-after-kill")  # must not raise even before the loss is noticed
    assert wait_until(lambda: gateway.routers() == [] and not pub.has_subscribers, 30.0)
    unmatched_before = pub.unmatched
    for _ in range(100):  # the publisher side keeps going; samples reach nobody
        assert pub.put(b"while-down")
    assert pub.failed == 0
    assert pub.unmatched - unmatched_before == 100

    router.start()  # same port
    assert router.zid != first_zid
    assert _deliver(gateway, rx, raw, b"after", 10.0)
    assert wait_until(lambda: gateway.routers() == [router.zid], 30.0)
    # The queryable was re-declared through the new router as well.
    assert wait_until(lambda: gateway.get(key("s1", "status"), timeout_s=0.5) != [], 30.0)


def test_client_cannot_open_while_router_is_down() -> None:
    config = zenoh_config(mode="client", connect=[loopback_endpoint(free_port())])
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError):
        Bus(config)
    assert time.monotonic() - t0 < 5.0


def test_peers_meet_through_router_with_gossip(
    router: RouterProcess, open_bus: Callable[[zenoh.Config], Bus]
) -> None:
    a = open_bus(zenoh_config(mode="peer", connect=router.listen_endpoints))
    b = open_bus(zenoh_config(mode="peer", connect=router.listen_endpoints))
    rx = b.receiver(key_pattern("calibrated"))
    assert _deliver(a, rx, key("s1", "calibrated"), b"hello", 5.0)
    # Gossip made the peers connect directly, so they keep talking without the router.
    assert wait_until(lambda: b.zid in a.peers(), 30.0)
    router.kill()
    assert _deliver(a, rx, key("s1", "calibrated"), b"still here", 5.0)


def test_peers_do_not_hear_each_other_through_router_without_gossip(
    router: RouterProcess, open_bus: Callable[[zenoh.Config], Bus]
) -> None:
    """Documents a Zenoh 1.10 behaviour: a router does not forward data between peers."""
    a = open_bus(zenoh_config(mode="peer", connect=router.listen_endpoints, gossip_scouting=False))
    b = open_bus(zenoh_config(mode="peer", connect=router.listen_endpoints, gossip_scouting=False))
    assert wait_until(lambda: a.routers() and b.routers(), 30.0)
    rx = b.receiver(key_pattern("calibrated"))
    assert not _deliver(a, rx, key("s1", "calibrated"), b"lost", 1.0)


def test_run_router_in_thread_stops_on_event(open_bus: Callable[[zenoh.Config], Bus]) -> None:
    endpoint = loopback_endpoint(free_port())
    stop = threading.Event()
    lines: list[str] = []
    thread = threading.Thread(
        target=run_router,
        kwargs={"listen_endpoints": [endpoint], "stop_event": stop, "out": lines.append},
        daemon=True,
    )
    thread.start()
    try:
        assert wait_until(lambda: any(s.startswith(READY_PREFIX) for s in lines), 10.0)
        client = open_bus(zenoh_config(mode="client", connect=[endpoint]))
        assert len(client.routers()) == 1
    finally:
        stop.set()
        thread.join(5.0)
    assert not thread.is_alive()
    assert lines[-1].startswith("recal-router stopped")


def test_router_process_stops_cleanly_on_sigterm(router: RouterProcess) -> None:
    assert router.alive and router.zid
    assert router.stop(timeout_s=5.0) == 0
    assert "recal-router stopped" in router.output


# --------------------------------------------------------------------------- process lifetime


def _run_python(code: str, timeout_s: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout_s
    )


def test_process_exits_even_if_the_bus_is_never_closed() -> None:
    """Callbacks run on Zenoh threads, not on non-daemon Python threads that block exit."""
    code = (
        "from recal.io.bus import Bus, key\n"
        "from recal.io.bus_config import zenoh_config\n"
        "bus = Bus(zenoh_config())\n"
        "bus.subscribe('recal/**', lambda m: None)\n"
        "rx = bus.receiver('recal/*/raw', capacity=8)\n"
        "bus.queryable(key('s1', 'status'), lambda k, p: b'ok')\n"
        "bus.publish(key('s1', 'raw'), b'x')\n"
        "assert rx.recv(2.0) is not None\n"
        "print('done', flush=True)\n"
    )
    result = _run_python(code, timeout_s=20.0)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "done"


def test_router_child_exits_when_its_parent_dies() -> None:
    """A router left by a crashed parent must not keep holding the port."""
    code = (
        "import os\n"
        "from recal.io.router import start_router_process\n"
        f"r = start_router_process(['{loopback_endpoint(free_port())}'])\n"
        "print(r.pid, flush=True)\n"
        "os._exit(0)\n"  # no cleanup at all
    )
    result = _run_python(code, timeout_s=20.0)
    pid = int(result.stdout.strip())
    try:
        assert wait_until(lambda: not _pid_alive(pid), 30.0, interval_s=0.05)
    finally:
        if _pid_alive(pid):
            os.kill(pid, signal.SIGKILL)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
