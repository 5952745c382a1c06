"""Which parser reads which wire format: the one place a configured ``format`` becomes a parser.

The formats: `recal.io.ascii_lines` (``"ascii"``) and `recal.io.cobs_frames` (``"cobs"``); what
they share: `recal.io.frames`.
"""

from __future__ import annotations

from collections.abc import Sequence

from recal.errors import ConfigError
from recal.io.ascii_lines import AsciiLineParser
from recal.io.cobs_frames import CobsFrameParser

__all__ = ["make_parser"]


def make_parser(fmt: str, aux_names: Sequence[str] | None = None,
                **kwargs: float | int | bool) -> AsciiLineParser | CobsFrameParser:
    """A streaming parser for ``fmt`` "ascii" or "cobs"; kwargs go to its constructor."""
    if fmt == "ascii":
        return AsciiLineParser(aux_names, **kwargs)  # type: ignore[arg-type]
    if fmt == "cobs":
        return CobsFrameParser(aux_names, **kwargs)  # type: ignore[arg-type]
    raise ConfigError(f"unknown wire format {fmt!r}; expected 'ascii' or 'cobs'")
