"""Checkpoints written by an older tree, continued by this one: the same outputs as the older
tree's own continuation, bit for bit.

For each case (a prior; a bootstrap; an unsigned 12-bit part's bootstrap, whose detector
restarts inside a batch) and each cut (after 1 234, 40 000 and 120 000 samples of 1 h at
50 Hz), the older tree steps to the cut in 997-sample batches, writes its checkpoint (JSON), and
continues from it in 1000-sample batches; this tree reads the same checkpoint and continues.
Compared: calibrated values, statuses and sigma bit for bit, and the final checkpoint's text::

    git archive <commit> | tar -x -C /tmp/recal-old
    python bench/checkpoint_carry.py --old-src /tmp/recal-old

Exit status 0 only if every case is identical.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

CUTS = (1234, 40_000, 120_000)


def _cases() -> Iterator[tuple[str, Any, Callable[[], Any]]]:
    from layout import module
    from recal.core.estimator import Prior
    from recal.core.model import SensorModel
    from recal.core.pipeline import Pipeline
    from recal.core.pipeline_config import PipelineConfig

    wearer = module("recal.sim.wearer", "recal.sim")
    SensorSpec, simulate = wearer.SensorSpec, wearer.simulate
    sensor_type = module("recal.sim.sensor", "recal.simulated_sensor").sensor_type

    raw = simulate(1.0, 50, 11, SensorSpec.random(np.random.default_rng(11), offset_mg=50,
                                                  gain_pct=3)).raw
    model = SensorModel.diagonal(1024.0)
    yield "prior", raw, lambda: Pipeline(PipelineConfig(rate_hz=50), model,
                                         Prior.default(model), raw.aux_names)
    yield "bootstrap", raw, lambda: Pipeline(PipelineConfig(rate_hz=50), SensorModel.diagonal(),
                                             None, raw.aux_names)
    adc = simulate(1.0, 50, 12, sensor_type("adxl335-adc12", np.random.default_rng(12))).raw
    yield "unsigned-bootstrap", adc, lambda: Pipeline(PipelineConfig(rate_hz=50),
                                                      SensorModel.diagonal(), None, adc.aux_names)


def _continue(pipe_of_state: Callable[[dict], Any], doc: dict, raw: Any,
              cut: int) -> tuple[dict[str, np.ndarray], str]:
    pipe = pipe_of_state(doc)
    cal = [pipe.step(raw[i:i + 1000]).calibrated for i in range(cut, len(raw), 1000)]
    out = {"a_g": np.concatenate([c.a_g for c in cal]),
           "status": np.concatenate([c.status for c in cal]),
           "sigma_mg": np.concatenate([c.sigma_mg for c in cal])}
    return out, json.dumps(pipe.state_dict())


def child(mode: str, folder: Path) -> int:
    """``write`` (the older tree): checkpoints and their continuations; ``read`` (this tree):
    the continuations compared."""
    from recal.core.pipeline import Pipeline

    same = True
    for name, raw, make in _cases():
        for cut in CUTS:
            key = folder / f"{name}-{cut}"
            if mode == "write":
                pipe = make()
                for i in range(0, cut, 997):
                    pipe.step(raw[i:min(i + 997, cut)])
                key.with_suffix(".json").write_text(json.dumps(pipe.state_dict()))
            doc = json.loads(key.with_suffix(".json").read_text())
            out, final = _continue(Pipeline.from_state_dict, doc, raw, cut)
            if mode == "write":
                np.savez(key.with_suffix(".npz"), **out)
                key.with_suffix(".final").write_text(final)
                continue
            ref = np.load(key.with_suffix(".npz"))
            ok = (all(np.array_equal(ref[k], out[k], equal_nan=True) for k in out)
                  and key.with_suffix(".final").read_text() == final)
            same &= ok
            print(f"| {name} | {cut} | {'identical' if ok else 'DIFFERENT'} |")
    return 0 if same else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old-src", type=Path, help="the older tree (its service/ is imported)")
    ap.add_argument("--child", choices=("write", "read"), help=argparse.SUPPRESS)
    ap.add_argument("--folder", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        return child(a.child, a.folder)
    if a.old_src is None:
        ap.error("--old-src is required")
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PYTHONPATH": str(a.old_src.resolve() / "service")}
        subprocess.run([sys.executable, __file__, "--child", "write", "--folder", tmp],
                       env=env, check=True)
        new = str(Path(__file__).resolve().parents[1] / "service")
        env = {**os.environ, "PYTHONPATH": new}
        print("| case | checkpoint after samples | continued |\n|---|---|---|", flush=True)
        return subprocess.run([sys.executable, __file__, "--child", "read", "--folder", tmp],
                              env=env).returncode


if __name__ == "__main__":
    sys.exit(main())
