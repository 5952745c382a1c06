"""Replay: a recording through the same node code path as the live gateway, without Zenoh."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from polling import wait_for
from recal.commands.replay import replay
from recal.config import parse_config
from recal.core.status import Status
from recal.daemon.gateway import Gateway, run_gateway
from recal.errors import RecordingError
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.io.repair import repair
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from recal.sim.wearer import SensorSpec, SimResult, WearerSpec, simulate

RATE_HZ = 100.0
SID = "s1"


def sim(minutes: float, seed: int, **wearer: Any) -> SimResult:
    spec = SensorSpec.random(np.random.default_rng(seed), offset_mg=40.0, gain_pct=3.0)
    w = WearerSpec(**{"still_s": (8.0, 20.0), "move_s": (2.0, 5.0), **wearer})
    return simulate(minutes / 60.0, RATE_HZ, seed, spec, w)


def live_run(tmp: Path, raw: RawBatch, mcap: Path, ckpt_dir: Path) -> None:
    """The gateway (in this process, Zenoh off) on a real pty, fed ``raw``, then stopped."""
    link = str(tmp / "tty0")
    cfg = parse_config({
        "zenoh": {"enabled": False}, "mcap": {"flush_interval_s": 0.2},
        "checkpoint": {"dir": str(ckpt_dir), "interval_s": 0.5},
        "sensors": [{"id": SID, "port": link, "aux_names": [], "rate_hz": RATE_HZ,
                     "prior": {"counts_per_g": 1024.0}}]}, tmp, "test")
    stop = threading.Event()
    ready: list[Gateway] = []
    with PtyDevice(link) as dev:
        th = threading.Thread(target=run_gateway, args=(cfg,), daemon=True, kwargs={
            "mcap_out": mcap, "stop_event": stop, "on_ready": ready.append,
            "out": lambda s: None})
        th.start()
        assert wait_for(lambda: bool(ready), 20)
        port = ready[0].ports[SID]
        assert wait_for(lambda: port.is_open, 10)
        for i in range(0, len(raw), 50):  # bounded: one pass over the data
            dev.write_batch(raw[i:i + 50])
            time.sleep(0.01)
        assert wait_for(lambda: port.samples_logged == len(raw) and not port.pending, 10)
        stop.set()
        th.join(30)
        assert not th.is_alive()


def test_replay_reproduces_live_runs_also_after_a_checkpoint_restore(tmp_path: Path) -> None:
    raw = sim(3.0, seed=21).raw
    ck = tmp_path / "ck"
    first, second = raw[:9000], raw[9000:]
    live_run(tmp_path, first, tmp_path / "a.mcap", ck)
    live_run(tmp_path, second, tmp_path / "b.mcap", ck)  # resumes from the checkpoint
    setups = [obj for _, obj, _ in rec.iter_json(tmp_path / "b.mcap", f"/{SID}/setup")]
    assert setups[0]["start"] == "checkpoint"
    for name in ("a", "b"):
        live = rec.read_all_calibrated(tmp_path / f"{name}.mcap", SID)
        out = replay(tmp_path / f"{name}.mcap", tmp_path / f"{name}-replay.mcap",
                     progress=False)
        assert out["sensors"][SID]["start"] == "recording"
        again = rec.read_all_calibrated(tmp_path / f"{name}-replay.mcap", SID)
        np.testing.assert_array_equal(again.t_us, live.t_us)
        np.testing.assert_array_equal(again.quasi_static, live.quasi_static)
        assert np.max(np.abs(again.a_g - live.a_g)) <= 1e-9
        live_states = [o["params"] for _, o, _ in
                       rec.iter_json(tmp_path / f"{name}.mcap", f"/{SID}/calibration")]
        replay_states = [o["params"] for _, o, _ in
                         rec.iter_json(tmp_path / f"{name}-replay.mcap", f"/{SID}/calibration")]
        assert live_states == replay_states
    # the second run continued the first: its calibration did not restart from the prior
    b_states = [o for _, o, _ in rec.iter_json(tmp_path / "b.mcap", f"/{SID}/calibration")]
    assert b_states[0]["counts"]["samples"] > 0


def _raw_only(path: Path, raw: RawBatch, batch: int = 100, **writer: Any) -> None:
    with RecordingWriter(path, background_flush=False, fsync=False, **writer) as w:
        for i in range(0, len(raw), batch):
            w.write_raw(SID, raw[i:i + batch], 1_000_000_000 + int(raw.t_us[i]) * 1000)


def test_replay_without_prior_bootstraps_and_infers_the_rate(tmp_path: Path) -> None:
    s = sim(10.0, seed=4, p_upright=0.2, p_lying=0.3, p_any=0.5)
    _raw_only(tmp_path / "raw.mcap", s.raw)
    out = replay(tmp_path / "raw.mcap", tmp_path / "out.mcap", progress=False)
    info = out["sensors"][SID]
    assert info["start"] == "bootstrap"
    assert info["rate_hz"] == pytest.approx(RATE_HZ)
    assert info["bootstrapped"] and info["samples"] == len(s.raw)
    events = [o["kind"] for _, o, _ in rec.iter_json(tmp_path / "out.mcap", f"/{SID}/events")]
    assert "bootstrap" in events
    true_mg = 1e3 * np.asarray(s.truth.sensor.offset_g)
    est_mg = np.array([info["described"]["offset"][f"{a}_mg"] for a in "xyz"])
    assert np.max(np.abs(est_mg - true_mg)) < 10.0, (est_mg, true_mg)
    # the output holds raw + calibrated + calibration + plot + events
    topics = set(rec.summary(tmp_path / "out.mcap").topics)
    assert {f"/{SID}/raw", f"/{SID}/calibrated", f"/{SID}/calibration", f"/{SID}/plot",
            f"/{SID}/events", f"/{SID}/setup"} <= topics
    assert len(rec.read_all_raw(tmp_path / "out.mcap", SID)) == len(s.raw)


def test_cli_replay_summary_json_and_overwrite(tmp_path: Path, capsys: Any) -> None:
    """`recal replay`: a short summary per sensor on stdout, the whole one with --json, and an
    existing --out replaced only with --overwrite (the first run's file is kept otherwise)."""
    from recal import cli

    s = sim(10.0, seed=4, p_upright=0.2, p_lying=0.3, p_any=0.5)
    _raw_only(tmp_path / "raw.mcap", s.raw)
    out, report = tmp_path / "out.mcap", tmp_path / "r.json"
    assert cli.main(["replay", str(tmp_path / "raw.mcap"), "--out", str(out), "--quiet",
                     "--json", str(report)]) == 0
    lines = capsys.readouterr().out.splitlines()
    doc = json.loads(report.read_text())
    info = doc["sensors"][SID]
    assert lines[0].startswith(f"replayed {len(s.raw)} samples of 1 sensor(s)")
    assert lines[1].startswith(f"  {SID}: started from bootstrap, model diagonal;")
    assert f"{info['counts']['updates']} updates" in lines[1] and info["counts"]["updates"] > 0
    x_mg = info["described"]["offset"]["x_mg"]
    assert any(line.startswith(f"    offset: x_mg {x_mg:.4g},") for line in lines), lines
    size = out.stat().st_size
    assert cli.main(["replay", str(tmp_path / "raw.mcap"), "--out", str(out), "--quiet"]) == 2
    assert "pass --overwrite" in capsys.readouterr().err and out.stat().st_size == size
    assert cli.main(["replay", str(tmp_path / "raw.mcap"), "--out", str(out), "--quiet",
                     "--overwrite"]) == 0
    assert len(rec.read_all_calibrated(out, SID)) == len(s.raw)


def test_replay_with_config_prior_model_file_and_rotated_parts(tmp_path: Path,
                                                             capsys: Any) -> None:
    s = sim(3.0, seed=8)
    _raw_only(tmp_path / "rot.mcap", s.raw, rotate_bytes=8_000, chunk_size=4096)
    parts = rec.recording_parts(tmp_path / "rot.mcap")
    assert len(parts) >= 3
    cfg = tmp_path / "replay.toml"
    cfg.write_text(f'[pipeline]\nmode = "offsets"\n\n[[sensors]]\nid = "{SID}"\n'
                   f'rate_hz = {RATE_HZ}\nprior = {{ counts_per_g = 1024.0 }}\n')
    out = replay(tmp_path / "rot.mcap", tmp_path / "cfg.mcap", config=cfg, progress=True)
    assert "replay" in capsys.readouterr().err  # tqdm's bar went to stderr
    info = out["sensors"][SID]
    assert info["start"] == "config" and info["samples"] == len(s.raw)
    assert all(v == 1024.0 for k, v in info["params"].items() if k.startswith("s_"))  # offsets
    # a model file (here a calibration state of that run) replaces the configured prior
    state = [o for _, o, _ in rec.iter_json(tmp_path / "cfg.mcap", f"/{SID}/calibration")][-1]
    (tmp_path / "model.json").write_text(json.dumps(state))
    out2 = replay(tmp_path / "rot.mcap", tmp_path / "model.mcap", model=tmp_path / "model.json",
                  config=cfg, progress=False)
    first = next(o for _, o, _ in rec.iter_json(tmp_path / "model.mcap", f"/{SID}/calibration"))
    assert first["params"] == pytest.approx(state["params"])
    assert out2["sensors"][SID]["start"] == "config"


def test_replay_of_a_truncated_file_needs_repair(tmp_path: Path) -> None:
    s = sim(1.0, seed=2)
    # one message per batch (not joined), so that half the file holds some of them
    _raw_only(tmp_path / "full.mcap", s.raw, chunk_size=4096, log_batch_samples=1)
    data = (tmp_path / "full.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[:len(data) // 2])
    with pytest.raises(RecordingError):
        replay(tmp_path / "cut.mcap", tmp_path / "x.mcap", progress=False)
    repair(tmp_path / "cut.mcap", tmp_path / "fixed.mcap")
    out = replay(tmp_path / "fixed.mcap", tmp_path / "y.mcap", progress=False)
    assert 0 < out["samples"] < len(s.raw)


def test_replaying_a_recording_twice_writes_the_same_bytes(tmp_path: Path) -> None:
    """A file-to-file command's chunks end by size alone, not by the wall clock: the same
    input gives the same file on a fast or a slow (or busy) machine."""
    from mcap.reader import make_reader

    res = sim(90, seed=12)
    src = tmp_path / "in.mcap"
    with RecordingWriter(src) as w:
        for lo in range(0, len(res.raw), 100):
            part = res.raw[lo:lo + 100]
            w.write_raw("s", part, int(part.t_us[0]) * 1000)
    outs = [tmp_path / "out0.mcap", tmp_path / "out1.mcap"]
    for out in outs:
        replay(src, out)
    assert outs[0].read_bytes() == outs[1].read_bytes()
    with outs[0].open("rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 3  # enough to show where chunks end
    # every chunk but the last was closed by its size (1 MiB), none early by a clock
    assert all(c.uncompressed_size >= 1024 * 1024 for c in chunks[:-1])


def _recording_with_a_reopen(path: Path, raw: RawBatch, reopen_at: int | None) -> None:
    """raw logged as a gateway logs it, 250 samples per message, the port opened at the
    start and (reopen_at: before that sample) opened again."""
    with RecordingWriter(path, background_flush=False, fsync=False, overwrite=True) as w:
        t0_ns = 1_760_000_000 * 10**9
        w.write_event("port_opened", t0_ns, sensor_id=SID, detail={"port": "/dev/ttyX"})
        for i in range(0, len(raw), 250):  # bounded: one pass over the data
            b = raw[i:i + 250]
            log_ns = t0_ns + 1000 * int(b.t_us[-1] - raw.t_us[0]) + 1_000_000
            if i == reopen_at:
                w.write_event("port_found", log_ns - 500_000, sensor_id=SID,
                              detail={"port": "/dev/ttyX"})
            w.log_raw(SID, b, log_ns)


def test_replay_doubts_where_the_recorded_port_opened_again(tmp_path: Path) -> None:
    """The live gateway holds a sensor's output from a reopened port until a still window
    agrees (`CalibrationNode.port_reopened`); replay reads the port events and does the same
    at the same arrival, so the statuses match a node told of the reopen there."""
    rate = 25.0
    res = simulate(50 / 60, rate, 1, SensorSpec.random(np.random.default_rng(1), 50, 3))
    k = int(40 * 60 * rate)
    statuses = {}
    for name, at in (("reopened", k), ("plain", None)):
        _recording_with_a_reopen(tmp_path / f"{name}.mcap", res.raw, at)
        replay(tmp_path / f"{name}.mcap", tmp_path / f"{name}-out.mcap", progress=False)
        statuses[name] = rec.read_all_calibrated(tmp_path / f"{name}-out.mcap", SID).status
    plain, reopened = statuses["plain"], statuses["reopened"]
    np.testing.assert_array_equal(plain[:k], reopened[:k])  # the same until the reopen
    assert plain[k - 1] == plain[k] == Status.CALIBRATED
    assert reopened[k] == Status.HELD  # held from the reopen on
    back = np.flatnonzero(reopened[k:] == Status.CALIBRATED)
    assert len(back) and back[0] / rate < 60  # until its first still window agreed
    assert not np.any(reopened[k:] == Status.SUSPECT)
