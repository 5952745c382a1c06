"""Does the live loop close? Discovery on by default in a streaming node, on undeclared effects.

    python bench/live_loop.py                 # 2 h at 50 Hz per case (several minutes)
    python bench/live_loop.py --hours 1.5 --rate 25 --only temp
    python bench/live_loop.py --cost          # a run's CPU, a window's, latency beside a run
    python bench/live_loop.py --live --only "supply, analog"   # through a pty into `recal run`

Each case is a simulated wearer (temperature excursions every 0.5 h on average, the supply
sagging: both move within the first hour) whose sensor has effects the diagonal model lacks,
or none. It streams through `CalibrationNode.process_many` in messages of 250 samples joined
JOIN_SAMPLES at a time: what `recal replay` does with its defaults (no model: the datasheet
prior, discovery on), which adopts at the same samples as the live node (`process` per
message, tests/test_live_discovery.py). The floor is the same node given the true model (the
effects' terms as `recal discover` adds them, honesty_cases.with_terms) with discovery off.
After the first hour of device time:

* cal %: samples marked calibrated (goal >= 90);
* err/floor: RMS 1 s vector error over RMS of the floor's (goal <= 1.2; after the best
  rotation onto the truth, a rotation being unobservable from gravity);
* >3 / >10: of the 1 s windows wholly calibrated, the share beyond 3 and 10 sigma_eff
  (honesty_cases.honesty; goal <= 1 % and none);
* med sig / med err: median sigma and median error of those windows, mg (goal: sigma <= 3 x
  error + 0.5);
* adopted: each adoption with its device time in minutes (goal: the undeclared effect within
  the first hour, nothing on the clean sensor, nothing the sensor lacks);
* runs, cpu s: discovery runs and their CPU seconds in all (time.process_time in the run's
  thread is not separable: the node's CPU with discovery minus the floor's is shown too).

``--live``: each case instead goes through a real pseudo-terminal (ASCII lines, `PtyDevice`)
into the real daemon, ``recal run`` with its defaults (discovery in its spawned worker
process, MCAP log, Zenoh on 127.0.0.1), written ``--speed`` times faster than real time (the
node keeps device time from the stream, so discovery's schedule is the recording's; the
daemon waits for a run it is due to take on). The same figures come from the daemon's log,
with where it adopted beside where the in-process stream above adopts (same sample: "same"),
the daemon's CPU per sample, and the peak RSS (VmHWM) of the daemon and of its discovery
worker. ``--old-src DIR`` runs the daemon from another tree (``DIR/service`` first on
PYTHONPATH) for the footprint beside it.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from recal.config import PipelineSection, RediscoveryConfig
from recal.core.effects import make_effect
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.status import Status
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import CalibratedBatch, RawBatch
from recal.sim import wearer as sim
from recal.sim.sensor import sensor_type

sys.path.insert(0, str(Path(__file__).resolve().parent))
from honesty_cases import _align, honesty, with_terms

MESSAGE = 250
JOIN = 8192
WEARER = {"temp_excursion_every_h": 0.5}


@dataclass(frozen=True)
class Case:
    name: str
    sensor: Callable[[np.random.Generator], sim.SensorSpec]
    terms: tuple[tuple[str, str], ...] = ()  # the true model's effects (kind, covariate)
    full: bool = False  # the true model has cross-axis terms
    wearer: tuple[tuple[str, float], ...] = ()


def _digital(rng: np.random.Generator, **over: object) -> sim.SensorSpec:
    return sim.SensorSpec.random(rng, offset_mg=50, gain_pct=3, **over)


def _with(**effects: object) -> Callable[[np.random.Generator], sim.SensorSpec]:
    """A digital sensor with these effects (``cross_axis_deg`` as `SensorSpec.random` takes
    it, the others as its fields)."""
    cross = effects.pop("cross_axis_deg", None)

    def make(rng: np.random.Generator) -> sim.SensorSpec:
        spec = _digital(rng, **({"cross_axis_deg": cross} if cross else {}))
        return replace(spec, **effects)
    return make


def _analog(rng: np.random.Generator, **effects: object) -> sim.SensorSpec:
    return replace(sensor_type("adxl335-adc12", rng, ratiometric_per_v=1 / 3.3, v_ref_v=3.3),
                   **effects)


TC = (0.002, -0.002, 0.002)  # g/°C on the offsets
GTC = (0.001, -0.001, 0.0008)  # /°C on the gains
DRIFT = (0.01, -0.01, 0.008)  # g/h
SAG = (("vdd_start_v", 3.3), ("vdd_end_v", 2.9))

CASES = (
    Case("clean", _digital),
    Case("temperature on offsets", _with(offset_tc_g_per_c=TC), (("offset", "temp_c"),)),
    Case("temperature on gains", _with(gain_tc_per_c=GTC), (("gain", "temp_c"),)),
    Case("supply, analog 12-bit", _analog, (("ratiometric", "vdd_v"),), wearer=SAG),
    Case("cross-axis 1.5 deg", _with(cross_axis_deg=1.5), full=True),
    Case("drift", _with(offset_drift_g_per_h=DRIFT), (("offset", "time"),)),
    Case("temperature + supply", lambda r: _analog(r, offset_tc_g_per_c=TC),
         (("offset", "temp_c"), ("ratiometric", "vdd_v")), wearer=SAG),
    Case("cross-axis + temperature", _with(cross_axis_deg=1.5, offset_tc_g_per_c=TC),
         (("offset", "temp_c"),), full=True),
    Case("drift + temperature gain", _with(offset_drift_g_per_h=DRIFT, gain_tc_per_c=GTC),
         (("offset", "time"), ("gain", "temp_c"))),
)


class _Keep:
    """A sink keeping the calibrated samples and the JSON messages."""

    def __init__(self) -> None:
        self.cal: list[CalibratedBatch] = []
        self.events: list[dict] = []

    def raw(self, *a: object, **k: object) -> None:
        pass

    def calibrated(self, sid: str, cal: CalibratedBatch, log_ns: int,
                   topic: str = "calibrated") -> None:
        if topic == "calibrated":
            self.cal.append(cal)

    def plot(self, *a: object, **k: object) -> None:
        pass

    def json(self, sid: str, suffix: str, obj: dict, log_ns: int) -> None:
        if suffix == "events":
            self.events.append(obj)


def _true_model(case: Case, s0: float, raw: RawBatch) -> SensorModel:
    model = SensorModel.full(s0) if case.full else SensorModel.diagonal(s0)
    chans = tuple(t for t in case.terms if t[1] != "time")
    model = with_terms(model, chans, raw)
    if ("offset", "time") in case.terms:
        model = model.with_effect(make_effect("offset", "time", 0.0), 1.0)
    return model


def simulated(case: Case, a: argparse.Namespace) -> tuple[Any, Any]:
    """The case's sensor and its recording (`sim.simulate`'s result) at the bench's settings."""
    spec = case.sensor(np.random.default_rng(a.seed))
    return spec, sim.simulate(a.hours, a.rate, a.seed, spec, sim.WearerSpec(
        **WEARER, **dict(case.wearer)))


def _run(raw: RawBatch, model: SensorModel, zero: float, discovery: bool, rate: float
         ) -> tuple[CalibratedBatch, list[dict], float]:
    p0 = model.nominal()
    p0[model.slice(("offset", None))] = zero
    cfg = RediscoveryConfig() if discovery else RediscoveryConfig(enabled=False)
    sink = _Keep()
    node = CalibrationNode(NodeSettings("s", PipelineSection(), model,
                                        Prior.default(model, p0), rate, rediscovery=cfg), sink)
    msgs = [(raw[i:i + MESSAGE], 0) for i in range(0, len(raw), MESSAGE)]
    per = JOIN // MESSAGE
    t = time.process_time()
    for k in range(0, len(msgs), per):  # bounded: one pass
        node.process_many(msgs[k:k + per])
    cpu = time.process_time() - t
    return CalibratedBatch.concat(sink.cal), [e for e in sink.events
                                              if e["kind"] == "discovery"], cpu


def _after(cal: CalibratedBatch, truth: np.ndarray, noise_g: float, rate: float,
           start: int) -> dict:
    c, a = cal.a_g[start:], truth[start:]
    h = honesty(c, a, cal.sigma_mg[start:], cal.status[start:], rate, noise_g)
    n = round(rate)
    k = len(c) // n
    cc = _align(np.asarray(c, np.float64), a)
    e = 1e3 * np.linalg.norm((cc - a)[:k * n].reshape(k, n, 3).mean(axis=1), axis=1)
    sig = np.asarray(cal.sigma_mg[start:], np.float64)[:k * n].reshape(k, n).mean(axis=1)
    ok = np.all(np.asarray(cal.status[start:])[:k * n].reshape(k, n) == Status.CALIBRATED,
                axis=1)
    return {"cal_pct": 100 * float(np.mean(cal.status[start:] == Status.CALIBRATED)),
            "err_rms_mg": float(np.sqrt(np.mean(e**2))), **h,
            "med_sig": float(np.median(sig[ok])) if ok.any() else float("nan"),
            "med_err": float(np.median(e[ok])) if ok.any() else float("nan")}


def _tick(stop: threading.Event, out: list[float]) -> None:
    """Sleep 1 ms over and over; how late each wake-up came, s."""
    while not stop.is_set():  # bounded by the caller's stop
        t = time.perf_counter()
        time.sleep(0.001)
        out.append(time.perf_counter() - t - 0.001)


def _beside(work: Callable[[], object]) -> str:
    """p50 / p99 / max of a 1 ms tick's lateness (ms) while ``work`` runs."""
    stop, out = threading.Event(), []
    th = threading.Thread(target=_tick, args=(stop, out))
    th.start()
    work()
    stop.set()
    th.join()
    o = 1e3 * np.array(out)
    return f"{np.percentile(o, 50):.2f} / {np.percentile(o, 99):.2f} / {o.max():.2f} ms"


def cost() -> None:
    """A run's CPU on evidence of 250 .. 2048 windows (3 h at 50 Hz, two aux channels, clean),
    a window's cost to the evidence, and a 1 ms tick's lateness idle, beside a run in a
    thread and beside one in a spawned process."""
    from recal.core import discovery as dc
    from recal.core import discovery_data as dd
    from recal.core.buffer import Windows
    from recal.core.evidence import EvidenceConfig, EvidenceStore
    from recal.core.pipeline_config import PipelineConfig

    spec = sim.SensorSpec.random(np.random.default_rng(1), 50, 3)
    r = sim.simulate(3.0, 50.0, 1, spec, sim.WearerSpec(always_aux=True, **WEARER))
    w = dd.data_from_batch(r.raw, PipelineConfig(rate_hz=50.0), 1024.0).windows
    m = SensorModel.diagonal(1024.0)
    args: tuple = ()
    for cap in (256, 512, 1024, 2048):
        st = EvidenceStore(EvidenceConfig(cap), 2)
        t = time.process_time()
        for i in range(len(w)):  # bounded: a window at a time, as a node adds them
            st.add(Windows(w.v[i:i + 1], w.aux[i:i + 1], w.t_us[i:i + 1], w.n[i:i + 1],
                           w.var[i:i + 1]))
        add_us = 1e6 * (time.process_time() - t) / len(w)
        args = (st.windows(), r.raw.aux_names, int(r.raw.t_us[0]), m, m.nominal())
        t = time.process_time()
        dc.discover_pipeline(*args)
        print(f"capacity {cap}: {len(st)} windows held, a run {time.process_time() - t:.2f} s "
              f"CPU, adding a window {add_us:.0f} us")
    print("1 ms tick lateness p50 / p99 / max: idle", _beside(lambda: time.sleep(3.0)))
    print("  beside a run in a thread", _beside(lambda: dc.discover_pipeline(*args)))
    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    pool.submit(int, 1).result()  # the worker is up
    print("  beside a run in a process",
          _beside(lambda: pool.submit(dc.discover_pipeline, *args).result()))
    pool.shutdown()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--rate", type=float, default=50.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", default="")
    ap.add_argument("--cost", action="store_true")
    ap.add_argument("--live", action="store_true", help="through a pty into `recal run`")
    ap.add_argument("--speed", type=float, default=20.0,
                    help="--live: times faster than real time")
    ap.add_argument("--old-src", help="--live: run the daemon from this source tree")
    a = ap.parse_args(argv)
    if a.cost:
        cost()
        return 0
    if a.live:
        import live_loop_pty
        return live_loop_pty.main(a, CASES, simulated, _run, _true_model, _after)
    print("| case | cal % | err/floor | >3 / >10 % | med sig / med err mg | adopted (min) "
          "| runs, cpu s |\n|---|---|---|---|---|---|---|")
    for case in CASES:
        if a.only and a.only not in case.name:
            continue
        spec, res = simulated(case, a)
        raw, truth = res.raw, res.truth.a_true_g
        s0 = float(spec.counts_per_g or 1.0)
        start = int(np.searchsorted(raw.t_us, raw.t_us[0] + 3.6e9))
        cal, evs, cpu = _run(raw, SensorModel.diagonal(s0), spec.zero_g_counts, True, a.rate)
        fl, _, cpu0 = _run(raw, _true_model(case, s0, raw), spec.zero_g_counts, False, a.rate)
        m = _after(cal, truth, spec.noise_g, a.rate, start)
        f = _after(fl, truth, spec.noise_g, a.rate, start)
        t0 = int(raw.t_us[0])
        adopted = "; ".join(
            f"{'+'.join(e['detail']['added']) or ''}"
            f"{' -' + '-'.join(e['detail']['dropped']) if e['detail']['dropped'] else ''}"
            f" @{(e['t_us'] - t0) / 60e6:.0f}" for e in evs if e["detail"]["adopted"]) or "-"
        print(f"| {case.name} | {m['cal_pct']:.1f} | {m['err_rms_mg'] / f['err_rms_mg']:.2f} "
              f"({m['err_rms_mg']:.2f}/{f['err_rms_mg']:.2f}) | "
              f"{100 * m['beyond_3']:.2f} / {100 * m['beyond_10']:.2f} | "
              f"{m['med_sig']:.2f} / {m['med_err']:.2f} | {adopted} | "
              f"{len(evs)}, {cpu - cpu0:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
