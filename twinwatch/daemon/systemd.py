"""systemd service notifications (``sd_notify(3)``) and the watchdog, without a C extension.

Under ``Type=notify`` systemd passes ``$NOTIFY_SOCKET``, an ``AF_UNIX`` datagram socket (a path,
or an abstract name written with a leading ``@``), and, with ``WatchdogSec=``, ``$WATCHDOG_USEC``
(and ``$WATCHDOG_PID``). The protocol is one datagram of newline-separated ``KEY=VALUE``
assignments per notification: ``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``RELOADING=1``
(with ``MONOTONIC_USEC=``, required by ``Type=notify-reload`` from systemd 253), ``STOPPING=1``,
``EXTEND_TIMEOUT_USEC=``. Outside systemd (no ``$NOTIFY_SOCKET``) every call is a no-op.

Not a library: ``systemd-python`` needs libsystemd headers and a C compiler on the target;
``sdnotify`` swallows every exception and knows nothing of the watchdog or ``MONOTONIC_USEC``.

Errors never propagate: a monitoring daemon must not stop because systemd did not hear it. The
first failure is logged as a WARNING, later ones at DEBUG.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping

logger = logging.getLogger(__name__)

STATE_WAIT = 2.0
"""Seconds a state change (``READY``, ``RELOADING``, ``STOPPING``) waits for room in a full
notification queue before it is dropped; a watchdog ping or STATUS line does not wait."""

_STATE_CHANGES = frozenset({"READY", "RELOADING", "STOPPING"})

__all__ = ["Notifier", "Watchdog"]


class Notifier:
    """Sends ``sd_notify`` messages to the service manager; a no-op outside systemd.

    Args:
        env: environment to read ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` from
            (default ``os.environ``).
        unset_environment: remove those variables from ``os.environ`` after reading them, so
            child processes do not notify on our behalf (as ``sd_notify(1, ...)``).

    Attributes:
        watchdog_usec: ``WatchdogSec=`` in microseconds, or None when the watchdog is off or
            meant for another process.
        dropped: notifications dropped because the manager's queue was full.

    Thread-safe: each notification is one ``sendto`` under a lock, never blocking the caller
    on a full queue beyond :data:`STATE_WAIT`.
    """

    def __init__(self, *, env: Mapping[str, str] | None = None,
                 unset_environment: bool = False) -> None:
        e = os.environ if env is None else env
        self._address: str | None = None
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._failed = False
        self.dropped = 0
        self._full = False  # the queue was found full: logged, until a notification passes
        raw = e.get("NOTIFY_SOCKET", "")
        if raw.startswith("@"):
            self._address = "\0" + raw[1:]  # Linux abstract namespace
        elif raw.startswith("/"):
            self._address = raw
        elif raw:
            logger.warning("NOTIFY_SOCKET=%r is not an AF_UNIX address (vsock is not "
                           "supported): systemd will not be told when twinwatch is ready", raw)
        self.watchdog_usec: int | None = None
        wd = e.get("WATCHDOG_USEC", "")
        pid = e.get("WATCHDOG_PID", "")
        if wd:
            try:
                usec = int(wd)
                if usec > 0 and (not pid or int(pid) == os.getpid()):
                    self.watchdog_usec = usec
            except ValueError:
                logger.warning("ignoring WATCHDOG_USEC=%r / WATCHDOG_PID=%r: not integers",
                               wd, pid)
        if unset_environment and env is None:
            for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
                os.environ.pop(k, None)

    @property
    def enabled(self) -> bool:
        return self._address is not None

    @property
    def watchdog_interval(self) -> float | None:
        """Seconds between ``WATCHDOG=1`` pings: half of ``WatchdogSec=`` (as systemd
        recommends), or None when the watchdog is off."""
        return None if self.watchdog_usec is None else self.watchdog_usec / 2e6

    def notify(self, *assignments: str) -> bool:
        """Send one datagram with the given ``KEY=VALUE`` assignments.

        Returns:
            True if it was sent, False outside systemd or on a (logged) socket error.
        """
        if self._address is None:
            return False
        payload = "\n".join(assignments).encode("utf-8", "replace")
        state = any(a.split("=", 1)[0] in _STATE_CHANGES for a in assignments)
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX,
                                               socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                deadline = time.monotonic() + (STATE_WAIT if state else 0.0)
                while True:
                    try:
                        self._sock.sendto(payload, socket.MSG_DONTWAIT, self._address)
                        break
                    except BlockingIOError:  # the manager's queue is full
                        if time.monotonic() < deadline:
                            time.sleep(0.01)
                            continue
                        self.dropped += 1
                        if not self._full:  # once per episode
                            self._full = True
                            logger.warning(
                                "the service manager does not read its notifications at %r "
                                "(its queue is full): %s and later ones are dropped and "
                                "counted, monitoring goes on; if its watchdog is on it may "
                                "restart the service", self._address.replace("\0", "@"),
                                assignments[0].split("=", 1)[0])
                        return False
                if self._full:
                    self._full = False
                    logger.info("the service manager reads its notifications again (%d "
                                "dropped so far)", self.dropped)
            except OSError as exc:
                if not self._failed:
                    logger.warning("cannot notify systemd at %r (%s): readiness and watchdog "
                                   "pings are lost; check NotifyAccess= and the unit file",
                                   self._address.replace("\0", "@"), exc)
                    self._failed = True
                else:
                    logger.debug("sd_notify failed: %s", exc)
                return False
            if self._failed:
                logger.info("systemd notifications work again")
                self._failed = False
        return True

    # -- the messages twinwatch sends --------------------------------------------------------
    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up or a reload finished."""
        return self.notify("READY=1", *self._status(status))

    def status(self, text: str) -> bool:
        """``STATUS=text``: one line shown by ``systemctl status`` (newlines are replaced)."""
        return self.notify(*self._status(text))

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: we are alive; must come at least every ``WatchdogSec=``."""
        return self.notify("WATCHDOG=1")

    def reloading(self, status: str | None = None) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC``: a reload (SIGHUP) started. Send
        :meth:`ready` when the new configuration runs (or the old one was kept)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify("RELOADING=1", f"MONOTONIC_USEC={usec}",
                           *self._status(status))

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown started (SIGTERM/SIGINT)."""
        return self.notify("STOPPING=1", *self._status(status))

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: ask for ``seconds`` more before systemd's start/stop
        timeout fires."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={max(0, int(seconds * 1e6))}")

    @staticmethod
    def _status(text: str | None) -> tuple[str, ...]:
        if text is None:
            return ()
        return ("STATUS=" + " ".join(text.splitlines()),)

    def close(self) -> None:
        """Close the socket (idempotent; a later notification reopens it)."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Watchdog:
    """When to send ``WATCHDOG=1``: from the acquisition loop, at the notifier's interval, and
    only while windows are being processed.

    The acquisition loop calls :meth:`tick`, so a hung driver read or a dead main loop stops
    the pings; the worker calls :meth:`busy` before and :meth:`idle` after each window. The
    pings stop (and systemd restarts the service) when the worker has been in one window for
    more than ``max_busy`` seconds, or, with ``require_windows`` (``[acquisition] watchdog =
    "windows"``), no window has finished for more than ``max_quiet`` seconds, unless the driver
    reports it is recovering the source (:attr:`source_waiting`).

    Args:
        max_busy: seconds one window may take before the worker counts as stuck (default
            ``WatchdogSec=``).
        max_quiet: seconds without a finished window before the pings stop (default
            ``WatchdogSec=``); counted from the first :meth:`tick`, so start-up has as long.
        clock: monotonic clock (tests inject one).
    """

    def __init__(self, notifier: Notifier, *, max_busy: float | None = None,
                 max_quiet: float | None = None, require_windows: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.notifier = notifier
        self.interval = notifier.watchdog_interval
        watchdog_sec = None if self.interval is None else 2.0 * self.interval
        self.max_busy = max_busy if max_busy is not None else watchdog_sec
        self.max_quiet = max_quiet if max_quiet is not None else watchdog_sec
        self.require_windows = require_windows
        self._clock = clock
        self._last_ping: float | None = None
        self._busy_since: float | None = None
        self._last_window: float | None = None
        self._why_logged: str | None = None
        self.pings = 0
        #: True while the driver recovers its source (``Driver.waiting``): the pings go on
        self.source_waiting: Callable[[], bool] = lambda: False

    @property
    def enabled(self) -> bool:
        return self.interval is not None and self.notifier.enabled

    def busy(self) -> None:
        """The worker starts a window (called from the worker thread)."""
        self._busy_since = self._clock()

    def idle(self) -> None:
        """The worker finished a window, successfully or not (worker thread)."""
        self._busy_since = None
        self._last_window = self._clock()

    def reset(self) -> None:
        """Restart the quiet clock (a reload's first window needs a window of samples)."""
        self._last_window = self._clock()

    def _unhealthy(self) -> tuple[str, str] | None:
        """Why the pings must stop now (a key and an operator message), or None."""
        now = self._clock()
        since = self._busy_since
        if since is not None and self.max_busy is not None and now - since > self.max_busy:
            return "stuck", (f"the adaptation worker has been in one window for "
                             f"{now - since:.0f} s: watchdog pings stop and systemd will "
                             "restart twinwatch")
        quiet = self.quiet_seconds()
        if self.source_waiting():  # the driver recovers the source: waiting is healthy
            self._last_window = now
            quiet = 0.0
        if (self.require_windows and since is None and self.max_quiet is not None
                and quiet > self.max_quiet):
            return "quiet", (f"no window processed for {quiet:.0f} s (no samples, or every "
                             "window abandoned for gaps or bad values: see the warnings "
                             "above): watchdog pings stop and systemd will restart twinwatch; "
                             "for a machine that is idle for long, set [acquisition] "
                             'watchdog = "alive"')
        return None

    def busy_seconds(self) -> float | None:
        """Seconds the worker has been in the window it is processing, None when idle."""
        since = self._busy_since
        return None if since is None else self._clock() - since

    def quiet_seconds(self) -> float:
        """Seconds since a window last finished (or since :meth:`reset`, the first call)."""
        now = self._clock()
        if self._last_window is None:
            self._last_window = now
        return now - self._last_window

    def healthy(self) -> bool:
        """False while the pings must stop (see the class)."""
        return self._unhealthy() is None

    def tick(self) -> bool:
        """Send ``WATCHDOG=1`` if one is due and the daemon is healthy (acquisition thread).

        Returns:
            True if a ping was sent now.
        """
        if not self.enabled:
            return False
        why = self._unhealthy()
        if why is not None:
            if why[0] != self._why_logged:  # logged once per episode
                logger.error("%s", why[1])
                self._why_logged = why[0]
            return False
        self._why_logged = None
        now = self._clock()
        assert self.interval is not None
        if self._last_ping is not None and now - self._last_ping < self.interval:
            return False
        self._last_ping = now
        if self.notifier.watchdog():
            self.pings += 1
            return True
        return False
