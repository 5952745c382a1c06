"""Scale out: gateways -> recal router -> one calibration node -> MCAP, on loopback.

For each number of gateways G in ``--gateways`` (default 1,2,3) this starts:

* one ``recal router`` (``python -m recal.io.router``) on 127.0.0.1;
* G gateway processes (``recal run``, ``run_nodes = false``: they read their
  ports, log raw to their own MCAP and publish ``recal/<sensor>/raw``), each a Zenoh client
  of the router, each serving ``--sensors-per-gateway`` 100 Hz sensors;
* one calibration node (``recal node --mcap node.mcap``), a client of the router,
  subscribed to ``recal/*/raw``: it logs raw and calibrated and publishes calibrated;
* one writer process for every simulated sensor (``bench/pty_fleet.py``, data made up front);
* this script: a client of the router subscribed to the calibrated stream of a few sensors
  (end-to-end latency: sensor write -> gateway -> router -> node -> router -> here).

It reports the samples offered and delivered per second, whether every sample written
reached both the gateway's MCAP and the node's (raw and calibrated: exactly once, in order),
the latency, and each process's CPU share, so the table shows how throughput grows with the
number of gateways and which process saturates first.

Full run (about 6 min per row)::

    python bench/scale_out.py --gateways 1,2,3 --sensors-per-gateway 50 --seconds 300

Quick check (20 s per row)::

    python bench/scale_out.py --quick

Everything shares this machine's 2 cores (writer, router, gateways, node, probe), so the
numbers are lower bounds of what separate machines would do.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from child_process import ChildProcess
from daemon_scale import (
    RATE_HZ,
    READY_PREFIX,
    LatencyProbe,
    gateway_toml,
    latencies_ms,
    pct,
    report,
    sensor_id,
    sleep_until,
    until,
    verify,
)
from pty_fleet import FleetProcess
from recal.commands.demo import free_port
from recal.daemon.remote_node import NODE_READY_PREFIX
from recal.io.bus_config import zenoh_config
from recal.io.router import READY_PREFIX as ROUTER_READY_PREFIX

__all__ = ["main", "run_row"]



def node_toml(n_sensors: int, router: str, workdir: Path) -> str:
    """The calibration node's config: a client of the router, priors for every sensor."""
    lines = ["[zenoh]", 'mode = "client"', "listen = []", f'connect = ["{router}"]',
             "[checkpoint]", f'dir = "{workdir / "node-ck"}"', "interval_s = 60"]
    for i in range(n_sensors):
        lines += ["[[sensors]]", f'id = "{sensor_id(i)}"', "aux_names = []",
                  f"rate_hz = {RATE_HZ}", "prior = { counts_per_g = 1024.0, zero_g = 0 }"]
    return "\n".join(lines) + "\n"


class _Deployment:
    """Router, G gateways and the node, started in order and stopped in reverse."""

    def __init__(self, work: Path, links: Sequence[str], gateways: int, batch_ms: float) -> None:
        self.router_ep = f"tcp/127.0.0.1:{free_port()}"
        self.router = ChildProcess.python("recal.io.router", ["--listen", self.router_ep],
                                          work / "router.log")
        self.router.wait_line(ROUTER_READY_PREFIX, 30)
        per = -(-len(links) // gateways)
        self.gateways: list[ChildProcess] = []
        self.mcaps: list[Path] = []
        self.slices: list[range] = []
        for g in range(gateways):
            part = range(g * per, min(len(links), (g + 1) * per))
            cfg = work / f"gw{g}.toml"
            cfg.write_text(gateway_toml([links[i] for i in part], 0, work, run_nodes=False,
                                        mode="client", connect=[self.router_ep],
                                        first=part.start))
            self.mcaps.append(work / f"gw{g}.mcap")
            self.slices.append(part)
            self.gateways.append(ChildProcess.python(
                "recal", ["run", "--config", str(cfg), "--mcap", str(self.mcaps[-1]),
                                  "--batch-ms", str(batch_ms)], work / f"gw{g}.log"))
        ncfg = work / "node.toml"
        ncfg.write_text(node_toml(len(links), self.router_ep, work))
        self.node_mcap = work / "node.mcap"
        self.node = ChildProcess.python("recal", ["node", "--config", str(ncfg), "--mcap",
                                                       str(self.node_mcap)], work / "node.log")
        for gw in self.gateways:
            gw.wait_line(READY_PREFIX, 120)
        self.node.wait_line(NODE_READY_PREFIX, 60)

    def processes(self) -> dict[str, ChildProcess]:
        return {"router": self.router, "node": self.node,
                **{f"gw{g}": gw for g, gw in enumerate(self.gateways)}}

    def cpu(self) -> dict[str, float]:
        return {name: p.cpu_seconds() for name, p in self.processes().items()}

    def stop(self) -> list[int | None]:
        codes = [gw.terminate(60) for gw in self.gateways]
        codes.append(self.node.terminate(300))  # it first calibrates what it has queued
        self.router.terminate(30)
        return codes

    def kill(self) -> None:
        for p in self.processes().values():
            p.kill()


def run_row(gateways: int, a: argparse.Namespace, root: Path) -> dict[str, Any]:
    """G gateways with ``a.sensors_per_gateway`` sensors each for ``a.seconds``; the row."""
    n = gateways * a.sensors_per_gateway
    work = Path(tempfile.mkdtemp(prefix=f"g{gateways}-", dir=root))
    fleet = FleetProcess(work, n, a.seconds, rate_hz=RATE_HZ, chunk=a.chunk)
    dep: _Deployment | None = None
    probe: LatencyProbe | None = None
    try:
        dep = _Deployment(work, fleet.links, gateways, a.batch_ms)
        probe = LatencyProbe(zenoh_config("client", [], [dep.router_ep]), range(min(n, a.probe)))
        if until(lambda: probe.counts(n)[0] >= n, 60) == float("inf"):
            raise RuntimeError("gateways did not open every port")
        started = fleet.go()
        warm_ns = started["start_ns"] + int(a.warmup_s * 1e9)
        sleep_until(warm_ns)
        cpu0, wall0 = dep.cpu(), time.monotonic()
        sleep_until(started["start_ns"] + int(a.seconds * 1e9))
        cpu1, wall1 = dep.cpu(), time.monotonic()
        written = fleet.done(60 + a.seconds)
        total = sum(written["sent"])
        t_done = time.monotonic()
        catchup = until(lambda: probe.counts(n)[2] >= total, a.max_catchup_s + 60)
        delivered_s = time.monotonic() - t_done + a.seconds
        lat = latencies_ms(probe.records, written, a.chunk, warm_ns)
        probe.close()
        probe = None
        codes = dep.stop()
        fleet.close()
        gw_check = [verify(m, [written["sent"][i] for i in part], calibrated=False,
                            first=part.start)
                    for m, part in zip(dep.mcaps, dep.slices, strict=True)]
        node_check = verify(dep.node_mcap, written["sent"])
        share = {k: 100 * (cpu1[k] - cpu0[k]) / (wall1 - wall0) for k in cpu0}
        row = {"gateways": gateways, "sensors": n, "offered_per_s": n * RATE_HZ,
               "delivered_per_s": total / delivered_s if np.isfinite(catchup) else 0.0,
               "seconds": a.seconds, "sent": total,
               "gw_lost": sum(c["lost"] + c["wrong"] for c in gw_check),
               "node_lost": node_check["lost"] + node_check["wrong"],
               "node_not_calibrated": node_check["cal_missing"], "catchup_s": catchup,
               "lat_p50_ms": pct(lat, 50), "lat_p99_ms": pct(lat, 99),
               "node_cpu_pct": share["node"], "router_cpu_pct": share["router"],
               "gw_cpu_pct": max(v for k, v in share.items() if k.startswith("gw")),
               "writer_cpu_pct": 100 * written["cpu_s"] / a.seconds,
               "exit_codes": codes, "load1": os.getloadavg()[0]}
        row["complete"] = (row["gw_lost"] == 0 and row["node_lost"] == 0
                           and row["node_not_calibrated"] == 0
                           and all(c == 0 for c in codes))
        return row
    finally:
        if probe is not None:
            probe.close()
        if dep is not None:
            dep.kill()
        fleet.close()
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)


COLUMNS = [("gateways", "gateways", "{:d}"), ("sensors", "sensors", "{:d}"),
           ("offered_per_s", "offered samples/s", "{:.0f}"),
           ("delivered_per_s", "calibrated samples/s", "{:.0f}"),
           ("sent", "samples sent", "{:d}"), ("gw_lost", "lost at gateways", "{:d}"),
           ("node_lost", "lost at node", "{:d}"),
           ("node_not_calibrated", "not calibrated", "{:d}"),
           ("catchup_s", "catch-up s", "{:.1f}"),
           ("lat_p50_ms", "latency p50 ms", "{:.1f}"), ("lat_p99_ms", "p99 ms", "{:.1f}"),
           ("gw_cpu_pct", "busiest gateway CPU %", "{:.1f}"),
           ("router_cpu_pct", "router CPU %", "{:.1f}"), ("node_cpu_pct", "node CPU %", "{:.1f}"),
           ("writer_cpu_pct", "writer CPU %", "{:.1f}"), ("load1", "load avg", "{:.1f}"),
           ("complete", "nothing lost", "{}")]



def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gateways", default="1,2,3", help="comma-separated gateway counts")
    ap.add_argument("--sensors-per-gateway", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--warmup-s", type=float, default=None)
    ap.add_argument("--chunk", type=int, default=1, help="samples per device write")
    ap.add_argument("--batch-ms", type=float, default=0.0, help="the gateways' --batch-ms")
    ap.add_argument("--probe", type=int, default=10, help="sensors whose latency is measured")
    ap.add_argument("--max-catchup-s", type=float, default=30.0)
    ap.add_argument("--quick", action="store_true", help="20 s per row, 10 sensors per gateway")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--json", help="also write the rows here")
    a = ap.parse_args(argv)
    if a.quick:
        a.seconds = min(a.seconds, 20.0)
        if a.sensors_per_gateway == ap.get_default("sensors_per_gateway"):
            a.sensors_per_gateway = 10
    if a.warmup_s is None:
        a.warmup_s = min(30.0, max(2.0, 0.1 * a.seconds))
    return a


def main(argv: Sequence[str] | None = None) -> int:
    a = _parse(argv)
    root = Path(tempfile.mkdtemp(prefix="scale-out-"))
    rows = []
    try:
        for g in (int(x) for x in a.gateways.split(",")):
            row = run_row(g, a, root)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    finally:
        if not a.keep:
            shutil.rmtree(root, ignore_errors=True)
    report(rows, f"# scale_out: {a.seconds:.0f} s per row, {a.sensors_per_gateway} sensors of "
           f"{RATE_HZ:.0f} Hz per gateway, gateways and node as Zenoh clients of one router; "
           f"{os.cpu_count()} cores shared by every process", a.json, COLUMNS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
