"""Zenoh adapter: key expressions and a byte-level bus.

This module moves bytes and strings. It knows nothing about the calibration algebra or the
payload codecs (``recal.io.messages`` turns messages into bytes and back).

Key-expression layout (one sensor id per chunk, see :func:`validate_sensor_id`)::

    recal/<sensor>/raw          pub/sub  raw samples from the gateway
    recal/<sensor>/calibrated   pub/sub  calibrated samples in the sensor frame
    recal/<sensor>/body         pub/sub  calibrated samples rotated into the body frame
    recal/<sensor>/calibration  pub/sub  calibration state (parameters, covariance, ...)
    recal/<sensor>/status       query    answers a get with the current state bytes
    recal/<sensor>/events       pub/sub  discrete events (gate rejections, resets, ...)
    recal/<sensor>/align        query    request a mounting re-alignment; the reply is the result

Wildcards select several sensors at once: ``recal/*/raw`` (every sensor's raw stream; the
sensor id comes back with :func:`parse_key`) or ``recal/<sensor>/**`` (everything about one).

Session configuration (loopback unless told otherwise) is `recal.io.bus_config`.

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

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import zenoh

from recal.errors import UsageError
from recal.io.bus_config import zenoh_config

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

log = logging.getLogger(__name__)

KEY_ROOT = "recal"
TOPICS: tuple[str, ...] = (
    "raw",
    "calibrated",
    "body",
    "calibration",
    "status",
    "events",
    "align",
)
QUERYABLE_TOPICS: frozenset[str] = frozenset({"status", "align"})

# Characters with a meaning in Zenoh key expressions (chunk separator, wildcards, DSL markers).
_FORBIDDEN_SENSOR_CHARS = frozenset("/*$?#")
_MAX_SENSOR_ID_LEN = 128
# A Bus keeps one declared publisher per key; sensors are few, so a cap catches key leaks.
_MAX_PUBLISHERS = 4096

Overflow = Literal["block", "drop_oldest"]


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
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}; expected one of {TOPICS}")
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


# --------------------------------------------------------------------------- bus objects


@dataclass(frozen=True, slots=True)
class Message:
    """One received sample: its concrete key, payload bytes and optional attachment bytes."""

    key: str
    payload: bytes
    attachment: bytes | None = None

    @property
    def sensor(self) -> str:
        """Sensor id parsed from :attr:`key` (ValueError if the key is outside the layout)."""
        return sensor_of(self.key)


def _message_from_sample(sample: zenoh.Sample) -> Message:
    attachment = sample.attachment
    return Message(
        key=str(sample.key_expr),
        payload=sample.payload.to_bytes(),
        attachment=None if attachment is None else attachment.to_bytes(),
    )


class _Counter:
    """A thread-safe integer counter (``+=`` on a shared int is not atomic across threads)."""

    __slots__ = ("_lock", "_value")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._value = 0

    def add(self, n: int = 1) -> None:
        with self._lock:
            self._value += n

    @property
    def value(self) -> int:
        return self._value


class _SparseLog:
    """Log the first few occurrences of a recurring problem, then one in ``every``.

    Why: a broken callback at 1 kHz would otherwise flood the log.
    """

    def __init__(self, first: int = 5, every: int = 1000) -> None:
        self._first = first
        self._every = every
        self._count = _Counter()

    def should_log(self) -> bool:
        self._count.add()
        n = self._count.value
        return n <= self._first or n % self._every == 0


class Publisher:
    """A declared Zenoh publisher on one key, with congestion control BLOCK and counters.

    BLOCK means a full transmission queue makes :meth:`put` wait instead of silently dropping
    (the Zenoh default DROP lost 40-65 % of samples under load in our measurements). Per the
    Zenoh config, a link that stays blocked for ``transport/link/tx/queue/congestion_control/
    block/wait_before_close`` (5 s by default) is closed, which bounds the wait (not measured).

    Counters: ``sent`` (accepted by Zenoh), ``failed`` (Zenoh raised, e.g. closed session),
    ``unmatched`` (no subscriber matched the key, so nobody would receive it and the put was
    skipped, though counted in ``sent`` too; this is how samples are lost while a router is
    down). Thread-safe.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, *, express: bool = False) -> None:
        self._key = key_expr
        self._publisher = session.declare_publisher(
            zenoh.KeyExpr(key_expr),
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=express,
        )
        self._sent = _Counter()
        self._failed = _Counter()
        self._unmatched = _Counter()
        self._errors = _SparseLog()

    def _matching_now(self) -> bool:
        # Asking is cheaper than a matching listener (which would need a Python
        # callback thread, and whose news arrive after the routing changed). The 1.10 stub
        # says ``matching_status`` is a bool, but it returns a MatchingStatus object, which is
        # always truthy: read its ``matching`` field.
        status: Any = self._publisher.matching_status
        return bool(status.matching)

    @property
    def key(self) -> str:
        """The key this publisher writes to."""
        return self._key

    @property
    def sent(self) -> int:
        """Number of samples accepted by Zenoh."""
        return self._sent.value

    @property
    def failed(self) -> int:
        """Number of samples Zenoh refused (exception in put)."""
        return self._failed.value

    @property
    def unmatched(self) -> int:
        """Number of samples accepted while no subscriber matched (nobody received them)."""
        return self._unmatched.value

    @property
    def has_subscribers(self) -> bool:
        """Whether some subscriber currently matches this key (as Zenoh knows it now)."""
        return self._matching_now()

    def wait_for_subscribers(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a matching subscriber; return whether one exists."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        while not self._matching_now():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)
        return True

    def put(self, payload: bytes | Callable[[], bytes], attachment: bytes | None = None) -> bool:
        """Publish ``payload``; return False (and count it) if Zenoh refused it.

        ``payload`` may be what makes the bytes (called only when a subscriber matches: a
        live topic nobody listens to then costs no encoding at each arrival).
        May block while the transmission queue is full (congestion control BLOCK).
        """
        try:
            if not self._matching_now():
                # Nobody would receive it: Zenoh routes a sample to matching subscribers
                # only, so the put itself is skipped (it cost as much again as this check, per
                # sample, on a gateway's raw topic that nobody watches). Counted as before.
                self._sent.add()
                self._unmatched.add()
                return True
            if callable(payload):
                payload = payload()
            self._publisher.put(payload, attachment=attachment)
        except zenoh.ZError as exc:  # e.g. undeclared (the bus closed)
            self._failed.add()
            if self._errors.should_log():
                log.warning("put on %s failed: %s", self._key, exc)
            return False
        self._sent.add()
        return True

    def undeclare(self) -> None:
        """Undeclare the publisher (idempotent; errors after session close are ignored)."""
        try:
            self._publisher.undeclare()
        except zenoh.ZError:
            pass


def _direct(callback: Callable[[Any], None]) -> zenoh.handlers.Callback[Any]:
    """Run ``callback`` on the Zenoh network thread (see the module notes on threading)."""
    return zenoh.handlers.Callback(callback, indirect=False)


class Subscription:
    """A subscriber that hands each :class:`Message` to a callback on a Zenoh thread.

    Exceptions raised by the callback are counted in ``errors`` and logged sparsely; they do
    not stop the subscription.
    """

    def __init__(
        self, session: zenoh.Session, key_expr: str, callback: Callable[[Message], None]
    ) -> None:
        self._key_expr = key_expr
        self._callback = callback
        self._received = _Counter()
        self._errors = _Counter()
        self._log = _SparseLog()
        self._subscriber = session.declare_subscriber(
            zenoh.KeyExpr(key_expr), _direct(self._on_sample)
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return  # recal never deletes keys; a DELETE carries no payload to pass on
        self._received.add()
        try:
            self._callback(_message_from_sample(sample))
        except Exception:
            self._errors.add()
            if self._log.should_log():
                log.exception("subscriber callback for %s failed", self._key_expr)

    @property
    def key_expr(self) -> str:
        """The (possibly wildcard) key expression subscribed to."""
        return self._key_expr

    @property
    def received(self) -> int:
        """Number of samples delivered to the callback."""
        return self._received.value

    @property
    def errors(self) -> int:
        """Number of callback invocations that raised."""
        return self._errors.value

    def undeclare(self) -> None:
        """Stop receiving (idempotent)."""
        try:
            self._subscriber.undeclare()
        except zenoh.ZError:
            pass


class Receiver:
    """A bounded buffer of received :class:`Message` objects with ``recv(timeout)``.

    Zenoh's own FifoChannel has no receive timeout, so the subscriber callback pushes into this
    buffer instead. When it holds ``capacity`` messages:

    * ``overflow="block"`` (default): the Zenoh thread waits for room, which back-pressures the
      sender (lossless, like FifoChannel). After ``block_timeout_s`` it gives up, drops the
      newest message and counts it, so a dead consumer cannot stall the session for ever.
      Keep ``block_timeout_s`` well under the link lease (10 s): a network thread that blocks
      longer stops reading keep-alives. For a subscriber on the publisher's own session, Zenoh
      delivers inside ``put``, so the publishing thread is the one that waits.
    * ``overflow="drop_oldest"``: the oldest message is discarded (like RingChannel), counted.

    Pushing happens on a Zenoh thread; ``recv``/``recv_batch`` are safe from any thread
    (normally one consumer).
    """

    def __init__(
        self, capacity: int = 1024, overflow: Overflow = "block", block_timeout_s: float = 1.0
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        if overflow not in ("block", "drop_oldest"):
            raise ValueError(f"overflow must be 'block' or 'drop_oldest', got {overflow!r}")
        self.capacity = int(capacity)
        self.overflow: Overflow = overflow
        self.block_timeout_s = float(block_timeout_s)
        self._items: deque[Message] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._received = 0
        self._dropped = 0
        self._subscription: Subscription | None = None

    @property
    def received(self) -> int:
        """Messages that arrived from Zenoh (kept or dropped)."""
        return self._received

    @property
    def dropped(self) -> int:
        """Messages discarded because the buffer was full (or closed)."""
        return self._dropped

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def __len__(self) -> int:
        return len(self._items)

    def push(self, message: Message) -> bool:
        """Add a message (called on a Zenoh thread); return False if it was dropped."""
        with self._cond:
            self._received += 1
            if not self._make_room():
                self._dropped += 1
                return False
            self._items.append(message)
            self._cond.notify_all()
            return True

    def _make_room(self) -> bool:
        """With the lock held, ensure one free slot; False means drop the new message."""
        if self._closed:
            return False
        if len(self._items) < self.capacity:
            return True
        if self.overflow == "drop_oldest":
            self._items.popleft()
            self._dropped += 1
            return True
        deadline = time.monotonic() + self.block_timeout_s
        while len(self._items) >= self.capacity and not self._closed:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            self._cond.wait(remaining)
        return not self._closed

    def recv(self, timeout: float | None = None) -> Message | None:
        """Next message, waiting up to ``timeout`` seconds (None: until one arrives or close).

        Returns None on timeout or once closed and empty.
        """
        with self._cond:
            if not self._cond.wait_for(lambda: self._items or self._closed, timeout):
                return None
            if not self._items:
                return None
            item = self._items.popleft()
            self._cond.notify_all()  # a blocked producer may go on
            return item

    def recv_batch(self, max_items: int, timeout: float | None = None) -> list[Message]:
        """Up to ``max_items`` messages: waits like :meth:`recv` for the first, not the rest."""
        first = self.recv(timeout)
        if first is None:
            return []
        batch = [first]
        with self._cond:
            while self._items and len(batch) < max_items:
                batch.append(self._items.popleft())
            self._cond.notify_all()
        return batch

    def close(self) -> None:
        """Stop accepting messages and wake every waiter (idempotent)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._subscription is not None:
            self._subscription.undeclare()


class Queryable:
    """Answers gets on one key with ``handler(query_key, query_payload) -> bytes | None``.

    ``query_key`` is the key the querier asked for, possibly a wildcard (``recal/*/status``).
    The handler runs on a Zenoh network thread, so it must be quick. Returning None sends no
    reply; raising sends an error reply (the querier's :meth:`Bus.get` skips it) and is counted
    in ``errors``. Replies go on the queryable's own key, or, if that has wildcards, on the
    query's key (a wildcard query to a wildcard queryable gets an error reply).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        handler: Callable[[str, bytes | None], bytes | None],
    ) -> None:
        self._key_expr = key_expr
        self._handler = handler
        self._wildcard = "*" in key_expr or "$" in key_expr
        self._answered = _Counter()
        self._errors = _Counter()
        self._log = _SparseLog()
        self._queryable = session.declare_queryable(
            zenoh.KeyExpr(key_expr), _direct(self._on_query)
        )

    def _reply_key(self, query_key: str) -> str:
        """The concrete key to reply on: ours, or the query's when ours has wildcards."""
        if not self._wildcard:
            return self._key_expr
        if "*" in query_key or "$" in query_key:
            raise ValueError(f"{self._key_expr!r} cannot answer the wildcard query {query_key!r}")
        return query_key

    def _on_query(self, query: zenoh.Query) -> None:
        # The context manager drops the query on exit, which tells the querier we are done.
        # Relying on garbage collection is not enough: a logged traceback keeps the frame,
        # hence the query, alive, and the querier then waits for its whole timeout.
        with query:
            self._answer(query)

    def _answer(self, query: zenoh.Query) -> None:
        query_key = str(query.key_expr)
        payload = query.payload
        try:
            answer = self._handler(query_key, None if payload is None else payload.to_bytes())
            if answer is not None:
                query.reply(self._reply_key(query_key), answer)
                self._answered.add()
        except Exception as exc:
            self._errors.add()
            if self._log.should_log():
                log.exception("queryable handler for %s failed", self._key_expr)
            try:
                query.reply_err(f"{type(exc).__name__}: {exc}".encode())
            except zenoh.ZError:
                pass  # the session is closing; the querier will time out

    @property
    def key_expr(self) -> str:
        """The key expression served."""
        return self._key_expr

    @property
    def answered(self) -> int:
        """Number of successful replies sent."""
        return self._answered.value

    @property
    def errors(self) -> int:
        """Number of queries whose handler raised."""
        return self._errors.value

    def undeclare(self) -> None:
        """Stop answering (idempotent)."""
        try:
            self._queryable.undeclare()
        except zenoh.ZError:
            pass


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
