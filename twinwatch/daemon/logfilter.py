"""A rate limit on third-party log floods.

A library that logs in a tight loop (python-can's socketcand bus retrying a server that does
not answer) buries the journal; twinwatch's own modules log each cause once.
:class:`RepeatFilter`, attached to the handlers the CLI logs through (:func:`install`), lets the
first ``burst`` identical messages of a third-party logger (same logger, level and text) through
in every ``interval`` and counts the others; once the interval is over, one line from the same
logger says how many were suppressed. Records of ``twinwatch`` loggers pass untouched; the
third-party records in :data:`BENIGN` are dropped.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["BENIGN", "RepeatFilter", "flush", "install"]

_SUMMARY = "_twinwatch_suppressed"
"""Attribute marking the filter's own summary records (they pass it)."""

_FILTERS: weakref.WeakSet[RepeatFilter] = weakref.WeakSet()

#: (logger, message) of third-party records that report nothing wrong at a level that says
#: otherwise: dropped. python-can's socketcand bus warns whenever one TCP read ends inside a
#: frame, which it completes from the next read (a busy bus, or frames taken in batches:
#: :data:`~twinwatch.drivers.base.BATCH_S`).
BENIGN = frozenset({
    ("can.interfaces.socketcand.socketcand", "Got incomplete message => waiting for more data"),
})


@dataclass
class _Seen:
    start: float  # monotonic time the interval began [s]
    count: int  # identical messages in the interval
    suppressed: int  # of them not logged and not yet reported
    level: int
    text: str


class RepeatFilter(logging.Filter):
    """Let through the first ``burst`` identical third-party messages per ``interval``.

    Args:
        own: the logger hierarchy left alone (twinwatch's own).
        max_kinds: distinct messages tracked at once; beyond it the oldest are forgotten
            (after reporting what they suppressed).

    Raises:
        ValueError: ``burst`` < 1 or ``interval`` <= 0.
    """

    def __init__(self, *, burst: int = 5, interval: float = 60.0, own: str = "twinwatch",
                 max_kinds: int = 1000, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        if burst < 1 or not interval > 0:
            raise ValueError(f"burst must be >= 1 and interval > 0, not {burst}, {interval}")
        self.burst = burst
        self.interval = interval
        self.own = own
        self.max_kinds = max_kinds
        self._clock = clock
        self._seen: dict[tuple[str, int, str], _Seen] = {}
        self._lock = threading.RLock()
        self._next_flush = 0.0
        self.suppressed = 0  #: messages suppressed in all, since installed
        _FILTERS.add(self)

    def filter(self, record: logging.LogRecord) -> bool:
        name = record.name
        if getattr(record, _SUMMARY, False) or name == self.own \
                or name.startswith(self.own + "."):
            return True
        text = str(record.msg)
        if (name, text) in BENIGN:
            return False
        key = (name, record.levelno, text)
        now = self._clock()
        with self._lock:
            seen = self._seen.get(key)
            if seen is not None and now - seen.start >= self.interval:
                self._report(key, seen, now)
                seen = None
            if seen is None:
                if len(self._seen) >= self.max_kinds:
                    oldest = next(iter(self._seen))
                    self._report(oldest, self._seen.pop(oldest), now)
                seen = self._seen[key] = _Seen(now, 0, 0, record.levelno, text)
            seen.count += 1
            if seen.count <= self.burst:
                return True
            seen.suppressed += 1
            self.suppressed += 1
            return False

    def _report(self, key: tuple[str, int, str], seen: _Seen, now: float) -> None:
        """One line from the message's logger: how many were suppressed (none: nothing)."""
        if not seen.suppressed:
            return
        n, seen.suppressed = seen.suppressed, 0
        text = seen.text if len(seen.text) <= 200 else seen.text[:197] + "..."
        logging.getLogger(key[0]).log(
            seen.level, "%d more identical messages suppressed in %.0f s (the first %d of "
            "every %.0f s are logged): %s", n, now - seen.start, self.burst, self.interval,
            text, extra={_SUMMARY: True})

    def flush(self, force: bool = False) -> None:
        """Report what was suppressed in the intervals that are over (``force``: in all, now)
        and forget the finished ones. Looks at most once a second unless forced."""
        now = self._clock()
        with self._lock:
            if not force and now < self._next_flush:
                return
            self._next_flush = now + 1.0
            for key, seen in list(self._seen.items()):
                over = now - seen.start >= self.interval
                if over or force:
                    self._report(key, seen, now)
                if over:
                    del self._seen[key]


def install(handler: logging.Handler, **kwargs: Any) -> RepeatFilter:
    """Attach a :class:`RepeatFilter` to ``handler`` (once: an existing one is returned).

    Args:
        **kwargs: :class:`RepeatFilter`'s arguments.
    """
    for f in handler.filters:
        if isinstance(f, RepeatFilter):
            return f
    f = RepeatFilter(**kwargs)
    handler.addFilter(f)
    return f


def flush(force: bool = False) -> None:
    """:meth:`RepeatFilter.flush` on every filter installed in this process."""
    for f in list(_FILTERS):
        f.flush(force)
