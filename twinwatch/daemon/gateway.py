"""Gateway mode: many machines monitored by one process (``twinwatch run DIR``).

A plant line often has one edge box for many machines. :class:`Gateway` runs one
:class:`~twinwatch.daemon.supervisor.Supervisor` per machine configuration (``DIR/*.toml``), each
in a thread of its own (``twinwatch-<file>``: it runs that machine's acquisition loop, as the
main thread does for one machine), with everything the one-machine daemon has: its driver, ring
buffer, queue, worker (``twinwatch-<file>-adaptation``), outputs, watchdog, reload. What the
machines share:

* one **Zenoh session** per distinct ``[zenoh]`` session setting
  (:class:`~twinwatch.sinks.base.SharedResources`, :func:`twinwatch.sinks.zenoh.session_key`):
  machines configured alike publish their keys (``twinwatch/<machine>/...``) through one
  session listening on one port, instead of one session (and port) each;
* one pool of **estimation slots** (:class:`EstimationSlots`, sized to the cores): a worker
  processes a window only while it holds a slot, so at most as many windows are estimated at
  once as there are cores (the rest wait in their machine's queue, the wait recorded in
  :attr:`~twinwatch.daemon.runner.Daemon.queue_waits`): a window's estimation is not stretched
  by dozens of others competing for the GIL. A slot held longer than ``stuck_after`` (a window
  stuck in the optimiser) no longer counts, so one stuck machine cannot starve the others.

Isolation: a machine whose configuration is invalid, whose device cannot be opened, whose driver
fails or whose thread raises is *lost*: logged and reported under its name (STATUS, the summary,
:meth:`Gateway.lost`), and the others go on. A source that stalls holds only its own machine's
thread; a window that raises is counted in its own machine's ``numeric_failures``. The gateway
tells systemd READY once every machine has started or been lost (at most 60 s: a machine whose
source never answers is named ``starting``), keeps STATUS to the machines
that are degraded (``DEGRADED: m3: lost (...); m7: no window for 42 s``), and pings the
watchdog from its own loop (a machine stuck in one window is reported, not restarted with the
others).

Signals (the main thread): SIGTERM/SIGINT stop every machine (each finishes its queued windows;
a second signal abandons them). SIGHUP re-reads the directory: a new file starts its machine, a
file removed stops its machine, a changed file reloads its machine (the one-machine reload:
validated first, built beside the running daemon, taking over at a window boundary), a machine
not running (lost, or its source ended) is started again; unchanged files are left alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from twinwatch.daemon import logfilter
from twinwatch.daemon.supervisor import Stopped, Supervisor
from twinwatch.daemon.systemd import Notifier, Watchdog
from twinwatch.errors import ConfigError, StartError
from twinwatch.sinks.base import SharedResources

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig

logger = logging.getLogger(__name__)

__all__ = ["EstimationSlots", "Gateway", "Machine", "default_workers"]

MACHINE_GLOB = "*.toml"
"""The machine configurations of a gateway's directory (one machine per file)."""


def default_workers() -> int:
    """Estimation slots by default: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class EstimationSlots:
    """At most ``size`` windows processed at once across the machines of a gateway.

    A worker calls :meth:`acquire` before a window and :meth:`release` after it. A slot held
    for more than ``stuck_after`` seconds stops counting (its window is stuck: a machine's
    optimiser that does not return), so the other machines go on with one more slot; it is
    listed by :meth:`stuck`.

    Args:
        size: slots (>= 1), normally the cores (:func:`default_workers`).
        stuck_after: seconds after which a held slot no longer counts [s].
        clock: monotonic clock (tests inject one).
    """

    def __init__(self, size: int, *, stuck_after: float = 30.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if size < 1:
            raise ValueError(f"estimation slots must be at least 1, not {size}")
        self.size = size
        self.stuck_after = stuck_after
        self._clock = clock
        self._cond = threading.Condition()
        self._held: dict[int, tuple[str, float]] = {}
        self._line: deque[int] = deque()  # tokens waiting, in arrival order
        self._next = 0

    def _active(self, now: float) -> int:
        return sum(1 for _, t in self._held.values() if now - t < self.stuck_after)

    def acquire(self, holder: str, cancelled: Callable[[], bool] | None = None) -> int | None:
        """Wait for a slot (the worker's thread), first come first served (a machine cannot be
        overtaken for ever by the others); returns the token :meth:`release` takes, or None
        once ``cancelled()`` is true (checked every 0.5 s: the machine is closing)."""
        with self._cond:
            self._next += 1
            token = self._next
            self._line.append(token)
            try:
                while self._line[0] != token or self._active(self._clock()) >= self.size:
                    if cancelled is not None and cancelled():
                        return None
                    self._cond.wait(timeout=0.5)  # a slot may turn stuck: look again
            finally:
                self._line.remove(token)
                self._cond.notify_all()  # the next in line may fit too
            self._held[token] = (holder, self._clock())
            return token

    def release(self, token: int) -> None:
        """Give the slot of ``token`` back."""
        with self._cond:
            self._held.pop(token, None)
            self._cond.notify_all()

    def busy(self) -> int:
        """Slots held now (stuck ones included)."""
        with self._cond:
            return len(self._held)

    def stuck(self) -> list[tuple[str, float]]:
        """``(holder, seconds)`` of the slots held longer than ``stuck_after``."""
        now = self._clock()
        with self._cond:
            return [(h, now - t) for h, t in self._held.values() if now - t >= self.stuck_after]


class Machine:
    """One machine of a gateway: its configuration file, its supervisor and thread, and how it
    ended.

    Attributes:
        path: the configuration file.
        name: ``[machine] name`` once the configuration loaded (the file's stem before).
        supervisor: its supervisor (its ``daemon`` holds the counters and history).
        watchdog: its own watchdog (pings nothing: the gateway reads it to find a worker
            stuck in one window or a machine whose windows stopped).
        lost: why the machine stopped or never started, or None (it ran, or runs).
        config_error: ``lost`` is an invalid configuration.
        digest: the file's SHA-256 when it was (re)loaded (a reload leaves it alone if equal).
    """

    def __init__(self, path: Path, gateway: Gateway) -> None:
        self.path = path
        self.name = path.stem
        self.gateway = gateway
        self.lost: str | None = None
        self.config_error = False
        self.digest = _digest(path)
        self.started = threading.Event()  # running, or lost/stopped before it ran
        self.watchdog = Watchdog(Notifier(env={}), max_busy=gateway.stuck_after)
        self.supervisor = Supervisor(
            self._load, base_dir=path.resolve().parent, source=str(path),
            resume=gateway.resume, notifier=Notifier(env={}), watchdog=self.watchdog,
            slots=gateway.slots, shared=gateway.shared,
            thread_prefix=f"twinwatch-{path.stem}")
        self.thread = threading.Thread(target=self._run, name=f"twinwatch-{path.stem}",
                                       daemon=True)

    # -- the machine's thread -----------------------------------------------------------------
    def _load(self) -> TwinwatchConfig:
        """The supervisor's loader: this file, checked to run in this machine's directory
        (``<work root>/<machine name>``), its name unique in the gateway.

        Raises:
            ConfigError: naming the file and key.
        """
        cfg = self.gateway.read(self.path)
        name = cfg.machine.name
        self.gateway.claim(name, self)
        work_dir = self.gateway.work_root / name
        work_dir.mkdir(mode=0o750, exist_ok=True)
        self.supervisor.work_dir = work_dir
        self.gateway.check(cfg, self.path, work_dir)
        self.name = name
        return cfg

    def _run(self) -> None:
        sup = self.supervisor
        try:
            sup.start()
        except Stopped:
            self.started.set()
            return
        except ConfigError as exc:
            self._lose(f"invalid configuration: {exc}", config_error=True)
            return
        except StartError as exc:
            self._lose(f"cannot start: {exc}", config_error=exc.config_error)
            return
        except Exception as exc:  # noqa: BLE001 - contained to this machine
            logger.debug("%s failed to start", self.name, exc_info=True)
            self._lose(f"internal error at start: {type(exc).__name__}: {exc}")
            return
        self.started.set()
        try:
            sup.run(duration=self.gateway.duration)
        except StartError as exc:
            self._lose(f"cannot restart after a reload: {exc}")
        except Exception as exc:  # noqa: BLE001 - contained to this machine
            logger.debug("%s failed", self.name, exc_info=True)
            self._lose(f"internal error: {type(exc).__name__}: {exc}")
        daemon = sup.daemon
        if self.lost is None and daemon is not None and daemon.failure is not None:
            self._lose(daemon.failure)

    def _lose(self, why: str, *, config_error: bool = False) -> None:
        lines = [ln.strip() for ln in why.splitlines() if ln.strip()]
        # a ConfigError lists one problem a line: the log keeps them all, STATUS one line
        self.lost = "; ".join(lines) if len(lines) <= 3 else "; ".join(lines[:3]) + "; ..."
        logger.error("machine %s (%s) lost: %s", self.name, self.path.name, why)
        self.config_error = config_error
        self.started.set()

    # -- state --------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.thread.is_alive() and self.started.is_set() and self.lost is None

    def problems(self) -> list[str]:
        """What is degraded for this machine now (for STATUS): lost, stuck, no windows, and
        the daemon's own problems."""
        if self.lost is not None:
            return [f"lost ({self.lost})"]
        if not self.started.is_set() and self.thread.is_alive():
            return ["starting (its source or outputs are still opening)"]
        daemon = self.supervisor.daemon
        if daemon is None or not self.thread.is_alive():
            return []
        out = list(daemon.problems())
        busy = self.watchdog.busy_seconds()
        if busy is not None and busy > self.gateway.stuck_after:
            out.append(f"stuck in one window for {busy:.0f} s")
        quiet = self.watchdog.quiet_seconds()
        if busy is None and quiet > self.gateway.quiet_after and not out:
            out.append(f"no window for {quiet:.0f} s")
        return out


class Gateway:
    """Runs the machines of a directory in one process (see the module docstring).

    Args:
        directory: the machine configurations (``*.toml``, one machine each).
        read: reads and validates one configuration file (raises :class:`ConfigError`
            naming the file and key).
        check: checks a configuration can run with its files in a machine's directory
            (``check(cfg, path, work_dir)``; raises :class:`ConfigError`).
        work_root: each machine's state database and recording go to
            ``<work_root>/<machine name>/`` (created).
        resume: as :class:`~twinwatch.daemon.supervisor.Supervisor`'s.
        duration: each machine stops after this many seconds of source time (None: runs on).
        workers: estimation slots (:class:`EstimationSlots`); None: the cores; 0: no limit.
        stuck_after: seconds one window may take before its machine counts as stuck (and
            its estimation slot stops counting).
        quiet_after: seconds without a finished window before a machine is reported.

    Attributes:
        machines: configuration file -> its machine, in file order (the current ones).
        retired: machines a reload removed (their summary is still given).
        notifier: the process's systemd notifier.
    """

    def __init__(self, directory: Path, *, read: Callable[[Path], TwinwatchConfig],
                 check: Callable[[TwinwatchConfig, Path, Path], None],
                 work_root: Path | None = None, resume: bool | None = None,
                 duration: float | None = None, workers: int | None = None,
                 stuck_after: float = 30.0, quiet_after: float = 30.0) -> None:
        self.directory = directory
        self.read = read
        self._check = check
        self.work_root = (work_root or Path.cwd()).resolve()
        self.resume = resume
        self.duration = duration
        n = default_workers() if workers is None else workers
        self.stuck_after = stuck_after
        self.quiet_after = quiet_after
        self.slots = EstimationSlots(n, stuck_after=stuck_after) if n > 0 else None
        self.shared = SharedResources()
        self.notifier = Notifier(unset_environment=True)
        self.machines: dict[Path, Machine] = {}
        self.retired: list[Machine] = []
        self._names: dict[str, Machine] = {}
        self._names_lock = threading.Lock()
        self._stop = threading.Event()
        self._stop_signals = 0
        self._reload = threading.Event()
        self._previous_handlers: dict[int, Any] = {}
        self._status = ""
        self._next_status = 0.0
        self._last_ping = 0.0

    # -- configuration ------------------------------------------------------------------------
    def files(self) -> list[Path]:
        """The machine configurations in the directory, sorted by name."""
        return sorted(p for p in self.directory.glob(MACHINE_GLOB) if p.is_file())

    def claim(self, name: str, machine: Machine) -> None:
        """Reserve ``[machine] name`` for ``machine``.

        Raises:
            ConfigError: another file of the gateway monitors a machine of that name.
        """
        with self._names_lock:
            other = self._names.get(name)
            if other is not None and other is not machine and other.thread.is_alive():
                raise ConfigError(f"{machine.path}: machine.name {name!r} is already monitored "
                                  f"by {other.path.name} in this gateway: each machine needs "
                                  f"a name of its own")
            self._names[name] = machine

    def check(self, cfg: TwinwatchConfig, path: Path, work_dir: Path) -> None:
        self._check(cfg, path, work_dir)

    # -- start --------------------------------------------------------------------------------
    def start(self, timeout: float | None = 60.0) -> None:
        """Install the signal handlers, start every machine of the directory (each opens in
        its own thread) and tell systemd ``READY=1`` once each has started or been lost, or
        after ``timeout`` seconds [s] (None: no limit) with the machines still opening named
        in STATUS: one machine whose opening hangs does not keep the others from READY.

        Raises:
            ConfigError: the directory holds no machine configuration.
        """
        files = self.files()
        if not files:
            raise ConfigError(f"{self.directory}: no machine configuration ({MACHINE_GLOB}) "
                              "in this directory")
        self._install_signal_handlers()
        for path in files:
            self._add(path)
        deadline = None if timeout is None else time.monotonic() + timeout
        for m in list(self.machines.values()):
            while not m.started.wait(0.2):
                if self._stop.is_set() or (deadline is not None
                                           and time.monotonic() > deadline):
                    break
        self.notifier.ready(status=self.status_line())

    def _add(self, path: Path) -> Machine:
        m = Machine(path, self)
        self.machines[path] = m
        m.thread.start()
        return m

    # -- run ----------------------------------------------------------------------------------
    def run(self) -> None:
        """Supervise the machines until every one has ended (their sources finished, or
        ``duration``) or a stop signal; act on SIGHUP; keep STATUS and the watchdog. Stops
        every machine (each finishes its queued windows) before returning."""
        try:
            while not self._stop.is_set():
                if self._reload.is_set():
                    self._reload.clear()
                    self._rescan()
                if not any(m.thread.is_alive() for m in self.machines.values()):
                    break
                self._tick()
                self._stop.wait(0.2)
        finally:
            self._stop_all()
            self._restore_signal_handlers()
            logfilter.flush(force=True)

    def _tick(self) -> None:
        now = time.monotonic()
        interval = self.notifier.watchdog_interval
        if interval is not None and now - self._last_ping >= interval:
            self._last_ping = now
            self.notifier.watchdog()
        if now >= self._next_status:
            self._next_status = now + 1.0
            line = self.status_line()
            if line != self._status:
                self._status = line
                self.notifier.status(line)

    def _stop_all(self) -> None:
        machines = [*self.machines.values(), *self.retired]
        self.notifier.stopping("stopping: the machines finish their queued windows")
        longest = max((m.supervisor.config.acquisition.shutdown_timeout
                       for m in machines if m.supervisor.config is not None), default=10.0)
        self.notifier.extend_timeout(longest + 10)
        for m in machines:
            m.supervisor.stop()
        deadline = time.monotonic() + longest + 5
        for m in machines:
            m.thread.join(timeout=max(0.1, deadline - time.monotonic()))
            if m.thread.is_alive():
                logger.error("machine %s did not stop within %.0f s", m.name, longest + 5)

    def stop(self) -> None:
        """Ask :meth:`run` to stop every machine and return (thread- and signal-safe)."""
        self._stop.set()

    def reload(self) -> None:
        """Ask for a re-read of the directory, as SIGHUP does (thread- and signal-safe)."""
        self._reload.set()

    def _rescan(self) -> None:
        """SIGHUP: start the machines of new files, stop those whose file was removed,
        reload those whose file changed, and start again those not running (lost, or their
        source ended)."""
        self.notifier.reloading("re-reading the machine directory")
        files = set(self.files())
        for path in list(self.machines):
            if path not in files:
                m = self.machines.pop(path)
                logger.warning("machine %s: %s was removed: stopping it", m.name, path.name)
                m.supervisor.stop()
                self.retired.append(m)
        for path in sorted(files):
            current = self.machines.get(path)
            if current is None:
                logger.warning("machine file %s added: starting it", path.name)
                self._add(path)
                continue
            m = current
            if m.lost is not None or not m.thread.is_alive():
                logger.warning("machine %s: trying %s again", m.name, path.name)
                if m.supervisor.daemon is not None:  # it ran: its summary is still given
                    self.retired.append(m)
                self._add(path)
            elif _digest(path) != m.digest:
                m.digest = _digest(path)
                logger.warning("machine %s: %s changed: reloading it", m.name, path.name)
                m.supervisor.reload()
        self.notifier.ready(status=self.status_line())

    # -- what to report -----------------------------------------------------------------------
    def all_machines(self) -> list[Machine]:
        """The current machines and those a reload retired, in file order."""
        return [*self.retired, *self.machines.values()]

    def lost(self) -> dict[str, str]:
        """Machine (file) -> why, for every machine lost (never started, or stopped on a
        failure); a machine tried again by a reload counts by its latest attempt."""
        current = {m.path for m in self.machines.values()}
        return {f"{m.name} ({m.path.name})": m.lost for m in self.all_machines()
                if m.lost is not None and (m.path not in current or m is self.machines[m.path])}

    def problems(self) -> dict[str, list[str]]:
        """Machine -> what is degraded now, for the machines that are."""
        return {m.name: p for m in self.machines.values() if (p := m.problems())}

    def status_line(self) -> str:
        """systemd's ``STATUS=``: how many machines run, and the degraded ones by name."""
        ms = list(self.machines.values())
        running = sum(1 for m in ms if m.running)
        line = f"gateway: {running} of {len(ms)} machines monitored ({self.directory})"
        problems = self.problems()
        if problems:
            line += "; DEGRADED: " + "; ".join(f"{name}: {', '.join(p)}"
                                               for name, p in problems.items())
        return line

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
        self._stop_signals += 1
        if self._stop_signals > 1:
            logger.warning("%s received again: abandoning the queued windows",
                           signal.Signals(signum).name)
            for m in self.all_machines():
                daemon = m.supervisor.daemon
                if daemon is not None:
                    daemon.abandon = True
                    daemon.stop()
            return
        logger.warning("%s received: every machine finishes its queued windows and stops",
                       signal.Signals(signum).name)
        self._stop.set()
        for m in self.all_machines():  # at once: a machine opening abandons its opening
            with contextlib.suppress(Exception):
                m.supervisor.stop()

    def _on_hup(self, signum: int, frame: FrameType | None) -> None:
        self._reload.set()


def _digest(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return ""
