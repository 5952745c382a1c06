"""``recal demo``: the whole service on one machine, with no hardware and no router.

A simulated wearer (``recal.sim.wearer``: a sensor with random offsets and gains) streams ASCII
lines in real time, sped up, on a pseudo-terminal (:class:`recal.sim.pty_device.PtyDevice`). The
gateway daemon reads it as it would a USB accelerometer, logs to MCAP and publishes on Zenoh in
peer mode on 127.0.0.1 (explicit endpoints, no scouting). The demo's own Zenoh session connects
to the gateway, queries ``recal/demo/status`` for a live progress line and times the calibrated
batches it receives. After ``seconds`` (or when the simulated recording is used up) it stops the
daemon and prints a summary with the error against the simulator's truth.

Every run starts fresh in a folder of its own, made new: ``run-<UTC time>`` inside ``--out DIR``,
or a new temporary folder without it. Nothing else is written (the current directory is left
alone), and a run never sees an earlier run's checkpoint, so its figures are its own. The
folder holds the recording (``demo.mcap``), ``summary.json`` (the truth is not stored: the seed
recreates it) and the checkpoint the daemon wrote (``checkpoints/demo.json``). The progress line
is redrawn in place only on a terminal; piped or logged, it is a plain line every 5 s.
"""

from __future__ import annotations

import json
import socket
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from recal.config import parse_config
from recal.daemon.gateway import Gateway, run_gateway
from recal.daemon.runtime import ERROR_PREFIX
from recal.io import recording as rec
from recal.io.wire_formats import DEFAULT_FORMAT
from recal.sim.pty_device import PtyDevice
from recal.sim.wearer import SensorSpec, SimResult, WearerSpec, simulate

__all__ = ["free_port", "new_run_dir", "run_demo"]

SENSOR_ID = "demo"
COUNTS_PER_G = 1024.0


def free_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def new_run_dir(parent: str | Path | None) -> Path:
    """A folder that did not exist before (absolute): ``parent/run-<UTC time>[-k]``, made with
    ``parent`` if need be, or a new temporary folder when ``parent`` is None."""
    if parent is None:
        return Path(tempfile.mkdtemp(prefix="recal-demo-")).resolve()
    base = Path(parent)
    base.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    for k in range(1, 1000):  # two runs in one second get -2, -3, ...
        path = base / (f"run-{stamp}" if k == 1 else f"run-{stamp}-{k}")
        try:
            path.mkdir()  # exclusive: never a folder an earlier run wrote
        except FileExistsError:
            continue
        return path.resolve()
    raise FileExistsError(f"no free run folder for {stamp} in {base}")


def _simulate(minutes: float, rate_hz: float, seed: int) -> SimResult:
    rng = np.random.default_rng(seed)
    spec = SensorSpec.random(rng, offset_mg=60.0, gain_pct=4.0, counts_per_g=COUNTS_PER_G)
    # short postures so a few minutes hold many orientations (the estimator needs them)
    wearer = WearerSpec(still_s=(8.0, 20.0), move_s=(2.0, 5.0), p_upright=0.4, p_lying=0.3,
                        p_any=0.3, upright_tilt_deg=5.0)
    return simulate(minutes / 60.0, rate_hz, seed, spec, wearer)


def _progress_line(st: dict[str, Any], elapsed_s: float, lat_ms: float | None) -> str:
    node = st.get("node") or {}
    counts = st.get("counts") or {}
    n = int(counts.get("samples", 0))
    qs = counts.get("quasi_static", 0) / n if n else 0.0
    d = st.get("described") or {}
    off = d.get("offset", {})
    sc = d.get("scale", {})
    offs = "/".join(f"{off.get(f'{a}_mg', float('nan')):+.1f}" for a in "xyz")
    gains = "/".join(f"{sc.get(f'gain_{a}_pct', float('nan')):+.2f}" for a in "xyz")
    res = st.get("residual_rms_mg")
    lat = f" lat {lat_ms:.0f} ms" if lat_ms is not None else ""
    return (f"{elapsed_s:5.1f}s  samples {n:7d}  still {100 * qs:4.1f}%  "
            f"offsets {offs} mg  gains {gains} %  resid "
            f"{'-' if res is None else f'{res:.2f}'} mg  updates {node.get('accepted_updates', 0)}"
            f"{lat}")


def _errors(state: dict[str, Any], sim: SimResult, cal: Any) -> dict[str, Any]:
    """Estimated vs true offsets (mg) and gains (%), and calibrated vs true acceleration."""
    spec = sim.truth.sensor
    d = state["described"]
    est_off = np.array([d["offset"][f"{a}_mg"] for a in "xyz"])
    est_gain = np.array([d["scale"][f"gain_{a}_pct"] for a in "xyz"])
    true_off = 1e3 * np.asarray(spec.offset_g)
    true_gain = 1e2 * np.asarray(spec.gain)
    out: dict[str, Any] = {
        "offset_true_mg": true_off.tolist(), "offset_est_mg": est_off.tolist(),
        "offset_err_mg": (est_off - true_off).tolist(),
        "gain_true_pct": true_gain.tolist(), "gain_est_pct": est_gain.tolist(),
        "gain_err_pct": (est_gain - true_gain).tolist()}
    if len(cal):
        idx = np.searchsorted(sim.raw.t_us, cal.t_us)
        ok = (idx < len(sim.raw)) & (sim.raw.t_us[np.minimum(idx, len(sim.raw) - 1)] == cal.t_us)
        err = np.linalg.norm(cal.a_g[ok] - sim.truth.a_true_g[idx[ok]], axis=1)
        last = slice(len(err) // 2, None)  # the second half: after the calibration settled
        out["accel_err_rms_mg_all"] = float(1e3 * np.sqrt(np.mean(err ** 2)))
        out["accel_err_rms_mg_second_half"] = float(1e3 * np.sqrt(np.mean(err[last] ** 2)))
        raw_err = np.linalg.norm(sim.raw.v[idx[ok]] / COUNTS_PER_G
                                 - sim.truth.a_true_g[idx[ok]], axis=1)
        out["uncalibrated_err_rms_mg"] = float(1e3 * np.sqrt(np.mean(raw_err ** 2)))
        out["noise_floor_rms_mg"] = float(1e3 * np.sqrt(3.0) * spec.noise_g)  # |white noise|
    return out


class _Latency:
    """Time from a sample's scheduled write on the pty to its calibrated batch on the bus."""

    def __init__(self, t0_us: int, speedup: float) -> None:
        self.t0_us, self.speedup = t0_us, speedup
        self.start_s: float | None = None
        self.ms: deque[float] = deque(maxlen=5000)  # bounded: the last few thousand batches

    def on_calibrated(self, msg: Any) -> None:
        from recal.io.messages import batch_extent

        if self.start_s is None:
            return
        _, _, last = batch_extent(msg.payload)
        if last is not None:
            due = self.start_s + (last - self.t0_us) / 1e6 / self.speedup
            self.ms.append(1e3 * (time.monotonic() - due))

    def p(self, q: float) -> float | None:
        return float(np.percentile(np.asarray(self.ms), q)) if self.ms else None


def run_demo(seconds: float = 45.0, out_dir: str | Path | None = None, *,
             minutes: float = 6.0, speedup: float | None = None, rate_hz: float = 100.0,
             seed: int = 7, out: Callable[[str], None] | None = None,
             live: bool | None = None) -> int:
    """Simulate, stream on a pty, run the gateway on loopback Zenoh, report; returns 0.

    Args:
        seconds: wall-clock budget of the live part (the demo stops then, or earlier when the
            simulated data has been streamed and calibrated).
        out_dir: the run's own new folder is made in here (``run-<UTC time>``); None: a new
            temporary folder. Either way the run starts from the prior.
        minutes: simulated recording length.
        speedup: how much faster than real time to stream (default: the recording fits into
            about 80 % of ``seconds``).
        rate_hz: simulated sample rate, Hz.
        seed: simulator seed (sensor errors and wearer).
        out: where lines go (default: stdout).
        live: redraw the progress line on stdout with ``\\r`` (default: when stdout is a
            terminal and ``out`` is not given; otherwise a plain line every 5 s).
    """
    emit = out or (lambda s: print(s, flush=True))
    if live is None:
        live = out is None and sys.stdout.isatty()
    out_path = new_run_dir(out_dir)
    ckpt_dir = out_path / "checkpoints"
    sim = _simulate(minutes, rate_hz, seed)
    sim_s = len(sim.raw) / rate_hz
    speed = speedup if speedup is not None else max(1.0, sim_s / max(1.0, 0.8 * seconds))
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    link = out_path / "demo-tty"
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint], "connect": []},
        "mcap": {"flush_interval_s": 0.5},
        "checkpoint": {"dir": str(ckpt_dir), "interval_s": 10.0},
        "sensors": [{"id": SENSOR_ID, "port": str(link), "format": DEFAULT_FORMAT, "aux_names": [],
                     "rate_hz": rate_hz, "prior": {"counts_per_g": COUNTS_PER_G}}],
    }, out_path, "demo")
    emit(f"recal demo: {minutes:g} min of simulated wear at {rate_hz:g} Hz, streamed "
         f"x{speed:.1f} on {link} -> gateway (Zenoh peer {endpoint}); a fresh run in "
         f"{out_path}")
    stop = threading.Event()
    ready: list[Gateway] = []
    lines: list[str] = []
    with PtyDevice(str(link), fmt=DEFAULT_FORMAT) as dev:
        th = threading.Thread(target=run_gateway, args=(cfg,), daemon=True, kwargs={
            "mcap_out": out_path / "demo.mcap", "stop_event": stop, "on_ready": ready.append,
            "out": lines.append})
        t_start = time.monotonic()
        th.start()
        summary = _live(dev, sim, speed, seconds, endpoint, ready, th, emit, live, t_start)
        stop.set()
        th.join(30.0)
    for line in lines:
        if line.startswith(ERROR_PREFIX):
            emit(line)  # an error from the daemon
    if not ready:
        emit("recal demo: the gateway did not start")
        return 1
    path = ready[0].writer.paths[0]
    summary.update(_report(path, sim, summary))
    summary["run_dir"] = str(out_path)
    (out_path / "summary.json").write_text(json.dumps(summary, indent=2))
    _print_summary(summary, emit)
    return 0


def _live(dev: PtyDevice, sim: SimResult, speed: float, seconds: float, endpoint: str,
          ready: list[Gateway], th: threading.Thread, emit: Callable[[str], None], live: bool,
          t_start: float) -> dict[str, Any]:
    """Stream and show progress until the budget or the data runs out; returns live numbers."""
    from recal.io.bus import Bus, key
    from recal.io.bus_config import zenoh_config
    from recal.io.messages import decode_json

    deadline = t_start + seconds
    while not ready and th.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    if not ready:
        return {}
    gw = ready[0]
    while not gw.ports[SENSOR_ID].is_open and time.monotonic() < deadline:
        time.sleep(0.01)
    lat = _Latency(int(sim.raw.t_us[0]), speed)
    bus = Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"], [endpoint]))
    try:
        bus.subscribe(key(SENSOR_ID, "calibrated"), lat.on_calibrated)
        lat.start_s = time.monotonic()
        dev.start_streaming(sim.raw, speedup=speed)
        t_stream = time.monotonic()
        next_print = 0.0
        state: dict[str, Any] = {}
        while time.monotonic() < deadline and th.is_alive():
            time.sleep(0.25)
            replies = bus.get(key(SENSOR_ID, "status"), timeout_s=1.0)
            if replies:
                state = decode_json(replies[0][1])
            line = _progress_line(state, time.monotonic() - t_start, lat.p(50))
            if live:
                sys.stdout.write("\r" + line[:160])
                sys.stdout.flush()
            elif time.monotonic() >= next_print:
                emit(line)
                next_print = time.monotonic() + 5.0
            done = not dev.streaming and state.get("node", {}).get("samples", 0) >= \
                dev.samples_streamed
            if done:
                break
        if live:
            sys.stdout.write("\n")
        wall = time.monotonic() - t_stream
    finally:
        dev.stop()
        bus.close()
    n = dev.samples_streamed
    return {"samples_streamed": n, "stream_wall_s": wall, "speedup": speed,
            "throughput_samples_per_s": n / wall if wall > 0 else None,
            "latency_ms_p50": lat.p(50), "latency_ms_p95": lat.p(95),
            "bytes_dropped_by_device": dev.bytes_dropped}


def _report(path: Path, sim: SimResult, live: dict[str, Any]) -> dict[str, Any]:
    cal = rec.read_all_calibrated(path, SENSOR_ID)
    states = [obj for _, obj, _ in rec.iter_json(path, f"/{SENSOR_ID}/calibration")]
    setups = [obj for _, obj, _ in rec.iter_json(path, f"/{SENSOR_ID}/setup")]
    raw_n = sum(len(b) for _, b, _ in rec.iter_raw(path, SENSOR_ID))
    final = states[-1] if states else None
    out: dict[str, Any] = {"mcap": str(path), "samples_logged": raw_n,
                           "calibration_states": len(states),
                           "started_from": setups[0].get("start") if setups else None}
    if final is not None:
        out["final_state"] = {k: final.get(k) for k in ("described", "residual_rms_mg",
                                                         "update_count", "alignment")}
        out["errors"] = _errors(final, sim, cal)
    return out


def _print_summary(s: dict[str, Any], emit: Callable[[str], None]) -> None:
    emit(f"recording: {s.get('mcap')}  ({s.get('samples_logged', 0)} samples, "
         f"{s.get('calibration_states', 0)} calibration states)")
    final = s.get("final_state") or {}
    start = s.get("started_from")
    emit(f"calibration: started from {start or 'nothing (no setup logged)'}, "
         f"{final.get('update_count', 0)} updates in this run"
         + ("" if start == "prior" else " (not a fresh start: these figures are not this run's "
                                        "alone)"))
    if s.get("throughput_samples_per_s"):
        p50, p95 = s.get("latency_ms_p50"), s.get("latency_ms_p95")
        emit(f"throughput {s['throughput_samples_per_s']:.0f} samples/s (x{s['speedup']:.1f} "
             f"real time); pty -> calibrated on Zenoh latency p50 "
             f"{'-' if p50 is None else f'{p50:.0f}'} ms, p95 "
             f"{'-' if p95 is None else f'{p95:.0f}'} ms")
    e = s.get("errors")
    if e:
        def fmt(v: list[float], spec: str) -> str:
            return "/".join(format(x, spec) for x in v)
        emit(f"offsets  true {fmt(e['offset_true_mg'], '+.1f')} mg  est "
             f"{fmt(e['offset_est_mg'], '+.1f')} mg  err {fmt(e['offset_err_mg'], '+.1f')} mg")
        emit(f"gains    true {fmt(e['gain_true_pct'], '+.2f')} %  est "
             f"{fmt(e['gain_est_pct'], '+.2f')} %  err {fmt(e['gain_err_pct'], '+.2f')} %")
        if "accel_err_rms_mg_all" in e:
            # the settled figure first: the whole-run mean carries the warm-up (bootstrap
            # and first updates) and read like the result
            emit(f"|a - a_true| rms: uncalibrated {e['uncalibrated_err_rms_mg']:.1f} mg, "
                 f"calibrated after warm-up {e['accel_err_rms_mg_second_half']:.1f} mg "
                 f"(second half of the run; sensor noise alone "
                 f"{e['noise_floor_rms_mg']:.1f} mg); whole run incl. warm-up "
                 f"{e['accel_err_rms_mg_all']:.1f} mg")
    else:
        emit("no calibration state was logged")
    emit(f"files: {s.get('run_dir')}")
