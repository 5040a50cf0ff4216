"""The bounded send buffer (drop oldest) and the reconnect backoff.

Every message a bridge takes from ROS waits here until it is written to the stream. While the peer is
unreachable the buffer fills; once it holds ``max_messages`` messages or ``max_bytes`` bytes, each new
message pushes the oldest out. Dropped messages are counted per topic (for the metrics) and collected in a
report that the bridge logs when the connection comes back (and while an outage goes on).

Producers (the ROS thread) call ``push``; the single consumer (the stream's sender) calls ``pop_batch``.
A consumer that found the buffer empty is woken through ``waker`` by the next push.
"""

from __future__ import annotations

import collections
import random
import threading
from collections.abc import Callable


class Outgoing:
    """One message taken from ROS, waiting to be sent."""

    __slots__ = ("cdr", "qos", "received_ns", "sequence", "source_ns", "topic", "type")

    def __init__(self, topic: str, type_name: str, cdr: bytes, sequence: int, source_ns: int, received_ns: int, qos):
        self.topic, self.type, self.cdr, self.sequence = topic, type_name, cdr, sequence
        self.source_ns, self.received_ns, self.qos = source_ns, received_ns, qos


class DropOldestBuffer:
    def __init__(self, max_messages: int, max_bytes: int):
        if max_messages < 1 or max_bytes < 1:
            raise ValueError("the buffer must hold at least one message and one byte")
        self.max_messages, self.max_bytes = max_messages, max_bytes
        self._items: collections.deque[Outgoing] = collections.deque()
        self._bytes = 0
        self._lock = threading.Lock()
        self._waiting = False
        self.waker: Callable[[], None] | None = None
        self.dropped: dict[str, int] = {}  # topic -> messages dropped since start
        self._report: dict[str, int] = {}  # topic -> messages dropped since the last take_report()

    def __len__(self) -> int:
        return len(self._items)

    @property
    def bytes(self) -> int:
        return self._bytes

    def _drop_oldest_locked(self) -> None:
        old = self._items.popleft()
        self._bytes -= len(old.cdr)
        self.dropped[old.topic] = self.dropped.get(old.topic, 0) + 1
        self._report[old.topic] = self._report.get(old.topic, 0) + 1

    def push(self, item: Outgoing) -> int:
        """Append item, dropping the oldest messages while over a limit; returns how many were dropped."""
        dropped = 0
        with self._lock:
            self._items.append(item)
            self._bytes += len(item.cdr)
            while len(self._items) > 1 and (len(self._items) > self.max_messages or self._bytes > self.max_bytes):
                self._drop_oldest_locked()
                dropped += 1
            if len(self._items) == 1 and self._bytes > self.max_bytes:  # a single message larger than the buffer
                self._drop_oldest_locked()
                dropped += 1
            wake, self._waiting = self._waiting, False
        if wake and self.waker is not None:
            self.waker()
        return dropped

    def pop_batch(self, max_messages: int, max_bytes: int) -> list[Outgoing]:
        """Up to max_messages oldest messages, at most max_bytes together (but always one, if any).

        Empty: the consumer is marked waiting, and the next push calls the waker.
        """
        with self._lock:
            if not self._items:
                self._waiting = True
                return []
            batch = [self._items.popleft()]
            size = len(batch[0].cdr)
            while self._items and len(batch) < max_messages and size + len(self._items[0].cdr) <= max_bytes:
                item = self._items.popleft()
                size += len(item.cdr)
                batch.append(item)
            self._bytes -= size
            return batch

    def requeue(self, batch: list[Outgoing]) -> int:
        """Put an unsent batch back in front, in order; the limits still hold (the oldest go). Returns drops."""
        dropped = 0
        with self._lock:
            for item in reversed(batch):
                self._items.appendleft(item)
                self._bytes += len(item.cdr)
            while self._items and (len(self._items) > self.max_messages or self._bytes > self.max_bytes):
                self._drop_oldest_locked()
                dropped += 1
        return dropped

    def take_report(self) -> dict[str, int]:
        """Messages dropped per topic since the last call."""
        with self._lock:
            report, self._report = self._report, {}
        return report

    def clear(self) -> int:
        with self._lock:
            count = len(self._items)
            self._items.clear()
            self._bytes = 0
        return count


class Backoff:
    """Exponential backoff with jitter: initial, initial*factor, ... up to maximum; reset after a good session."""

    def __init__(self, initial: float = 0.1, maximum: float = 5.0, factor: float = 2.0, jitter: float = 0.2, rng=None):
        if initial <= 0 or maximum < initial or factor < 1 or not 0 <= jitter < 1:
            raise ValueError("backoff needs 0 < initial <= maximum, factor >= 1 and 0 <= jitter < 1")
        self.initial, self.maximum, self.factor, self.jitter = initial, maximum, factor, jitter
        self.rng = rng or random.Random()
        self.attempt = 0

    def next_delay(self) -> float:
        base = min(self.maximum, self.initial * self.factor**self.attempt)
        self.attempt += 1
        return base * (1 + self.jitter * (2 * self.rng.random() - 1))

    def reset(self) -> None:
        self.attempt = 0
