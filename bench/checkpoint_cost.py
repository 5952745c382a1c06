"""What a checkpoint costs: building it, the checks before a save, the write, and a checked load.

One sensor (a simulated 2 h wearer at 50 Hz, offsets +-50 mg, gains +-3 %) through a node, then
each step timed on its checkpoint, medians of ``--runs``. The gateway saves each sensor every
``[checkpoint] interval_s`` and within ``after_update_s`` of an accepted update, so the total
per save times the number of sensors is what checkpointing costs per interval.

    python bench/checkpoint_cost.py [--runs 30]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from recal.config.settings import PriorConfig, SensorConfig, ServiceConfig
from recal.daemon.checkpoint_store import Checkpoints, load_checkpoint, save_checkpoint
from recal.node.checkpoint_doc import restore_pipeline
from recal.node.node import CalibrationNode, node_settings
from recal.node.sinks import NullSink
from recal.sim.wearer import SensorSpec, simulate


def median_ms(f: Callable[[], object], runs: int) -> float:
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=30)
    a = ap.parse_args()
    res = simulate(2.0, 50.0, 3, SensorSpec.random(np.random.default_rng(3), offset_mg=50,
                                                   gain_pct=3))
    sensor = SensorConfig(id="s1", rate_hz=50.0, prior=PriorConfig(counts_per_g=1024.0))
    node = CalibrationNode(node_settings(sensor, ServiceConfig()), NullSink())
    for i in range(0, len(res.raw), 1000):
        node.process(res.raw[i:i + 1000], 0)
    doc = node.checkpoint()
    assert doc is not None
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        keeper = Checkpoints(d, 60.0, out=print)
        rows = [
            ("node.checkpoint() (the state as a dict)", median_ms(node.checkpoint, a.runs)),
            ("checks before a save (restore_pipeline, no probe)",
             median_ms(lambda: restore_pipeline(doc["pipeline"], probe=False), a.runs)),
            ("write (strict JSON, fsync, previous kept, rename)",
             median_ms(lambda: save_checkpoint(d / "x.json", doc), a.runs)),
            ("a save in all (Checkpoints.save)",
             median_ms(lambda: keeper.save({"s1": node}), a.runs)),
            ("a checked load (file checks, restore, probe step)",
             median_ms(lambda: restore_pipeline(load_checkpoint(d / "s1.json")["pipeline"]),
                       a.runs)),
        ]
    print(f"checkpoint of one sensor: {len(json.dumps(doc)) / 1e3:.0f} kB, "
          f"{doc['pipeline']['counts']['windows']} windows seen; medians of {a.runs} runs")
    for what, ms in rows:
        print(f"  {what:<55} {ms:7.2f} ms")


if __name__ == "__main__":
    main()
