"""The service's settings: frozen dataclasses, one per table of the TOML file
(``configs/gateway.toml``; the layout and its checks are in :mod:`recal.config.loading`), and
the defaults that depend on the machine (the state folder, a sensor's id from its port)."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from recal.core.buffer import BufferConfig
from recal.core.estimator import EstimatorConfig
from recal.core.pipeline_config import PipelineConfig
from recal.errors import ConfigError
from recal.io.wire_formats import DEFAULT_FORMAT

__all__ = [
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
    "default_checkpoint_dir",
    "default_sensor_id",
    "default_state_dir",
]


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
        format: wire format, a name in `recal.io.wire_formats` ("ascii" lines, "cobs" frames).
        baudrate: UART rate (ignored by ptys).
        aux_names: auxiliary channels (None: learnt from the stream's header).
        rate_hz: nominal sample rate, Hz (None: inferred from the time stamps).
        full_scale_g: sensor range in g, for clipping detection (None: off).
        model: "diagonal" or "full" (None: the [pipeline] model).
        prior: the pre-calibration.
    """

    id: str
    port: str | None = None
    format: str = DEFAULT_FORMAT
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
    """Pipeline checkpoints: ``<dir>/<sensor>.json`` (see recal.daemon.checkpoint_store), every
    ``interval_s``, within ``after_update_s`` of an accepted update (at most that often;
    0: off), and at stop. ``dir`` None: none kept."""

    dir: Path | None = field(default_factory=default_checkpoint_dir)
    interval_s: float = 60.0
    after_update_s: float = 5.0


@dataclass(frozen=True)
class PipelineSection:
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
class RemoteNodeConfig:
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
    """Effect discovery on a node's own evidence (`recal.core.evidence`), on by default.

    The schedule (docs/design.md, effect discovery step 8): a run every ``first_h`` device
    hours for the first hour, then each time the evidence has doubled in time, the gap never
    longer than ``every_h``; a run with fewer than ``min_windows`` windows held is skipped.

    Attributes:
        enabled: False: never (so does every_h = 0, as in older configuration files).
        every_h: the longest gap between runs, device hours.
        first_h: device hours from the stream's start to the first run.
        min_windows: fewer windows held than this and the run is skipped.
        blocks: held-out time blocks (see recal.core.discovery.DiscoveryConfig).
        adopt_after_s: a run works on a copy of the evidence apart from the node (seconds
            of CPU) while the node goes on calibrating; its result is taken on at the first
            batch this many device seconds after it started, waiting for it then if need be,
            so a replay (which gets there sooner) adopts it at the same sample as the live
            node.
        capacity: windows the evidence keeps (`core.evidence.EvidenceConfig`).
    """

    enabled: bool = True
    every_h: float = 2.0
    first_h: float = 1.0 / 6.0
    min_windows: int = 60
    blocks: int = 10
    adopt_after_s: float = 60.0
    capacity: int = 2048

    @property
    def active(self) -> bool:
        return self.enabled and self.every_h > 0


@dataclass(frozen=True)
class ServiceConfig:
    """The whole service configuration."""

    sensors: tuple[SensorConfig, ...] = ()
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    mcap: McapConfig = field(default_factory=McapConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    pipeline: PipelineSection = field(default_factory=PipelineSection)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    run_nodes: bool = True
    batch_ms: float = 0.0
    idle_batch_ms: float = 0.0
    source: Path | None = None
    discovery: RediscoveryConfig = field(default_factory=RediscoveryConfig)
    node: RemoteNodeConfig = field(default_factory=RemoteNodeConfig)
    #: the named priors the config defines (``priors_file`` and ``[priors.<name>]``), by name
    priors: Mapping[str, PriorConfig] = field(default_factory=dict)

    def sensor(self, sensor_id: str) -> SensorConfig | None:
        return next((s for s in self.sensors if s.id == sensor_id), None)

    def with_sensors(self, sensors: Sequence[SensorConfig]) -> ServiceConfig:
        return replace(self, sensors=tuple(sensors))

