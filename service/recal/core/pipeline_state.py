"""The pipeline's state (`core.pipeline`) as its parts hold it: the checkpoint document
(`state_dict`, `load_state`), each part writing and reading its own (detector, windower, buffer,
refit, self-watch); and what the pipeline keeps only while a step runs or not to work it out
again (`Work`), which is neither.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

from recal.core import detector as det
from recal.core.buffer import Window, WindowBuffer
from recal.core.estimator import Estimate, Prior, UpdateReport
from recal.core.model import SensorModel
from recal.core.refit import RefitState
from recal.core.status import Watch
from recal.core.windower import WindowerState

if TYPE_CHECKING:
    from recal.core.correction import Segment
    from recal.core.effects import Covariates
    from recal.core.outputs import Marks, WatchEvent
    from recal.core.pipeline_config import PipelineConfig
    from recal.core.status import Status

__all__ = ["PipelineParts", "Work", "load_state", "state_dict"]


class Work:
    """What the pipeline keeps during one step (the marks, the segments in force, the self-watch's
    events, a detector restart or a reset due) and what it keeps not to work it out again (the
    last segment, the sigma form, whether the estimate is finite, what converges). Not state:
    never in a checkpoint (each cache is keyed by the objects it was made of, so it holds
    whatever the pipeline is loaded with)."""

    __slots__ = ("converging", "finite_estimate", "form", "last_segment", "marks", "reset_due",
                 "restart_at", "segs", "watch_events")

    def __init__(self) -> None:
        self.marks: Marks | None = None  # only during a step with marks
        self.segs: list[Segment] = []  # during a step: what is in force from where
        self.watch_events: list[WatchEvent] = []
        self.restart_at: int | None = None  # the detector restarts after this sample
        self.reset_due: str | None = None  # why the self-watch resets at this update point
        self.last_segment: Segment | None = None  # `Pipeline._segment`'s last, while it holds
        self.form: tuple | None = None  # (model, estimate, ...) of the last segment
        self.finite_estimate: Estimate | None = None
        # (estimate, model, `status.unsettled`, unobserved, `converging`)
        self.converging: tuple | None = None


class PipelineParts(Protocol):
    """The pipeline (`pipeline.Pipeline`) as its parts' modules read and change it: they are
    typed against this, so they need not import the pipeline that imports them."""

    cfg: PipelineConfig
    model: SensorModel
    prior: Prior | None
    aux_names: tuple[str, ...]
    t0_us: int | None
    estimate: Estimate | None
    bootstrapped: bool
    from_prior: bool
    centre0: np.ndarray
    buffer: WindowBuffer
    fresh: list[Window]
    detector: det.Detector | None
    windower: WindowerState
    counts: dict[str, int]
    last_report: UpdateReport | None
    refit: RefitState
    informed: bool
    watch: Watch
    unobserved: tuple[str, ...]
    _work: Work

    @property
    def params(self) -> np.ndarray: ...

    @property
    def status(self) -> Status: ...

    @property
    def det_cfg(self) -> det.DetectorConfig | None: ...

    def covariates(self, t_us: np.ndarray, aux: np.ndarray) -> Covariates: ...

    def _segment(self, idx: int) -> Segment: ...

    def _segment_cache(self) -> tuple: ...

    def _reach(self, idx: int) -> None: ...


def state_dict(pipe: PipelineParts) -> dict:
    """Everything needed to resume exactly where `pipe` stopped (JSON-able)."""
    rep = pipe.last_report
    win = pipe.windower.to_dict()
    return {
        "version": 1,
        "config": pipe.cfg.to_dict(),
        "model": pipe.model.to_dict(),
        "prior": pipe.prior.to_dict() if pipe.prior is not None else None,
        "estimate": pipe.estimate.to_dict() if pipe.estimate is not None else None,
        "bootstrapped": pipe.bootstrapped,
        "from_prior": pipe.from_prior,
        "centre0": pipe.centre0.tolist(),
        "aux_names": list(pipe.aux_names),
        "t0_us": pipe.t0_us,
        "buffer": pipe.buffer.to_dict(),
        "detector": pipe.detector.to_dict() if pipe.detector is not None else None,
        "open": win["open"],
        "pending": win["pending"],
        "fresh": [f.to_list() for f in pipe.fresh],
        "last_t_us": win["last_t_us"],
        "last_gate": win["last_gate"],
        "counts": dict(pipe.counts),
        "last_report": rep.record() if rep is not None else None,
        **pipe.refit.to_dict(),
        "informed": pipe.informed,
        "watch": pipe.watch.to_dict(),
        "unobserved": list(pipe.unobserved),
    }


def load_state(pipe: PipelineParts, d: dict) -> None:
    """The state `state_dict` wrote into a pipeline made with its config, model, prior, aux
    names and t0 (`pipeline.from_state_dict`); it continues bit for bit. Keys absent in older
    checkpoints take what those checkpoints meant."""
    prior = pipe.prior
    pipe.estimate = Estimate.from_dict(d["estimate"]) if d["estimate"] is not None else None
    pipe.bootstrapped = bool(d["bootstrapped"])
    pipe.from_prior = bool(d.get("from_prior", prior is not None and pipe.bootstrapped))
    pipe.centre0 = np.asarray(d.get("centre0", [0.0] * 3), np.float64)
    pipe.buffer = WindowBuffer.from_dict(d["buffer"])
    ds = d["detector"]
    pipe.detector = (None if ds is None else det.Detector(
        pipe.cfg.detector(float(ds["s0"]), np.asarray(ds.get("zero_raw", [0.0] * 3), float)),
        det.DetectorState.from_dict(ds)))
    pipe.windower = WindowerState.from_dict(d)
    pipe.fresh = [Window.from_list(f) for f in d["fresh"]]
    pipe.counts = dict(d["counts"])
    pipe.refit = RefitState.from_dict(d)
    informed = d.get("informed")  # absent in checkpoints from before statuses
    pipe.informed = (bool(informed) if informed is not None
                     else pipe.estimate is not None and pipe.estimate.t_us is not None)
    pipe.watch = Watch.from_dict(d.get("watch"))
    pipe.unobserved = tuple(str(x) for x in d.get("unobserved", ()))  # absent in older ones
    rep = d.get("last_report")
    pipe.last_report = UpdateReport.from_record(rep) if rep else None
