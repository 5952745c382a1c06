"""The numerical core of recal: pure numpy/scipy, no I/O, no clocks; state in, state out.

`pipeline` is the streaming core: `Pipeline.step` (or `step_many`) takes a batch of raw samples
and, in data-flow order (docs/design.md, "The core, module by module", has the why of each):

- `detector`: quasi-static detection, a band-passed norm against a threshold (Lötters eq. 1-2),
  and `channels`: which samples may enter a window (the model's channels finite);
- `windower`: cuts the gated runs into windows, its state passed in and returned (the one
  windower of the pipeline and of the batch `batch_windows`);
- `buffer`: the bounded set of window means the estimator fits, spread over orientations;
- `refit`: whether the new windows call for a re-fit (most repeat what the buffer says);
- `estimator`: the Bayesian re-fit of the parameters (Lötters 1998, eq. 11a/11b), its
  records (prior, settings, estimate, report) in `estimate`;
- `model`, `effects`: the sensor model as a chain of effects (offset, scale, cross-axis, ...;
  the registry `EFFECT_KINDS`, whose classes are public names here by their own),
  with `triaxial` for the per-axis arithmetic on (N, 3) readings;
- `correction`, `status`, `sigma`: each sample corrected with the parameters in force when it
  arrived, with its status and predicted error; the self-watch that doubts the estimate;
- `outputs`: what a step gives back (`StepOutput`), per batch also for joined batches;
- `pipeline_config`: the settings of all of it;
- the pipeline's parts: `pipeline_windows` (windows committed, re-fits due), `pipeline_watch`
  (the self-watch at work), `pipeline_fit` (updates, bootstrap), `pipeline_state` (its
  checkpoint, a step's scratch).

Beside it:

- `batch_windows`: a whole recording's window means at once, by the pipeline's windower;
- `discovery` (with `candidates`, `discovery_data`, `model_fit`, `residuals`): which effects a
  recording needs, chosen by held-out error among the forms each registered effect proposes;
- `hindsight`: one fit on a whole recording, every sample corrected with it;
- `static`: lab calibration from a table of still positions;
- `bootstrap`: zero-g, scale and starting values (sphere, ellipsoid fits) from no prior;
- `alignment`: the sensor's mounting relative to the body, and the slip alarm (the node's);
- `timebase`, `rate`: device time stamps to the service's microseconds (wraps, units,
  reboots) and a stream's rate from them (the node's, before the pipeline).

The names below are the core's public API; each lives in the module named above.
"""

from importlib import import_module
from typing import TYPE_CHECKING

# the registry names the effect classes below; the module is small (numpy and the axes helpers)
from recal.core.effects import EFFECT_KINDS as _EFFECT_KINDS

if TYPE_CHECKING:  # for type checkers and readers; at run time a name loads its module on use
    from recal.core.alignment import Alignment
    from recal.core.batch_windows import Windowing, window_means
    from recal.core.buffer import BufferConfig, Coverage, WindowBuffer, Windows
    from recal.core.channels import missing_channels
    from recal.core.covariates import TIME, Covariates
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
    from recal.core.effects import *  # noqa: F403  (the effect classes, as below)
    from recal.core.effects import EFFECT_KINDS, Effect, make_effect
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
    from recal.core.windower import WindowerState, WindowSums, cut

#: Each public name and the core module it lives in. Loaded on first use (PEP 562), so a
#: command imports only the core modules it runs (replay needs neither discovery nor static).
_HOMES = {
    "AffineCorrection": "model",
    "Alignment": "alignment",
    "BufferConfig": "buffer",
    "Covariates": "covariates",
    "Coverage": "buffer",
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
    "HindsightFit": "hindsight",
    "Lifecycle": "pipeline",
    "Pipeline": "pipeline",
    "PipelineConfig": "pipeline_config",
    "Prior": "estimate",
    "SensorModel": "model",
    "StaticFit": "static",
    "Status": "status",
    "StepOutput": "outputs",
    "TIME": "covariates",
    "TimebaseConfig": "timebase",
    "TimebaseState": "timebase",
    "UpdateEvent": "outputs",
    "UpdateReport": "estimate",
    "WatchEvent": "outputs",
    "WindowBuffer": "buffer",
    "WindowSums": "windower",
    "WindowerState": "windower",
    "Windowing": "batch_windows",
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
    "window_means": "batch_windows",
}


# every effect class of the registry, by its own name (a new effect is public once registered)
_HOMES |= {cls.__name__: "effects" for cls in _EFFECT_KINDS.values()}


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
    "DetectorConfig",
    "DetectorOutput",
    "DetectorState",
    "DiscoveryConfig",
    "DiscoveryData",
    "DiscoveryResult",
    "Effect",
    "Estimate",
    "EstimatorConfig",
    "HindsightFit",
    "Lifecycle",
    "Pipeline",
    "PipelineConfig",
    "Prior",
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
    # and every effect class of the registry, below
]
__all__ += [cls.__name__ for cls in _EFFECT_KINDS.values()]
