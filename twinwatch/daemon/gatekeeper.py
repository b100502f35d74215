"""The pipeline's gate and the windows it holds (:class:`GateKeeper`): each processed window
is written to the gate (the state store) first; while another process holds the gate's
database lock, the windows wait here in memory (:data:`HELD_MAX`), are tried again, and are
released, oldest first, stored (then published) or given up (left to the store's backlog).
The keeper decides, the :class:`~twinwatch.daemon.pipeline.WindowPipeline` acts.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from twinwatch.sinks.base import Gate, ProcessedWindow, Sink

__all__ = ["HELD_MAX", "GateKeeper", "Released"]

HELD_MAX = 1000
"""Windows kept in memory while the state database is locked by another process (about 33
minutes of 2 s windows). Beyond it a window waits in the store's own backlog and is not
published."""

Released = tuple[list[ProcessedWindow], bool]
"""Held windows let go, oldest first, and whether they are stored (publish them) or not (given
up: they wait in the gate's backlog, not published)."""


class GateKeeper:
    """The gate of one machine's pipeline and the windows held for its lock.

    Args:
        write: writes one window to one output (the pipeline's ``_write``); its result for
            the gate: False when not stored.

    Attributes:
        gate: the sink that must take a window before the publishing outputs get it (the
            state store), or None (every window counts as stored).
        delayed: windows that waited in memory for the gate's lock, in all.
        locked_longest: the longest such wait [s].
        writing: (the gate's name, since when [monotonic s]) while the gate writes a window.
    """

    def __init__(self, machine: str,
                 write: Callable[[Sink, ProcessedWindow], bool | None],
                 log: logging.Logger) -> None:
        self.machine = machine
        self._log = log
        self._write = write
        self.gate: Gate | None = None
        self.delayed = 0
        self.locked_longest = 0.0
        self.writing: tuple[str, float] | None = None
        self._held: list[ProcessedWindow] = []
        self._locked_since: float | None = None

    @property
    def held(self) -> int:
        """Windows held for the gate's lock now."""
        return len(self._held)

    def store(self, out: ProcessedWindow, *, can_hold: bool) -> bool | None:
        """Write ``out`` to the gate.

        Args:
            can_hold: the window may wait here if the gate's database is locked (the outputs
                have a thread of their own, which retries).

        Returns:
            True: stored (or no gate); False: not stored (it waits in the gate's backlog, not
            published); None: held for the lock (published once stored, see :meth:`retry`).
        """
        gate = self.gate
        if gate is None:
            return True
        self.writing = (gate.name, time.monotonic())
        try:
            stored = self._write(gate, out) is not False
        finally:
            self.writing = None
        if not stored and can_hold and gate.locked:
            # another process holds the database's lock: keep the window until it is stored
            self._locked_since = time.monotonic()
            self._held.append(out)
            self.delayed += 1
            return None
        return stored

    def hold(self, out: ProcessedWindow) -> bool | None:
        """A window behind the locked database: given to the gate's backlog without a write;
        kept here to be stored and published once the lock goes.

        Returns:
            None: held (published later); False: :data:`HELD_MAX` are held already, it is
            stored later but not published (counted in the gate's ``not_stored``).
        """
        gate = self.gate
        assert gate is not None
        gate.hold(out)
        if len(self._held) >= HELD_MAX:  # too long: stored later, not published
            gate.not_stored += 1
            return False
        self._held.append(out)
        self.delayed += 1
        return None

    def retry(self, give_up: bool) -> Released | None:
        """One more attempt to store the held windows (it waits up to the busy timeout).

        Returns:
            The held windows and whether they were stored (not stored: another failure than
            the lock, or ``give_up``); None while they still wait (or without a gate).
        """
        gate = self.gate
        if gate is None:
            self._held.clear()
            return None
        started = time.monotonic()
        self.writing = (gate.name, started)
        try:
            stored = gate.retry()
        except Exception as exc:  # noqa: BLE001 - as _write: one output must not stop the rest
            self._log.error("the %s output failed (%s: %s)", gate.name, type(exc).__name__, exc)
            stored = False
        finally:
            self.writing = None
        if self._locked_since is not None:
            self.locked_longest = max(self.locked_longest,
                                      time.monotonic() - self._locked_since)
        held = list(self._held)
        if not stored and time.monotonic() - started < 0.2:
            time.sleep(0.2)  # a lock error at once (not after the busy timeout): no spinning
        if stored:
            self._held.clear()
            self._locked_since = None
            gate.not_stored -= 1  # the first held window, counted when its write failed
            self._log.warning("state database of %s released: %d windows that waited in memory "
                           "are stored and published now", self.machine, len(held))
            return held, True
        if give_up or not gate.locked:
            self._held.clear()
            self._locked_since = None
            gate.not_stored += len(held) - 1
            why = "the daemon stops" if give_up else "it cannot be written"
            self._log.error("state database of %s: %d windows that waited for its lock are not "
                         "published (%s); they wait in its backlog", self.machine, len(held),
                         why)
            return held, False
        return None

    def counters(self) -> dict[str, int]:
        """``store_delayed``: :attr:`delayed`."""
        return {"store_delayed": int(self.delayed)}

    def summary(self) -> list[str]:
        """The windows that waited for a locked state database, if any."""
        if not self.delayed:
            return []
        held = len(self._held)
        return [f"state database: locked by another process for up to "
                f"{self.locked_longest:.0f} s; {self.delayed} windows waited in memory meanwhile "
                f"and were stored and published once it was released"
                + (f" ({held} still waiting at the end: not published)" if held else "")]
