"""The command line's per-sensor options (``recal run --rate --aux-names --prior ...``) laid
over a service configuration, as if the config said so.

A gateway started with only ``--port`` has no config file; these options are its sensor
entry. Named priors come from the config's priors, else from the shipped
configs/sensor-priors.toml.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from recal.config.loading import load_priors
from recal.config.settings import PriorConfig, SensorConfig, ServiceConfig
from recal.errors import ConfigError

__all__ = ["SHIPPED_PRIORS", "SensorOptions", "named_prior", "with_options"]

#: the priors `recal run --prior NAME` looks in without a --config (the shipped ones)
SHIPPED_PRIORS = Path(__file__).resolve().parents[3] / "configs" / "sensor-priors.toml"


@dataclass(frozen=True)
class SensorOptions:
    """Settings for every served sensor, None where the config's stand.

    Attributes:
        rate_hz: the sample rate (the config's ``rate_hz``).
        aux_names: the auxiliary channels after x, y, z (the config's ``aux_names``).
        prior: a prior's name (the config's priors, else the shipped ones).
        counts_per_g, zero_g: the prior's nominal sensitivity and 0 g reading, raw units.
    """

    rate_hz: float | None = None
    aux_names: tuple[str, ...] | None = None
    prior: str | None = None
    counts_per_g: float | None = None
    zero_g: float | None = None


def with_options(cfg: ServiceConfig, options: SensorOptions) -> ServiceConfig:
    """Every sensor of ``cfg`` with the options' rate, channels and prior (``prior``: a name,
    then ``counts_per_g`` and ``zero_g`` over it), as if the config said so."""
    changes: dict[str, Any] = {}
    if options.rate_hz is not None:
        changes["rate_hz"] = float(options.rate_hz)
    if options.aux_names is not None:
        changes["aux_names"] = tuple(options.aux_names)
    name = options.prior
    named = named_prior(cfg, name) if name is not None else None
    cpg, zero = options.counts_per_g, options.zero_g

    def prior(s: SensorConfig) -> PriorConfig:
        base = named or s.prior
        if cpg is None and zero is None:
            return base
        return replace(base, counts_per_g=cpg if cpg is not None else base.counts_per_g,
                       zero_g=(float(zero),) * 3 if zero is not None else base.zero_g)

    if not changes and named is None and cpg is None and zero is None:
        return cfg
    return cfg.with_sensors([replace(s, **changes, prior=prior(s)) for s in cfg.sensors])


def named_prior(cfg: ServiceConfig, name: str) -> PriorConfig:
    """The prior called ``name`` among the config's priors (``priors_file``, ``[priors]``), or
    among the shipped configs/sensor-priors.toml without a config file."""
    priors = cfg.priors if cfg.source is not None or not SHIPPED_PRIORS.exists() else (
        load_priors(SHIPPED_PRIORS))
    if name not in priors:
        known = ", ".join(sorted(priors)) or "none defined"
        raise ConfigError(f"--prior {name}: no prior named {name!r} ({known})")
    return priors[name]
