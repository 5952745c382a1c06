"""Process faults: the gateway killed with SIGKILL at random moments, and its Zenoh router killed.

Real parts only: `python -m recal run` as a child process reading a pseudo-terminal (PtyDevice),
MCAP files on disk repaired with `recal repair`, checkpoints on disk, a `recal router` child
process and Zenoh sessions on 127.0.0.1. Every wait is bounded in count and time.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np

from gateway_process import GatewayProcess, write_config
from polling import wait_for
from recal.cli import main as recal_main
from recal.commands.demo import free_port
from recal.daemon.checkpoint_store import checkpoint_path, load_checkpoint
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_raw
from recal.io.router import RouterProcess
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from test_gateway import sim_raw, stream

SID = "s1"
RATE_HZ = 100.0  # the sensor's rate (device time)
SEND_PER_S = 1000.0  # how fast the test device writes: 10x real time, to reach updates soon
CHUNK = 10  # samples per write
FLUSH_S = 0.01  # [mcap] flush_interval_s: what a kill may lose, at most (plus read latency)
KILLS = 10


def _start(config: Path, mcap: Path, dev: PtyDevice,
           children: list[GatewayProcess]) -> GatewayProcess:
    """Start the gateway and wait until it reads the device; the device then re-announces
    itself with a header. What the killed run left unread in the kernel comes first."""
    gw = GatewayProcess(config, mcap)
    children.append(gw)
    assert wait_for(lambda: gw.has_open(dev.slave_name), 20, 0.02), gw.lines
    time.sleep(0.2)
    dev.write_header(())
    return gw


def _stream(dev: PtyDevice, raw: RawBatch, start: int, seconds: float) -> int:
    """Write samples from ``start`` at SEND_PER_S for about ``seconds``; return how many."""
    return stream(dev, raw[start:], SEND_PER_S, chunk=CHUNK, stop_after_s=seconds)[0]


def _repair(broken: Path, fixed: Path) -> None:
    """`recal repair BROKEN --out FIXED`, the command's own code."""
    assert recal_main(["repair", str(broken), "--out", str(fixed)]) == 0


def _first_state(path: Path) -> dict:
    return next(obj for _, obj, _ in rec.iter_json(path, f"/{SID}/calibration"))


def _params(doc: dict) -> np.ndarray:
    return np.asarray(doc["pipeline"]["estimate"]["p"], float)


def test_kill9_at_ten_random_moments_then_repair_and_restart(
        tmp_path: Path, children: list[GatewayProcess]) -> None:
    rng = np.random.default_rng(2024)
    kill_after_s = rng.uniform(0.8, 2.0, KILLS)  # stream time before each kill
    raw = sim_raw(12.0, seed=5)
    link = str(tmp_path / "ttyKILL")
    config = write_config(tmp_path, link, "[zenoh]\nenabled = false\n", FLUSH_S, SID, RATE_HZ)
    ckpt = checkpoint_path(tmp_path / "ck", SID)
    sent_total = got_total = 0
    logged_end = 0  # index in raw after the last sample a run recovered
    table = []
    saved: dict | None = None
    with PtyDevice(link, "ascii", header=False, write_timeout_s=5.0) as dev:
        for k in range(KILLS + 1):
            gw = _start(config, tmp_path / "live.mcap", dev, children)
            assert ("'checkpoint'" in gw.ready_line) == (saved is not None), gw.ready_line
            if k == KILLS:  # the last run ends with SIGTERM: a clean stop
                sent = _stream(dev, raw, sent_total, 1.0)
                gw.proc.send_signal(signal.SIGTERM)
                assert gw.proc.wait(30) == 0, gw.lines
                fixed = gw.mcap  # closed and indexed: no repair needed
            else:
                sent = _stream(dev, raw, sent_total, float(kill_after_s[k]))
                time.sleep(float(rng.uniform(0.0, 0.02)))  # the kill lands mid-stream
                os.kill(gw.proc.pid, signal.SIGKILL)
                gw.proc.wait(10)
                fixed = tmp_path / f"fixed{k}.mcap"
                _repair(gw.mcap, fixed)
            assert dev.bytes_dropped == 0
            got = rec.read_all_raw(fixed, SID)
            # exactly once, in order, bit for bit: what the killed run left unread in the
            # kernel (the port is opened without a flush), then a prefix of what this run
            # was sent
            start = int(np.searchsorted(raw.t_us, got.t_us[0]))
            assert logged_end <= start <= sent_total, (logged_end, start, sent_total)
            np.testing.assert_array_equal(got.t_us, raw.t_us[start:start + len(got)])
            np.testing.assert_array_equal(got.v, raw.v[start:start + len(got)])
            lost = start - logged_end  # what the kill before this run lost
            logged_end = start + len(got)
            table.append((k, sent, len(got), lost))
            # the state resumed is the checkpoint the killed run left
            first = _first_state(fixed)
            if saved is not None:
                assert first["reason"] == "restored", first["reason"]
                p_first = np.array([first["params"][n] for n in first["param_names"]])
                np.testing.assert_allclose(p_first, _params(saved), rtol=0, atol=1e-9)
            before = saved
            saved = load_checkpoint(ckpt)  # never half written, whenever the kill came
            assert saved is not None
            if before is not None:
                assert (saved["pipeline"]["counts"]["samples"]
                        >= before["pipeline"]["counts"]["samples"])
            sent_total += sent
            got_total += len(got)
    assert saved is not None and saved["pipeline"]["counts"]["updates"] >= 5
    assert np.max(np.abs(_params(saved) - np.asarray(saved["pipeline"]["prior"]["mean"]))) > 1
    losses = np.array([row[3] for row in table[1:]])  # lost at each kill
    print("\nrun  sent  recovered  lost at the kill before\n" + "\n".join(
        f"{k:3d} {s:5d} {g:10d} {lo:5d}" for k, s, g, lo in table))
    print(f"recovered {got_total}/{sent_total} = {100 * got_total / sent_total:.2f} %")
    assert got_total >= 0.99 * sent_total
    assert np.all(losses <= 0.01 * np.array([row[1] for row in table[:KILLS]]) + 30), table
    assert logged_end == sent_total  # the clean stop loses nothing
    # a kill during a checkpoint write leaves at most its own temporary file behind
    leftovers = [p.name for p in (tmp_path / "ck").iterdir() if p.name != ckpt.name]
    assert len(leftovers) <= KILLS, leftovers


# --------------------------------------------------------------------------- router


def test_router_killed_gateway_keeps_logging_and_resumes_publishing(
        tmp_path: Path, children: list[GatewayProcess]) -> None:
    """Gateway and subscriber are Zenoh clients of a `recal router`. The router is killed
    (SIGKILL) and restarted on the same endpoint: meanwhile the gateway logs every sample, and
    once both clients have reconnected by themselves every sample is published again."""
    raw = sim_raw(4.0, seed=6)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    retry = {"period_init_ms": 50, "period_max_ms": 200}
    client_cfg = tmp_path / "zenoh-client.json5"
    client_cfg.write_text(json.dumps({
        "mode": "client", "connect": {"endpoints": [endpoint], "retry": retry},
        "scouting": {"multicast": {"enabled": False}}}))
    link = str(tmp_path / "ttyROUTE")
    config = write_config(tmp_path, link, f'[zenoh]\nconfig_file = "{client_cfg}"\n',
                          FLUSH_S, SID, RATE_HZ)
    router = RouterProcess([endpoint]).start()
    heard: list[np.ndarray] = []  # t_us of the raw samples the subscriber heard, per message

    def heard_t() -> np.ndarray:
        return np.concatenate(heard) if heard else np.zeros(0, np.int64)

    try:
        with PtyDevice(link, "ascii", header=False, write_timeout_s=5.0) as dev:
            gw = _start(config, tmp_path / "route.mcap", dev, children)
            sub = Bus(zenoh_config("client", connect=[endpoint],
                                   overrides={"connect/retry": retry}))
            try:
                sub.subscribe(key(SID, "raw"),
                              lambda m: heard.append(decode_raw(m.payload)[1].t_us))
                # until the gateway's client has learnt of the subscriber through the router,
                # it publishes to nobody: a warm-up (logged, maybe not heard) until one is heard
                warm = 0
                for _ in range(50):  # bounded: up to ~20 s of 0.2 s bursts
                    warm += _stream(dev, raw, warm, 0.2)
                    if wait_for(lambda: bool(heard), 0.2, 0.02):
                        break
                assert wait_for(lambda: raw.t_us[warm - 1] in heard_t(), 10), "never heard"
                base = len(heard_t())
                sent = _stream(dev, raw, warm, 1.0)
                assert wait_for(lambda: len(heard_t()) == base + sent, 10), \
                    (len(heard_t()) - base, sent)

                router.kill()  # a crash: no goodbye
                start = warm + sent
                down = _stream(dev, raw, start, 1.5)  # logged, but nobody can hear them
                heard_while_down = len(heard_t()) - base - sent
                router.start()  # the same endpoint
                for _ in range(50):  # bounded: up to ~20 s of 0.2 s bursts until heard again
                    down += _stream(dev, raw, start + down, 0.2)
                    if wait_for(lambda: len(heard_t()) > base + sent, 0.2, 0.02):
                        break
                assert len(heard_t()) > base + sent, "publishing did not resume"
                after = _stream(dev, raw, start + down, 1.0)
                total = start + down + after
                want = raw.t_us[start + down:total]
                assert wait_for(lambda: np.isin(want, heard_t()).all(), 10), \
                    (np.isin(want, heard_t()).sum(), after)
            finally:
                sub.close()
            gw.proc.send_signal(signal.SIGTERM)
            assert gw.proc.wait(30) == 0, gw.lines
    finally:
        router.kill()
    t = heard_t()
    assert heard_while_down == 0  # the router really was down
    assert len(np.unique(t)) == len(t)  # nothing heard twice
    np.testing.assert_array_equal(t[base:base + sent], raw.t_us[warm:start])
    print(f"\nheard: {base} of {warm} in the warm-up, {sent} of {sent} before the kill, "
          f"{np.isin(raw.t_us[start:start + down], t).sum()} of {down} while the router was "
          f"down or the clients reconnecting, {after} of {after} after")
    logged = rec.read_all_raw(gw.mcap, SID)  # the local log never stopped
    np.testing.assert_array_equal(logged.t_us, raw.t_us[:total])
    events = [obj["kind"] for _, obj, _ in rec.iter_json(gw.mcap, "/gateway/events")]
    assert events[0] == "start" and events[-1] == "stop"
