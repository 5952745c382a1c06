"""Live discovery in the daemon, end to end: a real pseudo-terminal, a real Zenoh session on
127.0.0.1, real processes (`recal run`, stopped and started again) and `recal replay` of the
live log. The sensor has an offset that follows its board temperature, which nothing in the
configuration declares; discovery runs with its defaults."""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest

from gateway_process import GatewayProcess, write_config
from polling import wait_for
from recal import cli
from recal.commands.demo import free_port
from recal.daemon.checkpoint_store import load_checkpoint
from recal.daemon.gateway import NOTE_PREFIX
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_json
from recal.sim import wearer as sim
from recal.sim.pty_device import PtyDevice
from test_discovery import OFFSET_TC, WEARER, _sensor
from test_gateway import stream

SID = "s1"
RATE_HZ = 25.0
MINUTES = 22.0  # past the second run (20 min), which confirms the first, and 60 s more


def _status(bus: Bus) -> dict:
    for _ in range(20):  # bounded
        for _k, payload in bus.get(key(SID, "status"), timeout_s=1.0):
            return decode_json(payload)
    raise AssertionError("no status reply")


def _discoveries(path: Path) -> list[dict]:
    return [o for _, o, _ in rec.iter_json([path], f"/{SID}/events")
            if o.get("kind") == "discovery"]


@pytest.mark.slow
def test_the_daemon_adopts_says_resumes_and_replay_agrees(tmp_path: Path, children: list,
                                                          capsys) -> None:
    raw = sim.simulate(MINUTES / 60, RATE_HZ, 11, _sensor(offset_tc_g_per_c=OFFSET_TC),
                       WEARER).raw
    zport = free_port()
    link = str(tmp_path / "tty0")
    zenoh = f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zport}"]\nconnect = []\n'
    config = write_config(tmp_path, link, zenoh, 0.05, SID, RATE_HZ,
                          aux_names=raw.aux_names)
    run1, run2 = tmp_path / "run1.mcap", tmp_path / "run2.mcap"
    # a run takes seconds; the node takes it on 60 device seconds after it began, here under
    # a wall second: the daemon may wait for it, and the writer waits for the daemon
    with PtyDevice(link, write_timeout_s=30.0) as dev:
        gp = GatewayProcess(config, run1)
        children.append(gp)
        bus = Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{zport}"]))
        try:
            assert wait_for(lambda: _status(bus)["gateway"]["open"], 10)
            stream(dev, raw, 3000.0)  # 22 min of device time in ~11 s, every line written
            assert wait_for(lambda: _status(bus)["node"]["samples"] >= len(raw), 60)
            said = [ln for ln in gp.lines if ln.startswith(f"{NOTE_PREFIX} {SID}: discovery:")]
            assert len(said) == 1 and "added offset[board_temp]" in said[0], gp.lines
            assert "held-out error" in said[0] and " -> " in said[0]
            assert "offset[board_temp]" in _status(bus)["described"]
        finally:
            bus.close()
        gp.proc.send_signal(signal.SIGTERM)
        assert gp.proc.wait(30) == 0, gp.lines
        saved = load_checkpoint(tmp_path / "ck" / f"{SID}.json")
        assert saved is not None and ["offset", "board_temp"] in [
            [e["kind"], e["covariate"]] for e in saved["pipeline"]["model"]["effects"]]
        assert saved["discovery"]["evidence"]["added"] >= len(saved["discovery"]["evidence"]
                                                             ["t_us"]) > 60

        # a restart resumes with the adopted model
        gp2 = GatewayProcess(config, run2)
        children.append(gp2)
        bus = Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{zport}"]))
        try:
            st = _status(bus)
            assert st["node"]["start"] == "checkpoint"
            assert "offset[board_temp]" in st["described"]
        finally:
            bus.close()
        gp2.proc.send_signal(signal.SIGTERM)
        assert gp2.proc.wait(30) == 0, gp2.lines

    live = _discoveries(run1)
    adopted = [e for e in live if e["detail"]["adopted"]]
    assert len(adopted) == 1 and adopted[0]["detail"]["added"] == ["offset[board_temp]"]
    err = adopted[0]["detail"]["heldout_error_mg"]
    assert err["final"] < 0.5 * err["base"]

    # `recal replay` of the live log, with its defaults, adopts at the same sample
    out = tmp_path / "replayed.mcap"
    capsys.readouterr()
    assert cli.main(["replay", str(run1), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "discovery" in printed and "added offset[board_temp]" in printed, printed
    again = _discoveries(out)
    assert [(e["t_us"], e["detail"]["started_t_us"], e["detail"]["added"]) for e in again] == [
        (e["t_us"], e["detail"]["started_t_us"], e["detail"]["added"]) for e in live]
    a_live = rec.read_all_calibrated(run1, SID)
    a_replay = rec.read_all_calibrated(out, SID)
    np.testing.assert_array_equal(a_replay.t_us, a_live.t_us)
    np.testing.assert_allclose(a_replay.a_g, a_live.a_g, rtol=0, atol=1e-9)
