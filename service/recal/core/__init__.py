"""The numerical core of recal: pure numpy/scipy, no I/O, no clocks; state in, state out.

`pipeline` is the streaming core: `Pipeline.step` (or `step_many`) takes a batch of raw samples
and, in data-flow order (docs/design.md, "The core, module by module", has the why of each):

- `detector`: quasi-static detection, a band-passed norm against a threshold (Lötters eq. 1-2),
  and `channels`: which samples may enter a window (the model's channels finite);
- `windower`: cuts the gated runs into windows, its state passed in and returned (the one
  windower of the pipeline and of the batch `window_means`);
- `buffer`: the bounded set of window means the estimator fits, spread over orientations;
- `refit`: whether the new windows call for a re-fit (most repeat what the buffer says);
- `estimator`: the Bayesian re-fit of the parameters (Lötters 1998, eq. 11a/11b), its
  records (prior, settings, estimate, report) in `estimate`;
- `model`, `effects`: the sensor model as a chain of effects (offset, scale, cross-axis, ...),
  with `triaxial` for the per-axis arithmetic on (N, 3) readings;
- `correction`, `status`, `sigma`: each sample corrected with the parameters in force when it
  arrived, with its status and predicted error; the self-watch that doubts the estimate;
- `outputs`: what a step gives back (`StepOutput`), per batch also for joined batches;
- `pipeline_config`: the settings of all of it;
- the pipeline's parts: `pipeline_windows` (windows committed, re-fits due), `pipeline_watch`
  (the self-watch at work), `pipeline_fit` (updates, bootstrap), `pipeline_state` (its
  checkpoint, the snapshot a step rolls back to).

Beside it:

- `window_means`: a whole recording's window means at once, by the pipeline's windower;
- `discovery` (with `discovery_data`, `model_fit`, `residuals`): which effects a recording
  needs, chosen by held-out error;
- `hindsight`: one fit on a whole recording, every sample corrected with it;
- `static`: lab calibration from a table of still positions;
- `bootstrap`: zero-g, scale and starting values (sphere, ellipsoid fits) from no prior;
- `alignment`: the sensor's mounting relative to the body, and the slip alarm (the node's);
- `timebase`, `rate`: device time stamps to the service's microseconds (wraps, units,
  reboots) and a stream's rate from them (the node's, before the pipeline).

The names below are the core's public API; each lives in the module named above.
"""

import sys
from importlib import import_module
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # for type checkers and readers; at run time a name loads its module on use
    from recal.core.alignment import Alignment
    from recal.core.buffer import BufferConfig, Coverage, WindowBuffer, Windows
    from recal.core.channels import missing_channels
    from recal.core.detector import (
        DetectorConfig,
        DetectorOutput,
        DetectorState,
        detect,
        init_state,
    )
    from recal.core.discovery import (
        DiscoveryConfig,
        DiscoveryResult,
        discover,
        discover_pipeline,
    )
    from recal.core.discovery_data import (
        DiscoveryData,
        data_from_batch,
        data_from_batches,
        data_from_table,
    )
    from recal.core.effects import (
        EFFECT_KINDS,
        TIME,
        Covariates,
        CrossAxis,
        Effect,
        Gain,
        Nonlinearity,
        Offset,
        Ratiometric,
        Scale,
        make_effect,
    )
    from recal.core.estimate import Estimate, EstimatorConfig, Prior, UpdateReport
    from recal.core.hindsight import HindsightFit
    from recal.core.model import AffineCorrection, SensorModel
    from recal.core.outputs import StepOutput, UpdateEvent, WatchEvent
    from recal.core.pipeline import Lifecycle, Pipeline, gain_reference
    from recal.core.pipeline_config import PipelineConfig
    from recal.core.rate import infer_rate_hz
    from recal.core.static import StaticFit, fit_known_orientations, fit_unknown_orientations
    from recal.core.status import Status
    from recal.core.timebase import TimebaseConfig, TimebaseState
    from recal.core.window_means import Windowing, window_means
    from recal.core.windower import WindowerState, WindowSums, cut

#: Each public name and the core module it lives in. Loaded on first use (PEP 562), so a
#: command imports only the core modules it runs (replay needs neither discovery nor static).
_HOMES = {
    "AffineCorrection": "model",
    "Alignment": "alignment",
    "BufferConfig": "buffer",
    "Covariates": "effects",
    "Coverage": "buffer",
    "CrossAxis": "effects",
    "DetectorConfig": "detector",
    "DetectorOutput": "detector",
    "DetectorState": "detector",
    "DiscoveryConfig": "discovery",
    "DiscoveryData": "discovery_data",
    "DiscoveryResult": "discovery",
    "EFFECT_KINDS": "effects",
    "Effect": "effects",
    "Estimate": "estimate",
    "EstimatorConfig": "estimate",
    "Gain": "effects",
    "HindsightFit": "hindsight",
    "Lifecycle": "pipeline",
    "Nonlinearity": "effects",
    "Offset": "effects",
    "Pipeline": "pipeline",
    "PipelineConfig": "pipeline_config",
    "Prior": "estimate",
    "Ratiometric": "effects",
    "Scale": "effects",
    "SensorModel": "model",
    "StaticFit": "static",
    "Status": "status",
    "StepOutput": "outputs",
    "TIME": "effects",
    "TimebaseConfig": "timebase",
    "TimebaseState": "timebase",
    "UpdateEvent": "outputs",
    "UpdateReport": "estimate",
    "WatchEvent": "outputs",
    "WindowBuffer": "buffer",
    "WindowSums": "windower",
    "WindowerState": "windower",
    "Windowing": "window_means",
    "Windows": "buffer",
    "cut": "windower",
    "data_from_batch": "discovery_data",
    "data_from_batches": "discovery_data",
    "data_from_table": "discovery_data",
    "detect": "detector",
    "discover": "discovery",
    "discover_pipeline": "discovery",
    "fit_known_orientations": "static",
    "fit_unknown_orientations": "static",
    "gain_reference": "pipeline",
    "infer_rate_hz": "rate",
    "init_state": "detector",
    "make_effect": "effects",
    "missing_channels": "channels",
    "window_means": "window_means",
}


class _Core(ModuleType):
    """The package's module type: `window_means` names both a module and the function it
    defines, and importing the module sets the module on its package; the public name stays
    the function (`from recal.core import window_means`, whatever was imported first)."""

    def __setattr__(self, name: str, value: object) -> None:
        if isinstance(value, ModuleType) and _HOMES.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Core


def __getattr__(name: str) -> object:
    if name not in _HOMES:
        raise AttributeError(f"module 'recal.core' has no attribute {name!r}")
    value = getattr(import_module(f"recal.core.{_HOMES[name]}"), name)
    globals()[name] = value  # once loaded, a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_HOMES})

__all__ = [
    "EFFECT_KINDS",
    "TIME",
    "AffineCorrection",
    "Alignment",
    "BufferConfig",
    "Covariates",
    "Coverage",
    "CrossAxis",
    "DetectorConfig",
    "DetectorOutput",
    "DetectorState",
    "DiscoveryConfig",
    "DiscoveryData",
    "DiscoveryResult",
    "Effect",
    "Estimate",
    "EstimatorConfig",
    "Gain",
    "HindsightFit",
    "Lifecycle",
    "Nonlinearity",
    "Offset",
    "Pipeline",
    "PipelineConfig",
    "Prior",
    "Ratiometric",
    "Scale",
    "SensorModel",
    "StaticFit",
    "Status",
    "StepOutput",
    "TimebaseConfig",
    "TimebaseState",
    "UpdateEvent",
    "UpdateReport",
    "WatchEvent",
    "WindowBuffer",
    "WindowSums",
    "WindowerState",
    "Windowing",
    "Windows",
    "cut",
    "data_from_batch",
    "data_from_batches",
    "data_from_table",
    "detect",
    "discover",
    "discover_pipeline",
    "fit_known_orientations",
    "fit_unknown_orientations",
    "gain_reference",
    "infer_rate_hz",
    "init_state",
    "make_effect",
    "missing_channels",
    "window_means",
]
