"""A device file's still windows on several threads, the same bit for bit as one reading from
its start (`core.batch_windows`, "in spans"): the detector on segments of the file, each
started early, then checked and joined in order; the windower on spans that start where the
detector gates nothing. numpy and scipy's filter release the interpreter's lock while they
work on a batch, so the threads share the cores (docs/design.md, "A long file on threads").

The file is in memory (`DeviceRecording`: any range of samples at will); a stream (an MCAP
or CSV recording) is read from its start instead (`batch_windows.in_order`).
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import replace
from typing import Any

import numpy as np

from recal.core import detector as det
from recal.core import windower
from recal.core.batch_windows import (
    Segment,
    Settler,
    WindowsFn,
    detect_segment,
    first_ungated,
    warm_samples,
    window_span,
)
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.io.device_files import DeviceRecording
from recal.samples import REBATCH_SAMPLES

__all__ = ["SEGMENT_BATCHES", "default_threads", "span_windows"]

#: Batches per segment of the detector and per span of the windower: 4 Mi samples, 11.6 h at
#: 100 Hz, so a week is 15 pieces of work for the threads, and a warm-up (15 min) costs 2 %.
SEGMENT_BATCHES = 64
#: Threads at most, whatever the cores: beyond, the memory's bandwidth is what they share.
MAX_THREADS = 8


def default_threads() -> int:
    """The cores this process may run on (its CPU affinity), at most MAX_THREADS."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_THREADS))


def span_windows(rec: DeviceRecording, threads: int,
                 progress: Callable[[int], None] | None = None, batch: int = REBATCH_SAMPLES,
                 segment_batches: int | None = None) -> WindowsFn:
    """The windows of ``rec`` (`batch_windows.WindowsFn`) on ``threads`` threads, the same as
    `rec.batches(batch)` read in order gives; progress(n) is called in the caller's thread as
    samples are done (half of each sample in each of the two steps)."""

    def windows(cfg: PipelineConfig, model: SensorModel, s0: float, zero: np.ndarray | None
                ) -> tuple[windower.WindowSums, tuple[str, ...] | None, int | None, np.ndarray]:
        dcfg = cfg.detector(s0, zero)
        n, every = len(rec), (segment_batches or SEGMENT_BATCHES) * batch
        warm = warm_samples(cfg.rate_hz, batch)

        def detect(lo: int, state: det.DetectorState | None = None) -> Segment:
            return detect_segment(dcfg, rec.readings_by_axis, lo, min(n, lo + every), batch,
                                  warm, state)

        def closed_form() -> bool:
            """The low-rate channels' sums apart, in closed form, where they have one and no
            channel the model uses can mask a sample (all finite); else as `batch` gives
            them."""
            return (rec.low_rate_closed is not None
                    and rec.finite_everywhere(model.covariates))

        def window(span: tuple[int, int]) -> windower.WindowSums:
            if not closed.result():
                return window_span(cfg, model, s0, zero, rec.batch, gate, *span, batch).kept()
            w = window_span(cfg, SensorModel.diagonal(s0), s0, zero, rec.window_batch, gate,
                            *span, batch)
            return _with_low_rate(rec, w.kept(), *span)

        told = 0

        def tell(samples: int) -> None:
            nonlocal told
            if progress is not None and samples:
                progress(samples)
            told += samples

        with ThreadPoolExecutor(threads, thread_name_prefix="recal-windows") as pool:
            closed = pool.submit(closed_form)  # beside the detector's first segments
            gate = np.empty(n, bool)
            segments = list(range(0, n, every))
            todo, detected, spans, tables = deque(segments), {}, deque(), {}
            settler, settled, span_lo = Settler(dcfg), 0, 0
            running: dict[Future, tuple[str, Any]] = {}
            while True:
                # a free thread takes a span ready to window, else the next segment: the
                # windower's work (memory-bound) runs beside the detector's (its filters'
                # recursion), and neither waits for all of the other
                while len(running) < threads and (spans or todo):
                    if spans:
                        span = spans.popleft()
                        running[pool.submit(window, span)] = ("span", span)
                    else:
                        lo = todo.popleft()
                        running[pool.submit(detect, lo)] = ("segment", lo)
                if not running:
                    break
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    kind, key = running.pop(f)
                    if kind == "segment":
                        detected[key] = f.result()
                        tell(len(detected[key].gate) // 2)
                    else:
                        tables[key] = f.result()
                        tell((key[1] - key[0]) // 2)
                # segments checked in order; each that starts a span ends the one before
                while settled < len(segments) and segments[settled] in detected:
                    s = settler.add(detected.pop(segments[settled]),
                                    lambda s, st: detect(s.lo, st))
                    gate[s.lo:s.hi] = s.gate
                    first = first_ungated(s.gate) if settled else None
                    if first is not None:
                        spans.append((span_lo, s.lo + first))
                        span_lo = s.lo + first
                    settled += 1
                    if settled == len(segments):
                        spans.append((span_lo, n))
            state = settler.state
            assert state is not None  # a device file has samples
        tell(n - told)
        first = rec.batch(0, 1)
        return (windower.WindowSums.concat([tables[k] for k in sorted(tables)]),
                first.aux_names, int(first.t_us[0]), state.step_raw)

    return windows


def _with_low_rate(rec: DeviceRecording, sums: windower.WindowSums, lo: int, hi: int
                   ) -> windower.WindowSums:
    """Windows cut from `DeviceRecording.window_batch`es with their channels as `batch`
    gives them: the low-rate channels' sums for each window's samples (its first from the
    sum of SAMPLE_INDEX: n first + n (n - 1) / 2, exact in float64 below 2^53), then the
    per-sample ones."""
    n = sums.n
    first = np.rint((sums.sum_aux[:, -1] - n * (n - 1) / 2) / np.maximum(n, 1)).astype(np.int64)
    low = rec.low_rate_sums(lo, hi, first, n)
    return replace(sums, sum_aux=np.hstack([low, sums.sum_aux[:, :-1]]))
