"""The service around one daemon: signals, systemd, reload with fallback, sink handover.

:class:`Supervisor` is what ``twinwatch run`` starts (the CLI keeps only its arguments and
printing). In the main thread it

* installs the signal handlers first (a SIGTERM while the drivers and sinks start stops
  cleanly too). The handlers only set flags; the acquisition loop acts on them (a handler that
  logged to systemd's socket or took a lock the interrupted code holds could deadlock).
  SIGTERM/SIGINT: finish the windows already queued, then stop (a second one abandons them).
  SIGHUP: reload.
* tells systemd where it is (``READY=1`` with a status line, ``RELOADING=1``, ``STOPPING=1``,
  ``EXTEND_TIMEOUT_USEC`` for the shutdown) and feeds the watchdog through the daemon
  (:class:`~twinwatch.daemon.systemd.Watchdog`).
* on SIGHUP, re-reads the configuration *while acquisition goes on* (a tick of the daemon's
  loop). A configuration that does not validate is refused (logged, naming the key) and the
  running one goes on. A valid one restarts the daemon in process: the outputs are handed to the
  new daemon open, which keeps those whose table is unchanged (each output's
  :meth:`~twinwatch.sinks.base.Sink.reload_key`: the Zenoh session, the Rerun file, the state
  database) and closes the others; the twin resumes from the state database. If the new
  configuration cannot start (a device, a port), the previous one is started again.
* compiles the twin's numba kernels before ``READY=1`` (:func:`warm_up`), so the first window
  does not look like a stuck worker to the watchdog.

The supervisor never reads files itself: ``load`` (given by the caller) returns the validated
configuration, at start and at each reload.
"""

from __future__ import annotations

import faulthandler
import logging
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from twinwatch.daemon.systemd import Notifier, Watchdog
from twinwatch.errors import StartError

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.pipeline import HealthCallback
    from twinwatch.daemon.runner import Daemon
    from twinwatch.sinks.base import Sink
    from twinwatch.twin.health import HealthMessage

logger = logging.getLogger(__name__)

__all__ = ["StartError", "Supervisor", "status_line", "warm_up"]


def warm_up(daemon: Daemon) -> None:
    """Compile the twin's numba kernels (cached on disk after the first run) with one
    simulation of a window of zeros. Best effort: the first window compiles them otherwise."""
    try:
        import numpy as np

        from twinwatch.twin.model import WindowData

        n = daemon.config.acquisition.window
        dt = daemon.config.acquisition.sample_period
        t = np.asarray(np.arange(n) * dt, dtype=np.float64)
        chans = {c: np.zeros(n) for c in daemon.model.required_channels()}
        theta = np.array([[daemon.nominal[p] for p in daemon.model.parameter_names]])
        daemon.model.simulate(theta, WindowData(t=t, channels=chans, index=-1))
    except Exception:  # noqa: BLE001 - best effort: the first window compiles otherwise
        logger.debug("numba warm-up skipped", exc_info=True)


def status_line(config: TwinwatchConfig, daemon: Daemon) -> str:
    """The ``STATUS=`` systemd shows: what is monitored and where the health goes."""
    parts = [f"monitoring {config.machine.name} ({config.machine.model}, "
             f"{config.driver.type} driver)", *daemon.status()]
    if daemon.restored is not None:
        parts.append("twin resumed")
    problems = daemon.problems()
    if problems:
        parts.append("DEGRADED: " + "; ".join(problems))
    return ", ".join(parts)


class Supervisor:
    """Runs one machine's daemon as a service (see the module docstring).

    Args:
        load: returns the validated configuration (called at :meth:`start` and at each
            SIGHUP); raises ``ValueError`` (:class:`~twinwatch.config.loader.ConfigError`)
            naming the bad key.
        base_dir: directory relative paths in the configuration are resolved against.
        source: how to name the configuration in messages (its path).
        resume: resume the twin and alarm levels saved in the state database at start
            (False: the nameplate values, ``twinwatch run --fresh``; a reload always resumes).

    Attributes:
        config: the running configuration (after :meth:`start`).
        daemon: the running daemon, also after :meth:`run` returned (closed; its counters
            and history stay readable for the summary).
        notifier: the systemd notifier (a no-op outside systemd).
    """

    def __init__(self, load: Callable[[], TwinwatchConfig], *, base_dir: Path,
                 source: str, resume: bool = True) -> None:
        self.notifier = Notifier(unset_environment=True)
        self.watchdog = Watchdog(self.notifier)
        self._load = load
        self.base_dir = base_dir
        self.source = source
        self.config: TwinwatchConfig | None = None
        self.daemon: Daemon | None = None
        self._callbacks: list[HealthCallback] = []
        self._stop_requested = threading.Event()
        self._reload_requested = threading.Event()
        self._pending: list[TwinwatchConfig] = []  # a validated configuration to restart with
        self._previous_handlers: dict[int, Any] = {}
        self._resume = resume
        self._problems: list[str] = []

    # -- start --------------------------------------------------------------------------------
    def start(self) -> None:
        """Load the configuration, install the signal handlers, open the daemon (driver and
        sinks), compile the twin and tell systemd ``READY=1``.

        Raises:
            ValueError: the configuration is invalid (from ``load``; systemd's status says so).
            StartError: the daemon cannot start.
        """
        # systemd's watchdog kills with SIGABRT: write every thread's stack to stderr (the
        # journal) first, so a stuck worker or a hung driver read shows where it was. (An
        # stderr without a file descriptor, e.g. click's test runner, has nowhere to write it.)
        try:
            faulthandler.enable()
        except (AttributeError, ValueError, OSError):
            logger.debug("faulthandler not enabled: stderr has no file descriptor")
        try:
            cfg = self._load()
        except ValueError as exc:
            self.notifier.notify(f"STATUS=invalid configuration: {exc}".splitlines()[0])
            raise
        self.config = cfg
        self._install_signal_handlers()
        try:
            daemon = self._open(cfg, resume=self._resume)
        except StartError as exc:
            self.notifier.notify(f"STATUS=cannot start: {exc}".splitlines()[0])
            self._restore_signal_handlers()
            raise
        self.daemon = daemon
        if self._stop_requested.is_set():
            daemon.stop()
        warm_up(daemon)
        self.notifier.ready(status=status_line(cfg, daemon))

    def add_callback(self, fn: HealthCallback) -> None:
        """Call ``fn(health)`` after each window, also from the daemons a reload starts."""
        self._callbacks.append(fn)
        if self.daemon is not None:
            self.daemon.add_callback(fn)

    def _open(self, cfg: TwinwatchConfig, reuse: dict[str, Sink] | None = None,
              resume: bool = True) -> Daemon:
        """A daemon on ``cfg`` (driver and outputs open), with the reload tick and callbacks.

        Raises:
            StartError: a device, port, file, an output or the state database cannot be
                opened.
        """
        from twinwatch.daemon.runner import Daemon
        from twinwatch.errors import DriverConfigError, DriverError, PluginError, SinkError

        # each output raises a SinkError subclass (PublisherError, RecorderError, StoreError,
        # a plug-in's own) that says what failed and what to do
        start_errors = (DriverError, SinkError, PluginError, ValueError, OSError)
        try:
            daemon = Daemon(cfg, base_dir=self.base_dir, persist=True, watchdog=self.watchdog,
                            reuse=reuse, resume=resume)
        except start_errors as exc:
            # Each of these says what failed and what to do; a traceback would add nothing.
            raise StartError(str(exc),
                             config_error=isinstance(exc, DriverConfigError)) from exc
        daemon.add_tick(self._check_reload)
        daemon.add_callback(self._watch_problems)
        for fn in self._callbacks:
            daemon.add_callback(fn)
        return daemon

    def _watch_problems(self, health: HealthMessage) -> None:
        """After each window (worker thread): systemd's STATUS follows what is degraded (the
        state database not writable, the recording stopped), and returns to normal."""
        daemon, cfg = self.daemon, self.config
        if daemon is None or cfg is None:
            return
        now = daemon.problems()
        if now != self._problems:
            self._problems = now
            self.notifier.status(status_line(cfg, daemon))

    # -- signals ------------------------------------------------------------------------------
    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for signum, handler in ((signal.SIGINT, self._on_stop_signal),
                                (signal.SIGTERM, self._on_stop_signal),
                                (signal.SIGHUP, self._on_hup)):
            self._previous_handlers[signum] = signal.signal(signum, handler)

    def _restore_signal_handlers(self) -> None:
        for signum, handler in self._previous_handlers.items():
            signal.signal(signum, handler)
        self._previous_handlers.clear()

    def _on_stop_signal(self, signum: int, frame: FrameType | None) -> None:
        daemon = self.daemon
        if self._stop_requested.is_set():
            if daemon is not None:
                daemon.abandon = True
            logger.warning("%s received again: abandoning the queued windows",
                           signal.Signals(signum).name)
            return
        logger.warning("%s received: finishing the queued windows and stopping",
                       signal.Signals(signum).name)
        self._stop_requested.set()
        if daemon is not None:
            daemon.stop()

    def _on_hup(self, signum: int, frame: FrameType | None) -> None:
        self._reload_requested.set()

    def stop(self) -> None:
        """Ask :meth:`run` to finish the queued windows and return (thread- and signal-safe)."""
        self._stop_requested.set()
        if self.daemon is not None:
            self.daemon.stop()

    def reload(self) -> None:
        """Ask for a reload, as SIGHUP does (thread- and signal-safe)."""
        self._reload_requested.set()

    # -- reload -------------------------------------------------------------------------------
    def _check_reload(self) -> None:
        """Acquisition-loop tick: validate a requested reload without stopping acquisition."""
        if not self._reload_requested.is_set() or self._stop_requested.is_set():
            return
        self._reload_requested.clear()
        self.notifier.reloading("reloading the configuration")
        try:
            new_cfg = self._load()
        except ValueError as exc:
            logger.error("reload refused, the running configuration goes on: %s", exc)
            self.notifier.ready(status=f"reload refused ({str(exc).splitlines()[-1].strip()}); "
                                "running the previous configuration")
            return
        logger.warning("reloading %s: restarting the daemon with the new configuration",
                       self.source)
        self._pending.append(new_cfg)
        if self.daemon is not None:
            self.daemon.stop()

    def _restart(self, new_cfg: TwinwatchConfig) -> None:
        """Replace the daemon by one on ``new_cfg``, handing over the outputs (it keeps those
        whose configuration is unchanged); if it cannot start, start the previous
        configuration again."""
        from twinwatch.sinks import SINKS

        assert self.daemon is not None and self.config is not None
        old_cfg = self.config
        reuse = self.daemon.close(keep=SINKS)
        self.daemon = None
        try:
            self.daemon = self._open(new_cfg, reuse=reuse)
            self.config = new_cfg
        except StartError as exc:
            logger.error("the new configuration cannot start (%s): going back to the "
                         "previous one", exc)
            for sink in reuse.values():  # what the failed start did not take over
                sink.close()
            self.daemon = self._open(old_cfg)
        logger.warning("configuration reloaded; the twin resumes from the state database")
        self.notifier.ready(status=status_line(self.config, self.daemon))

    # -- run ----------------------------------------------------------------------------------
    def run(self, duration: float | None = None) -> None:
        """Acquire and estimate until the source ends, ``duration`` seconds of source time
        have been acquired, or a stop signal; restart the daemon on each valid reload. Closes
        the daemon (driver, Zenoh, the Rerun file, the state database) before returning.

        Raises:
            StartError: after a reload, neither the new nor the previous configuration could
                start again.
        """
        assert self.daemon is not None and self.config is not None, "call start() first"
        try:
            while True:
                self.daemon.run(duration=duration)
                if self._stop_requested.is_set() or not self._pending:
                    break
                self._restart(self._pending.pop())
        finally:
            self.notifier.stopping("stopping: finishing the queued windows")
            self.notifier.extend_timeout(self.config.acquisition.shutdown_timeout + 10)
            if self.daemon is not None:
                self.daemon.close()
            self._restore_signal_handlers()
