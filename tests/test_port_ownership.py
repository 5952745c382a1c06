"""Who owns a serial port, and what a port's sensor is called.

Two `python -m recal run` processes started at the same instant on one real pseudo-terminal:
exactly one keeps it, the other exits at once with one line (8 tries). A port that comes to
name a tty another process holds stops the daemon. A port without a configured id is named
after its device (by-id link, USB serial number, else its path): two ptys, two ids."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path

from gateway_process import GatewayProcess
from polling import wait_for
from recal.sim.pty_device import PtyDevice

TRIES = 8
START_S = 30.0


def _config(tmp: Path, name: str) -> Path:
    """Zenoh off; a state folder of its own (the sensor locks must not decide)."""
    path = tmp / f"{name}.toml"
    path.write_text(f"""[zenoh]
enabled = false

[checkpoint]
dir = "{tmp / ('ck-' + name)}"
""")
    return path


def _run(tmp: Path, name: str, link: str) -> GatewayProcess:
    """`python -m recal run` on ``link`` as sensor ``name``, not waited for."""
    return GatewayProcess(_config(tmp, name), tmp / f"{name}.mcap",
                          ["--port", link, "--sensor-id", name, "--counts-per-g", "1024",
                           "--zero-g", "0", "--rate", "100"], wait_ready=False)


def _settled(runs: list[GatewayProcess]) -> bool:
    """One has exited and the other is ready."""
    return sum(r.proc.poll() is not None for r in runs) == 1 and any(r.ready for r in runs)


def test_two_daemons_started_at_once_on_one_port_leave_exactly_one(tmp_path: Path) -> None:
    link = str(tmp_path / "tty0")
    with PtyDevice(link, header=True):
        for attempt in range(TRIES):
            tmp = tmp_path / f"try{attempt}"
            tmp.mkdir()
            runs = [_run(tmp, "a", link), _run(tmp, "b", link)]
            try:
                assert wait_for(lambda runs=runs: _settled(runs), START_S, 0.05), \
                    [r.lines for r in runs]
                loser = next(r for r in runs if r.proc.poll() is not None)
                winner = next(r for r in runs if r is not loser)
                assert loser.proc.returncode != 0
                errors = [ln for ln in loser.lines if ln.startswith("recal: error:")]
                assert len(errors) == 1, loser.lines
                assert f"port {link} is in use by process {winner.proc.pid}" in errors[0]
                assert not any("Traceback" in ln for ln in loser.lines), loser.lines
                assert not loser.ready, loser.lines
                # the winner keeps running: no second exit while it is asked to stop
                assert winner.proc.poll() is None
                winner.proc.send_signal(signal.SIGTERM)
                assert winner.proc.wait(30) == 0, winner.lines
            finally:
                for r in runs:
                    r.kill()


# --------------------------------------------------------------------------- the default id


class _Listed:
    """What pyserial's list_ports gives for a port (device path and USB serial number)."""

    def __init__(self, device: str, serial_number: str | None, vid: int | None = 0x2341,
                 pid: int | None = 0x8057) -> None:
        self.device, self.serial_number, self.vid, self.pid = device, serial_number, vid, pid


def test_default_id_is_the_by_id_name_else_the_usb_serial_else_the_port_path(
        tmp_path: Path) -> None:
    from recal.config.settings import default_sensor_id
    from recal.io.recording import sensor_topic

    dev = tmp_path / "dev"
    dev.mkdir()
    for name in ("ttyACM0", "ttyACM1", "ttyUSB0"):
        (dev / name).write_text("")
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-Arduino_LLC_Nano 33 IoT_4F3A9C2E-if00").symlink_to("../dev/ttyACM0")
    (by_id / "usb-FTDI_FT232R_A50285BI-if00-port0").symlink_to(dev / "ttyUSB0")
    listed = [_Listed(str(dev / "ttyACM1"), "95735353032351A0E0A1"),
              _Listed(str(dev / "ttyACM0"), "SHOULD-NOT-WIN")]
    # the by-id name of the device the port is (through a symlink of the user's too)
    (tmp_path / "wrist").symlink_to(dev / "ttyACM0")
    ids = {p: default_sensor_id(p, by_id_dir=by_id, listed=listed)
           for p in (str(dev / "ttyACM0"), str(tmp_path / "wrist"), str(dev / "ttyUSB0"),
                     str(dev / "ttyACM1"))}
    assert ids[str(dev / "ttyACM0")] == "usb-Arduino_LLC_Nano_33_IoT_4F3A9C2E-if00"
    assert ids[str(tmp_path / "wrist")] == ids[str(dev / "ttyACM0")]
    assert ids[str(dev / "ttyUSB0")] == "usb-FTDI_FT232R_A50285BI-if00-port0"
    # no by-id link: the USB serial number from list_ports
    assert ids[str(dev / "ttyACM1")] == "usb-2341-8057-95735353032351A0E0A1"
    # neither: the port's path; no by-id folder at all is no error
    assert default_sensor_id("/dev/ttyS0", by_id_dir=tmp_path / "absent", listed=[]) == "ttyS0"
    assert default_sensor_id("/tmp/a b/tty0", by_id_dir=by_id, listed=[]) == "tmp-a_b-tty0"
    assert default_sensor_id("loop://", by_id_dir=by_id, listed=[]) == "loop"
    for sid in ids.values():
        sensor_topic(sid, "raw")  # a valid id


def test_two_ptys_without_ids_get_distinct_ids_from_their_paths(tmp_path: Path) -> None:
    """`recal run --port A --port B` with no config: each sensor its own id, its own
    checkpoint."""
    links = [str(tmp_path / "a" / "tty0"), str(tmp_path / "b" / "tty0")]
    for link in links:
        Path(link).parent.mkdir()
    with PtyDevice(links[0]), PtyDevice(links[1]):
        lines: list[str] = []
        stop = threading.Event()
        from recal.daemon.gateway import run_gateway

        ready: list[object] = []
        cfg = _config(tmp_path, "c")

        def on_ready(gw: object) -> None:
            ready.append(gw)
            stop.set()

        status = run_gateway(cfg, ports=links, mcap_out=tmp_path / "c.mcap", stop_event=stop,
                             out=lines.append, on_ready=on_ready)
        assert status == 0, lines
    ids = sorted(ready[0].ports)  # type: ignore[attr-defined]
    assert len(ids) == 2 and ids[0] != ids[1], ids
    assert all(sid.endswith("-tty0") and "sensor0" not in sid for sid in ids), ids
    assert {p.sensor.port for p in ready[0].ports.values()} == set(links)  # type: ignore


def test_a_port_another_process_takes_after_an_unplug_stops_the_daemon(tmp_path: Path) -> None:
    """The device path comes to name a tty someone else holds (flock, as another recal would):
    the daemon stops with one line naming the holder instead of waiting to take it over."""
    import fcntl

    from recal.daemon.gateway import run_gateway

    link = tmp_path / "tty0"
    first = os.openpty()
    other = os.openpty()
    holder = -1
    try:
        link.symlink_to(os.ttyname(first[1]))
        lines: list[str] = []
        opened = threading.Event()
        result: list[int] = []

        def out(line: str) -> None:
            lines.append(line)
            if "port opened" in line:
                opened.set()

        stop = threading.Event()
        runner = threading.Thread(target=lambda: result.append(run_gateway(
            _config(tmp_path, "a"), ports=[str(link)], sensor_ids=["a"],
            mcap_out=tmp_path / "a.mcap", stop_event=stop, out=out)), daemon=True)
        runner.start()
        try:
            assert opened.wait(20), lines
            holder = os.open(os.ttyname(other[1]), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            fcntl.flock(holder, fcntl.LOCK_EX | fcntl.LOCK_NB)
            swap = tmp_path / "tty0.new"
            swap.symlink_to(os.ttyname(other[1]))
            os.replace(swap, link)  # the path now names another device, held by "us"
            runner.join(30)
        finally:
            stop.set()
            runner.join(30)
        assert result == [2], lines
        assert lines[-1] == f"recal: error: port {link} is in use by process {os.getpid()}", \
            lines
    finally:
        for fd in (*first, *other, holder):
            if fd >= 0:
                os.close(fd)
