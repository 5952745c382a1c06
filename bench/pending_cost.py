"""What a waiting candidate model (`core.pending`) costs the one-sample path: CPU per
one-sample `Pipeline.step` on a tracking pipeline, without and with a candidate set.

    python bench/pending_cost.py --samples 5000 --runs 3

A diagonal model on a simulated wearer whose offsets follow temperature streams ``--minutes``
in 500-sample batches; then ``--samples`` further samples one per call on two copies of the
pipeline (from its checkpoint), one with the candidate (the model plus offset[temp_c], as
discovery adds it), alternated per round; process CPU per sample, median of ``--runs``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace

import numpy as np

from recal.core.effects import Offset
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pending import PendingCandidate
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.samples import RawBatch
from recal.sim import wearer as sim

RATE_HZ = 25.0


def _timed(pipe: Pipeline, raw: RawBatch) -> float:
    t0 = time.process_time()
    for i in range(len(raw)):
        pipe.step(raw[i:i + 1])
    return 1e6 * (time.process_time() - t0) / len(raw)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=20.0)
    ap.add_argument("--samples", type=int, default=5000)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    spec = replace(sim.SensorSpec.random(np.random.default_rng(2), 50, 3),
                   offset_tc_g_per_c=(1.5e-3, -1.5e-3, 1.5e-3))
    n_warm = round(args.minutes * 60 * RATE_HZ)
    res = sim.simulate((n_warm + args.samples) / RATE_HZ / 3600, RATE_HZ, 2, spec,
                       sim.WearerSpec(temp_excursion_every_h=0.5))
    model = SensorModel.diagonal(float(spec.counts_per_g or 1024.0))
    p0 = model.nominal()
    p0[model.slice(("offset", None))] = spec.zero_g_counts
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model, p0),
                    res.raw.aux_names)
    for i in range(0, n_warm, 500):
        pipe.step(res.raw[i:min(i + 500, n_warm)])
    cand_model, q = pipe.model.extend(pipe.params, Offset("temp_c", 30.0), 5.0)
    q[cand_model.slice(Offset("temp_c", 30.0))] = 1.5
    cand = PendingCandidate(cand_model, q, np.diag(cand_model.prior_sd() ** 2), "offset[temp_c]")
    state = json.dumps(pipe.state_dict())
    rest = res.raw[n_warm:n_warm + args.samples]
    got: dict[str, list[float]] = {"without": [], "with": []}
    for _ in range(args.runs):
        for name in ("without", "with"):
            p = Pipeline.from_state_dict(json.loads(state))
            if name == "with":
                p.set_pending(cand)
            got[name].append(_timed(p, rest))
    print("| pending candidate | CPU us per one-sample step (median) | rounds |")
    print("|---|---|---|")
    for name, xs in got.items():
        print(f"| {name} | {statistics.median(xs):.0f} | {', '.join(f'{x:.0f}' for x in xs)} |")


if __name__ == "__main__":
    main()
