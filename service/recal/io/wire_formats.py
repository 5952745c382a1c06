"""The wire formats by name: the one place a configured ``format`` becomes a parser, an
encoder and the format's options.

Each format's own module declares its :class:`recal.io.frames.WireFormat` (parser class,
device-side encoder, options); this module only lists them. A new format is its module plus
one entry in ``_DECLARED``. The formats: `recal.io.ascii_lines` (``"ascii"``, the default)
and `recal.io.cobs_frames` (``"cobs"``); what they share: `recal.io.frames`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType

from recal.errors import ConfigError
from recal.io import ascii_lines, cobs_frames
from recal.io.frames import FrameParser, WireFormat

__all__ = ["DEFAULT_FORMAT", "WIRE_FORMATS", "make_parser", "wire_format"]

_DECLARED = (ascii_lines.WIRE_FORMAT, cobs_frames.WIRE_FORMAT)

WIRE_FORMATS: Mapping[str, WireFormat] = MappingProxyType({f.name: f for f in _DECLARED})
DEFAULT_FORMAT = ascii_lines.WIRE_FORMAT.name


def wire_format(name: str) -> WireFormat:
    """The format called ``name``; ConfigError naming the known ones if there is none."""
    try:
        return WIRE_FORMATS[name]
    except KeyError:
        known = " or ".join(repr(n) for n in WIRE_FORMATS)
        raise ConfigError(f"unknown wire format {name!r}; expected {known}") from None


def make_parser(fmt: str, aux_names: Sequence[str] | None = None, *,
                rate_hz: float | None = None, **kwargs: float | int | bool) -> FrameParser:
    """A streaming parser for the format ``fmt``; kwargs go to its constructor.

    ``rate_hz`` (the configured sample rate) reaches the parser only where the format stamps
    records without time from it (``untimed_by_rate``); other formats take their time from
    each record and ignore it.
    """
    wire = wire_format(fmt)
    if rate_hz and wire.untimed_by_rate:
        kwargs["rate_hz"] = rate_hz
    return wire.parser(aux_names, **kwargs)
