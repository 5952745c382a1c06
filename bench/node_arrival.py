"""One sample per call, in the process: CPU and Python calls per arrival of the daemon's work
without its selector, pty and Zenoh.

A node for one 100 Hz sensor (prior as `daemon_scale`'s sensors) is fed ``--minutes`` of
simulated wear with the sensor mounted tilted (as `tests/test_node.py`'s ``worn_tilted``: the
pipeline is tracking, the mounting aligned, so every output the daemon makes per sample is
made) in 500-sample batches; then ``--samples`` further samples one per call, timed:

* ``--part node``: ``CalibrationNode.process`` alone, with a sink that keeps nothing;
* ``--part shell``: what the gateway's I/O thread does per arrival after its selector: parse
  the sample's ASCII line, log it (raw), calibrate it, log every output to an MCAP file and
  publish through the gateway's ``LoggedBusSink`` on a Zenoh session whose only subscriber
  (another process) takes the calibrated topic, as `daemon_scale`'s latency probe does.

Reported: CPU per sample (process time, median of ``--runs``) and Python function calls per
sample (cProfile, one more run). ``--old-src DIR`` runs the same in a child process with
``DIR/service`` first on PYTHONPATH (``git archive <commit> service | tar -x -C DIR``), old and
new alternated in every round::

    python bench/node_arrival.py --part shell --runs 5 --old-src /tmp/recal-old
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

RATE_HZ = 100.0
SUBSCRIBER = """
import sys
from recal.io.bus import Bus, key, zenoh_config
bus = Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"], [f"tcp/127.0.0.1:{sys.argv[1]}"]))
bus.receiver(key("s0", "calibrated"))
sys.stdin.read()
bus.close()
"""
SID = "s0"
WARM_BATCH = 500


def _workload(minutes: float, samples: int) -> tuple[Any, Any]:
    """(warm-up raw batch, the raw samples to time): a wearer, sensor mounted tilted."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from layout import module
    from recal.samples import RawBatch

    sim = module("recal.sim.wearer", "recal.sim")
    seed = 3
    wearer = sim.WearerSpec(upright_tilt_deg=1.0, still_s=(30.0, 90.0))
    rng = np.random.default_rng(seed)
    spec = replace(sim.SensorSpec.random(rng, offset_mg=40.0, gain_pct=2.0), noise_g=0.003)
    res = sim.simulate(minutes / 60 + samples / RATE_HZ / 3600, RATE_HZ, seed, spec, wearer)
    r_mount = Rotation.from_euler("xy", [3.0, -2.0], degrees=True).as_matrix()
    v = sim.forward_model(res.truth.a_true_g @ r_mount.T, spec,
                          rng=np.random.default_rng(seed + 100))
    raw = RawBatch(res.raw.t_us, v, np.empty((len(v), 0)), ())
    warm = len(raw) - samples
    return raw[:warm], raw[warm:]


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _node(sink: Any) -> Any:
    from layout import module

    cfg = module("recal.config.settings", "recal.config")
    AlignmentConfig, PriorConfig, SensorConfig = (cfg.AlignmentConfig, cfg.PriorConfig,
                                                  cfg.SensorConfig)
    # the [pipeline] section's settings, PipelineSettings in a tree before the name said so
    PipelineSection = getattr(cfg, "PipelineSection", None) or cfg.PipelineSettings
    model_and_prior = module("recal.config.model_prior", "recal.config.settings",
                             "recal.config").model_and_prior
    node_mod = module("recal.node.node", "recal.node")
    CalibrationNode, NodeSettings = node_mod.CalibrationNode, node_mod.NodeSettings

    sensor = SensorConfig(SID, rate_hz=RATE_HZ, prior=PriorConfig(counts_per_g=1024.0))
    settings = PipelineSection()
    model, prior = model_and_prior(sensor, settings)
    ali = AlignmentConfig(min_still_s=10.0, tilt_limit_deg=7.0, upright_max_deg=30.0)
    return CalibrationNode(NodeSettings(SID, settings, model, prior, RATE_HZ, None, ali), sink)


def child(part: str, minutes: float, samples: int, profile: bool,
          gap_s: float = 0.0) -> dict[str, Any]:
    """Set up, warm up, then time ``samples`` one-sample arrivals; the result as a dict."""
    from layout import module
    from recal.io.ascii_lines import encode_ascii

    sinks = module("recal.node.sinks", "recal.sinks")
    NullSink = sinks.NullSink

    warm, tail = _workload(minutes, samples)
    tmp = Path(tempfile.mkdtemp(prefix="node-arrival-"))
    writer = None
    if part == "shell":
        from recal.io.bus import Bus, key, zenoh_config
        from recal.io.recording_writer import RecordingWriter

        LoggedBusSink = sinks.LoggedBusSink

        writer = RecordingWriter(tmp / "a.mcap", fsync=False)
        port = _free_port()
        bus = Bus(zenoh_config("peer", [f"tcp/127.0.0.1:{port}"], []))
        raw_pub = bus.publisher(key(SID, "raw"))
        sink: Any = LoggedBusSink(writer, bus)
        # a subscriber to the calibrated topic in a process of its own, as the daemon's
        # latency probe: the calibrated message is encoded and put, raw and body are not
        listener = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(port)],
                                    stdin=subprocess.PIPE)
        if not bus.publisher(key(SID, "calibrated")).wait_for_subscribers(30.0):
            raise RuntimeError("the subscriber did not come")
    else:
        sink = NullSink()
    node = _node(sink)
    t0 = int(warm.t_us[0])
    for i in range(0, len(warm), WARM_BATCH):
        b = warm[i:i + WARM_BATCH]
        node.process(b, (int(b.t_us[0]) - t0) * 1000)
    assert node.pipeline is not None and node.alignment is not None, "not aligned: longer warm-up"
    if part == "shell":
        # the gateway's own per-port handling (log raw, publish raw, calibrate), on a
        # Gateway whose port is never opened: its parser is fed the lines directly
        cfg = module("recal.config.settings", "recal.config")
        CheckpointConfig, PriorConfig = cfg.CheckpointConfig, cfg.PriorConfig
        SensorConfig, ServiceConfig = cfg.SensorConfig, cfg.ServiceConfig
        Gateway = module("recal.daemon.gateway", "recal.gateway").Gateway

        sensor = SensorConfig(SID, port=str(tmp / "tty"), aux_names=(), rate_hz=RATE_HZ,
                              prior=PriorConfig(counts_per_g=1024.0))
        cfg = ServiceConfig(sensors=(sensor,), checkpoint=CheckpointConfig(dir=None))
        gw = Gateway(cfg, writer, bus, {SID: node}, out=lambda _line: None)
        port_ = gw.ports[SID]
        port_.raw_publisher = raw_pub
        parser = port_.source.parser
        data = encode_ascii(tail)
        lines = [ln + b"\n" for ln in data.split(b"\n")[:-1]]
        handle = gw._handle

        def run() -> None:
            for k, line in enumerate(lines):
                if gap_s:
                    time.sleep(gap_s)
                handle(port_, parser.feed(line), k * 10_000_000)
    else:
        ones = [tail[k:k + 1] for k in range(len(tail))]

        def run() -> None:
            for k, b in enumerate(ones):
                if gap_s:
                    time.sleep(gap_s)
                node.process(b, k * 10_000_000)

    c0, th0 = time.process_time(), time.thread_time()
    if profile:
        prof = cProfile.Profile()
        prof.runcall(run)
    else:
        run()
    cpu, thread = time.process_time() - c0, time.thread_time() - th0
    out: dict[str, Any] = {"src": str(Path(sys.modules["recal"].__file__).parent), "part": part,
                           "samples": samples, "us_per_sample": cpu / samples * 1e6,
                           "thread_us_per_sample": thread / samples * 1e6}
    if profile:
        st = pstats.Stats(prof)
        out["calls_per_sample"] = st.total_calls / samples  # type: ignore[attr-defined]
        st.sort_stats("tottime").print_stats(30)
        st.sort_stats("cumulative").print_stats(40)
    if writer is not None:
        writer.close()
        bus.close()
        assert listener.stdin is not None
        listener.stdin.close()
        listener.wait(30)
    return out


def _run_child(a: argparse.Namespace, src: str | None, profile: bool) -> dict[str, Any]:
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = str(Path(src) / "service") + (
            os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    argv = [sys.executable, __file__, "--child", "--part", a.part, "--minutes", str(a.minutes),
            "--samples", str(a.samples), "--gap-ms", str(a.gap_ms)] + (
                ["--profile"] if profile else [])
    res = subprocess.run(argv, env=env, capture_output=True, text=True, check=True)
    if profile and a.show_profile:
        print(res.stdout, file=sys.stderr)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("node", "shell"), default="node")
    ap.add_argument("--minutes", type=float, default=23.0, help="simulated wear before timing")
    ap.add_argument("--samples", type=int, default=6000, help="one-sample arrivals timed")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--gap-ms", type=float, default=0.0,
                    help="sleep before each arrival (10: a 100 Hz sensor's idle between them, "
                         "so that each arrival finds cold caches, as the daemon's do)")
    ap.add_argument("--old-src", help="also run from this source tree, alternated")
    ap.add_argument("--show-profile", action="store_true", help="print the profiles too")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--profile", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.part, a.minutes, a.samples, a.profile, a.gap_ms / 1e3)))
        return 0
    variants = [("new", None)] + ([("old", a.old_src)] if a.old_src else [])
    rows: dict[str, list[float]] = {name: [] for name, _ in variants}
    threads: dict[str, list[float]] = {name: [] for name, _ in variants}
    calls: dict[str, float] = {}
    for r in range(a.runs):
        for name, src in (variants if r % 2 == 0 else variants[::-1]):
            got = _run_child(a, src, False)
            rows[name].append(got["us_per_sample"])
            threads[name].append(got["thread_us_per_sample"])
            print(name, f"{rows[name][-1]:.1f} us, thread {threads[name][-1]:.1f} us",
                  file=sys.stderr, flush=True)
    for name, src in variants:
        calls[name] = _run_child(a, src, True)["calls_per_sample"]
    print(f"# node_arrival --part {a.part}: {a.samples} one-sample arrivals after "
          f"{a.minutes:g} min of wear, {a.gap_ms:g} ms before each, {a.runs} runs, "
          f"load {os.getloadavg()[0]:.2f}")
    print("| code | process CPU us/sample (median) | rounds | thread CPU us/sample (median) "
          "| Python calls/sample |")
    print("|---|---|---|---|---|")
    for name, _ in variants:
        print(f"| {name} | {statistics.median(rows[name]):.0f} | "
              f"{', '.join(f'{x:.0f}' for x in rows[name])} | "
              f"{statistics.median(threads[name]):.0f} | {calls[name]:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
