"""Calibration accuracy with the device clocks simple firmware has, against a clean clock.

Simulated wearers (recal simulate's default random sensor: offsets +-50 mg, gains +-3 %,
4 mg noise, 1024 counts/g), 40 min each, through the calibration node
(`recal.node.node.CalibrationNode`, the live and replay code path, 500-sample batches); error =
RMS over 1 s windows of |calibrated - true| after 30 min (`recal.sim.wearer.error_1s_mg`):

* a 32-bit micros() that wraps 10 minutes in (25 Hz, rate configured);
* millis() under a t_us header, no rate configured (the node must find the unit);
* x,y,z lines without a time column, through the ASCII parser with the rate (50 Hz);
each beside the same samples with a clean microsecond clock. The time base also has a cost
per call: a 1-sample step, as a sensor handled as it sends pays it per arrival.

    python bench/device_clocks.py [--seeds 1,2,3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from recal.config import PipelineSection, PriorConfig, SensorConfig, model_and_prior
from recal.core import timebase as tb
from recal.io.ascii_lines import AsciiLineParser, encode_ascii
from recal.node.node import CalibrationNode, NodeSettings
from recal.node.sinks import NullSink
from recal.samples import CalibratedBatch, RawBatch
from recal.sim.wearer import SensorSpec, SimResult, error_1s_mg, simulate

WRAP = 2**32


class _Keep(NullSink):
    def __init__(self) -> None:
        self.a: list[np.ndarray] = []

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        if suffix == "calibrated":
            self.a.append(batch.a_g)


def _error_mg(raw: RawBatch, res: SimResult, rate_hz: float, nominal: float | None) -> float:
    sensor = SensorConfig("s", rate_hz=nominal, prior=PriorConfig(counts_per_g=1024.0))
    model, prior = model_and_prior(sensor, PipelineSection())
    sink = _Keep()
    node = CalibrationNode(NodeSettings("s", PipelineSection(), model, prior, nominal), sink)
    for i in range(0, len(raw), 500):
        node.process(raw[i:i + 500], i)
    node.flush(len(raw))
    a = np.concatenate(sink.a)
    keep = np.arange(len(a)) >= 30 * 60 * rate_hz
    return error_1s_mg(a[keep], res.truth.a_true_g[keep], rate_hz)


def _wearer(seed: int, rate_hz: float, start_us: int = 0) -> SimResult:
    return simulate(40 / 60, rate_hz, seed, SensorSpec.random(np.random.default_rng(seed)),
                    start_us=start_us)


def _step_cost_us() -> float:
    cfg = tb.TimebaseConfig(rate_hz=100.0)
    state, _ = tb.start(np.arange(50, dtype=np.int64) * 10_000, cfg)
    batches = [np.array([i * 10_000], np.int64) for i in range(50, 20_050)]
    started = time.perf_counter()
    for b in batches:
        state, _, _ = tb.step(state, b, cfg)
    return (time.perf_counter() - started) / len(batches) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1,2,3")
    seeds = [int(s) for s in ap.parse_args().seeds.split(",")]
    print("seed | 25 Hz micros() wrapping / clean | millis() under t_us / clean | "
          "50 Hz x,y,z lines / t_us lines   (mg, 1 s, after 30 min)")
    for seed in seeds:
        start = WRAP - 600 * 10**6
        res = _wearer(seed, 25.0, start)
        wrapped = RawBatch(res.raw.t_us % WRAP, res.raw.v, res.raw.aux, res.raw.aux_names)
        ms = RawBatch((res.raw.t_us - start) // 1000, res.raw.v, res.raw.aux,
                      res.raw.aux_names)
        r50 = _wearer(seed, 50.0)
        parser = AsciiLineParser((), rate_hz=50.0)
        parser.anchor_time(1_700_000_000_000_000)
        xyz = parser.feed(encode_ascii(r50.raw, time_column=False))
        print(f"{seed:4d} | {_error_mg(wrapped, res, 25.0, 25.0):.3f} / "
              f"{_error_mg(res.raw, res, 25.0, 25.0):.3f} | "
              f"{_error_mg(ms, res, 25.0, None):.3f} / {_error_mg(res.raw, res, 25.0, None):.3f}"
              f" | {_error_mg(xyz, r50, 50.0, 50.0):.3f} / "
              f"{_error_mg(r50.raw, r50, 50.0, 50.0):.3f}")
    print(f"time base, one 1-sample step: {_step_cost_us():.1f} us")


if __name__ == "__main__":
    main()
