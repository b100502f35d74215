"""The in-memory outbox of an MQTT output without a state database (``[state] enabled =
false``): the windows not yet acknowledged, bounded, lost at exit (docs/mqtt.md).
"""

from __future__ import annotations

import threading
import time
from collections import deque

from twinwatch.sinks.base import OutboxRow


class MemoryOutbox:
    """An :class:`~twinwatch.sinks.base.Outbox` in memory (no state database): the last
    ``size`` windows given to :meth:`add`; older undelivered ones are :attr:`dropped`."""

    def __init__(self, size: int) -> None:
        self._rows: deque[OutboxRow] = deque()
        self._size = size
        self._next = 1
        self._delivered: set[int] = set()
        self._lock = threading.Lock()
        self.dropped = 0

    def add(self, doc: str, window: int) -> None:
        with self._lock:
            self._rows.append(OutboxRow(self._next, "memory", window, time.time(), doc))
            self._next += 1
            while len(self._rows) > self._size:
                old = self._rows.popleft()
                if old.id not in self._delivered:
                    self.dropped += 1
                self._delivered.discard(old.id)

    def start(self) -> int:
        with self._lock:
            return self._rows[0].id - 1 if self._rows else self._next - 1

    def pending(self, after: int, limit: int) -> list[OutboxRow]:
        with self._lock:
            return [r for r in self._rows if r.id > after
                    and r.id not in self._delivered][:limit]

    def count(self, position: int) -> int:
        with self._lock:
            return sum(1 for r in self._rows if r.id > position and r.id not in self._delivered)

    def latest_id(self) -> int | None:
        with self._lock:
            return self._rows[-1].id if self._rows else None

    def doc_at_or_before(self, health_id: int) -> str | None:
        with self._lock:
            return next((r.doc for r in reversed(self._rows) if r.id <= health_id), None)

    def ack(self, delivered: list[OutboxRow], position: int) -> None:
        with self._lock:
            self._delivered.update(r.id for r in delivered)
            self._delivered = {i for i in self._delivered if i > position}
            while self._rows and self._rows[0].id <= position:
                self._rows.popleft()


class Window:
    """A window handed to paho: its row and the message ids not acknowledged yet."""

    __slots__ = ("mids", "row", "sent")

    def __init__(self, row: OutboxRow) -> None:
        self.row = row
        self.mids: set[int] = set()
        self.sent = time.monotonic()
