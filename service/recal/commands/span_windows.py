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
from typing import Any

import numpy as np

from recal.core import detector as det
from recal.core import windower
from recal.core.batch_windows import (
    Segment,
    Settler,
    WindowsFn,
    detect_segment,
    warm_samples,
    window_span,
)
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.errors import InputError
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
            return rec.with_low_rate(w.kept(), *span)

        told = 0

        def tell(samples: int) -> None:
            nonlocal told
            if progress is not None and samples:
                progress(samples)
            told += samples

        with ThreadPoolExecutor(threads, thread_name_prefix="recal-windows") as pool:
            closed = pool.submit(closed_form)  # beside the detector's first segments
            gate = np.empty(n, bool)
            run = _Pass(pool, threads, range(0, n, every), n, Settler(dcfg), gate)
            tables = run.go(detect, window, tell)
        state = run.settler.state
        if state is None:
            raise InputError("a recording needs samples to find windows in")
        tell(n - told)
        first = rec.batch(0, 1)
        return (windower.WindowSums.concat(tables), first.aux_names, int(first.t_us[0]),
                state.step_raw)

    return windows


class _Pass:
    """One windows' pass on the pool: the segments detected, then checked in order (each that
    starts a span ends the one before), the spans windowed as they become ready. A free
    thread takes a span before the next segment: the windower's work (memory-bound) runs
    beside the detector's (its filters' recursion), and neither waits for all of the other."""

    def __init__(self, pool: ThreadPoolExecutor, threads: int, segments: range, n: int,
                 settler: Settler, gate: np.ndarray) -> None:
        self.pool, self.threads, self.n, self.settler, self.gate = pool, threads, n, settler, gate
        self.segments = list(segments)
        self.todo: deque[int] = deque(self.segments)
        self.spans: deque[tuple[int, int]] = deque()
        self.detected: dict[int, Segment] = {}
        self.tables: dict[tuple[int, int], windower.WindowSums] = {}
        self.running: dict[Future, tuple[str, Any]] = {}
        self.settled, self.span_lo = 0, 0

    def go(self, detect: Callable[..., Segment],
           window: Callable[[tuple[int, int]], windower.WindowSums],
           tell: Callable[[int], None]) -> list[windower.WindowSums]:
        """Every span's windows, in order. detect(lo[, state]): a segment; window(span)."""
        while True:
            while len(self.running) < self.threads and (self.spans or self.todo):
                if self.spans:
                    span = self.spans.popleft()
                    self.running[self.pool.submit(window, span)] = ("span", span)
                else:
                    lo = self.todo.popleft()
                    self.running[self.pool.submit(detect, lo)] = ("segment", lo)
            if not self.running:
                return [self.tables[k] for k in sorted(self.tables)]
            done, _ = wait(self.running, return_when=FIRST_COMPLETED)
            for f in done:
                kind, key = self.running.pop(f)
                if kind == "segment":
                    self.detected[key] = f.result()
                    tell(len(self.detected[key].gate) // 2)
                else:
                    self.tables[key] = f.result()
                    tell((key[1] - key[0]) // 2)
            self._settle(detect)

    def _settle(self, detect: Callable[..., Segment]) -> None:
        """The segments detected so far, checked in order (`Settler`: run again from the
        state before where the warm-up fell short); their gates in place; the spans they
        end queued."""
        while self.settled < len(self.segments) and self.segments[self.settled] in self.detected:
            s = self.settler.add(self.detected.pop(self.segments[self.settled]),
                                 lambda s, st: detect(s.lo, st))
            self.gate[s.lo:s.hi] = s.gate
            first = s.first_ungated if self.settled else None
            if first is not None:
                self.spans.append((self.span_lo, first))
                self.span_lo = first
            self.settled += 1
            if self.settled == len(self.segments):
                self.spans.append((self.span_lo, self.n))

