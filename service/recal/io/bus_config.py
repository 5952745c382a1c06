"""Zenoh session configuration that stays on loopback unless told otherwise.

Why: Zenoh's own defaults listen on every interface (``tcp/[::]:0`` for a peer,
``tcp/[::]:7447`` for a router), so :func:`zenoh_config` always writes explicit
``tcp/127.0.0.1:PORT`` endpoints and turns multicast scouting off. Deployment across hosts:
docs/design.md (bus).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import zenoh

from recal.errors import ConfigError, UsageError

__all__ = ["DEFAULT_ROUTER_ENDPOINT", "DEFAULT_ROUTER_PORT", "Mode", "loopback_endpoint",
           "zenoh_config"]

DEFAULT_ROUTER_PORT = 7447
DEFAULT_ROUTER_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_ROUTER_PORT}"

Mode = Literal["peer", "client", "router"]


def loopback_endpoint(port: int) -> str:
    """The Zenoh TCP endpoint ``tcp/127.0.0.1:<port>``."""
    if not 0 <= int(port) <= 65535:
        raise UsageError(f"port out of range: {port}")
    return f"tcp/127.0.0.1:{int(port)}"


def _default_listen(mode: str) -> list[str]:
    # Port 0 lets a peer take any free loopback port; a client needs no listener; a router
    # needs a well-known port for clients to connect to.
    return {"peer": ["tcp/127.0.0.1:0"], "client": [], "router": [DEFAULT_ROUTER_ENDPOINT]}[mode]


def _default_connect(mode: str) -> list[str]:
    return [DEFAULT_ROUTER_ENDPOINT] if mode == "client" else []


def _listen_is_zenoh_default(config: zenoh.Config) -> bool:
    """True when nobody set ``listen/endpoints`` (Zenoh then listens on all interfaces)."""
    value = _get_json(config, "listen/endpoints")
    # Zenoh reports its per-mode default as a dict {"router": [...], "peer": [...]}.
    return value is None or (isinstance(value, dict) and "peer" in value and "router" in value)


def _get_json(config: zenoh.Config, path: str) -> Any:
    raw = config.get_json(path)
    return json.loads(raw) if isinstance(raw, str) else raw


def _insert(config: zenoh.Config, path: str, value: Any) -> None:
    config.insert_json5(path, json.dumps(value))


def zenoh_config(
    mode: Mode | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    multicast_scouting: bool | None = None,
    config_file: str | Path | None = None,
    *,
    gossip_scouting: bool | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """Build a :class:`zenoh.Config` that stays on loopback unless told otherwise.

    Without ``config_file`` every ``None`` argument takes a recal default: ``mode="peer"``;
    ``listen`` ``tcp/127.0.0.1:0`` (peer), none (client), ``tcp/127.0.0.1:7447`` (router);
    ``connect`` the local router for a client, none otherwise; multicast scouting off;
    gossip scouting on (it only travels over links the session already has, and two peers
    behind one router need it to find each other).

    With ``config_file`` (JSON5, :meth:`zenoh.Config.from_file`) the file wins for every
    argument left ``None``; explicit arguments override it. Two safety nets still apply: if the
    file sets no listen endpoints we use the loopback default instead of Zenoh's all-interfaces
    one, and if it does not mention multicast scouting we turn it off.

    ``overrides`` maps Zenoh config paths to values inserted last, e.g.
    ``{"connect/timeout_ms": 5000, "connect/retry": {"period_init_ms": 100,
    "period_max_ms": 500}}``. Zenoh 1.10 rejects paths below an unset section
    (``connect/retry/period_max_ms`` raises "unknown key"): insert the whole section.

    Raises ``zenoh.ZError`` for a malformed file or value, ConfigError for a bad mode.
    """
    if mode is not None and mode not in ("peer", "client", "router"):
        raise ConfigError(f"mode must be 'peer', 'client' or 'router', got {mode!r}")
    if config_file is not None:
        config = zenoh.Config.from_file(str(config_file))
    else:
        config = zenoh.Config()
        mode = mode or "peer"
        listen = _default_listen(mode) if listen is None else listen
        connect = _default_connect(mode) if connect is None else connect
        gossip_scouting = True if gossip_scouting is None else gossip_scouting
    _apply_settings(config, mode, listen, connect, multicast_scouting, gossip_scouting)
    for path, value in (overrides or {}).items():
        _insert(config, path, value)
    return config


def _apply_settings(
    config: zenoh.Config,
    mode: str | None,
    listen: Sequence[str] | None,
    connect: Sequence[str] | None,
    multicast_scouting: bool | None,
    gossip_scouting: bool | None,
) -> None:
    """Write the explicit settings, then the loopback safety nets, into ``config``."""
    if mode is not None:
        _insert(config, "mode", mode)
    if listen is not None:
        _insert(config, "listen/endpoints", list(listen))
    if connect is not None:
        _insert(config, "connect/endpoints", list(connect))
    if multicast_scouting is not None:
        _insert(config, "scouting/multicast/enabled", bool(multicast_scouting))
    if gossip_scouting is not None:
        _insert(config, "scouting/gossip/enabled", bool(gossip_scouting))
    effective_mode = _get_json(config, "mode") or "peer"
    if _listen_is_zenoh_default(config):
        _insert(config, "listen/endpoints", _default_listen(effective_mode))
    if _get_json(config, "scouting/multicast/enabled") is None:
        _insert(config, "scouting/multicast/enabled", False)


