"""One machine's lifecycle: start, reload with fallback, sink handover, stop (docs/service.md).

:class:`Supervisor` runs one machine for the service host (:class:`~twinwatch.daemon.host.Host`,
which owns the signals, systemd, the summary and the exit status). In the machine's thread it

* opens every daemon in a thread of its own (``twinwatch-start``, ``twinwatch-reload``): a
  stop requested meanwhile abandons the opening (closed once open) and returns at once.
* tells its notifier where it is (``READY=1``, ``RELOADING=1``, ``STOPPING=1``,
  ``EXTEND_TIMEOUT_USEC``) and marks the watchdog through the daemon.
* on SIGHUP, re-reads the configuration while acquisition goes on. An invalid one is refused
  (logged, naming the key). A valid one is built beside the running daemon, sharing the driver
  and the outputs whose table is unchanged (:meth:`Daemon.handover`). If it cannot start, the
  running daemon goes on untouched; else the running daemon stops at its next window boundary,
  finishes its queued windows, and the new one continues the run from the same source.
* rate-limits third-party log floods (:mod:`twinwatch.daemon.logfilter`).

The supervisor never reads files itself: ``load`` returns the validated configuration.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twinwatch.daemon import logfilter
from twinwatch.daemon.systemd import Notifier, Watchdog
from twinwatch.errors import StartError

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig
    from twinwatch.daemon.pipeline import HealthCallback
    from twinwatch.daemon.runner import Daemon
    from twinwatch.daemon.slots import EstimationSlots
    from twinwatch.sinks.base import SharedResources
    from twinwatch.twin.health import HealthMessage

logger = logging.getLogger(__name__)

__all__ = ["StartError", "Stopped", "Supervisor", "status_line", "warm_up"]


class Stopped(StartError):
    """A stop (SIGTERM, SIGINT) was requested before the daemon had started."""


def warm_up(daemon: Daemon) -> None:
    """Compile the twin's numba kernels (cached on disk after the first run) with one
    simulation of a window of zeros, and the prognostics' with one trend fit. Best effort: the
    first window compiles them otherwise."""
    try:
        import numpy as np

        from twinwatch.twin.model import WindowData

        n = daemon.config.acquisition.window
        dt = daemon.config.acquisition.sample_period
        t = np.asarray(np.arange(n) * dt, dtype=np.float64)
        chans = {c: np.zeros(n) for c in daemon.model.required_channels()}
        theta = np.array([[daemon.nominal[p] for p in daemon.model.parameter_names]])
        daemon.model.simulate(theta, WindowData(t=t, channels=chans, index=-1))
        if daemon.config.prognostics.enabled:  # the trends' polish and grid
            from twinwatch.twin.prognostics.degradation import fit_models

            k = np.arange(20.0)
            fit_models(k, 1.0 + 1e-3 * k * k, np.full(k.size, 1e-3))
    except Exception:  # noqa: BLE001 - best effort: the first window compiles otherwise
        logger.debug("numba warm-up skipped", exc_info=True)


def status_line(config: TwinwatchConfig, daemon: Daemon) -> str:
    """The ``STATUS=`` systemd shows: what is monitored and where the health goes."""
    parts = [f"monitoring {config.machine.name} ({config.machine.model}, "
             f"{config.driver.type} driver)", *daemon.outputs.status()]
    if daemon.restored is not None:
        parts.append("twin resumed")
    problems = daemon.problems()
    if problems:
        parts.append("DEGRADED: " + "; ".join(problems))
    return ", ".join(parts)


class _Build:
    """A daemon being opened in a thread of its own, so that the main thread goes on acquiring
    (reload) and answers a stop at once. Nothing the running daemon handed over (``keep``) is
    ever closed by it.

    Args:
        open_daemon: opens the daemon (raises on failure).
        keep: output names (and ``"driver"``) shared with the running daemon.
    """

    def __init__(self, open_daemon: Callable[[], Daemon], *, keep: tuple[str, ...],
                 config: TwinwatchConfig, name: str) -> None:
        self.keep = keep
        self.config = config
        self.daemon: Daemon | None = None
        self.error: BaseException | None = None
        self._open = open_daemon
        self._abandoned = False
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            daemon = self._open()
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread
            self.error = exc
        else:
            with self._lock:
                abandoned = self._abandoned
                if not abandoned:
                    self.daemon = daemon
            if abandoned:
                daemon.close(keep=self.keep)
        finally:
            self._done.set()

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` [s]; True once the daemon is open or failed."""
        return self._done.wait(timeout)

    def abandon(self) -> None:
        """Nobody will run the daemon: close it now, or as soon as it is open."""
        with self._lock:
            self._abandoned = True
            daemon, self.daemon = self.daemon, None
        if daemon is not None:
            daemon.close(keep=self.keep)


class Supervisor:
    """Runs one machine's daemon as a service (see the module docstring).

    Args:
        load: returns the validated configuration (called at :meth:`start` and at each
            SIGHUP); raises ``ValueError`` (:class:`~twinwatch.config.loader.ConfigError`)
            naming the bad key.
        source: how to name the configuration in messages (its path).
        resume: as the :class:`~twinwatch.daemon.runner.Daemon`'s, at start; a reload always
            resumes, in the same run.
        notifier: where systemd's notifications go (default: the process's own, from
            ``NOTIFY_SOCKET``; a gateway's machines: their host).
        watchdog: the watchdog its daemons tick and mark busy/idle (default: one on the
            notifier).
        base_dir, work_dir, slots, shared: handed to every
            :class:`~twinwatch.daemon.runner.Daemon`.

    Attributes:
        config: the running configuration (after :meth:`start`).
        daemon: the running daemon, also after :meth:`run` returned (closed; its counters
            and history stay readable for the summary).
    """

    def __init__(self, load: Callable[[], TwinwatchConfig], *, base_dir: Path,
                 source: str, resume: bool | None = None, notifier: Notifier | None = None,
                 watchdog: Watchdog | None = None, work_dir: Path | None = None,
                 slots: EstimationSlots | None = None, shared: SharedResources | None = None,
                 thread_prefix: str = "twinwatch") -> None:
        self.notifier = notifier if notifier is not None else Notifier(unset_environment=True)
        self.watchdog = watchdog if watchdog is not None else Watchdog(self.notifier)
        self.work_dir = work_dir
        self.slots = slots
        self.shared = shared
        self._prefix = thread_prefix
        self._load = load
        self.base_dir = base_dir
        self.source = source
        self.config: TwinwatchConfig | None = None
        self.daemon: Daemon | None = None
        self._callbacks: list[HealthCallback] = []
        self._stop_requested = threading.Event()
        self._reload_requested = threading.Event()
        self._build: _Build | None = None  # a reload's daemon being opened
        self._next: _Build | None = None  # a reload's daemon, open: takes over at the boundary
        self._resume = resume
        self._problems: list[str] = []
        # the worker thread and the acquisition loop both report the problems (one step)
        self._problems_lock = threading.Lock()
        self._next_status = 0.0

    # -- start --------------------------------------------------------------------------------
    def start(self) -> None:
        """Load the configuration, open the daemon in the ``twinwatch-start`` thread, and tell
        systemd ``READY=1``.

        Raises:
            ValueError: the configuration is invalid (from ``load``).
            Stopped: a stop was requested before the daemon had started.
            StartError: the daemon cannot start.
        """
        try:
            cfg = self._load()
        except ValueError as exc:
            self.notifier.notify(f"STATUS=invalid configuration: {exc}".splitlines()[0])
            raise
        self.config = cfg
        build = _Build(lambda: self._open(cfg, resume=self._resume), keep=(), config=cfg,
                       name=f"{self._prefix}-start")
        while not build.wait(0.2):
            if self._stop_requested.is_set():  # the opening goes on alone and is closed after
                build.abandon()
                logfilter.flush(force=True)
                raise Stopped("stopped before the daemon had started")
        if build.error is not None:
            logfilter.flush(force=True)
            if isinstance(build.error, StartError):
                self.notifier.notify(f"STATUS=cannot start: {build.error}".splitlines()[0])
            raise build.error
        assert build.daemon is not None
        self.daemon = daemon = build.daemon
        if self._stop_requested.is_set():
            daemon.stop()
        self.notifier.ready(status=status_line(cfg, daemon))

    def add_callback(self, fn: HealthCallback) -> None:
        """Call ``fn(health)`` after each window, also from the daemons a reload starts."""
        self._callbacks.append(fn)
        if self.daemon is not None:
            self.daemon.add_callback(fn)

    def _open(self, cfg: TwinwatchConfig, reuse: dict[str, Any] | None = None,
              resume: bool | None = None, defer: tuple[str, ...] = (),
              run_id: str | None = None, wait_for_source: bool = True) -> Daemon:
        """A daemon on ``cfg`` (driver and sinks open, the twin's kernels compiled), with the
        reload tick and callbacks. Runs in a :class:`_Build`'s thread.

        Raises:
            StartError: a device, port, file or the state database cannot be opened.
        """
        from twinwatch.daemon.runner import Daemon

        with _start_errors():
            daemon = Daemon(cfg, base_dir=self.base_dir, persist=True, watchdog=self.watchdog,
                            reuse=reuse, resume=resume, defer=defer, run_id=run_id,
                            wait_for_source=wait_for_source, work_dir=self.work_dir,
                            slots=self.slots, shared=self.shared,
                            thread_prefix=self._prefix)
        daemon.add_tick(self._check_reload)
        daemon.add_tick(self._refresh_status)
        daemon.add_callback(self._watch_problems)
        for fn in self._callbacks:
            daemon.add_callback(fn)
        warm_up(daemon)
        return daemon

    def _refresh_status(self) -> None:
        """Acquisition-loop tick, at most once a second: STATUS follows the problems also while
        no window completes."""
        now = time.monotonic()
        if now < self._next_status:
            return
        self._next_status = now + 1.0
        self._watch_problems(None)

    def _watch_problems(self, health: HealthMessage | None) -> None:
        """After each window (worker thread) and every second (main thread): systemd's STATUS
        follows :meth:`Daemon.problems`."""
        daemon, cfg = self.daemon, self.config
        if daemon is None or cfg is None:
            return
        with self._problems_lock:  # else STATUS could end on the report read first
            now = daemon.problems()
            if now != self._problems:
                self._problems = now
                self.notifier.status(status_line(cfg, daemon))

    # -- requests (from the host) ----------------------------------------------------------
    def stop(self) -> None:
        """Ask :meth:`run` to finish the queued windows and return (thread- and signal-safe);
        a stop while the daemon is being opened abandons the opening (:meth:`start` raises
        :class:`Stopped`)."""
        self._stop_requested.set()
        if self.daemon is not None:
            self.daemon.stop()

    def abandon(self) -> None:
        """A second stop: the queued windows are abandoned (thread- and signal-safe)."""
        self._stop_requested.set()
        daemon = self.daemon
        if daemon is not None:
            daemon.worker.abandon = True
            daemon.stop()

    def reload(self) -> None:
        """Ask for a reload, as SIGHUP does (thread- and signal-safe)."""
        self._reload_requested.set()

    # -- reload -------------------------------------------------------------------------------
    def _check_reload(self) -> None:
        """Acquisition-loop tick (main thread): start a requested reload without stopping
        acquisition, and act on a reload's daemon once it is open or has failed."""
        logfilter.flush()
        if self._stop_requested.is_set():
            return
        if self._build is not None:
            if self._build.wait(0):
                self._built(self._build)
            return
        if not self._reload_requested.is_set() or self._next is not None:
            return
        self._reload_requested.clear()
        self.notifier.reloading("reloading the configuration")
        try:
            new_cfg = self._load()
            keep, defer = self._handover(new_cfg)
        except (ValueError, KeyError) as exc:  # invalid, or its machine's model cannot be built
            logger.error("reload refused, the running configuration goes on: %s",
                         one_line(str(exc)))
            self.notifier.ready(status=f"reload refused ({str(exc).splitlines()[-1].strip()}); "
                                "running the previous configuration")
            return
        assert self.daemon is not None
        running = self.daemon
        reuse = {name: running.driver if name == "driver" else running.sinks[name]
                 for name in keep}
        logger.warning("reloading %s: starting the new configuration beside the running one",
                       self.source)
        self._build = _Build(lambda: self._open(new_cfg, reuse=reuse, resume=False, defer=defer,
                                                run_id=running.run_id, wait_for_source=False),
                             keep=keep, config=new_cfg, name=f"{self._prefix}-reload")

    def _handover(self, new_cfg: TwinwatchConfig) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """``(keep, defer)``: :meth:`Daemon.handover`, plus the driver when the ``[driver]``
        table is unchanged."""
        assert self.daemon is not None and self.config is not None
        keep, wait = self.daemon.handover(new_cfg)
        if self.daemon.driver is not None and self.config.driver == new_cfg.driver:
            keep.append("driver")
        return tuple(keep), tuple(wait)

    def _built(self, build: _Build) -> None:
        """A reload's daemon is open (the running one stops at its next window boundary and
        hands over) or could not start (the running one goes on untouched)."""
        self._build = None
        if build.error is not None:
            exc = build.error
            if not isinstance(exc, StartError):
                logger.debug("the new configuration failed to start", exc_info=exc)
            logger.error("reload failed, the running configuration goes on (the same source, "
                         "run and window numbering): %s", exc)
            logfilter.flush(force=True)
            self.notifier.ready(status=f"reload failed ({str(exc).splitlines()[0].strip()}); "
                                "running the previous configuration")
            return
        logfilter.flush(force=True)
        self._next = build
        assert self.daemon is not None
        self.daemon.stop(at_window=True)

    def _take_over(self, build: _Build) -> None:
        """The running daemon has finished its queued windows: it releases what it does not
        hand over, and the reload's daemon takes over.

        Raises:
            StartError: a sink that had to wait for the old one's file or port cannot open.
        """
        old, new = self.daemon, build.daemon
        assert old is not None and new is not None
        old.close(keep=build.keep)
        try:
            with _start_errors():
                new.open_deferred()
        except StartError:
            new.close()
            raise
        new.continue_from(old)
        self.daemon, self.config = new, build.config
        if self._stop_requested.is_set():  # a stop that reached the old daemon only
            new.stop()
        logger.warning("configuration reloaded; the twin resumes from the state database")
        self.notifier.ready(status=status_line(build.config, new))

    def _abandon_reload(self) -> None:
        """A stop came before a reload's daemon took over: close it, sharing nothing."""
        pending = [b for b in (self._build, self._next) if b is not None]
        self._build = self._next = None
        for build in pending:
            build.abandon()
        if pending:
            logger.warning("reload abandoned: the daemon stopped (a stop was requested, or "
                           "the source ended) before the new configuration took over")

    # -- run ----------------------------------------------------------------------------------
    def run(self, duration: float | None = None) -> None:
        """Run the daemon until the source ends, ``duration`` seconds of source time, or a stop;
        a valid reload's daemon takes over. Closes the daemon before returning.

        Raises:
            StartError: after a reload, neither the new nor the previous configuration could
                start again.
        """
        assert self.daemon is not None and self.config is not None, "call start() first"
        try:
            while True:
                self.daemon.run(duration=duration)
                build = self._next
                if build is None or self._stop_requested.is_set() or self.daemon.ended:
                    break  # a reload's daemon still pending is abandoned below
                self._next = None
                self._take_over(build)
        finally:
            self._abandon_reload()
            self.notifier.stopping("stopping: finishing the queued windows")
            self.notifier.extend_timeout(self.config.acquisition.shutdown_timeout + 10)
            if self.daemon is not None:
                self.daemon.close()
            logfilter.flush(force=True)


@contextlib.contextmanager
def _start_errors() -> Iterator[None]:
    """Turn what opening a daemon raises for a missing device, port or file into
    :class:`StartError` (a traceback would add nothing); a driver's configuration error is
    marked as such (``run`` exits 78)."""
    from twinwatch.errors import DriverConfigError, DriverError, PluginError, SinkError

    try:
        yield
    except StartError:
        raise
    except DriverConfigError as exc:  # named by the configuration's key: driver.path
        raise StartError(exc.keyed(), config_error=True) from exc
    except (DriverError, SinkError, PluginError, ValueError, OSError) as exc:
        raise StartError(str(exc), config_error=False) from exc


def one_line(text: str) -> str:
    """A multi-line error in one log line: ``m.toml: invalid configuration: key: why; key:
    why``."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if len(lines) <= 1:
        return lines[0] if lines else text
    return f"{lines[0]}: " + "; ".join(lines[1:])
