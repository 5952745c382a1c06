"""The topic registry: every per-sensor stream recal names, in one table.

A topic is a suffix: MCAP topic ``/<sensor>/<suffix>`` in a recording, Zenoh key
``recal/<sensor>/<suffix>`` on the bus. Each record says what one message is (which codec),
the schema the log stores it under (None: never logged), and where it goes: published
(pub/sub), queryable (answers a get), live (a subscriber wants it with low latency, so the
gateway handles arrivals at once while someone listens), and whether a calibration node
emits it through its sink. The bus (`recal.io.bus`), the recording writer and reader, the
sinks and the gateway read this table; nothing else lists topics.

An unknown name fails where it is first resolved, with :class:`UnknownTopicError` naming the
known topics: at import or construction for the sets the components build (the bus's keys,
the gateway's live set, a sink's routes), instead of once per batch as a node error.

Adding an output: one record here, and the code that emits it (the node, through its sink).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

from recal.errors import RecalError
from recal.io.schemas import (
    CALIBRATED_SCHEMA,
    CALIBRATION_STATE_SCHEMA,
    EVENT_SCHEMA,
    GENERIC_JSON_SCHEMA,
    PLOT_SCHEMA,
    RAW_SCHEMA,
    SchemaSpec,
)

__all__ = ["TOPICS", "Payload", "Topic", "UnknownTopicError", "bus_topics", "live_topics",
           "log_schemas", "node_outputs", "published_topics", "queryable_topics", "require",
           "topic"]

Payload = Literal["raw", "calibrated", "json", "plot", "query"]
"""What one message is: a RawBatch, a CalibratedBatch, a JSON object, decimated PlotSamples
(log only), or the reply to a get (query topics have no message stream of their own)."""


class UnknownTopicError(RecalError, ValueError):
    """A topic name that is not in the registry (or not of the kind asked for)."""

    def __init__(self, name: str, known: Iterable[str], what: str = "topic") -> None:
        self.name = name
        self.known = tuple(known)
        super().__init__(f"unknown {what} {name!r}; known: {', '.join(self.known)}")


@dataclass(frozen=True, slots=True)
class Topic:
    """One topic of the layout (see the module notes)."""

    suffix: str
    payload: Payload
    schema: SchemaSpec | None  # the log's schema; None: not logged
    description: str
    published: bool = False  # pub/sub on recal/<sensor>/<suffix>
    queryable: bool = False  # answers a get on recal/<sensor>/<suffix>
    live: bool = False  # a subscriber wants it as samples arrive
    node_output: bool = False  # a calibration node emits it through its sink

    @property
    def logged(self) -> bool:
        """Whether a recording keeps it."""
        return self.schema is not None

    @property
    def on_bus(self) -> bool:
        """Whether it has a Zenoh key."""
        return self.published or self.queryable


_TABLE: tuple[Topic, ...] = (
    Topic("raw", "raw", RAW_SCHEMA, "a batch of raw samples",
          published=True, live=True, node_output=True),
    Topic("calibrated", "calibrated", CALIBRATED_SCHEMA, "the batch calibrated, sensor frame",
          published=True, live=True, node_output=True),
    Topic("body", "calibrated", CALIBRATED_SCHEMA,
          "the batch rotated to the body frame (the log keeps times and the rotation)",
          published=True, live=True, node_output=True),
    Topic("calibration", "json", CALIBRATION_STATE_SCHEMA, "calibration state after an update",
          published=True, node_output=True),
    Topic("status", "query", None, "answers a get with the current state", queryable=True),
    Topic("events", "json", EVENT_SCHEMA, "discrete events (gate rejections, resets, ...)",
          published=True, node_output=True),
    Topic("align", "query", None, "a get requests a re-alignment; the reply is the result",
          queryable=True),
    Topic("plot", "plot", PLOT_SCHEMA, "one calibrated sample, decimated (log only)",
          node_output=True),
    Topic("setup", "json", GENERIC_JSON_SCHEMA,
          "the pipeline's starting state, once per start (log only)", node_output=True),
)

TOPICS: dict[str, Topic] = {t.suffix: t for t in _TABLE}


def topic(name: str) -> Topic:
    """The record of ``name``; UnknownTopicError if there is none."""
    found = TOPICS.get(name)
    if found is None:
        raise UnknownTopicError(name, TOPICS)
    return found


def require(names: Iterable[str], payload: Payload | None = None) -> tuple[Topic, ...]:
    """The records of ``names`` (a component's topics, resolved once when it is built);
    UnknownTopicError for a name not registered or, with ``payload``, of another kind."""
    found = tuple(topic(n) for n in names)
    for t in found:
        if payload is not None and t.payload != payload:
            raise UnknownTopicError(t.suffix, _of(payload), f"{payload} topic")
    return found


def _of(payload: Payload) -> tuple[str, ...]:
    return tuple(t.suffix for t in _TABLE if t.payload == payload)


def bus_topics() -> tuple[str, ...]:
    """Suffixes with a Zenoh key, in the table's order."""
    return tuple(t.suffix for t in _TABLE if t.on_bus)


def published_topics() -> frozenset[str]:
    """Suffixes published pub/sub."""
    return frozenset(t.suffix for t in _TABLE if t.published)


def queryable_topics() -> frozenset[str]:
    """Suffixes answered by a queryable."""
    return frozenset(t.suffix for t in _TABLE if t.queryable)


def live_topics() -> tuple[str, ...]:
    """Suffixes whose subscribers want samples as they arrive, in the table's order."""
    return tuple(t.suffix for t in _TABLE if t.live)


def node_outputs() -> tuple[str, ...]:
    """Suffixes a calibration node emits through its sink, in the table's order."""
    return tuple(t.suffix for t in _TABLE if t.node_output)


def log_schemas() -> dict[str, SchemaSpec]:
    """Suffix -> the log's schema, for every logged topic."""
    return {t.suffix: t.schema for t in _TABLE if t.schema is not None}
