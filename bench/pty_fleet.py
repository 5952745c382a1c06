"""Simulated sensors on pseudo-terminals, written at their real rate by a process of their own.

The daemon benchmarks (``daemon_scale.py``, ``scale_out.py``) start this as a child process so
that producing the sensors' bytes never competes with the daemon for its GIL. Everything the
devices will send is simulated (``recal.sim.wearer``) and encoded up front; while streaming,
the only work left is one non-blocking ``os.write`` per device and chunk.

Timing: sensor ``i`` sends sample ``k`` at ``start + k / rate + phase_i``, with the phases
spread evenly over one sample period (real sensors are not synchronised; sending all of them
at the same instant would make bursts no deployment sees). A chunk of ``--chunk`` samples goes
out when its last sample is due. Every sample's device time stamp is ``t_us = k * 1e6 / rate``;
the moment each sample was actually written is saved (see :func:`stream_all`), so a consumer
measures latency from the write, not from a schedule the writer may have missed.

Writes never block and nothing is dropped: what a full pty does not take is kept and sent
first at the next chunk (hardware flow control, as it were); the largest such backlog is
reported, so a daemon that falls behind shows up here and in its latency.

Protocol on stdin/stdout (one line each, JSON after the first word)::

    -> ready {"links": [...]}                     ptys made, daemon may open them
    <- go
    -> started {"start_ns": ..., "phase_ns": [...], "rate_hz": ...}
    -> done {"sent": [...], "late_ms": {...}, "max_backlog_bytes": ..., "cpu_s": ...}
    <- close                                       (or EOF) ptys are closed, exit 0

Run alone: ``python bench/pty_fleet.py --dir /tmp/fleet --sensors 4 --seconds 10``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recal.io.ascii_lines import encode_ascii
from recal.io.cobs_frames import encode_cobs
from recal.sim.pty_device import PtyDevice
from recal.sim.wearer import SensorSpec, WearerSpec, simulate

__all__ = ["FleetProcess", "Stream", "encode_stream", "main", "phase_ns", "simulate_streams"]

_PHASES = 10  # distinct send instants per sample period
_DRAIN_S = 10.0  # longest wait for a backlog to go out after the last chunk


@dataclass(frozen=True)
class Stream:
    """One device's encoded bytes and where each sample ends in them."""

    data: bytes
    ends: np.ndarray  # ends[k]: offset just past sample k's bytes

    def chunk(self, k0: int, k1: int) -> memoryview:
        start = 0 if k0 == 0 else int(self.ends[k0 - 1])
        return memoryview(self.data)[start:int(self.ends[k1 - 1])]


def simulate_streams(count: int, samples: int, rate_hz: float, seed: int) -> list:
    """``count`` different simulated wearers and sensors (raw batches of ``samples``)."""
    out = []
    for j in range(count):
        spec = SensorSpec.random(np.random.default_rng(seed + j), offset_mg=40.0, gain_pct=3.0)
        wearer = WearerSpec(still_s=(8.0, 20.0), move_s=(2.0, 5.0))
        out.append(simulate(samples / rate_hz / 3600.0, rate_hz, seed + j, spec, wearer).raw)
    return out


def encode_stream(raw: object, fmt: str) -> Stream:
    """The bytes a device sends for ``raw`` (ASCII lines or COBS frames) and sample ends."""
    if fmt == "ascii":
        data = encode_ascii(raw, header=False)  # type: ignore[arg-type]
        delimiter = 10
    else:
        data = encode_cobs(raw)  # type: ignore[arg-type]
        delimiter = 0
    ends = np.flatnonzero(np.frombuffer(data, np.uint8) == delimiter) + 1
    if len(ends) != len(raw):  # type: ignore[arg-type]
        raise ValueError("one delimiter per sample expected")
    return Stream(data, ends)


def phase_ns(sensor_index: int, rate_hz: float) -> int:
    """When in each sample period sensor ``sensor_index`` sends (ns after the period starts)."""
    return round((sensor_index % _PHASES) * 1e9 / rate_hz / _PHASES)


class _Writer:
    """Writes every device's chunks on schedule from one thread, keeping unsent backlogs."""

    def __init__(self, devices: Sequence[PtyDevice]) -> None:
        self.devices = devices
        self.backlog: list[bytes] = [b""] * len(devices)
        self.max_backlog = 0
        self.blocked_writes = 0

    def send(self, i: int, data: bytes | memoryview) -> None:
        pending = self.backlog[i]
        if pending:
            data = pending + bytes(data)
        n = self.devices[i].write_nowait(data)
        rest = bytes(data[n:]) if n < len(data) else b""
        if rest:
            self.blocked_writes += 1
            self.max_backlog = max(self.max_backlog, len(rest))
        self.backlog[i] = rest

    def drain(self, deadline_s: float) -> None:
        while any(self.backlog) and time.monotonic() < deadline_s:
            for i, pending in enumerate(self.backlog):
                if pending:
                    self.send(i, b"")
            time.sleep(0.001)

    def unsent_samples(self, i: int, delimiter: bytes) -> int:
        return self.backlog[i].count(delimiter)


def stream_all(devices: Sequence[PtyDevice], streams: Sequence[Stream], samples: int,
               rate_hz: float, chunk: int, start_ns: int, times_path: Path) -> dict:
    """Write ``samples`` samples of every device on schedule; the ``done`` report.

    The moment each group of devices was written is saved to ``times_path`` (int64 ns,
    shape (chunks, groups)): sensor ``i``'s sample ``k`` went out at
    ``[k // chunk, i % 10]`` (give or take the writes to the group's other devices)."""
    writer = _Writer(devices)
    groups = [[i for i in range(len(devices)) if i % _PHASES == g] for g in range(_PHASES)]
    groups = [g for g in groups if g]
    n_chunks = -(-samples // chunk)
    # chunk c goes out when its last sample is due, at the group's phase
    last = np.minimum(np.arange(n_chunks) * chunk + chunk, samples) - 1
    due_ns = (start_ns + np.round(last * (1e9 / rate_hz)).astype(np.int64)[:, None]
              + np.array([phase_ns(m[0], rate_hz) for m in groups], np.int64)[None, :])
    written_ns = np.zeros((n_chunks, len(groups)), np.int64)
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    for c, k0 in enumerate(range(0, samples, chunk)):
        k1 = min(samples, k0 + chunk)
        for g, members in enumerate(groups):
            wait_ns = int(due_ns[c, g]) - time.time_ns()
            if wait_ns > 0:
                time.sleep(wait_ns / 1e9)
            written_ns[c, g] = time.time_ns()
            for i in members:
                writer.send(i, streams[i].chunk(k0, k1))
    writer.drain(time.monotonic() + _DRAIN_S)
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    np.save(times_path, written_ns)
    delimiter = b"\n" if streams[0].data.endswith(b"\n") else b"\x00"
    late = (written_ns - due_ns).ravel() / 1e6
    return {"times": str(times_path),
            "sent": [samples - writer.unsent_samples(i, delimiter) for i in range(len(devices))],
            "late_ms": {"p50": float(np.percentile(late, 50)),
                        "p99": float(np.percentile(late, 99)), "max": float(late.max())},
            "max_backlog_bytes": writer.max_backlog, "blocked_writes": writer.blocked_writes,
            "cpu_s": (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime)}


def _say(word: str, obj: dict) -> None:
    print(f"{word} {json.dumps(obj)}", flush=True)


def _wait_for(word: str) -> bool:
    """Read stdin lines until ``word`` (True) or EOF (False)."""
    for line in sys.stdin:
        if line.strip() == word:
            return True
    return False


class FleetProcess:
    """This module as a child process, driven through the protocol above."""

    def __init__(self, directory: Path, sensors: int, seconds: float, *, rate_hz: float = 100.0,
                 chunk: int = 1, fmt: str = "ascii", prefix: str = "tty", seed: int = 1) -> None:
        from child_process import ChildProcess

        argv = [sys.executable, str(Path(__file__).resolve()), "--dir", str(directory),
                "--sensors", str(sensors), "--seconds", str(seconds), "--rate", str(rate_hz),
                "--chunk", str(chunk), "--format", fmt, "--prefix", prefix, "--seed", str(seed)]
        self.child = ChildProcess(argv, directory / f"{prefix}-writer.log", stdin=True)
        self.links: list[str] = json.loads(self.child.wait_line("ready ", 300)[6:])["links"]
        self.started: dict = {}

    def _tell(self, word: str) -> None:
        stdin = self.child.proc.stdin
        if stdin is not None and self.child.proc.poll() is None:
            stdin.write(word + "\n")
            stdin.flush()

    def go(self) -> dict:
        """Start streaming; {"start_ns", "phase_ns", "rate_hz"}."""
        self._tell("go")
        self.started = json.loads(self.child.wait_line("started ", 30)[8:])
        return self.started

    def done(self, timeout_s: float) -> dict:
        """Wait for the end of streaming; the writer's report."""
        return json.loads(self.child.wait_line("done ", timeout_s)[5:])

    def close(self) -> None:
        self._tell("close")
        if self.child.wait(15.0) is None:
            self.child.kill()


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", required=True, help="where the pty links go (tty000, ...)")
    ap.add_argument("--sensors", type=int, required=True)
    ap.add_argument("--seconds", type=float, required=True)
    ap.add_argument("--rate", type=float, default=100.0, help="samples/s per sensor")
    ap.add_argument("--chunk", type=int, default=1, help="samples per write")
    ap.add_argument("--format", choices=("ascii", "cobs"), default="ascii")
    ap.add_argument("--streams", type=int, default=16,
                    help="distinct simulated recordings, shared round-robin by the sensors")
    ap.add_argument("--prefix", default="tty", help="link name prefix")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    samples = max(1, round(a.seconds * a.rate))
    raws = simulate_streams(min(a.sensors, a.streams), samples, a.rate, a.seed)
    encoded = [encode_stream(r, a.format) for r in raws]
    streams = [encoded[i % len(encoded)] for i in range(a.sensors)]
    os.makedirs(a.dir, exist_ok=True)
    links = [os.path.join(a.dir, f"{a.prefix}{i:03d}") for i in range(a.sensors)]
    devices = [PtyDevice(link, a.format, header=False) for link in links]
    try:
        _say("ready", {"links": links})
        if not _wait_for("go"):
            return 1
        # A first delimiter (an ASCII header line) ends the resync a freshly opened port
        # applies to its first line, so sample 0 counts like every other.
        sync = b"#t_us,x,y,z\n" if a.format == "ascii" else b"\x00"
        for dev in devices:
            dev.write_bytes(sync)
        start_ns = time.time_ns() + 300_000_000
        _say("started", {"start_ns": start_ns, "rate_hz": a.rate,
                         "phase_ns": [phase_ns(i, a.rate) for i in range(a.sensors)]})
        _say("done", stream_all(devices, streams, samples, a.rate, a.chunk, start_ns,
                                Path(a.dir) / f"{a.prefix}-written.npy"))
        _wait_for("close")
    finally:
        for dev in devices:
            dev.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
