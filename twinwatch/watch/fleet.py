"""The fleet's state: the machines of one key prefix as the network shows them (:class:`Fleet`:
liveliness, the last health message, the alarm events, the windows missed and recovered;
thread-safe, Zenoh's threads update it) and :meth:`Fleet.snapshot`, the one summary every
view reads.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from twinwatch.watch.session import health_view
from twinwatch.watch.view import Machine, machine_view

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView


SETTLE_S = 0.5
"""Tokens that arrive this soon after a watcher starts [s] existed before it."""


Delivery = Literal["live", "history"]
"""How a health message reached the watcher: ``live`` (published, or from a daemon's cache:
the latest at start, a late joiner's history, a loss zenoh recovered) or ``history`` (asked from
the daemon's state database after zenoh reported windows missed)."""


@dataclass
class Gap:
    """Windows of one machine zenoh reported missed, and what the history query got back.

    Attributes:
        machine: the machine.
        missed: windows zenoh's sample-miss detection counted (not received live, not
            recovered from the publisher's cache).
        recovered: the windows the history query returned that this watcher had not seen,
            oldest first (their window numbers). The query is not bounded above, so
            ``len(recovered)`` may exceed ``missed``; each window is delivered once.
        error: why the history could not be asked (after every attempt), or None.
    """

    machine: str
    missed: int
    recovered: list[int] = field(default_factory=list)
    error: str | None = None


class Fleet:
    """The machines of one key prefix as the network shows them.

    Args:
        stale_after: seconds without a window (at least 3 window lengths) before a machine
            whose token is present is shown ``stale``.
        forget_after: seconds after which a gone machine is no longer listed (None: never).
        clock: wall clock [s since the epoch].

    Thread-safe: Zenoh's threads call :meth:`token`, :meth:`health`, :meth:`alarm`; a view
    reads :meth:`snapshot`.
    """

    def __init__(self, *, stale_after: float = 10.0, forget_after: float | None = 600.0,
                 clock: Callable[[], float] = time.time) -> None:
        self.stale_after = stale_after
        self.forget_after = forget_after
        self._clock = clock
        self._lock = threading.Lock()
        self._machines: dict[str, Machine] = {}
        self.changed = threading.Event()
        self.started = clock()

    def _get(self, name: str) -> Machine:
        m = self._machines.get(name)
        if m is None:
            m = self._machines[name] = Machine(name)
        return m

    def token(self, machine: str, present: bool) -> None:
        """The machine's liveliness token appeared (``present``) or went. A token present
        within :data:`SETTLE_S` of the start was there before the watcher (since unknown)."""
        now = self._clock()
        with self._lock:
            m = self._get(machine)
            if m.token != present:
                before = present and m.token is None and now - self.started < SETTLE_S
                m.token, m.since = present, None if before else now
        self.changed.set()

    def health(self, machine: str, doc: HealthView | Mapping[str, Any]) -> bool:
        """A health message of ``machine`` (the latest, or one published: its typed view, or
        decoded). An older window of the same run than the one held (a late reply to the first
        query) is ignored.

        Returns:
            True if it is now the machine's latest.
        """
        doc = health_view(doc)
        with self._lock:
            m = self._get(machine)
            old = m.health
            if old is not None and old.run == doc.run and isinstance(
                    doc.window, int) and isinstance(old.window, int) and (
                    doc.window <= old.window):
                return False
            m.health, m.received = doc, self._clock()
        self.changed.set()
        return True

    def alarm(self, machine: str, event: Mapping[str, Any]) -> None:
        """An alarm event of ``machine`` (``<prefix>/<machine>/alarm``)."""
        with self._lock:
            self._get(machine).events.append(dict(event))
        self.changed.set()

    def gap(self, gap: Gap) -> None:
        """Windows of a machine zenoh reported missed, and what its history returned."""
        with self._lock:
            m = self._get(gap.machine)
            m.missed += gap.missed
            m.recovered += len(gap.recovered)
            m.gap_error = gap.error
        self.changed.set()

    def machines(self) -> list[str]:
        """The machines listed now, sorted."""
        return [m["machine"] for m in self.snapshot()["machines"]]

    def snapshot(self) -> dict[str, Any]:
        """What the network shows now, as plain JSON types (``watch --once --json``)::

            {"t": <wall s>, "machines": [{"machine", "state", "token", "state_since_s",
              "last_window_age_s", "model", "run", "window", "t_start", "t_end",
              "parameters": {name: {"value", "unit", "nominal", "deviation_pct", "status",
                                    "alarm", "rul_s", "rul_status"}},
              "alarms": {name: {"level", "since_t", "deviation_pct"}},
              "terms": [{"equation", "meaning"}],
              "diagnosis": {"fault", "probability", "action"} | null,
              "quality": {"nrmse", "model_check", "trusted", "elapsed_ms", "problems"},
              "delivery": {"missed", "recovered", "error"},
              "last_event": {...} | null}, ...]}

        ``state_since_s``: since the watcher saw the token appear or go (null: it was there
        before the watcher started). Parameters ``tied`` or ``fixed`` are left out; ``alarm``
        is the parameter's alarm level when it has a rule; ``rul_s`` the median remaining
        useful life to the alarm threshold [s]. ``delivery``: the windows zenoh reported this
        watcher missed (beyond the publisher's cache), how many the daemon's history query
        returned, and why the last such query failed (null: it did not).
        """
        now = self._clock()
        with self._lock:
            if self.forget_after is not None:
                for name in [n for n, m in self._machines.items()
                             if m.token is False and m.since is not None
                             and now - m.since > self.forget_after]:
                    del self._machines[name]
            machines = [machine_view(m, now, self.stale_after)
                        for _, m in sorted(self._machines.items())]
        return {"t": now, "machines": machines}
