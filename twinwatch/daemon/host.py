"""The service host: what ``twinwatch run`` is to systemd and to the person at the terminal
(docs/service.md, docs/gateway.md).

One code path for one machine (``twinwatch run m1.toml``) and a directory of machines
(``twinwatch run DIR``): one machine is a fleet of one. :class:`Host` is the threads' strategy
of the :class:`~twinwatch.daemon.service.ServiceHost` (which owns the loop, the signals, the
stop and the exit status):

* **systemd**: a fleet of one's machine's lines (``READY=1``, ``STATUS=``, ``RELOADING=1``...)
  are the service's; a fleet keeps one line (``gateway: 3 of 4 machines monitored (DIR);
  DEGRADED: ...``). The watchdog is pinged while at least one machine is healthy or opening
  (:meth:`Machine.healthy`): a stuck machine among healthy ones is reported in STATUS.
* the **reload** (SIGHUP): a changed machine is reloaded
  (:class:`~twinwatch.daemon.supervisor.Supervisor`); a file added starts its machine, a file
  removed stops it, a machine not running starts again.

Each machine runs in a thread of its own (``twinwatch-<file>`` in a fleet); the machines share
one Zenoh session per ``[zenoh]`` setting (:class:`~twinwatch.sinks.base.SharedResources`) and
the estimation slots (:class:`~twinwatch.daemon.slots.EstimationSlots`). A machine whose
configuration is invalid, whose device cannot be opened or whose thread raises is *lost*:
logged and reported under its name, and the others go on.
"""

from __future__ import annotations

import faulthandler
import gc
import hashlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from twinwatch.daemon.service import (
    EX_CONFIG,
    EX_IOERR,
    EX_TEMPFAIL,
    FLEET_REPORT,
    MACHINE_GLOB,
    FleetStatus,
    MachineSummary,
    Progress,
    RunSummary,
    ServiceHost,
    gateway_total,
    worst_exit,
)
from twinwatch.daemon.slots import EstimationSlots, default_workers
from twinwatch.daemon.summary import failed_line, machine_lines, new_run_line, resumed_line
from twinwatch.daemon.supervisor import Stopped, Supervisor, status_line
from twinwatch.daemon.systemd import Notifier, Watchdog
from twinwatch.errors import ConfigError, StartError
from twinwatch.sinks.base import SharedResources

if TYPE_CHECKING:
    from twinwatch.config.schema import TwinwatchConfig

logger = logging.getLogger(__name__)

__all__ = ["MACHINE_GLOB", "Host", "Machine", "MachineNotifier"]


class MachineNotifier(Notifier):
    """What a machine tells systemd goes to its host instead (:meth:`Host._from_machine`);
    ``WATCHDOG=1`` from its acquisition loop is only noted (:attr:`last_ping`): the host pings
    systemd while a machine is healthy.
    """

    def __init__(self, host: Host, machine: Machine) -> None:
        super().__init__(env={})
        self._host = host
        self._machine = machine
        self.last_ping: float | None = None

    @property
    def enabled(self) -> bool:
        return self._host.notifier.watchdog_interval is not None

    @property
    def watchdog_interval(self) -> float | None:
        return self._host.notifier.watchdog_interval

    def notify(self, *assignments: str) -> bool:
        if assignments == ("WATCHDOG=1",):
            self.last_ping = time.monotonic()
            return True
        self._host._from_machine(self._machine, assignments)
        return True


class Machine:
    """One machine of a host: its configuration, its supervisor and thread, and how it ended.

    Args:
        path: the configuration file (None: the built-in default configuration).
        load: a fleet of one's loader (the host's ``load``); None: the host reads ``path``
            and checks it in the machine's directory (``<work root>/<machine name>``).

    Attributes:
        name: ``[machine] name`` once the configuration loaded (the file's stem before).
        watchdog: its own watchdog (the host reads it to find a stuck or quiet machine).
        lost: why the machine stopped or never started (one line), or None.
        failure: the same in full (every line), or None.
        error: what its start raised (a configuration error, a start error, :class:`Stopped`).
        watched: what a reload compares: label (``m1.toml``, ``diagnosis.library``) -> path
            of the configuration file and every file it reads.
        digests: their contents' SHA-256 when the machine (re)loaded them.
    """

    def __init__(self, host: Host, path: Path | None,
                 load: Callable[[], TwinwatchConfig] | None = None) -> None:
        self.host = host
        self.path = path
        stem = path.stem if path is not None else "default"
        self.file = path.name if path is not None else "the built-in default"
        self.name = stem
        self.lost: str | None = None
        self.failure: str | None = None
        self.error: BaseException | None = None
        self.config_error = False
        self.base_dir = path.resolve().parent if path is not None else host.base_dir
        self.watched: dict[str, Path] = {}
        self.digests: dict[str, str] = {}
        self._watch(None)
        self.started = threading.Event()  # running, or lost/stopped before it ran
        self.notifier = MachineNotifier(host, self)
        self.watchdog = Watchdog(self.notifier, max_busy=host.stuck_after,
                                 max_quiet=host.quiet_after)
        self._own_load = load
        self._loaded = False  # loaded once: a load is a reload
        prefix = f"twinwatch-{stem}" if host.fleet else "twinwatch"
        self.supervisor = Supervisor(
            self._load, base_dir=self.base_dir, source=str(path) if path else self.file,
            resume=host.resume, notifier=self.notifier, watchdog=self.watchdog,
            slots=host.slots, shared=host.shared, thread_prefix=prefix)
        self.thread = threading.Thread(target=self._run, name=prefix if host.fleet
                                       else "twinwatch-machine", daemon=True)

    # -- the machine's thread -----------------------------------------------------------------
    def _load(self) -> TwinwatchConfig:
        """The supervisor's loader. In a fleet: this file, checked to run in this machine's
        directory (``<work root>/<machine name>``), its name unique in the fleet.

        Raises:
            ConfigError: naming the file and key.
        """
        if self._own_load is not None:
            if self._loaded:  # a reload (SIGHUP): one line says what changed, or nothing
                changed = self.changed()
                logger.warning("SIGHUP: %s; reloading %s", (
                    "changed: " + ", ".join(changed) if changed else
                    "nothing changed in the configuration nor the files it reads"), self.file)
            self._loaded = True
            cfg = self._own_load()
            self.name = cfg.machine.name
            self._watch(cfg)
            return cfg
        host = self.host
        assert self.path is not None and host.read is not None  # a fleet has its reader
        cfg = host.read(self.path)
        name = self.name = cfg.machine.name
        host.claim(name, self)
        work_dir = host.work_root / name
        work_dir.mkdir(mode=0o750, exist_ok=True)
        self.supervisor.work_dir = work_dir
        if host.check is not None:
            host.check(cfg, self.path, work_dir)
        self._watch(cfg)
        return cfg

    def _watch(self, cfg: TwinwatchConfig | None) -> None:
        """Keep the digests of the configuration file and the files ``cfg`` reads (what the
        next SIGHUP compares)."""
        from twinwatch.config.preflight import referenced_files

        watched = {self.path.name: self.path} if self.path is not None else {}
        if cfg is not None:
            watched.update(referenced_files(cfg, base_dir=self.base_dir))
        self.digests = {k: _digest(p) for k, p in watched.items()}
        self.watched = watched

    def changed(self) -> list[str]:
        """What changed since the machine loaded: ``m1.toml``, ``diagnosis.library
        (faults.toml)``...; each one's new digest is kept (a reload that is refused is not
        tried again until the file changes again)."""
        out: list[str] = []
        for key, path in list(self.watched.items()):
            digest = _digest(path)
            if digest != self.digests.get(key):
                self.digests[key] = digest
                out.append(key if key == path.name else f"{key} ({path.name})")
        return out

    def rename(self, path: Path) -> None:
        """Its configuration file was renamed to ``path`` (the same ``[machine] name``): the
        machine goes on. The next :meth:`changed` compares the old file's content as it loaded
        (an edit made with the rename is a change)."""
        old = self.path
        assert old is not None
        self.path = path
        self.file = path.name
        self.supervisor.source = str(path)
        self.digests[path.name] = self.digests.pop(old.name, "")
        self.watched = {(path.name if k == old.name else k): (path if k == old.name else p)
                        for k, p in self.watched.items()}

    def _run(self) -> None:
        sup = self.supervisor
        try:
            sup.start()
        except Stopped as exc:
            self.error = exc
            if self.host.fleet:  # a fleet of one: the command line says it
                logger.warning("machine %s (%s): %s", self.name, self.file, exc)
            self.started.set()
            return
        except ValueError as exc:  # ConfigError, a validation error naming the key
            self.error = exc
            self._lose(f"invalid configuration: {exc}", config_error=True)
            return
        except StartError as exc:
            self.error = exc
            self._lose(f"cannot start: {exc}", config_error=exc.config_error)
            return
        except Exception as exc:  # noqa: BLE001 - contained to this machine
            self.error = exc
            logger.debug("%s failed to start", self.name, exc_info=True)
            self._lose(f"internal error at start: {type(exc).__name__}: {exc}")
            return
        self.started.set()
        try:
            sup.run(duration=self.host.duration)
        except StartError as exc:
            self._lose(f"cannot restart after a reload: {exc}")
        except Exception as exc:  # noqa: BLE001 - contained to this machine
            logger.debug("%s failed", self.name, exc_info=True)
            self._lose(f"internal error: {type(exc).__name__}: {exc} (run with --log-level "
                       "debug for the traceback, and please report it)")
        daemon = sup.daemon
        if self.lost is None and daemon is not None and daemon.failure is not None:
            self._lose(daemon.failure)

    def _lose(self, why: str, *, config_error: bool = False) -> None:
        lines = [ln.strip() for ln in why.splitlines() if ln.strip()]
        # a ConfigError lists one problem a line: the log keeps them all, STATUS one line
        self.lost = "; ".join(lines) if len(lines) <= 3 else "; ".join(lines[:3]) + "; ..."
        self.failure = why
        if self.host.fleet:
            logger.error("machine %s (%s) lost: %s", self.name, self.file, why)
        self.config_error = config_error
        self.started.set()
        self.host._changed()

    # -- state --------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.thread.is_alive() and self.started.is_set() and self.lost is None

    @property
    def opening(self) -> bool:
        """Its thread is opening the daemon (driver, outputs, kernels)."""
        return self.thread.is_alive() and not self.started.is_set()

    def healthy(self) -> bool:
        """For the host's watchdog: opening, or running with an acquisition loop that ticked
        its watchdog within the last ``WatchdogSec=``."""
        if self.opening:
            return True
        if not self.running:
            return False
        interval, last = self.host.notifier.watchdog_interval, self.notifier.last_ping
        # no last ping: its loop has not ticked yet (the daemon just started)
        return interval is None or last is None or time.monotonic() - last < 2.0 * interval

    def problems(self) -> list[str]:
        """What is degraded for this machine now (for STATUS)."""
        if self.lost is not None:
            return [f"lost ({self.lost})"]
        if self.opening:
            return ["starting (its source or outputs are still opening)"]
        daemon = self.supervisor.daemon
        if daemon is None or not self.thread.is_alive():
            return []
        out = list(daemon.problems())
        busy = self.watchdog.busy_seconds()
        if busy is not None and busy > self.host.stuck_after:
            out.append(f"stuck in one window for {busy:.0f} s")
        quiet = self.watchdog.quiet_seconds()
        if busy is None and quiet > self.host.quiet_after and not out:
            out.append(f"no window for {quiet:.0f} s")
        return out


class Host(ServiceHost):
    """The service: one machine's configuration file, or a directory of them (see the module
    docstring).

    Args:
        target: a machine configuration file (a fleet of one), a directory of them
            (``*.toml``), or None (the built-in default configuration).
        read: reads and validates one configuration file of a directory (raises
            :class:`ConfigError` naming the file and key).
        check: ``check(cfg, path, work_dir)``: a directory's configuration can run with its
            files in its machine's directory (raises :class:`ConfigError`).
        load: a fleet of one's loader (at start and at each SIGHUP); required when ``target``
            is not a directory.
        work_root: a fleet's machines work in ``<work_root>/<machine name>/`` (created); a
            fleet of one in the current directory.
        duration: each machine stops after this many seconds of source time (None: runs on).
        workers: estimation slots (:class:`EstimationSlots`); None: the cores; 0: no limit.
        stuck_after: seconds one window may take before its machine counts as stuck (and its
            estimation slot stops counting); None: ``WatchdogSec=``, 30 s without it.
        quiet_after: seconds without a finished window before a machine counts as quiet;
            None: as ``stuck_after``.
        assignment: a worker process's (:mod:`twinwatch.daemon.workers`): a file naming the
            directory's machine files it runs, one a line (re-read at each SIGHUP).
        start_timeout: seconds :meth:`start` waits for the machines to open before READY
            (None: a fleet of one waits for its machine, a fleet 60 s).

    Attributes:
        machines: configuration file -> its machine, in file order (the current ones).
        retired: machines a reload removed or replaced (their summary is still given).
    """

    def __init__(self, target: Path | None, *,
                 read: Callable[[Path], TwinwatchConfig] | None = None,
                 check: Callable[[TwinwatchConfig, Path, Path], None] | None = None,
                 load: Callable[[], TwinwatchConfig] | None = None,
                 work_root: Path | None = None, resume: bool | None = None,
                 duration: float | None = None, workers: int | None = None,
                 stuck_after: float | None = None, quiet_after: float | None = None,
                 start_timeout: float | None = None,
                 notifier: Notifier | None = None, assignment: Path | None = None) -> None:
        super().__init__(notifier=notifier, work_root=work_root, resume=resume,
                         duration=duration)
        self.target = target
        self.assignment = assignment
        if assignment is not None:  # a worker process: its host says the signals once
            self.signal_log_level = logging.DEBUG
        self.fleet = target is not None and target.is_dir()
        if (read if self.fleet else load) is None:
            raise ValueError("a directory needs a reader" if self.fleet
                             else "a fleet of one needs its loader")
        self.directory = target if self.fleet else None
        self.read = read
        self.check = check
        self._load = load
        self.base_dir = (target.resolve().parent if target is not None and not self.fleet
                         else Path.cwd())
        interval = self.notifier.watchdog_interval
        if stuck_after is None:
            stuck_after = 2.0 * interval if interval is not None else 30.0
        self.stuck_after = stuck_after
        self.quiet_after = quiet_after if quiet_after is not None else stuck_after
        self.start_timeout = start_timeout if start_timeout is not None else (
            60.0 if self.fleet else None)
        n = default_workers() if workers is None else workers
        self.slots = (EstimationSlots(n, stuck_after=self.stuck_after) if n > 0 and self.fleet
                      else None)
        self.shared = SharedResources(self.work_root)
        self.machines: dict[Path | None, Machine] = {}
        self.retired: list[Machine] = []
        self._names: dict[str, Machine] = {}
        self._owners: dict[str, Path] = {}  # machine name -> the first file naming it
        self._warned: set[tuple[str, str]] = set()  # the skipped entries named so far
        self._names_lock = threading.Lock()
        self._status_lock = threading.Lock()
        self._ready = False

    # -- configuration ------------------------------------------------------------------------
    def _scan(self) -> list[Path]:
        """A fleet's machine files sorted by name (a worker process's: those its assignment
        names). Notes the first file naming each machine (two files naming one machine resolve
        by file name, not by which opens first) and logs the skipped entries."""
        assert self.directory is not None
        files = sorted(p for p in self.directory.glob(MACHINE_GLOB) if p.is_file())
        if self.assignment is not None:
            try:
                names = set(self.assignment.read_text(encoding="utf-8").split("\n"))
            except OSError:
                names = set()
            files = [p for p in files if p.name in names]
        else:  # a worker process's host names the skipped entries, once for all
            warn_skipped(skipped(self.directory), self._warned)
        owners: dict[str, Path] = {}
        for p in files:
            if (name := _machine_name(p)) is not None:
                owners.setdefault(name, p)
        self._owners = owners
        return files

    def claim(self, name: str, machine: Machine) -> None:
        """Reserve ``[machine] name`` for ``machine``.

        Raises:
            ConfigError: another file of the fleet monitors a machine of that name.
        """
        first = self._owners.get(name)
        if first is not None and machine.path is not None and first != machine.path:
            raise ConfigError(f"{machine.path}: machine.name {name!r} is already monitored "
                              f"by {first.name} in this gateway (the first file by name "
                              "runs): each machine needs a name of its own")
        deadline = time.monotonic() + 60.0
        while True:
            with self._names_lock:
                other = self._names.get(name)
                if (other is None or other is machine or not other.thread.is_alive()):
                    self._names[name] = machine
                    return
                current = other.path in self.machines and self.machines[other.path] is other
            if current:
                raise ConfigError(f"{machine.path}: machine.name {name!r} is already monitored "
                                  f"by {other.file} in this gateway: each machine needs "
                                  f"a name of its own")
            # a file renamed: its old file's machine is stopping (it holds the state
            # database's lock until it has finished its queued windows): wait for it
            if time.monotonic() > deadline:
                raise ConfigError(f"{machine.path}: machine.name {name!r}: the machine of "
                                  f"{other.file} (removed) did not stop within 60 s")
            other.thread.join(0.2)

    # -- start --------------------------------------------------------------------------------
    def start(self) -> None:
        """Install the signal handlers, start every machine (each opens in its own thread) and
        tell systemd ``READY=1`` once each has started or been lost (a fleet: or after
        ``start_timeout``, the machines still opening named in STATUS).

        Raises:
            ConfigError: the directory holds no machine configuration.
        """
        # systemd's watchdog kills with SIGABRT: every thread's stack to stderr (the journal)
        try:
            faulthandler.enable()
        except (AttributeError, ValueError, OSError):
            logger.debug("faulthandler not enabled: stderr has no file descriptor")
        files: list[Path | None] = [*self._scan()] if self.fleet else [self.target]
        if not files:
            raise ConfigError(f"{self.directory}: no machine configuration ({MACHINE_GLOB}) "
                              "in this directory")
        self._install_signal_handlers()
        for path in files:
            self._add(path)
        deadline = None if self.start_timeout is None else time.monotonic() + self.start_timeout
        for m in list(self.machines.values()):
            while not m.started.wait(0.2):
                if self._stop.is_set():  # the opening is abandoned at once (within 0.2 s)
                    m.started.wait(5.0)
                    break
                if deadline is not None and time.monotonic() > deadline:
                    break
        # what the started process holds is kept out of the collector's full passes (they
        # stall every machine's window of a large worker); a reload and the stop unfreeze it
        gc.freeze()
        if self.fleet:
            self._ready = True
            self._send_status(ready=True)
        # a fleet of one: its machine said READY (or why it cannot start) itself

    def _add(self, path: Path | None) -> Machine:
        m = Machine(self, path, load=None if self.fleet else self._load)
        self.machines[path] = m
        m.thread.start()
        return m

    @property
    def only(self) -> Machine:
        """A fleet of one's machine."""
        assert not self.fleet and len(self.machines) == 1
        return next(iter(self.machines.values()))

    # -- what the machines say ----------------------------------------------------------------
    def _from_machine(self, machine: Machine, assignments: tuple[str, ...]) -> None:
        """A machine's notification: a fleet of one's go to systemd as they are; a fleet's
        change the host's STATUS line."""
        if not self.fleet:
            self.notifier.notify(*assignments)
            return
        if self._ready and any(a.startswith("STATUS=") for a in assignments):
            self._changed()

    def _changed(self) -> None:
        """Send a fleet's STATUS now if it changed."""
        if not self.fleet or not self._ready:
            return
        with self._status_lock:
            line = self.status_line()
            if line != self._status:
                self._status = line
                self._send_status()

    def _send_status(self, *, ready: bool = False) -> None:
        """A fleet's STATUS (with READY=1 after a start or a reload); a worker process's host
        adds its :class:`FleetStatus` in the :data:`FLEET_REPORT` assignment, for its host."""
        status = self.fleet_status()
        assignments = [f"STATUS={status.line(str(self.directory))}"]
        if self.assignment is not None:
            assignments.append(f"{FLEET_REPORT}={status.model_dump_json()}")
        self.notifier.notify(*(["READY=1"] if ready else []), *assignments)

    # -- run: the loop's turn (ServiceHost.run) ------------------------------------------------
    def _turn(self) -> bool:
        return any(m.thread.is_alive() for m in self.machines.values())

    def _stopped_why(self) -> str | None:
        if self.fleet:
            lost = self.lost()
            return f"{len(lost)} machine(s) lost" if lost else None
        m = self.only
        daemon = m.supervisor.daemon
        if m.error is not None or m.supervisor.config is None or daemon is None:
            return None  # it did not start: its error says why
        if m.failure is not None:
            return m.failure
        code = self.exit_status()
        if code == EX_IOERR:
            return "; ".join(daemon.problems())
        if code == EX_TEMPFAIL:
            return failed_line(daemon)
        return None

    def _healthy(self, interval: float) -> bool:
        return any(m.healthy() for m in self.machines.values())

    def _refresh_status(self) -> None:
        """A fleet's STATUS when it changed; a worker process's heartbeat to its host."""
        self._changed()
        if self.assignment is not None and self._ready:
            # its host calls a worker that sends nothing for a window plus a margin stalled
            self.notifier.notify(f"{FLEET_REPORT}={self.fleet_status().model_dump_json()}")

    def _grace(self) -> float:
        """The longest ``shutdown_timeout`` of the machines' configurations [s] (10 s)."""
        return max((m.supervisor.config.acquisition.shutdown_timeout
                    for m in self.all_machines()
                    if m.supervisor.config is not None), default=10.0)

    def _ask_to_stop(self) -> None:
        for m in self.all_machines():
            m.supervisor.stop()

    def _wait_stopped(self, deadline: float, limit: float) -> None:
        for m in self.all_machines():
            m.thread.join(timeout=max(0.1, deadline - time.monotonic()))
            if m.thread.is_alive():
                logger.error("machine %s did not stop within %.0f s", m.name, limit)
        gc.unfreeze()  # the stopped machines' cycles are the collector's again

    def stop(self) -> None:
        super().stop()
        self._ask_to_stop()  # at once: a machine opening abandons its opening

    def reload(self) -> None:
        gc.unfreeze()  # the machines replaced are the collector's again (start)
        if not self.fleet:  # its acquisition loop acts on it at its next tick
            for m in list(self.machines.values()):
                m.supervisor.reload()
            return
        super().reload()

    def _rescan(self) -> None:
        """SIGHUP in a fleet (a fleet of one reloads in :meth:`reload`): start, stop, reload or
        rename machines as the module docstring says, and log one line."""
        self.notifier.reloading("re-reading the machine directory")
        files = set(self._scan())
        done: list[str] = []
        for old, new in self._renamed(files).items():
            # a machine is its name, not its file: it goes on (twin, trends, alarms, runs)
            m = self.machines.pop(old)
            m.rename(new)
            self.machines[new] = m
            done.append(f"{m.name} goes on ({old.name} renamed {new.name})")
        for path in list(self.machines):
            if path not in files:
                m = self.machines.pop(path)
                done.append(f"{m.name} stopped ({m.file} removed)")
                m.supervisor.stop()
                self.retired.append(m)
        for path in sorted(p for p in files if p is not None):
            said = self._rescan_file(path)
            if said is not None:
                done.append(said)
        # one line per SIGHUP, also when nothing changed (a worker's host merges its workers')
        line = reload_line(done, len(self.machines), str(self.directory))
        if self.assignment is not None:
            self.notifier.notify(f"{RELOAD_REPORT}={json.dumps(done)}")
        else:
            logger.warning("%s", line)
        self._send_status(ready=True)

    def _rescan_file(self, path: Path) -> str | None:
        """SIGHUP, one file of the directory: start, start again or reload its machine; what
        was done, or None."""
        m = self.machines.get(path)
        if m is None:
            self._add(path)
            return f"{path.stem} started ({path.name} added)"
        if m.lost is not None or not m.thread.is_alive():
            if m.supervisor.daemon is not None:  # it ran: its summary is still given
                self.retired.append(m)
            self._add(path)
            return f"{m.name} tried again ({path.name}: it was not running)"
        if changed := m.changed():
            m.supervisor.reload()
            return f"{m.name} reloaded ({', '.join(changed)} changed)"
        return None

    def _renamed(self, files: set[Path]) -> dict[Path, Path]:
        """Old file -> new file, for each running machine whose file is gone while a new file
        (the first file naming it, :meth:`_scan`) names the same machine. A machine that is not
        running is started again under its new file instead."""
        out: dict[Path, Path] = {}
        for path, m in self.machines.items():
            if path is None or path in files or not m.running or m.supervisor.config is None:
                continue
            new = self._owners.get(m.supervisor.config.machine.name)
            if new is not None and new in files and new not in self.machines \
                    and new not in out.values():
                out[path] = new
        return out

    # -- what to report -----------------------------------------------------------------------
    def all_machines(self) -> list[Machine]:
        """The current machines and those a reload retired, in file order."""
        return [*self.retired, *self.machines.values()]

    def counted(self) -> list[Machine]:
        """The fleet's machines, each once, by its latest attempt: the current ones and, of
        those a reload retired, the last of each machine whose name and file no current one
        has. A file renamed, or tried again by a reload, is one machine."""
        current = list(self.machines.values())
        names = {m.name for m in current}
        paths = {m.path for m in current}
        gone: dict[str, Machine] = {}
        for m in self.retired:
            if m.name not in names and m.path not in paths:
                gone.pop(m.name, None)
                gone[m.name] = m
        return [*gone.values(), *current]

    def lost(self) -> dict[str, str]:
        """Machine (file) -> why, for every machine lost, by its latest attempt
        (:meth:`counted`)."""
        return {f"{m.name} ({m.file})": m.lost for m in self.counted() if m.lost is not None}

    def problems(self) -> dict[str, list[str]]:
        """Machine -> what is degraded now, for the machines that are."""
        return {m.name: p for m in self.machines.values() if (p := m.problems())}

    def status_line(self) -> str:
        """systemd's ``STATUS=``: a fleet of one's machine's line; a fleet's: how many
        machines run, and the degraded ones by name."""
        if not self.fleet:
            m = self.only
            cfg, daemon = m.supervisor.config, m.supervisor.daemon
            if cfg is None or daemon is None:
                return m.lost or "starting"
            return status_line(cfg, daemon)
        return self.fleet_status().line(str(self.directory))

    def fleet_status(self) -> FleetStatus:
        """A fleet's STATUS content (also what a worker process reports to its host)."""
        ms = list(self.machines.values())
        acq = [m.supervisor.config.acquisition for m in ms if m.supervisor.config is not None]
        return FleetStatus(monitored=sum(1 for m in ms if m.running), machines=len(ms),
                           degraded=[f"{name}: {', '.join(p)}"
                                     for name, p in self.problems().items()],
                           window_s=max((a.window * a.sample_period for a in acq),
                                        default=None),
                           stalled_restart=min((a.stalled_restart for a in acq),
                                               default=None))

    def exit_status(self) -> int:
        """:meth:`ServiceHost.exit_status`; 0 also after a stop during the start."""
        if self.lost():
            return worst_exit([EX_CONFIG if m.lost is not None and m.config_error else 1
                               for m in self.machines.values()] or [EX_CONFIG])
        return worst_exit(EX_IOERR if d.lost() else EX_TEMPFAIL if d.mostly_failed() else 0
                          for m in self.all_machines() if (d := m.supervisor.daemon) is not None)

    def abandon(self) -> None:
        for m in self.all_machines():
            m.supervisor.abandon()

    def notices(self) -> list[str]:
        """A fleet of one that started: what it resumed from its state database, or why it
        starts a new run (a fleet: nothing, each machine logs it)."""
        if self.fleet:
            return []
        daemon = self.only.supervisor.daemon
        if self.only.error is not None or daemon is None:
            return []
        if daemon.resumed is not None:
            return [resumed_line(daemon)]
        if daemon.new_run is not None:
            return [new_run_line(daemon)]
        return []

    def progress(self) -> Progress | None:
        """A fleet of one's machine once it runs: its name, the source time the run covers
        (``duration``, else the driver's own) and its callbacks."""
        if self.fleet:
            return None
        sup = self.only.supervisor
        cfg = sup.config
        if self.only.error is not None or sup.daemon is None or cfg is None:
            return None
        from twinwatch.drivers import get_driver_class

        total = self.duration if self.duration is not None else (
            get_driver_class(cfg.driver.type).duration(cfg.driver))
        return Progress(name=cfg.machine.name, total=total, add_callback=sup.add_callback)

    def summary(self) -> RunSummary:
        """The run's summary: a fleet of one's block (or why it did not run, for stderr); a
        fleet's block per machine attempt, in file order, and the total line."""
        code = self.exit_status()
        if not self.fleet:
            m = self.only
            block = (self._machine_summary(m) if m.error is None  # it started
                     else MachineSummary(name=m.name, file=m.file, lost=m.lost))
            return RunSummary(machines=[block], errors=self._errors(m), exit_status=code)
        machines = self.all_machines()
        lost = self.lost()
        n = len(self.counted())  # a machine renamed or tried again counts once
        total = gateway_total(n, [f"{k}: {v}" for k, v in lost.items()])
        return RunSummary(machines=[self._machine_summary(m) for m in machines], total=total,
                          exit_status=code)

    @staticmethod
    def _machine_summary(m: Machine) -> MachineSummary:
        cfg, daemon = m.supervisor.config, m.supervisor.daemon
        lines = machine_lines(cfg, daemon) if cfg is not None and daemon is not None else []
        return MachineSummary(name=m.name, file=m.file, lost=m.lost, lines=lines)

    @staticmethod
    def _errors(m: Machine) -> list[str]:
        """A fleet of one's lines for stderr: why it did not start, or stopped."""
        if isinstance(m.error, Stopped):  # a stop while it was starting: nothing ran
            return [f"twinwatch: {m.error}"]
        if isinstance(m.error, StartError):
            return [f"Error: cannot start: {m.error}"]
        if isinstance(m.error, ValueError):  # ConfigError, a validation error naming the key
            return [f"Error: {m.error}"]
        if m.error is not None:
            return [f"Error: {m.failure}"]
        if m.supervisor.config is None or m.supervisor.daemon is None:  # stopped as it opened
            return [f"twinwatch: {m.failure or 'stopped before it had started'}"]
        return [f"Error: {m.failure}"] if m.failure is not None else []


def _machine_name(path: Path) -> str | None:
    """``[machine] name`` of a configuration file, or None (unreadable: its machine is lost
    with the loader's error)."""
    import tomllib

    try:
        name = tomllib.loads(path.read_text(encoding="utf-8")).get("machine", {}).get("name")
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, AttributeError):
        return None
    return name if isinstance(name, str) else None


def skipped(directory: Path) -> dict[str, str]:
    """The entries of a machine directory that are not run, each with why: every entry is
    run, lost or named here."""
    out: dict[str, str] = {}
    try:
        entries = sorted(directory.iterdir())
    except OSError:
        return out
    for p in entries:
        if p.is_symlink() and not p.exists():
            out[p.name] = f"a link to {os.readlink(p)!s}, which does not exist"
        elif p.match(MACHINE_GLOB) and not p.is_file():
            out[p.name] = "not a regular file"
        elif not p.match(MACHINE_GLOB):
            out[p.name] = f"not a machine configuration (only {MACHINE_GLOB} files are run)"
    return out


def warn_skipped(entries: dict[str, str], warned: set[tuple[str, str]]) -> None:
    """Log each skipped entry of a machine directory (:func:`skipped`) once per reason."""
    for entry, why in entries.items():
        if (entry, why) not in warned:
            warned.add((entry, why))
            logger.warning("%s: skipped: %s", entry, why)


def _digest(path: Path) -> str:
    """The file's SHA-256 ("" when it cannot be read: a file that appears or goes away is a
    change too)."""
    try:
        with path.open("rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError:
        return ""


RELOAD_REPORT = "TWINWATCH_RELOAD"
"""The notification assignment a worker process's host sends what its SIGHUP did in (a JSON
list of :func:`reload_line`'s items): its host logs one line for every worker."""


def reload_line(done: list[str], machines: int, directory: str) -> str:
    """The one line a gateway logs per SIGHUP: what it did (``m3 started (m3.toml added)``...),
    or that nothing changed."""
    if done:
        return f"SIGHUP: {directory}: " + "; ".join(done)
    return (f"SIGHUP: {directory}: nothing changed ({machines} machines: their files and the "
            f"files they read are as loaded)")

