"""Reading a TOML config file and checking its values: each check raises one
:class:`ConfigError` whose one-line message names the file, the table and the key
(``gateway.toml: [pipeline] threshold_g: expected a number, got 'x'``), so the command line can
print it without a traceback."""

from __future__ import annotations

import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from recal.errors import ConfigError

__all__ = ["Place", "boolean", "integer", "number", "numbers_by_name", "path_value",
           "read_config_text", "read_toml", "string", "strings", "table"]


class Place:
    """Where a value lives (file name and table), for error messages."""

    def __init__(self, name: str, table: str, base: Path) -> None:
        self.name, self.table, self.base = name, table, base

    def sub(self, table: str) -> Place:
        return Place(self.name, table, self.base)

    def error(self, key: str | None, problem: str) -> ConfigError:
        where = f"[{self.table}]" if self.table else "top level"
        what = f" {key}" if key else ""
        return ConfigError(f"{self.name}: {where}{what}: {problem}")


def table(ctx: Place, d: Any, allowed: Sequence[str]) -> dict[str, Any]:
    if not isinstance(d, Mapping):
        raise ctx.error(None, f"expected a table, got {type(d).__name__}")
    unknown = sorted(set(d) - set(allowed))
    if unknown:
        raise ctx.error(unknown[0], f"unknown key (expected one of {', '.join(allowed)})")
    return dict(d)


def number(ctx: Place, d: Mapping, key: str, default: Any, *, positive: bool = False,
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


def integer(ctx: Place, d: Mapping, key: str, default: int, minimum: int = 1) -> int:
    if key not in d:
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ctx.error(key, f"expected an integer >= {minimum}, got {v!r}")
    return int(v)


def boolean(ctx: Place, d: Mapping, key: str, default: bool) -> bool:
    if key not in d:
        return default
    if not isinstance(d[key], bool):
        raise ctx.error(key, f"expected true or false, got {d[key]!r}")
    return d[key]


def string(ctx: Place, d: Mapping, key: str, default: str | None,
           choices: Sequence[str] | None = None) -> str | None:
    if key not in d:
        return default
    v = d[key]
    if not isinstance(v, str):
        raise ctx.error(key, f"expected a string, got {v!r}")
    if choices is not None and v not in choices:
        raise ctx.error(key, f"expected one of {', '.join(choices)}, got {v!r}")
    return v


def strings(ctx: Place, d: Mapping, key: str) -> tuple[str, ...] | None:
    if key not in d:
        return None
    v = d[key]
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ctx.error(key, f"expected a list of strings, got {v!r}")
    return tuple(v)


def path_value(ctx: Place, d: Mapping, key: str, default: Path | None) -> Path | None:
    v = string(ctx, d, key, None)
    if v is None or v == "":
        return default if v is None else None
    p = Path(v).expanduser()
    return p if p.is_absolute() else ctx.base / p


def numbers_by_name(ctx: Place, d: Mapping, key: str) -> dict[str, float]:
    if key not in d:
        return {}
    v = d[key]
    if not isinstance(v, Mapping) or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in v.values()):
        raise ctx.error(key, f"expected a table of numbers by parameter name, got {v!r}")
    return {str(k): float(x) for k, x in v.items()}


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


def read_toml(path: Path) -> dict[str, Any]:
    text = read_config_text(path, "TOML config")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path.name}: not valid TOML: {exc}") from None

