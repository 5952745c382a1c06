"""The calibration state message a node publishes (``recal/<sensor>/calibration``), and the
name of a sensor model in it."""

from __future__ import annotations

from typing import Any

from recal.core import alignment as al
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline

__all__ = ["model_name", "state_message"]


def model_name(model: SensorModel) -> str:
    """A named model's name ("diagonal", "full"), or the effect labels joined by "+" for
    discovered models."""
    return model.name or "+".join(e.label for e in model.effects)


def state_message(sensor_id: str, pipeline: Pipeline, alignment: al.Alignment | None,
                  t_us: int | None, reason: str,
                  state: tuple[SensorModel, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The calibration state message: the summary plus identity and alignment. ``state``:
    the model and summary to report (`StepOutput.state`); None: the pipeline's now."""
    model, s = state if state is not None else (pipeline.model, pipeline.summary())
    s = dict(s)
    spec = s.pop("model")
    rep = s.get("last_update") or {}
    rms = s.get("residual_rms_mg")
    return {"sensor_id": sensor_id, "t_us": t_us, "reason": reason,
            "model": model_name(model), "model_spec": spec,
            "param_names": list(model.names), **s,
            "residual_g": None if rms is None else rms / 1e3,
            "observable": rep.get("observable"),
            "update_count": int(s["counts"]["updates"]),
            "alignment": alignment.to_dict() if alignment else None}
