"""Service configuration: a TOML file (``configs/gateway.toml``) -> frozen dataclasses.

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
    [discovery] every_h = 0 (off), min_windows = 60, blocks = 10: rediscover effects on the
                live buffer (recal.core.discovery) and continue with the extended model
    [[sensors]] id, port, format = "ascii"|"cobs", baudrate, aux_names, rate_hz,
                full_scale_g, model, prior = "<name in priors_file>" | { inline table }

A prior (inline, or ``[priors.<name>]`` in the priors file): ``counts_per_g`` (nominal
sensitivity s0, raw units per g), ``zero_g`` (the reading at 0 g, raw units: one number or
three), optional ``mean`` and ``sd`` tables by parameter name (``o_x`` ... ``s_z``, ``c_xy``
..., raw units) for a full prior, optional ``model_file`` (JSON: a SensorModel dict, or a
calibration state / model file with ``model`` and ``params``). Without ``counts_per_g`` and
without a model file the sensor bootstraps (no prior).
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from recal.core.buffer import BufferConfig
from recal.core.channels import missing_channels
from recal.core.estimator import EstimatorConfig, Prior
from recal.core.model import SensorModel
from recal.core.pipeline_config import KEYS as PIPELINE_KEYS
from recal.core.pipeline_config import PipelineConfig
from recal.errors import ConfigError

__all__ = [
    "AlignmentConfig",
    "CheckpointConfig",
    "ConfigError",
    "McapConfig",
    "NodeConfig",
    "PipelineSettings",
    "PriorConfig",
    "RediscoveryConfig",
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
]

FORMATS = ("ascii", "cobs")
MODELS = ("diagonal", "full")
MODES = ("all", "offsets")
ZENOH_MODES = ("peer", "client", "router")
COMPRESSIONS = ("zstd", "lz4", "none")


# ---------------------------------------------------------------------------------------------
# Dataclasses
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PriorConfig:
    """What is known about a sensor before it is worn.

    Attributes:
        counts_per_g: nominal sensitivity s0 in raw units per g (None: unknown, bootstrap).
        zero_g: the reading at 0 g per axis, raw units (the offsets' prior mean).
        mean: prior mean by parameter name (raw units), overriding the two above.
        sd: prior standard deviation by parameter name (raw units), else the model default.
        model_file: JSON model / calibration file (see :func:`load_model_file`).
    """

    counts_per_g: float | None = None
    zero_g: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mean: Mapping[str, float] = field(default_factory=dict)
    sd: Mapping[str, float] = field(default_factory=dict)
    model_file: Path | None = None

    @property
    def known(self) -> bool:
        return self.counts_per_g is not None or self.model_file is not None


@dataclass(frozen=True)
class SensorConfig:
    """One sensor on one serial port.

    Attributes:
        id: sensor id (topic- and key-safe: ``[A-Za-z0-9][A-Za-z0-9_.-]*``).
        port: device path or pyserial URL (None: only a remote node sees this sensor).
        format: wire format, "ascii" lines or "cobs" frames.
        baudrate: UART rate (ignored by ptys).
        aux_names: auxiliary channels (None: learnt from the stream's header).
        rate_hz: nominal sample rate, Hz (None: inferred from the time stamps).
        full_scale_g: sensor range in g, for clipping detection (None: off).
        model: "diagonal" or "full" (None: the [pipeline] model).
        prior: the pre-calibration.
    """

    id: str
    port: str | None = None
    format: str = "ascii"
    baudrate: int = 115200
    aux_names: tuple[str, ...] | None = None
    rate_hz: float | None = None
    full_scale_g: float | None = None
    model: str | None = None
    prior: PriorConfig = field(default_factory=PriorConfig)


@dataclass(frozen=True)
class ZenohSettings:
    """Zenoh session settings (see recal.io.bus_config.zenoh_config; loopback unless told
    otherwise)."""

    enabled: bool = True
    mode: str | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] | None = None
    config_file: Path | None = None


@dataclass(frozen=True)
class McapConfig:
    """Where and how the gateway logs.

    Attributes:
        path: the recording file (an existing one is never overwritten: a time-stamped name
            next to it is used instead). None: an auto-named file in ``dir``.
        dir: directory for auto-named recordings ``recal-<UTC time>.mcap``.
        chunk_size: uncompressed bytes per MCAP chunk (small chunks bound crash loss).
        flush_interval_s: longest time a message stays unflushed, seconds.
        rotate_mb, rotate_hours: start a new part after this size / this time (None: never).
        compression: "zstd", "lz4" or "none".
        fsync: fsync at every flush.
        backlog_mb: while the disk refuses writes (full), up to this much of the recording
            (compressed) waits in memory for it; beyond it the oldest is dropped and counted.
            Reading, calibrating and publishing go on either way.
    """

    path: Path | None = None
    dir: Path = Path("recordings")
    chunk_size: int = 32 * 1024
    flush_interval_s: float = 1.0
    rotate_mb: float | None = None
    rotate_hours: float | None = None
    compression: str = "zstd"
    fsync: bool = True
    backlog_mb: float = 4.0


BY_ID_DIR = Path("/dev/serial/by-id")  # udev's stable names of USB serial devices
_NOT_IN_ID = re.compile(r"[^A-Za-z0-9_.-]+")


def default_sensor_id(port: str, by_id_dir: str | Path = BY_ID_DIR,
                      listed: Sequence[Any] | None = None) -> str:
    """The id of a sensor given only its ``port``: the device's own name, so that two devices
    never share a calibration (and a device keeps its own on another port).

    In order: the name of the ``by_id_dir`` link that points at the port's device
    (``usb-Arduino_LLC_Nano_33_IoT_4F3A9C2E-if00``); else the USB serial number pyserial's
    ``list_ports`` gives for it (``usb-<vid>-<pid>-<serial>``; ``listed``: its entries, by
    default read now); else the port's path (``/dev/ttyUSB0`` -> ``ttyUSB0``,
    ``/tmp/a/tty0`` -> ``tmp-a-tty0``). Made fit for the id's charset
    ``[A-Za-z0-9][A-Za-z0-9_.-]*``."""
    if "://" in port:
        return _id_from(port.split("://", 1)[0])
    device = os.path.realpath(port)
    try:
        links = sorted(Path(by_id_dir).iterdir())
    except OSError:  # no USB serial device plugged, or not Linux
        links = []
    for link in links:
        if os.path.realpath(link) == device:
            return _id_from(link.name)
    if listed is None:
        from serial.tools import list_ports

        listed = list_ports.comports()
    for info in listed:
        if os.path.realpath(info.device) == device and info.serial_number:
            vid_pid = (f"{info.vid:04x}-{info.pid:04x}-" if info.vid is not None
                       and info.pid is not None else "")
            return _id_from(f"usb-{vid_pid}{info.serial_number}")
    path = port.removeprefix("/dev/") if port.startswith("/dev/") else port
    return _id_from(path.strip("/").replace("/", "-"))


def _id_from(name: str) -> str:
    sid = _NOT_IN_ID.sub("_", name).lstrip("_.-")
    return sid if sid and sid != "gateway" else f"port-{sid or 'unnamed'}"


def default_state_dir() -> Path:
    """Where recal keeps its state when the config does not say, never the current directory:
    systemd's ``StateDirectory=`` (it sets ``$STATE_DIRECTORY``), else ``$XDG_STATE_HOME/recal``,
    else ``/var/lib/recal`` for root, else ``~/.local/state/recal``."""
    systemd = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    if systemd:
        return Path(systemd)
    xdg = os.environ.get("XDG_STATE_HOME", "")
    if xdg and Path(xdg).is_absolute():  # the XDG spec: a relative value is to be ignored
        return Path(xdg) / "recal"
    if os.geteuid() == 0:
        return Path("/var/lib/recal")
    return Path.home() / ".local" / "state" / "recal"


def default_checkpoint_dir() -> Path:
    return default_state_dir() / "checkpoints"


@dataclass(frozen=True)
class CheckpointConfig:
    """Pipeline checkpoints: ``<dir>/<sensor>.json`` (see recal.checkpoints), every
    ``interval_s``, within ``after_update_s`` of an accepted update (at most that often;
    0: off), and at stop. ``dir`` None: none kept."""

    dir: Path | None = field(default_factory=default_checkpoint_dir)
    interval_s: float = 60.0
    after_update_s: float = 5.0


@dataclass(frozen=True)
class PipelineSettings:
    """Calibration settings shared by every sensor (rate and range come per sensor).

    Attributes:
        model: "diagonal" (Lötters, 6 parameters) or "full" (9, with cross-axis).
        mode: "all" parameters or "offsets" only (Lötters' two modes).
        plot_hz: rate of the decimated per-sample plot topic, Hz (2: each plot message costs
            about 47 bytes on disk, the record and its index entry; docs/design.md).
        options: further PipelineConfig fields (threshold_g, window_s, ...).
        estimator, buffer: EstimatorConfig / BufferConfig fields.
    """

    model: str = "diagonal"
    mode: str = "all"
    plot_hz: float = 2.0
    options: Mapping[str, Any] = field(default_factory=dict)
    estimator: Mapping[str, Any] = field(default_factory=dict)
    buffer: Mapping[str, Any] = field(default_factory=dict)

    def pipeline_config(self, rate_hz: float, full_scale_g: float | None = None
                        ) -> PipelineConfig:
        """The core PipelineConfig for one sensor."""
        est = EstimatorConfig(**{"mode": self.mode, **self.estimator})
        return PipelineConfig.of(**{**self.options, "rate_hz": float(rate_hz),
                                    "full_scale_g": full_scale_g},
                                 estimator=est, buffer=BufferConfig(**self.buffer))

    def plot_every(self, rate_hz: float) -> int:
        """Decimation factor that gives about ``plot_hz`` plot messages per second."""
        return max(1, round(rate_hz / self.plot_hz)) if self.plot_hz > 0 else 1


@dataclass(frozen=True)
class AlignmentConfig:
    """Mounting alignment (Zheng et al.).

    Attributes:
        enabled: look for a reference posture at all.
        min_still_s: a quasi-static run this long is a reference posture, seconds.
        tilt_limit_deg: alarm when the mounting slips farther than this from the reference,
            degrees (Zheng's 7°; the rule is recal.core.alignment.SlipWatch's).
        upright_max_deg: an automatic reference must be within this angle of the sensor's +z
            (otherwise the wearer is lying, not upright), degrees.
        require_update: wait for one accepted calibration update before the reference.
        max_offset_sd_mg: ... and until the x/y offsets are known this well (posterior sd, mg):
            an offset error of e mg tilts the reference by about e/1000 rad (17 mg ≈ 1°;
            the first updates, made on one or two postures, are not that good yet).
        request_interval_s: a re-alignment request (query on recal/<sensor>/align) less than
            this long after the last one accepted is refused, seconds (0: never refused).
    """

    enabled: bool = True
    min_still_s: float = 10.0
    tilt_limit_deg: float = 7.0
    upright_max_deg: float = 30.0
    require_update: bool = True
    max_offset_sd_mg: float = 10.0
    request_interval_s: float = 60.0


@dataclass(frozen=True)
class NodeConfig:
    """Which sensors a calibration node on the bus (`recal node`) serves.

    Attributes:
        accept_any: serve any sensor that publishes recal/<id>/raw, not only the configured
            ones (a stranger's stream is then logged, calibrated and checkpointed too).
        max_sensors: with accept_any, serve at most this many sensors; later ids are dropped.
    """

    accept_any: bool = False
    max_sensors: int = 16


@dataclass(frozen=True)
class RediscoveryConfig:
    """Periodic effect discovery on a node's live window buffer (off by default).

    Attributes:
        every_h: device hours between runs; 0 = never.
        min_windows: fewer buffered windows than this and the run is skipped.
        blocks: held-out time blocks (see recal.core.discovery.DiscoveryConfig).
        adopt_after_s: a run works on a copy of the buffer in a thread of its own (1-2 s of
            CPU) while the node goes on calibrating; its result is taken on at the first batch
            this many device seconds after it started, waiting for it then if need be, so a
            replay (which gets there sooner) adopts it at the same sample as the live node.
    """

    every_h: float = 0.0
    min_windows: int = 60
    blocks: int = 10
    adopt_after_s: float = 60.0

    @property
    def enabled(self) -> bool:
        return self.every_h > 0


@dataclass(frozen=True)
class ServiceConfig:
    """The whole service configuration."""

    sensors: tuple[SensorConfig, ...] = ()
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    mcap: McapConfig = field(default_factory=McapConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    pipeline: PipelineSettings = field(default_factory=PipelineSettings)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    run_nodes: bool = True
    batch_ms: float = 0.0
    idle_batch_ms: float = 0.0
    source: Path | None = None
    discovery: RediscoveryConfig = field(default_factory=RediscoveryConfig)
    node: NodeConfig = field(default_factory=NodeConfig)
    #: the named priors the config defines (``priors_file`` and ``[priors.<name>]``), by name
    priors: Mapping[str, PriorConfig] = field(default_factory=dict)

    def sensor(self, sensor_id: str) -> SensorConfig | None:
        return next((s for s in self.sensors if s.id == sensor_id), None)

    def with_sensors(self, sensors: Sequence[SensorConfig]) -> ServiceConfig:
        return replace(self, sensors=tuple(sensors))


# ---------------------------------------------------------------------------------------------
# Parsing helpers: each raises ConfigError naming where the value came from
# ---------------------------------------------------------------------------------------------

class _Ctx:
    """Where a value lives (file name and table), for error messages."""

    def __init__(self, name: str, table: str, base: Path) -> None:
        self.name, self.table, self.base = name, table, base

    def sub(self, table: str) -> _Ctx:
        return _Ctx(self.name, table, self.base)

    def error(self, key: str | None, problem: str) -> ConfigError:
        where = f"[{self.table}]" if self.table else "top level"
        what = f" {key}" if key else ""
        return ConfigError(f"{self.name}: {where}{what}: {problem}")


def _table(ctx: _Ctx, d: Any, allowed: Sequence[str]) -> dict[str, Any]:
    if not isinstance(d, Mapping):
        raise ctx.error(None, f"expected a table, got {type(d).__name__}")
    unknown = sorted(set(d) - set(allowed))
    if unknown:
        raise ctx.error(unknown[0], f"unknown key (expected one of {', '.join(allowed)})")
    return dict(d)


def _num(ctx: _Ctx, d: Mapping, key: str, default: Any, *, positive: bool = False,
         allow_none: bool = False) -> Any:
    if key not in d:
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        if allow_none and v in ("", "none", "None"):
            return None
        raise ctx.error(key, f"expected a number, got {v!r}")
    if not np.isfinite(v) or (positive and v <= 0):
        raise ctx.error(key, f"expected a {'positive ' if positive else ''}finite number, "
                             f"got {v!r}")
    return float(v)


def _int(ctx: _Ctx, d: Mapping, key: str, default: int, minimum: int = 1) -> int:
    if key not in d:
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ctx.error(key, f"expected an integer >= {minimum}, got {v!r}")
    return int(v)


def _bool(ctx: _Ctx, d: Mapping, key: str, default: bool) -> bool:
    if key not in d:
        return default
    if not isinstance(d[key], bool):
        raise ctx.error(key, f"expected true or false, got {d[key]!r}")
    return d[key]


def _str(ctx: _Ctx, d: Mapping, key: str, default: str | None,
         choices: Sequence[str] | None = None) -> str | None:
    if key not in d:
        return default
    v = d[key]
    if not isinstance(v, str):
        raise ctx.error(key, f"expected a string, got {v!r}")
    if choices is not None and v not in choices:
        raise ctx.error(key, f"expected one of {', '.join(choices)}, got {v!r}")
    return v


def _strings(ctx: _Ctx, d: Mapping, key: str) -> tuple[str, ...] | None:
    if key not in d:
        return None
    v = d[key]
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ctx.error(key, f"expected a list of strings, got {v!r}")
    return tuple(v)


def _path(ctx: _Ctx, d: Mapping, key: str, default: Path | None) -> Path | None:
    v = _str(ctx, d, key, None)
    if v is None or v == "":
        return default if v is None else None
    p = Path(v).expanduser()
    return p if p.is_absolute() else ctx.base / p


def _batch_ms(ctx: _Ctx, d: Mapping, key: str, default: float) -> float:
    v = _num(ctx, d, key, default)
    if v < 0:
        raise ctx.error(key, f"expected 0 or more, got {v!r}")
    return float(v)


def _numbers(ctx: _Ctx, d: Mapping, key: str) -> dict[str, float]:
    if key not in d:
        return {}
    v = d[key]
    if not isinstance(v, Mapping) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in v.values()):
        raise ctx.error(key, f"expected a table of numbers by parameter name, got {v!r}")
    return {str(k): float(x) for k, x in v.items()}


# ---------------------------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------------------------

_PRIOR_KEYS = ("counts_per_g", "zero_g", "mean", "sd", "model_file")


def _prior(ctx: _Ctx, d: Any) -> PriorConfig:
    d = _table(ctx, d, _PRIOR_KEYS)
    zero = d.get("zero_g", 0.0)
    if isinstance(zero, (int, float)) and not isinstance(zero, bool):
        zero3 = (float(zero),) * 3
    elif (isinstance(zero, list) and len(zero) == 3
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in zero)):
        zero3 = tuple(float(x) for x in zero)
    else:
        raise ctx.error("zero_g", f"expected a number or a list of 3 numbers, got {zero!r}")
    return PriorConfig(_num(ctx, d, "counts_per_g", None, positive=True), zero3,  # type: ignore[arg-type]
                       _numbers(ctx, d, "mean"), _numbers(ctx, d, "sd"),
                       _path(ctx, d, "model_file", None))


_SENSOR_KEYS = ("id", "port", "format", "baudrate", "aux_names", "rate_hz", "full_scale_g",
                "model", "prior")


def _sensor(ctx: _Ctx, d: Any, priors: Mapping[str, PriorConfig]) -> SensorConfig:
    d = _table(ctx, d, _SENSOR_KEYS)
    sid = _str(ctx, d, "id", None)
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
        id=sid, port=_str(ctx, d, "port", None), format=_str(ctx, d, "format", "ascii",
                                                               FORMATS) or "ascii",
        baudrate=_int(ctx, d, "baudrate", 115200),
        aux_names=_strings(ctx, d, "aux_names"),
        rate_hz=_num(ctx, d, "rate_hz", None, positive=True),
        full_scale_g=_num(ctx, d, "full_scale_g", None, positive=True),
        model=_str(ctx, d, "model", None, MODELS), prior=prior)


def _check_sensor_id(ctx: _Ctx, sid: str) -> None:
    from recal.io.recording import sensor_topic  # the one rule shared by MCAP and Zenoh

    try:
        sensor_topic(sid, "raw")
    except ValueError as exc:
        raise ctx.error("id", str(exc)) from None


def _zenoh(ctx: _Ctx, d: Any) -> ZenohSettings:
    d = _table(ctx, d, ("enabled", "mode", "listen", "connect", "config_file"))
    return ZenohSettings(_bool(ctx, d, "enabled", True), _str(ctx, d, "mode", None, ZENOH_MODES),
                         _strings(ctx, d, "listen"), _strings(ctx, d, "connect"),
                         _path(ctx, d, "config_file", None))


def _mcap(ctx: _Ctx, d: Any) -> McapConfig:
    d = _table(ctx, d, ("path", "dir", "chunk_size", "flush_interval_s", "rotate_mb",
                        "rotate_hours", "compression", "fsync", "backlog_mb"))
    return McapConfig(
        path=_path(ctx, d, "path", None), dir=_path(ctx, d, "dir", ctx.base / "recordings")
        or ctx.base, chunk_size=_int(ctx, d, "chunk_size", 32 * 1024, 1024),
        flush_interval_s=_num(ctx, d, "flush_interval_s", 1.0, positive=True),
        rotate_mb=_num(ctx, d, "rotate_mb", None, positive=True),
        rotate_hours=_num(ctx, d, "rotate_hours", None, positive=True),
        compression=_str(ctx, d, "compression", "zstd", COMPRESSIONS) or "zstd",
        fsync=_bool(ctx, d, "fsync", True),
        backlog_mb=_num(ctx, d, "backlog_mb", 4.0, positive=True))


def _checkpoint(ctx: _Ctx, d: Any) -> CheckpointConfig:
    d = _table(ctx, d, ("dir", "interval_s", "after_update_s"))
    after = _num(ctx, d, "after_update_s", 5.0)
    if not after >= 0:
        raise ctx.error("after_update_s", f"expected seconds >= 0 (0 = off), got {after!r}")
    return CheckpointConfig(_path(ctx, d, "dir", default_checkpoint_dir()),
                            _num(ctx, d, "interval_s", 60.0, positive=True), after)


_PIPELINE_OWN = ("model", "mode", "plot_hz", "estimator", "buffer")
_PIPELINE_FIELDS = tuple(k for k in PIPELINE_KEYS if k not in ("rate_hz", "full_scale_g"))


def _typed(ctx: _Ctx, d: Mapping[str, Any], cls: type, names: Sequence[str]) -> dict[str, Any]:
    """The keys of ``d`` that are fields of dataclass ``cls``, each checked against the type of
    the field's default (a number where the default is one, a string where it is one)."""
    defaults = {f.name: f.default for f in fields(cls)}
    out: dict[str, Any] = {}
    for k in names:
        if k not in d:
            continue
        default, v = defaults.get(k), d[k]
        if isinstance(default, bool):
            out[k] = _bool(ctx, d, k, default)
        elif isinstance(default, int):
            out[k] = _int(ctx, d, k, default, minimum=0)
        elif isinstance(default, float) or default is None:
            out[k] = _num(ctx, d, k, default)
        elif isinstance(default, str):
            out[k] = _str(ctx, d, k, default)
        else:
            out[k] = v
    return out


def _pipeline(ctx: _Ctx, d: Any) -> PipelineSettings:
    d = _table(ctx, d, (*_PIPELINE_OWN, *_PIPELINE_FIELDS))
    est_fields = tuple(f.name for f in fields(EstimatorConfig) if f.name != "mode")
    ectx, bctx = ctx.sub("pipeline.estimator"), ctx.sub("pipeline.buffer")
    est = _typed(ectx, _table(ectx, d.get("estimator", {}), est_fields), EstimatorConfig,
                 est_fields)
    buf_fields = tuple(f.name for f in fields(BufferConfig))
    buf = _typed(bctx, _table(bctx, d.get("buffer", {}), buf_fields), BufferConfig, buf_fields)
    options = _typed(ctx, d, PipelineConfig, _PIPELINE_FIELDS)
    settings = PipelineSettings(_str(ctx, d, "model", "diagonal", MODELS) or "diagonal",
                                _str(ctx, d, "mode", "all", MODES) or "all",
                                _num(ctx, d, "plot_hz", 2.0, positive=True), options, est, buf)
    try:  # the core checks ranges and types; a sample rate is needed to build one
        settings.pipeline_config(100.0)
    except (TypeError, ValueError) as exc:
        raise ctx.error(None, f"invalid pipeline settings: {exc}") from None
    return settings


def _alignment(ctx: _Ctx, d: Any) -> AlignmentConfig:
    d = _table(ctx, d, ("enabled", "min_still_s", "tilt_limit_deg", "upright_max_deg",
                        "require_update", "max_offset_sd_mg", "request_interval_s"))
    return AlignmentConfig(_bool(ctx, d, "enabled", True),
                           _num(ctx, d, "min_still_s", 10.0, positive=True),
                           _num(ctx, d, "tilt_limit_deg", 7.0, positive=True),
                           _num(ctx, d, "upright_max_deg", 30.0, positive=True),
                           _bool(ctx, d, "require_update", True),
                           _num(ctx, d, "max_offset_sd_mg", 10.0, positive=True),
                           _nonnegative(ctx, d, "request_interval_s", 60.0))


def _nonnegative(ctx: _Ctx, d: Mapping, key: str, default: float) -> float:
    v = _num(ctx, d, key, default)
    if v < 0:
        raise ctx.error(key, f"expected a number >= 0, got {v!r}")
    return float(v)


def _node(ctx: _Ctx, d: Any) -> NodeConfig:
    d = _table(ctx, d, ("accept_any", "max_sensors"))
    return NodeConfig(_bool(ctx, d, "accept_any", False), _int(ctx, d, "max_sensors", 16))


def _discovery(ctx: _Ctx, d: Any) -> RediscoveryConfig:
    d = _table(ctx, d, ("every_h", "min_windows", "blocks", "adopt_after_s"))
    every = _num(ctx, d, "every_h", 0.0)
    if every < 0:
        raise ctx.error("every_h", f"expected hours >= 0 (0 = off), got {every!r}")
    adopt = _num(ctx, d, "adopt_after_s", 60.0)
    if adopt < 0:
        raise ctx.error("adopt_after_s", f"expected seconds >= 0, got {adopt!r}")
    return RediscoveryConfig(every, _int(ctx, d, "min_windows", 60, 10),
                             _int(ctx, d, "blocks", 10, 3), adopt)


def read_config_text(path: Path, what: str = "config") -> str:
    """The text of a config file; ConfigError (one line naming the file) for anything that is
    not readable UTF-8 text: missing, a directory, no permission, binary or another encoding."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: a directory, not a {what} file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a {what} file: not UTF-8 text (byte "
                          f"0x{data[exc.start]:02x} at offset {exc.start})") from None


def _read_toml(path: Path) -> dict[str, Any]:
    text = read_config_text(path, "TOML config")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path.name}: not valid TOML: {exc}") from None


def load_priors(path: Path) -> dict[str, PriorConfig]:
    """``[priors.<name>]`` tables of a priors file (ConfigError if bad)."""
    doc = _read_toml(path)
    ctx = _Ctx(path.name, "", path.parent)
    _table(ctx, doc, ("priors",))
    named = _table(ctx.sub("priors"), doc.get("priors", {}), tuple(doc.get("priors", {})))
    return {name: _prior(ctx.sub(f"priors.{name}"), d) for name, d in named.items()}


_TOP_KEYS = ("priors_file", "run_nodes", "batch_ms", "idle_batch_ms", "zenoh", "mcap",
             "checkpoint", "pipeline", "alignment", "sensors", "priors", "discovery", "node")


def parse_config(doc: Mapping[str, Any], base_dir: Path | str = ".",
                 name: str = "<config>") -> ServiceConfig:
    """Build a ServiceConfig from a parsed TOML document (paths relative to ``base_dir``)."""
    ctx = _Ctx(name, "", Path(base_dir))
    doc = _table(ctx, doc, _TOP_KEYS)
    priors: dict[str, PriorConfig] = {}
    priors_path = _path(ctx, doc, "priors_file", None)
    if priors_path is not None:
        priors.update(load_priors(priors_path))
    inline = _table(ctx.sub("priors"), doc.get("priors", {}), tuple(doc.get("priors", {})))
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
        run_nodes=_bool(ctx, doc, "run_nodes", True),
        batch_ms=_batch_ms(ctx, doc, "batch_ms", 0.0),
        idle_batch_ms=_batch_ms(ctx, doc, "idle_batch_ms", 0.0),
        discovery=_discovery(ctx.sub("discovery"), doc.get("discovery", {})),
        node=_node(ctx.sub("node"), doc.get("node", {})), priors=priors)


def load_config(path: str | Path | None) -> ServiceConfig:
    """Read a TOML service config; None gives the defaults (no sensors). ConfigError if bad."""
    if path is None:
        return ServiceConfig()
    p = Path(path).expanduser()
    cfg = parse_config(_read_toml(p), p.resolve().parent, p.name)
    return replace(cfg, source=p)


# ---------------------------------------------------------------------------------------------
# Model and prior of a sensor
# ---------------------------------------------------------------------------------------------

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
    return SensorModel.full(s0) if name == "full" else SensorModel.diagonal(s0)


def model_and_prior(sensor: SensorConfig, settings: PipelineSettings,
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
