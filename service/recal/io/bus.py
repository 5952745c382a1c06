"""Zenoh adapter: key expressions and a byte-level bus.

This module moves bytes and strings. It knows nothing about the calibration algebra or the
payload codecs (``recal.io.messages`` turns messages into bytes and back).

Key-expression layout (one sensor id per chunk, see :func:`validate_sensor_id`; the topics are
the registry's, `recal.io.topics`, that have a bus key; the rules are `recal.io.bus_keys`)::

    recal/<sensor>/raw          pub/sub  raw samples from the gateway
    recal/<sensor>/calibrated   pub/sub  calibrated samples in the sensor frame
    recal/<sensor>/body         pub/sub  calibrated samples rotated into the body frame
    recal/<sensor>/calibration  pub/sub  calibration state (parameters, covariance, ...)
    recal/<sensor>/status       query    answers a get with the current state bytes
    recal/<sensor>/events       pub/sub  discrete events (gate rejections, resets, ...)
    recal/<sensor>/align        query    request a mounting re-alignment; the reply is the result

Wildcards select several sensors at once: ``recal/*/raw`` (every sensor's raw stream; the
sensor id comes back with :func:`parse_key`) or ``recal/<sensor>/**`` (everything about one).

Session configuration (loopback unless told otherwise) is `recal.io.bus_config`; the entities
declared on a session (publisher, subscription, receiver, queryable) are `recal.io.bus_entities`.

Threading: subscriber and queryable callbacks run directly on Zenoh's network threads
(``zenoh.handlers.Callback(..., indirect=False)``). A callback that blocks stalls reception on
that link, so keep callbacks short (a :class:`Receiver` only appends to a buffer) and do slow
work, such as a re-alignment, on a thread of your own. Why not zenoh-python's default
(``indirect=True``, one Python thread per callback): those threads are not daemons, and a
process that forgets to close its session then never exits (measured: hung until killed).
:class:`Publisher`, :class:`Receiver` and :class:`Bus` methods may be called from any thread.

Reconnection, peers behind a router and the measured latencies: docs/design.md (bus); the
behaviours are pinned in tests/test_bus.py.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import zenoh

from recal.io.bus_config import zenoh_config
from recal.io.bus_entities import (
    Message,
    Overflow,
    Publisher,
    Queryable,
    Receiver,
    Subscription,
    _Counter,
)
from recal.io.bus_keys import (
    KEY_ROOT,
    QUERYABLE_TOPICS,
    TOPICS,
    key,
    key_pattern,
    parse_key,
    sensor_of,
    validate_sensor_id,
)

__all__ = [
    "KEY_ROOT",
    "QUERYABLE_TOPICS",
    "TOPICS",
    "Bus",
    "Message",
    "Publisher",
    "Queryable",
    "Receiver",
    "Subscription",
    "key",
    "key_pattern",
    "parse_key",
    "sensor_of",
    "validate_sensor_id",
]

# A Bus keeps one declared publisher per key; sensors are few, so a cap catches key leaks.
_MAX_PUBLISHERS = 4096



class Bus:
    """One Zenoh session plus the publishers, subscriptions and queryables declared on it.

    Use as a context manager, or call :meth:`close`. All methods are thread-safe; callbacks
    passed to :meth:`subscribe` and :meth:`queryable` run on Zenoh threads.

    Raises ``zenoh.ZError`` at construction if the session cannot open (e.g. client mode with
    the router down and no ``connect/timeout_ms``).
    """

    def __init__(self, config: zenoh.Config | None = None) -> None:
        self._session = zenoh.open(config if config is not None else zenoh_config())
        self._lock = threading.Lock()
        self._publishers: dict[str, Publisher] = {}
        self._subscriptions: list[Subscription] = []
        self._receivers: list[Receiver] = []
        self._queryables: list[Queryable] = []
        self._query_errors = _Counter()
        self._closed = False

    # -- lifecycle

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("bus is closed")

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            # Entities stay listed so stats() still reports final counts after close.
            receivers = list(self._receivers)
            entities = (*self._subscriptions, *self._queryables, *self._publishers.values())
        # Receivers first: waking a callback blocked on a full buffer lets Zenoh wind down.
        for receiver in receivers:
            receiver.close()
        for entity in entities:
            entity.undeclare()
        self._session.close()

    # -- information

    @property
    def zid(self) -> str:
        """This session's Zenoh id."""
        return str(self._session.zid())

    def routers(self) -> list[str]:
        """Zenoh ids of the routers this session is connected to right now."""
        return [str(z) for z in self._session.info.routers_zid()]

    def peers(self) -> list[str]:
        """Zenoh ids of the peers this session is connected to right now."""
        return [str(z) for z in self._session.info.peers_zid()]

    def stats(self) -> dict[str, int]:
        """Summed counters of every entity on this bus (a snapshot, for status and logs)."""
        with self._lock:
            pubs = list(self._publishers.values())
            subs = list(self._subscriptions)
            recs = list(self._receivers)
            qrys = list(self._queryables)
        return {
            "published": sum(p.sent for p in pubs),
            "publish_failed": sum(p.failed for p in pubs),
            "published_unmatched": sum(p.unmatched for p in pubs),
            "received": sum(s.received for s in subs),
            "callback_errors": sum(s.errors for s in subs),
            "receiver_dropped": sum(r.dropped for r in recs),
            "queries_answered": sum(q.answered for q in qrys),
            "query_handler_errors": sum(q.errors for q in qrys),
            "query_error_replies": self._query_errors.value,
        }

    # -- publishing

    def publisher(self, key_expr: str, *, express: bool = False) -> Publisher:
        """The publisher for ``key_expr``, declared on first use and reused afterwards.

        ``express=True`` skips batching (lower latency, lower throughput); it only applies
        when the publisher is first declared.
        """
        with self._lock:
            self._check_open()
            pub = self._publishers.get(key_expr)
            if pub is None:
                if len(self._publishers) >= _MAX_PUBLISHERS:
                    raise RuntimeError(f"more than {_MAX_PUBLISHERS} publishers on one bus")
                pub = Publisher(self._session, key_expr, express=express)
                self._publishers[key_expr] = pub
            return pub

    def publish(self, key_expr: str, payload: bytes, attachment: bytes | None = None) -> bool:
        """Publish ``payload`` on ``key_expr`` (see :meth:`Publisher.put`)."""
        return self.publisher(key_expr).put(payload, attachment)

    # -- receiving

    def subscribe(self, key_expr: str, callback: Callable[[Message], None]) -> Subscription:
        """Call ``callback(message)`` on a Zenoh thread for each sample matching ``key_expr``."""
        with self._lock:
            self._check_open()
            sub = Subscription(self._session, key_expr, callback)
            self._subscriptions.append(sub)
            return sub

    def receiver(
        self,
        key_expr: str,
        capacity: int = 1024,
        overflow: Overflow = "block",
        block_timeout_s: float = 1.0,
    ) -> Receiver:
        """A bounded :class:`Receiver` fed by a subscription on ``key_expr``."""
        receiver = Receiver(capacity, overflow, block_timeout_s)
        with self._lock:
            self._check_open()
            sub = Subscription(self._session, key_expr, receiver.push)
            receiver._subscription = sub
            self._subscriptions.append(sub)
            self._receivers.append(receiver)
        return receiver

    # -- query / reply

    def queryable(
        self, key_expr: str, handler: Callable[[str, bytes | None], bytes | None]
    ) -> Queryable:
        """Answer gets on ``key_expr`` with ``handler(query_key, payload)`` (Zenoh thread)."""
        with self._lock:
            self._check_open()
            qbl = Queryable(self._session, key_expr, handler)
            self._queryables.append(qbl)
            return qbl

    def get(
        self,
        key_expr: str,
        payload: bytes | None = None,
        timeout_s: float = 1.0,
        max_replies: int = 256,
    ) -> list[tuple[str, bytes]]:
        """Query every matching queryable; return ``(key, payload)`` of the successful replies.

        Waits at most ``timeout_s`` (Zenoh ends the query then) and keeps at most
        ``max_replies``. Error replies are skipped and counted in ``stats()``. Every reply is
        kept: Zenoh's default consolidation keeps one per key, and a gateway and a remote
        node both answer ``recal/<sensor>/status`` (which one survived was a coin toss).
        """
        self._check_open()
        replies = self._session.get(
            zenoh.KeyExpr(key_expr),
            zenoh.handlers.FifoChannel(max(1, max_replies)),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            payload=payload,
            timeout=max(0.001, float(timeout_s)),
        )
        results: list[tuple[str, bytes]] = []
        for reply in replies:  # ends when Zenoh finalises the query (all done or timeout)
            sample = reply.ok
            if sample is None:
                self._query_errors.add()
                continue
            results.append((str(sample.key_expr), sample.payload.to_bytes()))
            if len(results) >= max_replies:
                break
        return results
