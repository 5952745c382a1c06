"""The entities a :class:`recal.io.bus.Bus` declares on its Zenoh session: a publisher, a
subscription, a bounded receiver, a queryable, and the message a subscription delivers.
Threading and the reasons behind each: `recal.io.bus`."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import zenoh

from recal.io.bus_keys import sensor_of

__all__ = ["Message", "Overflow", "Publisher", "Queryable", "Receiver", "Subscription"]

log = logging.getLogger("recal.io.bus")

Overflow = Literal["block", "drop_oldest"]



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
