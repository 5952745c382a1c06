"""Configuration: the TOML file and the command line's per-sensor options -> frozen settings.

The settings dataclasses are in :mod:`~recal.config.settings`, the TOML file's reading and
checks in :mod:`~recal.config.loading` (its values: :mod:`~recal.config.toml_values`), a
sensor's model and prior in :mod:`~recal.config.model_prior`; this package names them all.
"""

from recal.config.loading import FORMATS, MODELS, load_config, load_priors, parse_config
from recal.config.model_prior import check_model_channels, load_model_file, model_and_prior
from recal.config.settings import (
    AlignmentConfig,
    CheckpointConfig,
    ConfigError,
    McapConfig,
    PipelineSection,
    PriorConfig,
    RediscoveryConfig,
    RemoteNodeConfig,
    SensorConfig,
    ServiceConfig,
    ZenohSettings,
    default_sensor_id,
    default_state_dir,
)
from recal.config.toml_values import read_config_text

__all__ = [
    "FORMATS",
    "MODELS",
    "AlignmentConfig",
    "CheckpointConfig",
    "ConfigError",
    "McapConfig",
    "PipelineSection",
    "PriorConfig",
    "RediscoveryConfig",
    "RemoteNodeConfig",
    "SensorConfig",
    "ServiceConfig",
    "ZenohSettings",
    "check_model_channels",
    "default_sensor_id",
    "default_state_dir",
    "load_config",
    "load_model_file",
    "load_priors",
    "model_and_prior",
    "parse_config",
    "read_config_text",
]
