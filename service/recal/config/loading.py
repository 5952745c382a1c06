"""Service configuration: a TOML file (``configs/gateway.toml``) -> the frozen dataclasses of
:mod:`recal.config.settings`.

Every problem in a file becomes one :class:`ConfigError` with a one-line message naming the file,
the table and the key (``gateway.toml: [pipeline] threshold_g: expected a number, got 'x'``),
so the command line can print it without a traceback. Unknown keys are errors too: a typo
must not silently fall back to a default.

Layout (every table optional except ``[[sensors]]`` for the gateway; relative paths are
relative to the file)::

    priors_file = "sensor-priors.toml"     # named priors, see below
    run_nodes = true                       # calibrate in the gateway (false: a remote node does)
    batch_ms = 0                           # gateway: handle arrivals every N ms (0: at once)
    idle_batch_ms = 0                      # ... and every N ms while nobody subscribes live

    [zenoh]     mode = "peer", listen = [...], connect = [...], config_file = "zenoh-peer.json5"
    [mcap]      dir = "recordings" | path = "rec.mcap", chunk_size = 32768, flush_interval_s,
                rotate_mb, rotate_hours, compression = "zstd", fsync = true
    [checkpoint] dir = "<state folder>/checkpoints", interval_s = 60, after_update_s = 5
    [pipeline]  threshold_g, window_s, model = "diagonal"|"full", mode = "all"|"offsets",
                plot_hz = 2, any other PipelineConfig field; [pipeline.estimator],
                [pipeline.buffer] pass to EstimatorConfig / BufferConfig
    [alignment] enabled, min_still_s = 10, tilt_limit_deg = 7, upright_max_deg = 30,
                request_interval_s = 60 (at most one recal/<sensor>/align request per sensor)
    [node]      accept_any = false, max_sensors = 16: which sensors a `recal node` serves
                (default: only those in [[sensors]] or --sensor-id)
    [discovery] enabled = true, every_h = 2 (0 = off), first_h = 1/6, min_windows = 60,
                blocks = 10, adopt_after_s = 60, capacity = 2048: discover effects on each
                node's evidence (recal.core.evidence) and continue with the extended model
    [[sensors]] id, port, format = "ascii" (a name in recal.io.wire_formats), baudrate,
                aux_names, rate_hz, full_scale_g, model,
                prior = "<name in priors_file>" | { inline table }

A prior (inline, or ``[priors.<name>]`` in the priors file): ``counts_per_g`` (nominal
sensitivity s0, raw units per g), ``zero_g`` (the reading at 0 g, raw units: one number or
three), optional ``mean`` and ``sd`` tables by parameter name (``o_x`` ... ``s_z``, ``c_xy``
..., raw units) for a full prior, optional ``model_file`` (JSON: a SensorModel dict, or a
calibration state / model file with ``model`` and ``params``). Without ``counts_per_g`` and
without a model file the sensor bootstraps (no prior).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from recal.config.settings import (
    AlignmentConfig,
    CheckpointConfig,
    McapConfig,
    PipelineSection,
    PriorConfig,
    RediscoveryConfig,
    RemoteNodeConfig,
    SensorConfig,
    ServiceConfig,
    ZenohSettings,
    default_checkpoint_dir,
)
from recal.config.toml_values import (
    Place,
    boolean,
    integer,
    number,
    numbers_by_name,
    path_value,
    read_toml,
    string,
    strings,
    table,
)
from recal.core.buffer import BufferConfig
from recal.core.estimator import EstimatorConfig
from recal.core.model import NAMED_MODELS
from recal.core.pipeline_config import KEYS as PIPELINE_KEYS
from recal.core.pipeline_config import PipelineConfig
from recal.io.wire_formats import DEFAULT_FORMAT, WIRE_FORMATS

__all__ = ["load_config", "load_priors", "parse_config"]

FORMATS = tuple(WIRE_FORMATS)
MODELS = tuple(NAMED_MODELS)
MODES = ("all", "offsets")
ZENOH_MODES = ("peer", "client", "router")
COMPRESSIONS = ("zstd", "lz4", "none")


_PRIOR_KEYS = ("counts_per_g", "zero_g", "mean", "sd", "model_file")


def _prior(ctx: Place, d: Any) -> PriorConfig:
    d = table(ctx, d, _PRIOR_KEYS)
    zero = d.get("zero_g", 0.0)
    if isinstance(zero, (int, float)) and not isinstance(zero, bool):
        zero3 = (float(zero),) * 3
    elif (isinstance(zero, list) and len(zero) == 3
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in zero)):
        zero3 = tuple(float(x) for x in zero)
    else:
        raise ctx.error("zero_g", f"expected a number or a list of 3 numbers, got {zero!r}")
    return PriorConfig(number(ctx, d, "counts_per_g", None, positive=True), zero3,  # type: ignore[arg-type]
                       numbers_by_name(ctx, d, "mean"), numbers_by_name(ctx, d, "sd"),
                       path_value(ctx, d, "model_file", None))


_SENSOR_KEYS = ("id", "port", "format", "baudrate", "aux_names", "rate_hz", "full_scale_g",
                "model", "prior")


def _sensor(ctx: Place, d: Any, priors: Mapping[str, PriorConfig]) -> SensorConfig:
    d = table(ctx, d, _SENSOR_KEYS)
    sid = string(ctx, d, "id", None)
    if not sid:
        raise ctx.error("id", "every sensor needs an id")
    _check_sensor_id(ctx, sid)
    prior_v = d.get("prior")
    if prior_v is None:
        prior = PriorConfig()
    elif isinstance(prior_v, str):
        if prior_v not in priors:
            known = ", ".join(sorted(priors)) or "none defined"
            raise ctx.error("prior", f"no prior named {prior_v!r} ({known})")
        prior = priors[prior_v]
    else:
        prior = _prior(ctx.sub(f"{ctx.table}.prior"), prior_v)
    return SensorConfig(
        id=sid, port=string(ctx, d, "port", None), format=string(ctx, d, "format", DEFAULT_FORMAT,
                                                               FORMATS) or DEFAULT_FORMAT,
        baudrate=integer(ctx, d, "baudrate", 115200),
        aux_names=strings(ctx, d, "aux_names"),
        rate_hz=number(ctx, d, "rate_hz", None, positive=True),
        full_scale_g=number(ctx, d, "full_scale_g", None, positive=True),
        model=string(ctx, d, "model", None, MODELS), prior=prior)


def _check_sensor_id(ctx: Place, sid: str) -> None:
    from recal.io.recording import sensor_topic  # the one rule shared by MCAP and Zenoh

    try:
        sensor_topic(sid, "raw")
    except ValueError as exc:
        raise ctx.error("id", str(exc)) from None


def _zenoh(ctx: Place, d: Any) -> ZenohSettings:
    d = table(ctx, d, ("enabled", "mode", "listen", "connect", "config_file"))
    return ZenohSettings(boolean(ctx, d, "enabled", True),
                         string(ctx, d, "mode", None, ZENOH_MODES), strings(ctx, d, "listen"),
                         strings(ctx, d, "connect"),
                         path_value(ctx, d, "config_file", None))


def _mcap(ctx: Place, d: Any) -> McapConfig:
    d = table(ctx, d, ("path", "dir", "chunk_size", "flush_interval_s", "rotate_mb",
                       "rotate_hours", "compression", "fsync", "backlog_mb"))
    return McapConfig(
        path=path_value(ctx, d, "path", None),
        dir=path_value(ctx, d, "dir", ctx.base / "recordings") or ctx.base,
        chunk_size=integer(ctx, d, "chunk_size", 32 * 1024, 1024),
        flush_interval_s=number(ctx, d, "flush_interval_s", 1.0, positive=True),
        rotate_mb=number(ctx, d, "rotate_mb", None, positive=True),
        rotate_hours=number(ctx, d, "rotate_hours", None, positive=True),
        compression=string(ctx, d, "compression", "zstd", COMPRESSIONS) or "zstd",
        fsync=boolean(ctx, d, "fsync", True),
        backlog_mb=number(ctx, d, "backlog_mb", 4.0, positive=True))


def _checkpoint(ctx: Place, d: Any) -> CheckpointConfig:
    d = table(ctx, d, ("dir", "interval_s", "after_update_s"))
    after = number(ctx, d, "after_update_s", 5.0)
    if not after >= 0:
        raise ctx.error("after_update_s", f"expected seconds >= 0 (0 = off), got {after!r}")
    return CheckpointConfig(path_value(ctx, d, "dir", default_checkpoint_dir()),
                            number(ctx, d, "interval_s", 60.0, positive=True), after)


_PIPELINE_OWN = ("model", "mode", "plot_hz", "estimator", "buffer")
_PIPELINE_FIELDS = tuple(k for k in PIPELINE_KEYS if k not in ("rate_hz", "full_scale_g"))


def _typed(ctx: Place, d: Mapping[str, Any], cls: type, names: Sequence[str]) -> dict[str, Any]:
    """The keys of ``d`` that are fields of dataclass ``cls``, each checked against the type of
    the field's default (a number where the default is one, a string where it is one)."""
    defaults = {f.name: f.default for f in fields(cls)}
    out: dict[str, Any] = {}
    for k in names:
        if k not in d:
            continue
        default, v = defaults.get(k), d[k]
        if isinstance(default, bool):
            out[k] = boolean(ctx, d, k, default)
        elif isinstance(default, int):
            out[k] = integer(ctx, d, k, default, minimum=0)
        elif isinstance(default, float) or default is None:
            out[k] = number(ctx, d, k, default)
        elif isinstance(default, str):
            out[k] = string(ctx, d, k, default)
        else:
            out[k] = v
    return out


def _pipeline(ctx: Place, d: Any) -> PipelineSection:
    d = table(ctx, d, (*_PIPELINE_OWN, *_PIPELINE_FIELDS))
    est_fields = tuple(f.name for f in fields(EstimatorConfig) if f.name != "mode")
    ectx, bctx = ctx.sub("pipeline.estimator"), ctx.sub("pipeline.buffer")
    est = _typed(ectx, table(ectx, d.get("estimator", {}), est_fields), EstimatorConfig,
                 est_fields)
    buf_fields = tuple(f.name for f in fields(BufferConfig))
    buf = _typed(bctx, table(bctx, d.get("buffer", {}), buf_fields), BufferConfig, buf_fields)
    options = _typed(ctx, d, PipelineConfig, _PIPELINE_FIELDS)
    settings = PipelineSection(string(ctx, d, "model", "diagonal", MODELS) or "diagonal",
                                string(ctx, d, "mode", "all", MODES) or "all",
                                number(ctx, d, "plot_hz", 2.0, positive=True), options, est, buf)
    try:  # the core checks ranges and types; a sample rate is needed to build one
        settings.pipeline_config(100.0)
    except (TypeError, ValueError) as exc:
        raise ctx.error(None, f"invalid pipeline settings: {exc}") from None
    return settings


def _alignment(ctx: Place, d: Any) -> AlignmentConfig:
    d = table(ctx, d, ("enabled", "min_still_s", "tilt_limit_deg", "upright_max_deg",
                       "require_update", "max_offset_sd_mg", "request_interval_s"))
    return AlignmentConfig(boolean(ctx, d, "enabled", True),
                           number(ctx, d, "min_still_s", 10.0, positive=True),
                           number(ctx, d, "tilt_limit_deg", 7.0, positive=True),
                           number(ctx, d, "upright_max_deg", 30.0, positive=True),
                           boolean(ctx, d, "require_update", True),
                           number(ctx, d, "max_offset_sd_mg", 10.0, positive=True),
                           _nonnegative(ctx, d, "request_interval_s", 60.0))


def _batch_ms(ctx: Place, d: Mapping, key: str, default: float) -> float:
    v = number(ctx, d, key, default)
    if v < 0:
        raise ctx.error(key, f"expected 0 or more, got {v!r}")
    return float(v)


def _nonnegative(ctx: Place, d: Mapping, key: str, default: float) -> float:
    v = number(ctx, d, key, default)
    if v < 0:
        raise ctx.error(key, f"expected a number >= 0, got {v!r}")
    return float(v)


def _node(ctx: Place, d: Any) -> RemoteNodeConfig:
    d = table(ctx, d, ("accept_any", "max_sensors"))
    return RemoteNodeConfig(boolean(ctx, d, "accept_any", False),
                            integer(ctx, d, "max_sensors", 16))


def _discovery(ctx: Place, d: Any) -> RediscoveryConfig:
    d = table(ctx, d, ("enabled", "every_h", "first_h", "min_windows", "blocks",
                       "adopt_after_s", "capacity"))
    dflt = RediscoveryConfig()
    every = number(ctx, d, "every_h", dflt.every_h)
    if every < 0:
        raise ctx.error("every_h", f"expected hours >= 0 (0 = off), got {every!r}")
    first = number(ctx, d, "first_h", dflt.first_h)
    if not first > 0:
        raise ctx.error("first_h", f"expected hours > 0, got {first!r}")
    adopt = number(ctx, d, "adopt_after_s", dflt.adopt_after_s)
    if adopt < 0:
        raise ctx.error("adopt_after_s", f"expected seconds >= 0, got {adopt!r}")
    return RediscoveryConfig(boolean(ctx, d, "enabled", dflt.enabled), every, first,
                             integer(ctx, d, "min_windows", dflt.min_windows, 10),
                             integer(ctx, d, "blocks", dflt.blocks, 3), adopt,
                             integer(ctx, d, "capacity", dflt.capacity, 100))


def load_priors(path: Path) -> dict[str, PriorConfig]:
    """``[priors.<name>]`` tables of a priors file (ConfigError if bad)."""
    doc = read_toml(path)
    ctx = Place(path.name, "", path.parent)
    table(ctx, doc, ("priors",))
    named = table(ctx.sub("priors"), doc.get("priors", {}), tuple(doc.get("priors", {})))
    return {name: _prior(ctx.sub(f"priors.{name}"), d) for name, d in named.items()}


_TOP_KEYS = ("priors_file", "run_nodes", "batch_ms", "idle_batch_ms", "zenoh", "mcap",
             "checkpoint", "pipeline", "alignment", "sensors", "priors", "discovery", "node")


def parse_config(doc: Mapping[str, Any], base_dir: Path | str = ".",
                 name: str = "<config>") -> ServiceConfig:
    """Build a ServiceConfig from a parsed TOML document (paths relative to ``base_dir``)."""
    ctx = Place(name, "", Path(base_dir))
    doc = table(ctx, doc, _TOP_KEYS)
    priors: dict[str, PriorConfig] = {}
    priors_path = path_value(ctx, doc, "priors_file", None)
    if priors_path is not None:
        priors.update(load_priors(priors_path))
    inline = table(ctx.sub("priors"), doc.get("priors", {}), tuple(doc.get("priors", {})))
    priors.update({n: _prior(ctx.sub(f"priors.{n}"), d) for n, d in inline.items()})
    raw_sensors = doc.get("sensors", [])
    if not isinstance(raw_sensors, list):
        raise ctx.error("sensors", "expected [[sensors]] tables")
    sensors = tuple(_sensor(ctx.sub(f"sensors.{i}"), s, priors)
                    for i, s in enumerate(raw_sensors))
    ids = [s.id for s in sensors]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ctx.error("sensors", f"sensor id {dup[0]!r} appears twice")
    return ServiceConfig(
        sensors=sensors, zenoh=_zenoh(ctx.sub("zenoh"), doc.get("zenoh", {})),
        mcap=_mcap(ctx.sub("mcap"), doc.get("mcap", {})),
        checkpoint=_checkpoint(ctx.sub("checkpoint"), doc.get("checkpoint", {})),
        pipeline=_pipeline(ctx.sub("pipeline"), doc.get("pipeline", {})),
        alignment=_alignment(ctx.sub("alignment"), doc.get("alignment", {})),
        run_nodes=boolean(ctx, doc, "run_nodes", True),
        batch_ms=_batch_ms(ctx, doc, "batch_ms", 0.0),
        idle_batch_ms=_batch_ms(ctx, doc, "idle_batch_ms", 0.0),
        discovery=_discovery(ctx.sub("discovery"), doc.get("discovery", {})),
        node=_node(ctx.sub("node"), doc.get("node", {})), priors=priors)


def load_config(path: str | Path | None) -> ServiceConfig:
    """Read a TOML service config; None gives the defaults (no sensors). ConfigError if bad."""
    if path is None:
        return ServiceConfig()
    p = Path(path).expanduser()
    cfg = parse_config(read_toml(p), p.resolve().parent, p.name)
    return replace(cfg, source=p)

