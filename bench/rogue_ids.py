"""A stranger on the bus: N made-up sensor ids published through a router (no access control)
into a calibration node configured for one sensor, ``wrist``. Prints how many checkpoint files,
recorded sensors and console lines the node produced.

    python bench/rogue_ids.py --ids 200

Run it against another checkout with ``PYTHONPATH=<checkout>/service`` to compare: a node that
serves every id that publishes checkpoints, logs and calibrates each of them.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from recal.commands.demo import free_port
from recal.config import parse_config
from recal.daemon.remote_node import run_node
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import encode_raw
from recal.io.router import RouterProcess
from recal.samples import RawBatch

RATE_HZ = 50.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ids", type=int, default=200, help="made-up sensor ids (default 200)")
    ap.add_argument("--samples", type=int, default=60, help="samples per id (default 60)")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="rogue-ids-"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = parse_config({
        "zenoh": {"mode": "client", "connect": [endpoint], "listen": []},
        "checkpoint": {"dir": str(work / "ck"), "interval_s": 60.0},
        "sensors": [{"id": "wrist", "rate_hz": RATE_HZ, "aux_names": [],
                     "prior": {"counts_per_g": 1024.0}}]}, work, "rogue-ids")
    t_us = np.arange(a.samples, dtype=np.int64) * round(1e6 / RATE_HZ)
    batch = RawBatch(t_us, np.tile([60.0, 60.0, 1084.0], (a.samples, 1)),
                     np.empty((a.samples, 0)), ())
    lines: list[str] = []
    stop = threading.Event()
    with RouterProcess([endpoint]):
        node = threading.Thread(target=run_node, args=(cfg,), daemon=True, kwargs={
            "mcap_out": work / "node.mcap", "stop_event": stop, "out": lines.append})
        node.start()
        rogue = Bus(zenoh_config("client", [], [endpoint], overrides={"connect/timeout_ms": 5000}))
        try:
            for i in range(a.ids):
                pub = rogue.publisher(key(f"fake{i:04d}", "raw"))
                pub.wait_for_subscribers(5.0)
                pub.put(encode_raw(f"fake{i:04d}", batch))
            time.sleep(3.0)  # let the node take what arrived
        finally:
            rogue.close()
            stop.set()
            node.join(120)
    ck = work / "ck"
    files = len(list(ck.glob("*.json"))) if ck.exists() else 0
    recorded = rec.sensors(work / "node.mcap") if (work / "node.mcap").exists() else []
    print(f"ids published: {a.ids}  checkpoint files: {files}  sensors in the node's log: "
          f"{len(recorded)}  console lines: {len(lines)}")
    for line in lines[:3] + (["..."] if len(lines) > 3 else []):
        print("  " + line[:160])
    print(f"work folder: {work}")


if __name__ == "__main__":
    main()
