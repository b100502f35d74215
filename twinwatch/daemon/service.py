"""The service contract: what ``twinwatch run`` is, whichever way its machines run.

A :class:`ServiceHost` owns, in the main thread, the loop (:meth:`~ServiceHost.run`), its tick
(the watchdog and ``STATUS``), the signals, the stop, the reload and the end of the run: the
exit status and a structured summary (:class:`RunSummary`). How the machines run is its
strategy, one of two hosts:

* :class:`~twinwatch.daemon.host.Host`: the machines in threads of this process (a file, a
  directory with ``--workers 1``, and each worker process of the other);
* :class:`~twinwatch.daemon.workers.ProcessHost`: a directory's machines in worker processes,
  each one a :class:`~twinwatch.daemon.host.Host` on the machine files it is assigned.

The command line holds one ``ServiceHost`` and only prints what it returns; a
worker reports to its host in typed messages (:class:`FleetStatus`, :class:`RunSummary`).
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field

from twinwatch.daemon.systemd import Notifier

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthMessage

logger = logging.getLogger(__name__)

__all__ = ["EX_CONFIG", "EX_IOERR", "EX_TEMPFAIL", "FLEET_REPORT", "MACHINE_GLOB", "FleetStatus",
           "MachineSummary", "Progress", "RunSummary", "ServiceHost", "gateway_total",
           "worst_exit"]

#: The machine configurations of a directory.
MACHINE_GLOB = "*.toml"

EX_CONFIG = 78
"""Exit status: no machine's configuration can run here (sysexits.h); the units do not restart
on it."""

EX_IOERR = 74
"""Exit status: estimated windows were lost, not stored or not recorded (sysexits.h)."""

EX_TEMPFAIL = 75
"""Exit status: a machine ran but more of its windows failed than were estimated."""

FLEET_REPORT = "TWINWATCH_FLEET"
"""The notification assignment a worker process's host sends its :class:`FleetStatus` in (JSON,
beside ``STATUS=``; systemd ignores assignments it does not know)."""


def gateway_total(machines: int, lost: list[str]) -> str:
    """A gateway's summary line: ``twinwatch gateway: 3 machines, 2 ran, 1 lost: m3 (...)``."""
    return (f"twinwatch gateway: {machines} machines, {machines - len(lost)} ran, {len(lost)} "
            "lost" + (": " + "; ".join(lost) if lost else ""))


class _Report(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class FleetStatus(_Report):
    """What a fleet's ``STATUS=`` line says, as data: the machines monitored and the degraded
    ones (a worker sends it to its host, which adds them up)."""

    monitored: int = Field(description="machines running (started, not lost)")
    machines: int = Field(description="machines of the fleet (current files)")
    degraded: list[str] = Field(description="each degraded machine, ``name: problem, ...``")
    window_s: float | None = Field(None, description="a worker's longest window [s] (window x "
                                   "sample period of its machines): its host calls it stalled "
                                   "when it sent nothing for this plus STALL_MARGIN")
    stalled_restart: float | None = Field(None, description="a worker's machines' smallest "
                                          "``[acquisition] stalled_restart`` [s] (0: never)")

    def line(self, where: str) -> str:
        """The ``STATUS=`` text, e.g. ``gateway: 2 of 3 machines monitored (DIR); DEGRADED: bad:
        lost (...)``; ``where`` goes in the brackets (the directory, and the worker processes)."""
        text = f"gateway: {self.monitored} of {self.machines} machines monitored ({where})"
        return text + ("; DEGRADED: " + "; ".join(self.degraded) if self.degraded else "")


class MachineSummary(_Report):
    """One machine's block of the run's summary."""

    name: str = Field(description="``[machine] name`` (the file's stem before it loaded)")
    file: str = Field(description="its configuration file's name")
    lost: str | None = Field(None, description="why it stopped or never started (one line)")
    lines: list[str] = Field(default_factory=list,
                             description="its summary (:func:`~twinwatch.daemon.summary."
                             "machine_lines`); empty when no daemon ran")

    def header(self) -> str:
        """``== m1 (m1.toml): stopped``, or ``...: lost: why``."""
        return f"== {self.name} ({self.file}): " + (
            f"lost: {self.lost}" if self.lost is not None else "stopped")


class RunSummary(_Report):
    """The end of a run, as the host knows it: what to print and the exit status.

    A fleet of one has one machine and no ``total``: its block is printed without a header.
    A fleet prints each machine's header and block, in file order, then ``total``.
    """

    machines: list[MachineSummary] = Field(description="every machine that ran or was lost "
                                           "(a machine tried again by a reload: each attempt)")
    total: str | None = Field(None, description="a fleet's last line (``twinwatch gateway: 3 "
                              "machines, 2 ran, 1 lost...``); None for a fleet of one")
    errors: list[str] = Field(default_factory=list,
                              description="lines for stderr (why a fleet of one stopped)")
    exit_status: int = Field(description="the process's exit status (0, 1, 74, 75, 78)")

    def lines(self) -> list[str]:
        """The lines for stdout."""
        if self.total is None:
            return [line for m in self.machines for line in m.lines]
        return [*(line for m in self.machines for line in (m.header(), *m.lines)), self.total]


@dataclass(frozen=True)
class Progress:
    """A fleet of one's progress, for a bar at the terminal.

    Attributes:
        name: the machine's name.
        total: the source time the run covers [s] (None: open-ended).
        add_callback: registers a function called with each window's typed message (in the
            machine's worker thread).
    """

    name: str
    total: float | None
    add_callback: Callable[[Callable[[HealthMessage], None]], None]


def worst_exit(codes: Iterable[int]) -> int:
    """The service's exit status from its machines' (or its worker processes') own: 78 when
    every one is 78 (no configuration could run), 1 when one was lost (1, a 78 among others,
    or ended by a signal), else 74 (estimated windows lost) before 75 (more windows failed than
    estimated) before 0."""
    codes = list(codes)
    if codes and all(c == EX_CONFIG for c in codes):
        return EX_CONFIG
    if any(c in (1, EX_CONFIG) or c < 0 for c in codes):
        return 1
    return next((c for c in (EX_IOERR, EX_TEMPFAIL) if c in codes), 0)


class ServiceHost(ABC):
    """The service: the loop, the signals, systemd, the stop, the summary and the exit status
    (see the module docstring).

    Use: :meth:`start`, :meth:`notices` and :meth:`progress` for the terminal, :meth:`run`
    until every machine ended or a stop, then :meth:`summary`.

    Signals, installed by :meth:`start` in the main thread: SIGTERM/SIGINT call :meth:`stop` (a
    second one :meth:`abandon`), SIGHUP :meth:`reload`; once a stop was requested they stay
    installed to the end of the process (a late SIGTERM must not end a cleanly stopped service
    with -15).

    Args:
        notifier: the process's systemd notifier (default: from ``NOTIFY_SOCKET``, which it
            takes from the environment).
        work_root: where the machines work (default: the current directory).
        resume: as :class:`~twinwatch.daemon.supervisor.Supervisor`'s.
        duration: each machine stops after this many seconds of source time (None: runs on).

    Attributes:
        fleet: a directory of machines (one block per machine in the summary).
    """

    fleet: bool
    notifier: Notifier
    #: the level the stop signals are logged at (a worker process: debug; its host logs them)
    signal_log_level: int = logging.WARNING

    #: seconds between two turns of the loop
    turn_s: float = 0.2

    def __init__(self, *, notifier: Notifier | None, work_root: Path | None,
                 resume: bool | None, duration: float | None) -> None:
        self.notifier = notifier if notifier is not None else Notifier(unset_environment=True)
        self.work_root = (work_root or Path.cwd()).resolve()
        self.resume = resume
        self.duration = duration
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._stop_signals = 0
        self._previous_handlers: dict[int, Any] = {}
        self._status = ""  # the last STATUS line sent
        self._last_ping = 0.0
        self._next_status = 0.0

    # -- the contract -------------------------------------------------------------------------
    @abstractmethod
    def start(self) -> None:
        """Install the signal handlers, start the machines and tell systemd ``READY=1``.

        Raises:
            ConfigError: there is no machine to run (a directory without configurations).
        """

    def run(self) -> None:
        """Supervise until every machine has ended or a stop; act on SIGHUP; keep ``STATUS``
        and the watchdog. Stops every machine before returning (``STATUS=stopped: ...`` when
        the run failed)."""
        from twinwatch.daemon import logfilter

        try:
            while not self._stop.is_set():
                if self._reload.is_set():
                    self._reload.clear()
                    self._rescan()
                if not self._turn():
                    break
                self._tick()
                self._stop.wait(self.turn_s)
        finally:
            self._stop_all()
            self._restore_signal_handlers()
            logfilter.flush(force=True)
        why = self._stopped_why()
        if why is not None:
            self.notifier.status(f"stopped: {why}")

    def _tick(self) -> None:
        """The watchdog pinged while a machine is healthy; ``STATUS`` refreshed every second."""
        now = time.monotonic()
        interval = self.notifier.watchdog_interval
        if (interval is not None and now - self._last_ping >= interval
                and self._healthy(interval)):
            self._last_ping = now
            self.notifier.watchdog()
        if now >= self._next_status:
            self._next_status = now + 1.0
            self._refresh_status()

    def _stop_all(self) -> None:
        """Stop every machine, systemd's stop timeout extended to :meth:`_grace` plus 10 s;
        each is waited for until the grace plus 5 s."""
        self.notifier.stopping("stopping: the machines finish their queued windows"
                               if self.fleet else "stopping: finishing the queued windows")
        grace = self._grace()
        self.notifier.extend_timeout(grace + 10)
        self._ask_to_stop()
        self._wait_stopped(time.monotonic() + grace + 5, grace + 5)

    # -- the strategy ---------------------------------------------------------------------------
    @abstractmethod
    def _turn(self) -> bool:
        """One turn of the loop; False when every machine has ended."""

    @abstractmethod
    def _rescan(self) -> None:
        """SIGHUP: the machines started, stopped and reloaded as the configuration says."""

    @abstractmethod
    def _healthy(self, interval: float) -> bool:
        """A machine is healthy (the watchdog is pinged every ``interval`` [s])."""

    def _refresh_status(self) -> None:
        """Send ``STATUS`` when it changed."""
        line = self.status_line()
        if line != self._status:
            self._status = line
            self.notifier.status(line)

    @abstractmethod
    def _grace(self) -> float:
        """The longest the machines take to finish their queued windows [s]."""

    @abstractmethod
    def _ask_to_stop(self) -> None:
        """Ask every machine to stop."""

    @abstractmethod
    def _wait_stopped(self, deadline: float, limit: float) -> None:
        """Wait for every machine until ``deadline`` [s, monotonic], ``limit`` [s] after
        the stop was asked."""

    def _stopped_why(self) -> str | None:
        """Why the run failed, for the last STATUS; None when it did not."""
        code = self.exit_status()
        return f"exit status {code}" if code else None

    @abstractmethod
    def status_line(self) -> str:
        """systemd's ``STATUS=`` now."""

    @abstractmethod
    def exit_status(self) -> int:
        """The process's exit status once :meth:`run` returned (:func:`worst_exit`)."""

    @abstractmethod
    def summary(self) -> RunSummary:
        """The run's summary once :meth:`run` returned."""

    @abstractmethod
    def abandon(self) -> None:
        """A second stop: every machine abandons its queued windows."""

    def notices(self) -> list[str]:
        """Lines for the terminal once started."""
        return []

    def progress(self) -> Progress | None:
        """A fleet of one's running machine, for a progress bar; None otherwise."""
        return None

    def stop(self) -> None:
        """Ask :meth:`run` to stop every machine and return (thread- and signal-safe)."""
        self._stop.set()

    def reload(self) -> None:
        """Ask for a reload, as SIGHUP does (thread- and signal-safe)."""
        self._reload.set()

    # -- signals ------------------------------------------------------------------------------
    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for signum, handler in ((signal.SIGINT, self._on_stop_signal),
                                (signal.SIGTERM, self._on_stop_signal),
                                (signal.SIGHUP, self._on_hup)):
            self._previous_handlers[signum] = signal.signal(signum, handler)

    def _restore_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread() or self._stop_signals:
            # a late SIGTERM must find our handler (see the class)
            return
        for signum, handler in self._previous_handlers.items():
            signal.signal(signum, handler)
        self._previous_handlers.clear()

    def _on_stop_signal(self, signum: int, frame: FrameType | None) -> None:
        self._stop_signals += 1
        if self._stop_signals > 1:
            logger.log(self.signal_log_level, "%s received again: abandoning the queued "
                       "windows", signal.Signals(signum).name)
            self.abandon()
            return
        logger.log(self.signal_log_level, "%s received: %s", signal.Signals(signum).name,
                       "every machine finishes its queued windows and stops" if self.fleet
                       else "finishing the queued windows and stopping")
        self.stop()

    def _on_hup(self, signum: int, frame: FrameType | None) -> None:
        self.reload()
