"""Estimation slots: at most as many windows processed at once in one process as it has cores.

A process that runs many machines (:class:`~twinwatch.daemon.host.Host`, or one of its worker
processes) gives every machine's window worker the same :class:`EstimationSlots`: a worker
processes a window only while it holds a slot, so a window's estimation is not stretched by
dozens of others competing for the GIL (the rest wait in their machine's queue).
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from collections.abc import Callable

__all__ = ["MACHINES_PER_WORKER", "EstimationSlots", "default_processes", "default_workers"]


def default_workers() -> int:
    """Estimation slots by default: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


#: Machines one worker process takes by default (more, and its interpreter lock is the limit:
#: docs/gateway.md).
MACHINES_PER_WORKER = 50


def default_processes(machines: int) -> int:
    """Worker processes by default for a directory of ``machines``: one per core, more when
    the cores would have more than :data:`MACHINES_PER_WORKER` machines each."""
    return max(default_workers(), -(-machines // MACHINES_PER_WORKER))


class EstimationSlots:
    """At most ``size`` windows processed at once across the machines of a gateway.

    A worker calls :meth:`acquire` before a window and :meth:`release` after it. A slot held
    for more than ``stuck_after`` seconds stops counting (its window is stuck), so one stuck
    machine cannot starve the others; it is listed by :meth:`stuck`.

    Args:
        size: slots (>= 1), normally the cores (:func:`default_workers`).
        clock: monotonic clock (tests inject one).
    """

    def __init__(self, size: int, *, stuck_after: float = 30.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if size < 1:
            raise ValueError(f"estimation slots must be at least 1, not {size}")
        self.size = size
        self.stuck_after = stuck_after
        self._clock = clock
        self._lock = threading.Lock()
        self._held: dict[int, tuple[str, float]] = {}
        #: the waiting tokens in arrival order, each with the event that wakes its thread
        self._line: deque[tuple[int, threading.Event]] = deque()
        self._next = 0

    def _active(self, now: float) -> int:
        return sum(1 for _, t in self._held.values() if now - t < self.stuck_after)

    def _wake_head(self) -> None:
        """Wake the first in line, only it (the lock held)."""
        if self._line:
            self._line[0][1].set()

    def acquire(self, holder: str, cancelled: Callable[[], bool] | None = None) -> int | None:
        """Wait for a slot (the worker's thread), first come first served; returns the token
        :meth:`release` takes, or None once ``cancelled()`` is true (checked every 0.5 s)."""
        wake = threading.Event()
        with self._lock:
            self._next += 1
            token = self._next
            self._line.append((token, wake))
        acquired = False
        try:
            while True:
                wake.clear()
                with self._lock:
                    if (self._line[0][0] == token
                            and self._active(self._clock()) < self.size):
                        self._line.popleft()
                        self._held[token] = (holder, self._clock())
                        acquired = True
                        if self._active(self._clock()) < self.size:
                            self._wake_head()  # the next in line fits too
                        return token
                if cancelled is not None and cancelled():
                    return None
                wake.wait(timeout=0.5)  # a slot may turn stuck: look again
        finally:
            if not acquired:
                with self._lock:
                    first = bool(self._line) and self._line[0][0] == token
                    self._line = deque(w for w in self._line if w[0] != token)
                    if first:
                        self._wake_head()

    def release(self, token: int) -> None:
        """Give the slot of ``token`` back."""
        with self._lock:
            self._held.pop(token, None)
            self._wake_head()

    def busy(self) -> int:
        """Slots held now (stuck ones included)."""
        with self._lock:
            return len(self._held)

    def stuck(self) -> list[tuple[str, float]]:
        """``(holder, seconds)`` of the slots held longer than ``stuck_after``."""
        now = self._clock()
        with self._lock:
            return [(h, now - t) for h, t in self._held.values() if now - t >= self.stuck_after]
