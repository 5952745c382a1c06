"""The model and prior of a sensor, from its config: a named model (``diagonal``, ``full``)
or a JSON model file, and the prior its ``[[sensors]] prior`` table gives."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from recal.config.settings import PipelineSection, SensorConfig, ServiceConfig
from recal.core.channels import missing_channels
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.errors import ConfigError

__all__ = ["check_model_channels", "load_model_file", "model_and_prior"]


def load_model_file(path: str | Path) -> tuple[SensorModel, Prior | None]:
    """A model (and prior, if the file has parameters) from JSON.

    Accepted: a ``SensorModel.to_dict()`` (``s0`` and ``effects``), or an object with ``model``
    (or ``model_spec``, as in a calibration state message) plus optional ``params`` (by name or
    in order), and either ``prior`` (``{"mean", "info"}``), ``covariance`` or ``sd``.
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such model file") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{p.name}: not a readable JSON model file ({exc})") from None
    try:
        return _model_doc(doc)
    except (KeyError, TypeError, ValueError, np.linalg.LinAlgError) as exc:
        raise ConfigError(f"{p.name}: invalid model file ({type(exc).__name__}: {exc})") from None


def _model_doc(doc: Mapping[str, Any]) -> tuple[SensorModel, Prior | None]:
    if "effects" in doc:
        return SensorModel.from_dict(doc), None
    spec = doc.get("model_spec") if isinstance(doc.get("model_spec"), Mapping) else doc["model"]
    model = SensorModel.from_dict(spec)
    if "prior" in doc:
        return model, Prior.from_dict(doc["prior"])
    if "params" not in doc:
        return model, None
    mean = model.params_from(doc["params"])
    if doc.get("covariance") is not None:
        cov = np.asarray(doc["covariance"], np.float64)
        return model, Prior(mean, np.linalg.inv(cov))
    sd = model.prior_sd()
    if isinstance(doc.get("sd"), Mapping):
        for k, v in doc["sd"].items():
            sd[model.index(k)] = float(v)
    return model, Prior.from_sd(mean, sd)


def _named_model(name: str, s0: float) -> SensorModel:
    return SensorModel.named(name, s0)


def model_and_prior(sensor: SensorConfig, settings: PipelineSection,
                    model_path: str | Path | None = None) -> tuple[SensorModel, Prior | None]:
    """The sensor model and prior (None: bootstrap) from a sensor's config.

    ``model_path`` (e.g. from the command line) replaces the prior's model file. A model file
    with parameters gives the prior mean; otherwise ``counts_per_g`` and ``zero_g`` do, with
    ``mean`` and ``sd`` overriding single parameters.
    """
    pc = sensor.prior
    name = sensor.model or settings.model
    file = Path(model_path) if model_path is not None else pc.model_file
    model, prior = (load_model_file(file) if file is not None
                    else (_named_model(name, pc.counts_per_g or 1.0), None))
    if prior is not None:
        return model, prior
    if pc.counts_per_g is None and file is None:
        return model, None  # nothing known: the pipeline bootstraps
    if pc.counts_per_g is not None and file is not None:
        model = SensorModel(model.effects, float(pc.counts_per_g), model.spreads)
    try:
        mean = model.nominal()
        if model.has("offset"):
            mean[model.slice(("offset", None))] = pc.zero_g
        sd = model.prior_sd()
        for k, v in pc.mean.items():
            mean[model.index(k)] = v
        for k, v in pc.sd.items():
            if not v > 0:
                raise ValueError(f"sd of {k} must be positive")
            sd[model.index(k)] = v
    except ValueError as exc:
        raise ConfigError(f"sensor {sensor.id}: prior: {exc} (parameters: "
                          f"{', '.join(model.names)})") from None
    return model, Prior.from_sd(mean, sd)


def check_model_channels(cfg: ServiceConfig, model_path: str | Path | None = None) -> None:
    """ConfigError if a sensor's model reads a channel its configured channels lack: said at
    the start, not at the first batch (channels learnt from the stream are checked at its
    first batch, by the node)."""
    for s in cfg.sensors:
        if s.aux_names is None:
            continue
        model = model_and_prior(s, cfg.pipeline, model_path)[0]
        missing = missing_channels(model, s.aux_names)
        if missing:
            raise ConfigError(f"sensor {s.id}: the model needs channel {missing[0]!r}, the "
                              f"sensor's channels are {list(s.aux_names)}")

