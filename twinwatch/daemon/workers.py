"""Every core: the host spreads a directory's machines over worker processes (docs/gateway.md).

With ``twinwatch run DIR --workers N`` (default: one per core) :class:`ProcessHost` starts
``N`` worker processes, each one ``twinwatch run DIR --assignment FILE``: the same
:class:`~twinwatch.daemon.host.Host` on the machines its assignment file names. What crosses:

* **down**: the assignment file (rewritten atomically, then SIGHUP), SIGHUP, SIGTERM (a second
  one abandons the queued windows);
* **up**, typed (:mod:`twinwatch.daemon.service`), never prose: systemd's notification protocol
  on a datagram socket per worker (a :class:`~twinwatch.daemon.service.FleetStatus` in
  ``TWINWATCH_FLEET=`` beside ``STATUS=``), the worker's
  :class:`~twinwatch.daemon.service.RunSummary` as one JSON document on its stdout, its log
  lines on the host's stderr, and its exit status.

A worker that a signal ended is started again at once with ``--resume``, at most
:data:`RESTART_LIMIT` times within :data:`RESTART_WINDOW` s, then given up (its machines are
lost). One that ended by itself is started again only by a SIGHUP. One that sends nothing for
a window plus :data:`STALL_MARGIN` is **stalled** (not monitored, no watchdog ping, exit 74) and
after ``[acquisition] stalled_restart`` seconds (0: never) killed and started with ``--resume``.

Placement: machines sharing a ``[zenoh]`` session, an ``[outputs.opcua]`` endpoint or a
Sparkplug edge node (broker, ``group_id``, ``edge_node_id``) go to the same worker; the others
are spread to balance the workers. A machine keeps its worker across reloads; a new file goes
to the worker with fewest machines.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from collections.abc import Sequence
from pathlib import Path

from pydantic import ValidationError

from twinwatch.daemon.host import MACHINE_GLOB, RELOAD_REPORT, reload_line, skipped, warn_skipped
from twinwatch.daemon.service import (
    EX_IOERR,
    EX_TEMPFAIL,
    FLEET_REPORT,
    FleetStatus,
    MachineSummary,
    RunSummary,
    ServiceHost,
    gateway_total,
    worst_exit,
)
from twinwatch.daemon.systemd import Notifier
from twinwatch.errors import ConfigError

logger = logging.getLogger(__name__)

__all__ = ["ProcessHost", "Worker", "place", "worker_processes"]

RESTART_LIMIT = 5
"""Restarts of one worker within :data:`RESTART_WINDOW` seconds before it is given up."""

RESTART_WINDOW = 120.0

STALL_MARGIN = 5.0
"""Seconds beyond one window (its machines' longest) a worker may send its host nothing before
it is stalled (it sends its :class:`FleetStatus` every second)."""

DEFAULT_WINDOW = 2.0
"""The window [s] assumed for a worker that has not reported its own (the default 200 x 10 ms)."""

DEFAULT_STALLED_RESTART = 30.0
"""``[acquisition] stalled_restart``'s default [s], for a worker that has not reported its own."""


_GROUPS: dict[Path, tuple[str, ...]] = {}
"""The last keys read for each file (a file renamed away keeps its group for placement)."""

#: ``[outputs.opcua] endpoint``'s default (:class:`twinwatch.sinks.opcua.OpcUaConfig`).
OPCUA_ENDPOINT = "opc.tcp://127.0.0.1:4840"


def session_keys(path: Path) -> tuple[str, ...]:
    """What ties a machine file to others, each key a resource one process must hold for
    every machine that names it (the module's "Placement"); else its machine's name (two files
    naming one machine: one process decides which runs); the file itself when unreadable."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return _GROUPS.get(path, (f"file:{path.name}",))
    zenoh = data.get("zenoh", {})
    machine = data.get("machine", {})
    name = machine.get("name") if isinstance(machine, dict) else None
    keys: list[str] = []
    if isinstance(zenoh, dict) and zenoh.get("enabled", True) is not False:
        keys.append("zenoh:" + json.dumps(zenoh, sort_keys=True, default=str))
    outputs = data.get("outputs", {})
    opcua = outputs.get("opcua") if isinstance(outputs, dict) else None
    if isinstance(opcua, dict) and opcua.get("enabled", True) is not False:
        keys.append(f"opcua:{opcua.get('endpoint', OPCUA_ENDPOINT)}")
    spb = outputs.get("sparkplug") if isinstance(outputs, dict) else None
    if (isinstance(spb, dict) and spb.get("enabled", True) is not False
            and spb.get("edge_node_id") is not None):
        keys.append(f"sparkplug:{spb.get('host', '127.0.0.1')}:{spb.get('port', 1883)}/"
                    f"{spb.get('group_id', 'twinwatch')}/{spb.get('edge_node_id')}")
    if not keys:
        keys.append(f"name:{name}" if isinstance(name, str) else f"file:{path.name}")
    _GROUPS[path] = tuple(keys)
    return _GROUPS[path]


def session_groups(paths: Sequence[Path]) -> dict[Path, str]:
    """Each file's group: files that share any of :func:`session_keys` form one group,
    transitively; a group cannot be split over processes."""
    parent: dict[str, str] = {}

    def find(k: str) -> str:
        parent.setdefault(k, k)
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for p in paths:
        keys = session_keys(p)
        for k in keys[1:]:
            a, b = find(keys[0]), find(k)
            if a != b:
                parent[max(a, b)] = min(a, b)
    return {p: find(session_keys(p)[0]) for p in paths}


def place(files: Sequence[Path], current: Sequence[Sequence[Path]], n: int) -> list[list[Path]]:
    """The machine files of each of ``n`` workers: a file stays where it is (``current``),
    a file of a session group goes where its group is, the others to the worker with fewest.

    Args:
        current: each worker's files so far (may be shorter than ``n``).
        n: workers (>= 1).
    """
    present = set(files)
    group = session_groups(sorted(set(files) | {p for ps in current for p in ps}))
    where: dict[str, int] = {}
    for k in range(min(n, len(current))):
        for p in current[k]:  # removed files too: a renamed file follows its machine
            where.setdefault(group[p], k)
    out = [[p for p in (current[k] if k < len(current) else []) if p in present]
           for k in range(n)]
    placed = {p for ps in out for p in ps}
    groups: dict[str, list[Path]] = {}
    for p in sorted(files):
        if p not in placed:
            groups.setdefault(group[p], []).append(p)
    # the largest groups first, each to the worker with fewest machines (or to its session's)
    for g, ps in sorted(groups.items(), key=lambda kv: (-len(kv[1]), kv[1][0])):
        worker = where.get(g)
        if worker is None:
            worker = min(range(n), key=lambda i: (len(out[i]), i))
            where[g] = worker
        out[worker].extend(ps)
    return [sorted(ps) for ps in out]


def worker_processes(directory: Path, workers: int | None) -> int:
    """The worker processes a directory's machines run in: ``workers`` (default
    :func:`~twinwatch.daemon.slots.default_processes`), at most one per session group; 1 for a
    directory of fewer than two machines.
    """
    from twinwatch.daemon.slots import default_processes

    files = sorted(p for p in directory.glob(MACHINE_GLOB) if p.is_file())
    n = workers if workers is not None else default_processes(len(files))
    if n <= 1 or len(files) <= 1:
        return 1
    return max(1, min(n, sum(1 for ps in place(files, [], n) if ps)))


class Worker:
    """One worker process of a :class:`ProcessHost`: its assignment, its notification socket,
    its process (started again when it dies) and what it said.
    """

    def __init__(self, index: int, host: ProcessHost) -> None:
        self.index = index
        self.host = host
        self.files: list[Path] = []
        self.assignment = host.run_dir / f"worker-{index}.list"
        self.socket_path = host.run_dir / f"worker-{index}.notify"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self.sock.bind(str(self.socket_path))
        self.sock.setblocking(False)
        self.proc: subprocess.Popen[str] | None = None
        self.summaries: list[RunSummary] = []  # each incarnation's that ended by itself
        self.codes: list[int] = []
        self.ready = False
        self.report: FleetStatus | None = None  # its machines, as it last reported them
        self.last_ping: float | None = None
        self.restarts: list[float] = []
        self.given_up: str | None = None
        self.started_at = 0.0
        self.last_heard = 0.0  # monotonic time of its last notification
        self.stalled_since: float | None = None
        self.stalls = 0  # times it was found stalled
        self.killed_stalled = False
        self.reloaded: list[str] | None = None  # what its last SIGHUP did (RELOAD_REPORT)
        self.ended = False
        self._reader: threading.Thread | None = None

    def write_assignment(self) -> None:
        tmp = self.assignment.with_suffix(".tmp")
        tmp.write_text("".join(f"{p.name}\n" for p in self.files), encoding="utf-8")
        tmp.replace(self.assignment)

    def start(self, *, resume: bool | None) -> None:
        """Start (again) the worker process on its assignment."""
        self.write_assignment()
        h = self.host
        cmd = [sys.executable, "-m", "twinwatch", "run", str(h.directory), "--no-progress",
               "--log-level", h.log_level, "--assignment", str(self.assignment),
               "--slots", str(h.slots_per_worker)]
        if h.duration is not None:
            cmd += ["--duration", repr(h.duration)]
        if resume is True:
            cmd.append("--resume")
        elif resume is False:
            cmd.append("--fresh")
        env = dict(os.environ, NOTIFY_SOCKET=str(self.socket_path))
        env.pop("WATCHDOG_PID", None)
        interval = h.notifier.watchdog_interval
        if interval is not None:
            env["WATCHDOG_USEC"] = str(int(2 * interval * 1e6))
        else:
            env.pop("WATCHDOG_USEC", None)
        self.ready = False
        self.ended = False
        self.last_ping = None
        self.started_at = self.last_heard = time.monotonic()
        self.stalled_since = None
        self.proc = subprocess.Popen(cmd, cwd=h.work_root, env=env, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, text=True,
                                     start_new_session=True)  # a terminal's ^C goes to the host
        proc = self.proc
        self._reader = threading.Thread(target=self._read, args=(proc,), daemon=True,
                                        name=f"twinwatch-worker-{self.index}-stdout")
        self._reader.start()
        logger.info("worker %d (pid %d) started on %d machines", self.index, proc.pid,
                    len(self.files))

    def _read(self, proc: subprocess.Popen[str]) -> None:
        """Read the worker's stdout to its end: its summary, one JSON document."""
        assert proc.stdout is not None
        out = proc.stdout.read()
        if not out.strip():
            return
        try:
            self.summaries.append(RunSummary.model_validate_json(out))
        except ValidationError as exc:
            logger.error("worker %d (pid %d): its summary could not be read: %s", self.index,
                         proc.pid, exc)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def send(self, signum: int) -> None:
        if self.alive():
            assert self.proc is not None
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signum)

    def drain(self) -> None:
        """Read what the worker told its notification socket."""
        while True:
            try:
                msg = self.sock.recv(65536).decode("utf-8", "replace")
            except (BlockingIOError, OSError):
                return
            self.last_heard = time.monotonic()
            for line in msg.splitlines():
                key, _, value = line.partition("=")
                if line == "READY=1":
                    self.ready = True
                elif line == "WATCHDOG=1":
                    self.last_ping = time.monotonic()
                elif key == RELOAD_REPORT:
                    try:
                        self.reloaded = [str(x) for x in json.loads(value)]
                    except (ValueError, TypeError):
                        self.reloaded = [f"worker {self.index}: its reload report could not "
                                         "be read"]
                elif key == FLEET_REPORT:
                    try:
                        self.report = FleetStatus.model_validate_json(value)
                    except ValidationError as exc:
                        logger.error("worker %d: its status could not be read: %s",
                                     self.index, exc)

    def healthy(self, interval: float | None) -> bool:
        if not self.alive() or self.stalled_since is not None:
            return False
        if interval is None or not self.ready:
            return True
        last = self.last_ping if self.last_ping is not None else self.started_at
        return time.monotonic() - last < 2.0 * interval + 5.0

    def stall_limit(self) -> float:
        """Seconds without a notification before it is stalled: its longest window plus
        :data:`STALL_MARGIN`."""
        window = self.report.window_s if self.report is not None else None
        return (window if window is not None else DEFAULT_WINDOW) + STALL_MARGIN

    def stalled_restart(self) -> float:
        """Seconds stalled before it is killed and started again (0: never)."""
        after = self.report.stalled_restart if self.report is not None else None
        return DEFAULT_STALLED_RESTART if after is None else after

    def join_output(self, timeout: float) -> None:
        if self._reader is not None:
            self._reader.join(timeout)

    def close(self) -> None:
        self.sock.close()
        with contextlib.suppress(OSError):
            self.socket_path.unlink()


class ProcessHost(ServiceHost):
    """The service host of a directory, its machines in ``workers`` processes (see the module
    docstring): the :class:`~twinwatch.daemon.service.ServiceHost` contract.

    Args:
        workers: worker processes (>= 2).
        work_root, resume, duration: as :class:`~twinwatch.daemon.host.Host`'s (a restarted
            worker resumes).
        slots: estimation slots per worker (default: the cores shared out, at least 1).
    """

    fleet = True
    turn_s = 0.1

    def __init__(self, directory: Path, *, workers: int, work_root: Path | None = None,
                 resume: bool | None = None, duration: float | None = None,
                 log_level: str = "warning", slots: int | None = None,
                 notifier: Notifier | None = None) -> None:
        from twinwatch.daemon.slots import default_workers

        super().__init__(notifier=notifier, work_root=work_root, resume=resume,
                         duration=duration)
        self.directory = directory
        self.n = workers
        self.log_level = log_level
        self.slots_per_worker = slots if slots is not None else max(
            1, default_workers() // workers)
        self.run_dir = Path(tempfile.mkdtemp(prefix="twinwatch-host-"))
        self.workers: list[Worker] = []
        # (deadline, the workers signalled, what the host itself did) of a pending SIGHUP
        self._reload_pending: tuple[float, list[Worker], list[str]] | None = None
        self._warned: set[tuple[str, str]] = set()

    def files(self) -> list[Path]:
        """The machine files; the directory's other entries are named once (the workers do
        not: they would each say it)."""
        warn_skipped(skipped(self.directory), self._warned)
        return sorted(p for p in self.directory.glob(MACHINE_GLOB) if p.is_file())

    # -- start --------------------------------------------------------------------------------
    def start(self, timeout: float | None = 120.0) -> None:
        """Install the signal handlers, start the workers and tell systemd READY once each
        said READY (or after ``timeout`` [s]).

        Raises:
            ConfigError: the directory holds no machine configuration.
        """
        files = self.files()
        if not files:
            raise ConfigError(f"{self.directory}: no machine configuration ({MACHINE_GLOB}) "
                              "in this directory")
        self._install_signal_handlers()
        placed = place(files, [], self.n)
        for k, ps in enumerate(placed):
            w = Worker(k, self)
            w.files = ps
            self.workers.append(w)
            if ps:
                w.start(resume=self.resume)
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._stop.is_set():
            for w in self.workers:
                w.drain()
            if all(w.ready or not w.alive() for w in self.workers if w.files):
                break
            if deadline is not None and time.monotonic() > deadline:
                break
            self._stop.wait(0.1)
        self.notifier.ready(status=self.status_line())

    # -- run: the loop's turn (ServiceHost.run) ------------------------------------------------
    def _turn(self) -> bool:
        """One turn over the workers; True while a worker runs."""
        for w in self.workers:
            w.drain()
            self._check(w)
            self._watch(w)
        self._reload_done()
        return any(w.alive() for w in self.workers)

    def _check(self, w: Worker) -> None:
        """A worker that a signal ended is started again; one that ended by itself is left."""
        if (w.proc is None or w.alive() or w.given_up is not None or self._stop.is_set()
                or w.ended):
            return
        w.ended = True
        code = w.proc.returncode
        assert code is not None  # it is not alive
        w.codes.append(code)
        if code >= 0:
            (logger.info if code == 0 else logger.warning)(
                "worker %d (pid %d) ended (exit status %d): its machines stopped", w.index,
                w.proc.pid, code)
            return
        self._restart(w, code)

    def _restart(self, w: Worker, code: int) -> None:
        """A worker ended by signal ``-code``: started again, unless it ended so more than
        :data:`RESTART_LIMIT` times within :data:`RESTART_WINDOW` seconds."""
        assert w.proc is not None
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        now = time.monotonic()
        w.restarts = [t for t in w.restarts if now - t < RESTART_WINDOW] + [now]
        if len(w.restarts) > RESTART_LIMIT:
            w.given_up = (f"worker {w.index} ended by {name} {len(w.restarts)} times within "
                          f"{RESTART_WINDOW:.0f} s: given up")
            logger.error("%s; its machines are lost: %s", w.given_up,
                         ", ".join(p.name for p in w.files))
            return
        how = (f"was killed after it stalled {w.stalled_restart():g} s" if w.killed_stalled
               else f"ended by {name}")
        w.killed_stalled = False
        logger.error("worker %d (pid %d) %s: starting it again; its %d machines resume "
                     "from their state databases, the other workers go on", w.index,
                     w.proc.pid, how, len(w.files))
        w.join_output(1.0)
        w.start(resume=True)

    def _watch(self, w: Worker) -> None:
        """A worker alive that sent nothing for :meth:`Worker.stall_limit` is stalled: reported
        at once; killed after its ``stalled_restart`` (:meth:`_check` restarts it)."""
        if not w.alive() or not w.ready or self._stop.is_set():
            w.stalled_since = None
            return
        assert w.proc is not None
        now = time.monotonic()
        silent = now - w.last_heard
        if silent <= w.stall_limit():
            if w.stalled_since is not None:
                logger.warning("worker %d (pid %d) sends again after %.0f s stalled: its "
                               "machines are monitored again", w.index, w.proc.pid,
                               now - w.stalled_since)
                w.stalled_since = None
            return
        restart = w.stalled_restart()
        if w.stalled_since is None:
            w.stalled_since = now
            w.stalls += 1
            logger.error("worker %d (pid %d) sent nothing for %.0f s (one window and %g s): "
                         "stalled (stopped or frozen); its %d machines are not monitored: %s; "
                         "%s", w.index, w.proc.pid, silent, STALL_MARGIN, len(w.files),
                         ", ".join(p.stem for p in w.files),
                         f"it is restarted if still stalled in {restart:g} s" if restart > 0
                         else "stalled_restart = 0: it is not restarted")
            self._next_status = 0.0  # STATUS says it now
        elif restart > 0 and now - w.stalled_since >= restart and not w.killed_stalled:
            w.killed_stalled = True
            with contextlib.suppress(ProcessLookupError):
                w.proc.kill()  # SIGKILL ends a stopped process too

    def _healthy(self, interval: float) -> bool:
        return any(w.healthy(interval) for w in self.workers)

    def _rescan(self) -> None:
        """SIGHUP: place the directory's files again (:func:`place`), write each worker's
        assignment, and SIGHUP the workers; a worker that ended and has machines is started."""
        self.notifier.reloading("re-reading the machine directory")
        placed = place(self.files(), [w.files for w in self.workers], self.n)
        signalled: list[Worker] = []
        done: list[str] = []
        for w, ps in zip(self.workers, placed, strict=True):
            w.files = ps
            w.write_assignment()
            if w.alive():
                w.reloaded = None
                w.send(signal.SIGHUP)
                signalled.append(w)
            elif ps and w.given_up is None:
                done.append(f"worker {w.index} started again ({len(ps)} machines)")
                w.join_output(1.0)
                w.start(resume=self.resume)
        self._reload_pending = (time.monotonic() + 10.0, signalled, done)
        self.notifier.ready(status=self.status_line())

    def _reload_done(self) -> None:
        """Log a SIGHUP's one line once every worker signalled said what it did (or after
        10 s, naming those that did not)."""
        if self._reload_pending is None:
            return
        deadline, signalled, done = self._reload_pending
        waiting = [w for w in signalled if w.reloaded is None and w.alive()
                   and w.stalled_since is None]
        if waiting and time.monotonic() < deadline:
            return
        self._reload_pending = None
        items = [*done, *(x for w in signalled for x in (w.reloaded or []))]
        items += [f"worker {w.index} did not say what it reloaded" for w in waiting]
        logger.warning("%s", reload_line(items, sum(len(w.files) for w in self.workers),
                                         str(self.directory)))

    def _grace(self) -> float:
        """A worker's machines finish their queued windows within 20 s [s]."""
        return 20.0

    def _ask_to_stop(self) -> None:
        for w in self.workers:
            w.send(signal.SIGTERM)
            if w.stalled_since is not None:
                w.send(signal.SIGCONT)  # a stopped worker can then stop as asked

    def _wait_stopped(self, deadline: float, limit: float) -> None:
        for w in self.workers:
            if w.proc is None:
                continue
            try:
                w.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                logger.error("worker %d did not stop within %.0f s: killed", w.index, limit)
                w.proc.kill()
                w.proc.wait()
            w.join_output(5.0)
            if not w.ended:
                w.ended = True
                w.codes.append(w.proc.returncode)
        for w in self.workers:
            w.close()
        with contextlib.suppress(OSError):
            for p in self.run_dir.iterdir():
                p.unlink()
            self.run_dir.rmdir()

    def close(self) -> None:
        """Remove the run directory (a host that was never started)."""
        with contextlib.suppress(OSError):
            self.run_dir.rmdir()

    # -- what to report -----------------------------------------------------------------------
    def fleet_status(self) -> FleetStatus:
        """The workers' machines summed from their reports, the degraded ones by name; a
        worker that has not reported is named."""
        running = total = 0
        degraded: list[str] = []
        for w in self.workers:
            if not w.files:
                continue
            if w.stalled_since is None and w.report is not None:
                running += w.report.monitored if w.alive() else 0
                total += w.report.machines
                degraded += w.report.degraded
                continue
            total += len(w.files)
            if w.stalled_since is not None:
                degraded.append(f"worker {w.index}: stalled for "
                                f"{time.monotonic() - w.stalled_since + w.stall_limit():.0f} s "
                                f"(sent nothing; not monitored: "
                                f"{', '.join(p.stem for p in w.files)})")
            else:
                degraded.append(w.given_up or f"worker {w.index}: "
                                + ("starting" if w.alive() else "not running"))
        return FleetStatus(monitored=running, machines=total, degraded=degraded)

    def status_line(self) -> str:
        """The workers' machines summed, the degraded ones by name."""
        return self.fleet_status().line(
            f"{self.directory}; {sum(w.alive() for w in self.workers)} worker processes")

    def summary(self) -> RunSummary:
        """Each machine's last block, in file order, and the total line."""
        machines = self._machine_summaries()
        counted = self._counted(machines)
        lost = [f"{m.name} ({m.file}): {m.lost}" for m in counted if m.lost is not None]
        restarted = sum(1 for w in self.workers for c in w.codes if c < 0)
        stalls = [f"worker {w.index} {w.stalls} time{'s' if w.stalls > 1 else ''} "
                  f"({', '.join(p.stem for p in w.files)})" for w in self.workers if w.stalls]
        total = (gateway_total(len(counted), lost)
                 + f" ({len(self.workers)} worker processes, {restarted} restarted"
                 + (f"; stalled: {'; '.join(stalls)}: their machines' windows meanwhile were "
                    f"not estimated" if stalls else "") + ")")
        return RunSummary(machines=machines, total=total, exit_status=self.exit_status())

    def _machine_summaries(self) -> list[MachineSummary]:
        """Each machine's last block, in file order; a given-up worker's machines lost."""
        by_file: dict[str, MachineSummary] = {}
        for w in self.workers:
            for report in w.summaries:
                for m in report.machines:
                    by_file[m.file] = m
        for w in self.workers:
            if w.given_up is not None:
                for p in w.files:
                    by_file.setdefault(p.name, MachineSummary(name=p.stem, file=p.name,
                                                              lost=w.given_up))
        return [by_file[f] for f in sorted(by_file)]

    def _counted(self, machines: list[MachineSummary]) -> list[MachineSummary]:
        """The machines counted once each: a machine is its name, not its file (a file
        renamed counts once, by its current file)."""
        current = {p.name for w in self.workers for p in w.files}
        names = {m.name for m in machines if m.file in current}
        gone = {m.name: m for m in machines if m.file not in current and m.name not in names}
        return [m for m in machines if m.file in current] + list(gone.values())

    def exit_status(self) -> int:
        """The worst of the workers' last exit statuses; 1 when a worker was given up, 74 when
        a worker stalled (its machines' windows meanwhile were not estimated)."""
        if any(w.given_up is not None for w in self.workers):
            return 1
        code = worst_exit(w.codes[-1] for w in self.workers if w.codes)
        if code in (0, EX_TEMPFAIL) and any(w.stalls for w in self.workers):
            return EX_IOERR
        return code

    def abandon(self) -> None:
        """A second stop signal: each worker gets its second SIGTERM."""
        for w in self.workers:
            w.send(signal.SIGTERM)
