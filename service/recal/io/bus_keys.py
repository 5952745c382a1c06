"""Zenoh key expressions of recal: ``recal/<sensor>/<topic>``, the topics being the
registry's (`recal.io.topics`) that have a bus key. Layout and wildcards: `recal.io.bus`."""

from __future__ import annotations

from recal.errors import UsageError
from recal.io import topics

__all__ = ["KEY_ROOT", "QUERYABLE_TOPICS", "TOPICS", "key", "key_pattern", "parse_key",
           "sensor_of", "validate_sensor_id"]

KEY_ROOT = "recal"
TOPICS: tuple[str, ...] = topics.bus_topics()
QUERYABLE_TOPICS: frozenset[str] = topics.queryable_topics()
_BUS_TOPICS = frozenset(TOPICS)

# Characters with a meaning in Zenoh key expressions (chunk separator, wildcards, DSL markers).
_FORBIDDEN_SENSOR_CHARS = frozenset("/*$?#")
_MAX_SENSOR_ID_LEN = 128

# --------------------------------------------------------------------------- key expressions


def validate_sensor_id(sensor: str) -> str:
    """Return ``sensor`` if it can be one key-expression chunk, else raise UsageError.

    A sensor id must be a non-empty printable string of at most 128 characters without
    ``/``, ``*``, ``$``, ``?`` or ``#`` (Zenoh gives those a meaning).
    """
    if not isinstance(sensor, str) or not sensor:
        raise UsageError(f"sensor id must be a non-empty string, got {sensor!r}")
    if len(sensor) > _MAX_SENSOR_ID_LEN:
        raise UsageError(f"sensor id longer than {_MAX_SENSOR_ID_LEN} characters: {sensor!r}")
    bad = sorted(set(sensor) & _FORBIDDEN_SENSOR_CHARS)
    if bad:
        raise UsageError(f"sensor id {sensor!r} contains forbidden characters {bad}")
    if not sensor.isprintable():
        raise UsageError(f"sensor id {sensor!r} contains non-printable characters")
    return sensor


def _validate_topic(topic: str) -> str:
    if topic not in _BUS_TOPICS:
        raise topics.UnknownTopicError(topic, TOPICS, "bus topic")
    return topic



def key(sensor: str, topic: str) -> str:
    """Build the concrete key ``recal/<sensor>/<topic>`` after validating both parts."""
    return f"{KEY_ROOT}/{validate_sensor_id(sensor)}/{_validate_topic(topic)}"


def key_pattern(topic: str) -> str:
    """Key expression matching ``topic`` for every sensor, e.g. ``recal/*/raw``."""
    return f"{KEY_ROOT}/*/{_validate_topic(topic)}"


def parse_key(key_expr: str) -> tuple[str, str]:
    """Split a concrete received key ``recal/<sensor>/<topic>`` into ``(sensor, topic)``.

    Raises ValueError for anything outside the layout (other roots, wildcards, unknown topics).
    """
    parts = str(key_expr).split("/")
    if len(parts) != 3 or parts[0] != KEY_ROOT:
        raise ValueError(f"key {key_expr!r} is not of the form {KEY_ROOT}/<sensor>/<topic>")
    return validate_sensor_id(parts[1]), _validate_topic(parts[2])


def sensor_of(key_expr: str) -> str:
    """The sensor id in a concrete key ``recal/<sensor>/<topic>``."""
    return parse_key(key_expr)[0]
