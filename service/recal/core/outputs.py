"""What a pipeline step gives back for a batch (`StepOutput`), with the estimator updates
(`UpdateEvent`) and the self-watch's events (`WatchEvent`) in it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from recal.core.estimator import Estimate, UpdateReport
from recal.core.model import SensorModel
from recal.samples import CalibratedBatch

__all__ = ["StepOutput", "UpdateEvent", "WatchEvent"]


@dataclass(frozen=True)
class UpdateEvent:
    """An estimator update that happened at sample `index` of the batch (device time t_us),
    with the estimate and model in force after it."""

    index: int
    t_us: int
    report: UpdateReport
    bootstrap: bool = False
    estimate: Estimate | None = field(default=None, compare=False)
    model: SensorModel | None = field(default=None, compare=False)


@dataclass(frozen=True)
class WatchEvent:
    """The self-watch at sample `index` of the batch (device time t_us): ``suspect`` (the
    still windows contradicted the estimate for a sustained time: the output is suspect and
    the estimate was reset toward the prior and re-fitted on the recent windows), ``agrees``
    (the windows agree again: suspect no more) or ``reset`` (the estimate was not finite)."""

    index: int
    t_us: int
    kind: str
    detail: dict = field(default_factory=dict, compare=False)


@dataclass(frozen=True, eq=False)
class StepOutput:
    """What one batch produced (`Pipeline.step`, `Pipeline.step_many`): its calibrated samples,
    the updates and the self-watch's events in it (indices into the batch, in order), the
    windows committed in it; and the state as of the batch's end: the model and estimate in
    force, and ``state``, the model and `Pipeline.summary()` then when the batch holds an
    update or a reset (`step_many` only: after `step` the pipeline's own summary is that)."""

    calibrated: CalibratedBatch
    updates: tuple[UpdateEvent, ...]
    windows_committed: int
    watch: tuple[WatchEvent, ...] = ()
    model: SensorModel | None = None
    estimate: Estimate | None = None
    state: tuple[SensorModel, dict] | None = None
