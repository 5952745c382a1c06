"""A device that prints its header only at boot, heard by the daemon before and after a restart.

Real parts only: `python -m recal run` as a child process reading a pseudo-terminal
(PtyDevice), checkpoints on disk. Every wait is bounded in count and time.
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np

from gateway_process import GatewayProcess, write_config
from polling import wait_for
from recal.daemon.checkpoint_store import checkpoint_path, load_checkpoint
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from test_gateway import sim_raw, stream

SID = "wrist"


def _start(config: Path, mcap: Path, dev: PtyDevice,
           children: list[GatewayProcess]) -> GatewayProcess:
    gw = GatewayProcess(config, mcap)
    children.append(gw)
    assert wait_for(lambda: gw.has_open(dev.slave_name), 20, 0.02), gw.lines
    return gw


def _stop(gw: GatewayProcess) -> None:
    gw.proc.send_signal(signal.SIGTERM)
    assert gw.proc.wait(30) == 0, gw.lines


def test_a_restart_without_the_header_keeps_the_channel_and_the_checkpoints(
        tmp_path: Path, children: list[GatewayProcess]) -> None:
    """Run 1 hears the boot header (aux channel temp_c) and saves checkpoints; SIGTERM. Run 2:
    the device does not print its header again, so the channel arrives unnamed (aux0). The
    daemon says it takes aux0 as temp_c, and its checkpoints go on being saved (no 'not
    saved' line), holding the samples of run 2."""
    raw = sim_raw(4.0, seed=7)
    temp = 24.0 + 0.5 * np.sin(np.arange(len(raw)) / 3000.0)
    raw = RawBatch(raw.t_us, raw.v, temp[:, None], ("temp_c",))
    unnamed = RawBatch(raw.t_us, raw.v, raw.aux, ("aux0",))
    link = str(tmp_path / "ttyHDR")
    # one sensor without aux_names: the channels are whatever the device's header says
    config = write_config(tmp_path, link, "[zenoh]\nenabled = false\n", 0.05, SID,
                          aux_names=None, after_update_s=0.2)
    ckpt = checkpoint_path(tmp_path / "ck", SID)
    half = len(raw) // 2
    with PtyDevice(link, "ascii", header=False, write_timeout_s=5.0) as dev:
        gw = _start(config, tmp_path / "run1.mcap", dev, children)
        dev.write_header(("temp_c",))
        sent, _ = stream(dev, raw[:half], 2000.0, chunk=20)
        assert wait_for(lambda: (load_checkpoint(ckpt) or {}).get("pipeline", {}).get(
            "counts", {}).get("samples", 0) >= sent - 200, 30), gw.lines
        _stop(gw)
        first = load_checkpoint(ckpt)
        assert first is not None and first["pipeline"]["aux_names"] == ["temp_c"]

        gw = _start(config, tmp_path / "run2.mcap", dev, children)
        assert "'checkpoint'" in gw.ready_line, gw.ready_line
        more, _ = stream(dev, unnamed[half:], 2000.0, chunk=20)
        target = first["pipeline"]["counts"]["samples"] + more - 200
        assert wait_for(lambda: (load_checkpoint(ckpt) or {}).get("pipeline", {}).get(
            "counts", {}).get("samples", 0) >= target, 30), gw.lines
        _stop(gw)
    assert not [ln for ln in gw.lines if "not saved" in ln], gw.lines
    assert any("aux0" in ln and "temp_c" in ln for ln in gw.lines), gw.lines
    last = load_checkpoint(ckpt)
    assert last is not None and last["pipeline"]["aux_names"] == ["temp_c"]
    assert last["pipeline"]["counts"]["samples"] >= target
