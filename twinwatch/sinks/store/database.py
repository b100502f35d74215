"""Persistent state in the service's state directory: the health history and the last accepted
twin, in one SQLite database (stdlib :mod:`sqlite3`), so a restart resumes from the last trusted
twin and a subscriber that was away can catch up on the history.

Durability. WAL mode; each window is one transaction (its health row and, when trusted, the
twin), so after any crash the database holds a prefix of the windows, never half of one.
``synchronous=FULL`` (default) survives power loss; ``NORMAL`` survives any crash of the
process, and on power loss may roll back the windows since the last checkpoint.

Threads. Each thread gets its own connection (``threading.local``): in WAL mode readers never
block the writer nor see a half-written window.

Faults. A database that is not SQLite or is corrupt raises :class:`StoreError` with what to do
(or, with ``recover_corrupt=True``, is moved aside to ``<name>.corrupt-<time>`` and a new one
started), wherever SQLite reports it. A locked or full database at save time does not stop the
daemon: the window stays in a bounded in-memory backlog until the next successful save. The
file deleted, replaced or moved away while the daemon runs is noticed before the next window
and before any read (:meth:`~twinwatch.sinks.locks.FileLock.changed`) and handled as
docs/runtime.md describes.

Size: a DC-motor health message is about 2 kB of JSON, so one machine writes about 85 MB a day;
the defaults keep 30 days or 1,000,000 windows (about 2 GB), whichever is less, pruned in batches.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import sqlite3
import threading
import time
import zlib
from collections import deque
from collections.abc import Hashable, Mapping
from pathlib import Path
from typing import Any, ClassVar, Literal, Self

from twinwatch.errors import StoreError
from twinwatch.io.encoding import to_json
from twinwatch.sinks.base import Gate, ProcessedWindow, SinkContext, _frozen
from twinwatch.sinks.locks import FileLock, LockedError
from twinwatch.sinks.store import queries
from twinwatch.sinks.store.outbox import StoreOutbox
from twinwatch.sinks.store.schema import CACHE_KIB, SCHEMA, SCHEMA_VERSION, StateConfig, is_corrupt
from twinwatch.twin.health import HealthView, read_health

logger = logging.getLogger(__package__)  # the log lines name the package

__all__ = ["StateStore"]

_INSERT_HEALTH = ("INSERT INTO health (machine, run, window, t_start, t_end, wall, doc) "
                  "VALUES (?, ?, ?, ?, ?, ?, ?)")
_INSERT_TWIN = ("INSERT OR REPLACE INTO twin (machine, run, window, t_end, wall, state) "
                "VALUES (?, ?, ?, ?, ?, ?)")
_INSERT_DIAGNOSIS = ("INSERT OR REPLACE INTO diagnosis (machine, run, window, wall, state) "
                     "VALUES (?, ?, ?, ?, ?)")


class StateStore(Gate):
    """The health history and the last accepted twin of one machine, in SQLite: the
    pipeline's gate (:class:`~twinwatch.sinks.base.Gate`, the built-in output ``store``,
    table ``[state]``).

    Args:
        path: database file (created with its tables if absent; the directory must exist).
        synchronous: ``"FULL"`` (survives power loss) or ``"NORMAL"`` (survives SIGKILL).
        keep_days: delete health rows older than this (wall time); None keeps them.
        keep_rows: keep at most this many health rows; None for no limit.
        prune_every: prune after this many saved windows.
        prune_batch: rows deleted per pruning transaction.
        busy_timeout: seconds a statement waits for a lock held by another connection.
        backlog: windows kept in memory while the database cannot be written.
        recover_corrupt: move a corrupt database aside and start a new one instead of raising.
        check: run ``PRAGMA quick_check`` at open (reads the whole file).
        recent: windows kept in memory once written, to write them again to a database file
            that was deleted or replaced (``[acquisition] history``).
        run: the run id of the windows it stores (a health message that carries its own
            ``run`` is stored under it); None: a new one.

    Attributes:
        run_id: the run whose windows it stores ("this run" below).
        lost: windows lost for good: :attr:`never_stored` or :attr:`history_lost`.
        history_lost: windows of this run that were stored, then lost with a deleted or
            replaced database file (not in memory to write again).
        file_event: what happened to the file last (None: nothing), for the status.

    Raises:
        StoreError: the file is in use by another process (an exclusive ``flock`` is held
            until :meth:`close`), is not a database, is corrupt, is locked, or has a schema
            version above :data:`SCHEMA_VERSION`.
    """

    config_class: ClassVar[type[StateConfig]] = StateConfig
    counter_prefix: ClassVar[str | None] = "store"
    open_order: ClassVar[int] = 20  # its lock before the recording's (which truncates a file)

    def __init__(self, path: str | os.PathLike[str], *,
                 synchronous: Literal["FULL", "NORMAL"] = "FULL",
                 keep_days: float | None = 30.0, keep_rows: int | None = 1_000_000,
                 prune_every: int = 100, prune_batch: int = 1000, busy_timeout: float = 5.0,
                 backlog: int = 10_000, recover_corrupt: bool = False, check: bool = False,
                 recent: int = 1000, run: str | None = None) -> None:
        if synchronous not in ("FULL", "NORMAL"):
            raise ValueError(f"synchronous must be FULL or NORMAL, not {synchronous!r}")
        self.path = Path(path)
        self.synchronous = synchronous
        self.keep_days = keep_days
        self.keep_rows = keep_rows
        self.prune_every = prune_every
        self.prune_batch = prune_batch
        self.busy_timeout = busy_timeout
        self.run_id = run or f"{time.time():.6f}-{os.getpid()}"
        self._local = threading.local()
        self._conns: list[tuple[threading.Thread, sqlite3.Connection]] = []
        self._conns_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._pending: deque[tuple[Any, ...]] = deque(maxlen=backlog)
        #: the twin and the diagnosis evidence to write (their INSERT -> row)
        self._state_pending: dict[str, tuple[Any, ...]] = {}
        self._recent: deque[tuple[Any, ...]] = deque(maxlen=max(recent, 0))
        #: the twin's row last committed, written again into a replaced file (the
        #: diagnosis evidence, 400 kB, is not kept: the next checkpoint writes it)
        self._twin_saved: tuple[Any, ...] | None = None
        self._file_gone: str | None = None  # "deleted" / "replaced" / "moved", until reopened
        self._old_file: tuple[set[tuple[str, int]] | None, int] = (None, 0)
        # (output, machine) -> (run, window) delivered, read from the file left behind
        self._old_delivered: dict[tuple[str, str], set[tuple[str, int]]] = {}
        #: the database file the store writes: +1 each time it opens another one at the path
        #: (deleted, replaced or moved away); an outbox of an earlier file is stale
        self.generation = 0
        self._sidecars: dict[str, tuple[int, int]] = {}  # our -wal / -shm: (st_dev, st_ino)
        self.history_lost = 0
        self.outbox_dropped: dict[tuple[str, str], int] = {}  # (output, machine) -> windows
        self.file_event: str | None = None
        self._failing = False
        self._failing_since: float | None = None
        self.locked = False
        self._closed_for_good = False
        self._since_prune = 0
        self.saved = 0
        self.errors = 0
        self.dropped = 0
        self.pruned = 0
        self.lost = 0
        self.recovered = 0
        self.not_stored = 0
        self.recover_corrupt = recover_corrupt
        self._check = check
        self._lock: FileLock | None = None
        self._lock_file()
        try:
            try:
                self._open(check)
            except StoreError as exc:
                if not (recover_corrupt and self.path.exists() and exc.corrupt):
                    raise
                self._recover(exc)
        except BaseException:
            self._close_all()
            self._release()
            raise
        self._closed = False

    def _lock_file(self) -> None:
        """Take the exclusive lock on the database file before SQLite opens it."""
        try:
            self._lock = FileLock(self.path, "state database",
                                  "stop it, or give this one its own [state] path")
        except LockedError as exc:
            raise StoreError(str(exc)) from None
        except OSError as exc:
            raise self._error("cannot open", exc) from exc

    def _release(self) -> None:
        """Release the file lock (only once SQLite's connections are closed: see locks.py)."""
        lock, self._lock = self._lock, None
        if lock is not None:
            lock.release()

    @property
    def waiting(self) -> int:
        """Windows kept in memory because the database could not be written (yet)."""
        return len(self._pending)

    @property
    def failing(self) -> bool:
        """The last write failed (the windows since then are :attr:`waiting`)."""
        return self._failing

    # -- connections --------------------------------------------------------------------------
    def _connect(self) -> sqlite3.Connection:
        conn: sqlite3.Connection | None = getattr(self._local, "conn", None)
        if conn is not None:
            return conn
        if self._closed_for_good:
            raise StoreError(f"{self.path}: the state store is closed")
        try:
            conn = sqlite3.connect(self.path, timeout=self.busy_timeout, isolation_level=None,
                                   check_same_thread=False)
            conn.execute(f"PRAGMA synchronous={self.synchronous}")
            conn.execute("PRAGMA foreign_keys=ON")
            conn.execute(f"PRAGMA cache_size=-{CACHE_KIB}")
        except sqlite3.Error as exc:
            raise self._error("cannot open", exc) from exc
        self._local.conn = conn
        with self._conns_lock:
            ended = [c for t, c in self._conns if not t.is_alive()]
            self._conns = [(t, c) for t, c in self._conns if t.is_alive()]
            self._conns.append((threading.current_thread(), conn))
        for c in ended:  # a worker a reload replaced: its descriptors would stay open
            c.close()
        return conn

    def _error(self, what: str, exc: BaseException) -> StoreError:
        msg = str(exc)
        corrupt = is_corrupt(exc)
        if corrupt:
            hint = (f"the file is corrupt or not a twinwatch database: stop the service, move "
                    f"it aside (mv {self.path} {self.path}.bad) and start again to begin a new "
                    f"history")
            hint += (" (recover_corrupt is set but moving it aside failed)"
                     if getattr(self, "recover_corrupt", False) else
                     ", or set [state] recover_corrupt = true to do this automatically")
        elif "locked" in msg or "busy" in msg:
            hint = ("another process holds a lock on it (a second twinwatch on the same state "
                    "directory, or an open sqlite3 shell in a transaction): stop that process")
        elif "readonly" in msg or "unable to open" in msg or isinstance(exc, PermissionError):
            hint = ("check that the directory exists and is writable by the service user "
                    "(StateDirectory= in the unit)")
        elif "full" in msg or "disk I/O" in msg:
            hint = ("the disk is full, failing or read-only: free space (or lower the retention, "
                    "keep_days, keep_rows); windows wait in memory, not published, until it can "
                    "be written")
        else:
            hint = "check the file and the disk"
        return StoreError(f"state database {self.path}: {what}: {msg}: {hint}", corrupt=corrupt,
                          detail=f"{what}: {msg}")

    def _recover(self, exc: BaseException) -> None:
        """Move the corrupt database (and its WAL and shared-memory files) aside to
        ``<name>.corrupt-<time>`` and start a new one; the windows waiting stay pending.

        Raises:
            StoreError: the file cannot be moved or the new database cannot be created.
        """
        stamp = time.strftime("%Y%m%dT%H%M%S")
        aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        n = 1
        while aside.exists():
            aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{n}")
            n += 1
        why = exc.detail if isinstance(exc, StoreError) else str(exc)
        self._close_all()
        try:
            for suffix in ("-wal", "-shm"):
                side = Path(str(self.path) + suffix)
                if side.exists():
                    side.rename(Path(str(aside) + suffix))
            self.path.rename(aside)
            self._release()
            self._lock_file()
        except OSError as err:
            raise StoreError(f"state database {self.path} is corrupt ({why}) and cannot be "
                             f"moved aside ({err.strerror or err}): move it away by hand",
                             corrupt=True) from err
        self.recovered += 1
        logger.error("state database %s was corrupt (%s): moved aside to %s and started a new "
                     "one; the history before now is only in that file", self.path, why, aside)
        self._open(self._check)

    def _read(self, what: str, fn: Any) -> Any:
        """Run ``fn(connection)`` for a read; a corrupt database is moved aside and the read
        retried once on the new one when ``recover_corrupt`` is set.

        Raises:
            StoreError: the read failed (the message says what to do).
        """
        with self._write_lock:
            self._check_file()
            gone = self._file_gone
        if gone is not None:
            raise StoreError(f"state database {self.path} was {gone} and cannot be opened "
                             f"again yet ({self.file_event})")
        try:
            return fn(self._connect())
        except sqlite3.Error as exc:
            err = self._error(what, exc)
        if not (err.corrupt and self.recover_corrupt):
            raise err
        with self._write_lock:
            self._recover(err)
        try:
            return fn(self._connect())
        except sqlite3.Error as exc:
            raise self._error(what, exc) from exc

    def _open(self, check: bool) -> None:
        conn = self._connect()
        try:
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                logger.warning("state database %s: journal mode is %s, not WAL (a network "
                               "file system?): readers may block the writer", self.path, mode)
            if check:
                res = [r[0] for r in conn.execute("PRAGMA quick_check").fetchall()]
                if res != ["ok"]:
                    raise sqlite3.DatabaseError("database disk image is malformed: "
                                                + "; ".join(res[:5]))
            have = {r[0] for r in conn.execute(
                "SELECT name FROM sqlite_master WHERE type='table'")}
            if "schema_version" in have:
                row = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()
                version = int(row[0] or 0)
                if version > SCHEMA_VERSION:
                    raise StoreError(
                        f"state database {self.path} was written by a newer twinwatch (schema "
                        f"version {version}; this one reads up to {SCHEMA_VERSION}): upgrade "
                        f"twinwatch, or move the file aside to start a new history")
            elif have - {"sqlite_sequence"}:
                raise StoreError(f"state database {self.path} holds tables {sorted(have)} but "
                                 f"no schema_version: it is not a twinwatch database; point "
                                 f"the store at another file")
            conn.execute("BEGIN IMMEDIATE")
            for stmt in SCHEMA.split(";"):
                if stmt.strip():
                    conn.execute(stmt)
            if conn.execute("SELECT COUNT(*) FROM schema_version").fetchone()[0] == 0:
                conn.execute("INSERT INTO schema_version VALUES (?, ?)",
                             (SCHEMA_VERSION, time.time()))
            conn.execute("COMMIT")
        except StoreError:
            raise
        except sqlite3.Error as exc:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise self._error("cannot open", exc) from exc
        self._sidecars = {}
        for suffix in ("-wal", "-shm"):
            try:
                st = os.stat(str(self.path) + suffix)
            except OSError:
                continue
            self._sidecars[suffix] = (st.st_dev, st.st_ino)

    # -- the file deleted, replaced or moved away under the running daemon ---------------------
    def _check_file(self, window: int | None = None) -> None:
        """If the file at :attr:`path` is no longer the one this store has open (deleted,
        replaced or moved away), open (create) the one at the path and write to it what it
        should hold. Called with the write lock held, before each write and each read.

        Args:
            window: the window about to be written (for the log), None for a read.
        """
        if self._closed_for_good:
            return
        if self._file_gone is None:
            why = self._lock.changed() if self._lock is not None else None
            if why is None:
                return
            self._leave_old_file(why, window)
        self._adopt_file_at_path(window)

    def _leave_old_file(self, why: str, window: int | None) -> None:
        """Read what this run stored in the file the store has open (still readable through
        its connections), checkpoint it, close it, and remove its ``-wal`` and ``-shm``."""
        self._file_gone = why
        stored: set[tuple[str, int]] | None = None
        earlier = 0
        with self._conns_lock:
            conns = [c for _, c in self._conns]
        for conn in conns[:1]:
            try:
                stored = {(str(m), int(w)) for m, w in conn.execute(
                    "SELECT machine, window FROM health WHERE run = ?", (self.run_id,))}
                earlier = int(conn.execute("SELECT COUNT(*) FROM health WHERE run != ?",
                                           (self.run_id,)).fetchone()[0])
                delivered: dict[tuple[str, str], set[tuple[str, int]]] = {}
                for output, machine, position in conn.execute(
                        "SELECT output, machine, health_id FROM outbox_position").fetchall():
                    delivered[(str(output), str(machine))] = {(str(r), int(w)) for r, w in
                                                              conn.execute(
                        "SELECT h.run, h.window FROM health h WHERE +h.machine = ? AND "
                        "h.run = ? AND (h.id <= ? OR EXISTS (SELECT 1 FROM outbox_ack a WHERE "
                        "a.output = ? AND a.machine = h.machine AND a.run = h.run AND "
                        "a.window = h.window))", (machine, self.run_id, position, output))}
                self._old_delivered = delivered
                conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")  # a file moved away: complete
            except sqlite3.Error as exc:
                logger.debug("reading the old state database %s failed: %s", self.path, exc)
        self._old_file = (stored, earlier)
        self._close_all()
        self._release()
        for suffix, ident in self._sidecars.items():
            side = Path(str(self.path) + suffix)
            try:
                st = side.stat()
                if (st.st_dev, st.st_ino) == ident:
                    side.unlink()
            except OSError:
                pass
        self._sidecars = {}
        at = f" (noticed at window {window})" if window is not None else ""
        self.file_event = f"state database {self.path} was {why} while running{at}"

    def _adopt_file_at_path(self, window: int | None) -> None:
        """Open (create) the database at the path, write the saved twin and the windows in
        memory it lacks, count what is lost. On failure the store stays without a file
        (windows wait in memory, not published) and the next window tries again."""
        why = self._file_gone
        try:
            self._lock_file()
            try:
                self._open(self._check)
            except StoreError as exc:
                if not (exc.corrupt and self.recover_corrupt and self.path.exists()):
                    raise
                self._recover(exc)
            conn = self._connect()
            have = {(str(m), int(w)) for m, w in conn.execute(
                "SELECT machine, window FROM health WHERE run = ?", (self.run_id,))}
            rows = [_unpacked(r) for r in self._recent if (r[0], r[2]) not in have]
            conn.execute("BEGIN IMMEDIATE")
            top = int(conn.execute("SELECT COALESCE(MAX(id), 0) FROM health").fetchone()[0])
            try:
                conn.executemany(_INSERT_HEALTH, rows)
                if self._twin_saved is not None:
                    conn.execute(_INSERT_TWIN, self._twin_saved)
                self._carry_outboxes(conn, top)
                conn.execute("COMMIT")
            except sqlite3.Error:
                conn.execute("ROLLBACK")
                raise
        except (StoreError, sqlite3.Error, OSError) as exc:
            self._close_all()
            self._release()
            if self.file_event is not None and "cannot be opened again" not in self.file_event:
                self.file_event += f"; cannot be opened again ({exc})"
                logger.error("%s: the database at the path cannot be opened again (%s); windows "
                             "wait in memory, not published, and it is tried again with each "
                             "window", self.file_event, exc)
            return
        self.generation += 1
        self._old_delivered = {}
        stored, earlier = self._old_file
        kept = have | {(r[0], r[2]) for r in self._recent}
        lost = 0 if why == "moved" or stored is None else len(stored - kept)
        self.history_lost += lost
        self.lost += lost  # lost for good: `twinwatch run` exits 74
        self._file_gone = None
        event = (self.file_event or f"state database {self.path} was {why}").split(
            "; cannot be opened again")[0]
        twin = "the saved twin and " if self._twin_saved is not None else ""
        if why == "moved":
            self.file_event = (f"{event}: the windows stored until then stay in that file; a new "
                               f"one at the path holds {twin}the {len(rows)} windows in memory")
            logger.warning("%s", self.file_event)
        else:
            earlier_note = (f", and {earlier} windows of earlier runs" if earlier else "")
            self.file_event = (f"{event}: opened again, {twin}{len(rows)} windows still in "
                               f"memory written to it; {lost} windows of this run stored before "
                               f"are lost with the old file{earlier_note}")
            logger.log(logging.ERROR if lost or earlier else logging.WARNING, "%s",
                       self.file_event)

    def _carry_outboxes(self, conn: sqlite3.Connection, top: int) -> None:
        """Carry the outboxes of the file left behind into the file at the path (in the
        caller's transaction): an output without a position there gets one at ``top`` (the
        older rows are history, not sent), and this run's windows it had delivered are marked
        delivered; the others stay pending."""
        wall = time.time()
        for (output, machine), done in self._old_delivered.items():
            conn.execute("INSERT OR IGNORE INTO outbox_position (output, machine, health_id, "
                         "wall) VALUES (?, ?, ?, ?)", (output, machine, top, wall))
            marks = [(output, machine, r, w, i, wall) for i, r, w in conn.execute(
                "SELECT id, run, window FROM health WHERE +machine = ? AND run = ?",
                (machine, self.run_id)) if (str(r), int(w)) in done]
            conn.executemany("INSERT OR IGNORE INTO outbox_ack (output, machine, run, window, "
                             "health_id, wall) VALUES (?, ?, ?, ?, ?, ?)", marks)

    # -- the sink contract ---------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: StateConfig, context: SinkContext) -> Self:
        """Open ``[state] path`` (relative to the working directory).

        Raises:
            StoreError: as the class.
        """
        return cls(config.output_files(context.cwd)["path"], synchronous=config.synchronous,
                   keep_days=config.keep_days, keep_rows=config.keep_rows,
                   recover_corrupt=config.recover_corrupt, recent=context.recent_windows,
                   run=context.run or None)

    @classmethod
    def reload_key(cls, config: StateConfig, context: SinkContext) -> Hashable:
        """The table alone: the database holds every machine's rows."""
        return _frozen(config.model_dump())

    @property
    def never_stored(self) -> int:
        """Windows lost without ever being stored (the backlog full, or not written by
        :meth:`close`); :attr:`lost` also counts :attr:`history_lost`."""
        return int(self.lost - self.history_lost)

    def counters(self) -> dict[str, int]:
        """``errors`` (failed writes), ``waiting`` (windows in memory), ``lost`` (never
        stored), ``history_lost`` (stored, then lost with a deleted or replaced file)."""
        return {"errors": int(self.errors), "waiting": int(self.waiting),
                "lost": self.never_stored, "history_lost": int(self.history_lost)}

    @property
    def problem(self) -> str | None:
        """The database not writable (windows waiting, not published), windows lost."""
        out = []
        if self.failing and self.locked:
            since = (time.monotonic() - self._failing_since
                     if self._failing_since is not None else 0.0)
            out.append(f"state database locked by another process for {since:.0f} s: "
                       f"{self.waiting} windows waiting in memory, published once stored")
        elif self.failing:
            out.append(f"state database not writable: {self.waiting} windows waiting "
                       f"in memory, not published")
        if self.never_stored:
            out.append(f"{self.never_stored} windows lost (never stored)")
        if self.history_lost:
            out.append(f"{self.history_lost} stored windows lost with a deleted or replaced "
                       f"state database file")
        return "; ".join(out) or None

    @property
    def status(self) -> str:
        return f"state {self.path}"

    def summary(self) -> list[str]:
        """The windows not stored when estimated, and those lost with the file, if any."""
        out = []
        if self.not_stored:
            late = self.not_stored - self.never_stored - self.waiting
            out.append(f"state database: {self.not_stored} windows could not be stored when "
                       f"estimated, so they were not published ({max(late, 0)} written later, "
                       f"served by the history query; {self.never_stored} lost)")
        if self.history_lost:
            out.append(f"state database: {self.history_lost} windows stored by this run were "
                       f"lost with its deleted or replaced file (no longer in memory to write "
                       f"again)")
        return out

    def write(self, out: ProcessedWindow) -> bool:
        """:meth:`save_window` with the processed window.

        Returns:
            True if the window is stored; False if it waits in memory (it is then not
            published; counted in :attr:`not_stored`).
        """
        ok = self._save(out)
        self.not_stored += not ok
        return ok

    def hold(self, out: ProcessedWindow) -> None:
        """Keep the window in memory without trying to write it (the database is
        :attr:`locked`: a try would wait the busy timeout). Not counted in :attr:`not_stored`
        (the pipeline counts it if it is not published)."""
        self._save(out, flush=False)

    def _save(self, out: ProcessedWindow, flush: bool = True) -> bool:
        h, twin = out.health, out.twin_state
        return self.save_window({"machine": h.machine, "run": h.run, "window": h.window,
                                 "t_start": h.t_start, "t_end": h.t_end},
                                None if twin is None else twin.as_dict(), doc=out.health_json,
                                flush=flush)

    def retry(self) -> bool:
        """One attempt to write the windows waiting in memory (waits up to the busy timeout
        for another process's lock). True when nothing waits any more."""
        with self._write_lock:
            self._check_file()
            if not self._pending and not self._state_pending:
                return True
            return self._flush()

    # -- writing ------------------------------------------------------------------------------
    def save_window(self, health: Mapping[str, Any], twin_state: Mapping[str, Any] | None,
                    *, wall: float | None = None, doc: str | None = None,
                    flush: bool = True) -> bool:
        """Store one window's health message and, if given, the latest accepted twin, in one
        transaction.

        Args:
            health: the health message (``machine``, ``run``, ``window``, ``t_start``,
                ``t_end`` are indexed; without ``run`` it is stored under :attr:`run_id`).
            twin_state: the twin to resume from (any JSON-serialisable mapping, numpy
                allowed), or None when this window was not trusted (the stored twin is kept);
                its ``diagnosis`` (the diagnoser's evidence), when there, is kept in a row of
                its own (:meth:`_keep_state`).
            wall: wall-clock time [s since the epoch] of the window (default now).
            doc: the message already encoded, stored byte for byte; ``health`` then needs
                only the indexed keys. None: ``health`` is encoded here.
            flush: False: only keep the window in memory, written with the next successful
                save or :meth:`retry`.

        Returns:
            True if committed; False if the database could not be written (the window waits
            in memory).
        """
        w = time.time() if wall is None else float(wall)
        machine = str(health["machine"])
        with self._write_lock:
            self.run_id = str(health.get("run") or self.run_id)  # the run whose windows it holds
            row = (machine, self.run_id, int(health["window"]), float(health["t_start"]),
                   float(health["t_end"]), w, to_json(health) if doc is None else doc)
            self._check_file(row[2])
            if len(self._pending) == self._pending.maxlen:
                self.dropped += 1
                self.lost += 1
                logger.error("state database %s: %d windows waiting in memory, the most it "
                             "keeps: window %d is lost", self.path, len(self._pending),
                             self._pending[0][2])
            self._pending.append(row)
            if twin_state is not None:
                self._keep_state(machine, row[2], row[4], w, twin_state)
            if not flush:
                return False
            ok = self._flush()
        if ok:
            self._since_prune += 1
            if self.prune_every and self._since_prune >= self.prune_every:
                self._since_prune = 0
                self.prune()
        return ok

    def save_state(self, machine: str, window: int, t_end: float,
                   twin_state: Mapping[str, Any]) -> bool:
        """Store the twin to resume from, without a window (a daemon's last, at its stop):
        :meth:`save_window`'s ``twin_state`` of window ``window`` ending at ``t_end`` [s].
        Returns True if committed (else it waits in memory, as a window's twin does)."""
        with self._write_lock:
            self._check_file(window)
            self._keep_state(machine, window, t_end, time.time(), twin_state)
            return self._flush()

    def _keep_state(self, machine: str, window: int, t_end: float, wall: float,
                    twin_state: Mapping[str, Any]) -> None:
        """Queue the twin's row and, when it carries one, the diagnosis evidence's: the
        evidence (hundreds of kB) is written when the pipeline sends it, every few windows,
        the twin (a few kB) with each trusted window. :meth:`load_twin_state` joins them."""
        diagnosis = twin_state.get("diagnosis")
        if diagnosis is not None:
            twin_state = {k: v for k, v in twin_state.items() if k != "diagnosis"}
            self._state_pending[_INSERT_DIAGNOSIS] = (machine, self.run_id, window, wall,
                                                      to_json(diagnosis))
        self._state_pending[_INSERT_TWIN] = (machine, self.run_id, window, t_end, wall,
                                             to_json(twin_state))

    def _flush(self, retry: bool = True) -> bool:
        if self._file_gone is not None:  # no database file to write to yet: wait in memory
            return self._flush_failed(StoreError(f"{self.file_event}: not written yet"))
        try:
            conn = self._connect()
        except StoreError as exc:
            return self._flush_failed(exc)
        try:
            conn.execute("BEGIN IMMEDIATE")
            conn.executemany(_INSERT_HEALTH, list(self._pending))
            for sql, pending in self._state_pending.items():
                conn.execute(sql, pending)
            conn.execute("COMMIT")
        except sqlite3.Error as exc:
            _rollback(conn)
            if retry and self.recover_corrupt and is_corrupt(exc):
                try:
                    self._recover(exc)
                except StoreError as err:
                    return self._flush_failed(err)
                return self._flush(retry=False)
            return self._flush_failed(exc)
        if self._failing:
            logger.warning("state database %s writable again%s: %d delayed windows written",
                           self.path, f" after {time.monotonic() - self._failing_since:.0f} s"
                           if self._failing_since is not None else "", len(self._pending))
            self._failing = False
        self.locked = False
        self._failing_since = None
        self.saved += len(self._pending)
        if self._recent.maxlen:
            self._recent.extend(_packed(row) for row in self._pending)
        self._pending.clear()
        self._twin_saved = self._state_pending.get(_INSERT_TWIN, self._twin_saved)
        self._state_pending.clear()
        return True

    def _flush_failed(self, exc: BaseException) -> bool:
        self.errors += 1
        msg = str(exc)
        self.locked = isinstance(exc, sqlite3.OperationalError) and (
            "locked" in msg or "busy" in msg)
        if self._failing_since is None:
            self._failing_since = time.monotonic()
        err = exc if isinstance(exc, StoreError) else self._error(
            f"window {self._pending[-1][2]} not written yet ({len(self._pending)} waiting in "
            f"memory)", exc)
        if not self._failing:
            logger.error("%s", err)
            self._failing = True
        else:
            logger.debug("%s", err)
        return False

    def prune(self, now: float | None = None) -> int:
        """Delete health rows beyond the retention, ``prune_batch`` rows per transaction.

        Returns:
            The number of rows deleted.
        """
        conn = self._connect()
        now = time.time() if now is None else now
        deleted = 0
        try:
            if self.keep_days is not None:
                cutoff = now - self.keep_days * 86400.0
                deleted += self._delete_batches(conn, "wall < ?", (cutoff,))
            if self.keep_rows is not None:
                row = conn.execute("SELECT id FROM health ORDER BY id DESC LIMIT 1 OFFSET ?",
                                   (self.keep_rows,)).fetchone()
                if row is not None:
                    deleted += self._delete_batches(conn, "id <= ?", (row[0],))
        except sqlite3.Error as exc:
            logger.warning("%s", self._error("pruning failed (retried later)", exc))
        self.pruned += deleted
        if deleted:
            logger.debug("pruned %d health rows from %s", deleted, self.path)
        return deleted

    def _delete_batches(self, conn: sqlite3.Connection, where: str,
                        args: tuple[Any, ...]) -> int:
        total = 0
        while True:
            with self._write_lock:
                batch = f"SELECT id FROM health WHERE {where} ORDER BY id LIMIT ?"
                conn.execute("BEGIN IMMEDIATE")
                try:
                    self._outbox_prune(conn, batch, (*args, self.prune_batch))
                    cur = conn.execute(f"DELETE FROM health WHERE id IN ({batch})",
                                       (*args, self.prune_batch))
                    n = cur.rowcount
                    conn.execute("COMMIT")
                except BaseException:
                    conn.execute("ROLLBACK")
                    raise
            total += n
            if n < self.prune_batch:
                return total

    def _outbox_prune(self, conn: sqlite3.Connection, batch: str, args: tuple[Any, ...]) -> None:
        """Before a batch of health rows is deleted: count per outbox the rows it had not
        delivered (:attr:`outbox_dropped`), move its position past the batch and forget its
        delivery marks there (in the caller's transaction)."""
        positions = conn.execute("SELECT output, machine, health_id FROM outbox_position"
                                 ).fetchall()
        if not positions:
            return
        top = conn.execute(f"SELECT MAX(id) FROM ({batch})", args).fetchone()[0]
        if top is None:
            return
        for output, machine, position in positions:
            lost = conn.execute(
                f"SELECT COUNT(*) FROM health h WHERE h.id IN ({batch}) AND h.machine = ? "
                f"AND h.id > ? AND NOT EXISTS (SELECT 1 FROM outbox_ack a WHERE a.output = ? "
                f"AND a.machine = h.machine AND a.run = h.run AND a.window = h.window)",
                (*args, machine, position, output)).fetchone()[0]
            if lost:
                key = (str(output), str(machine))
                self.outbox_dropped[key] = self.outbox_dropped.get(key, 0) + int(lost)
                logger.warning("state database %s: retention deleted %d windows of %s that "
                               "the output %s had not delivered", self.path, lost, machine,
                               output)
            if position < top:
                conn.execute("UPDATE outbox_position SET health_id = ? WHERE output = ? AND "
                             "machine = ?", (top, output, machine))
        conn.execute("DELETE FROM outbox_ack WHERE health_id <= ?", (top,))

    # -- reading ------------------------------------------------------------------------------
    def load_twin_state(self, machine: str | None = None) -> dict[str, Any] | None:
        """The last accepted twin, exactly as saved (None if none was saved), with the
        diagnosis evidence its run saved last as ``diagnosis`` (a twin saved whole, by an
        earlier version, keeps its own).

        Args:
            machine: whose twin (default: the most recently saved one).
        """
        got = self._read("cannot read the twin state",
                         lambda conn: queries.twin_state(conn, machine))
        if got is None:
            return None
        state = dict(json.loads(got[0]))
        if got[1] is not None and state.get("diagnosis") is None:
            state["diagnosis"] = json.loads(got[1])
        return state

    def history(self, t_from: float | None = None, t_to: float | None = None,
                limit: int | None = 1000, *, by: Literal["plant", "wall"] = "plant",
                machine: str | None = None, run: str | None = None,
                after: float | None = None) -> list[HealthView]:
        """Health messages in a time range, oldest first (in the order they were saved).

        Args:
            t_from, t_to: range [s]; None leaves that end open. By plant time a window is
                returned if it overlaps the range (``t_end >= t_from`` and
                ``t_start <= t_to``); by wall time if it was saved inside it.
            limit: at most this many (page on with ``after``), None for all.
            by: ``"plant"`` (the source's time, as in the health message) or ``"wall"``
                (seconds since the epoch when the window was saved).
            machine: only this machine.
            run: only this run's windows (plant time starts over with every run of a replay).
            after: only windows ending strictly after this time [s]: the paging cursor
                (``t_from`` is inclusive: it would return the last window again).

        Returns:
            The stored health messages through their typed views
            (:func:`~twinwatch.twin.health.read_health`), as a :class:`HistoryPage`.
        """
        sql, args = queries.history_query(t_from, t_to, limit, by=by, machine=machine, run=run,
                                          after=after)
        rows = self._read("cannot read the history",
                          lambda conn: conn.execute(sql, args).fetchall())
        return queries.history_page(rows)

    def timeline(self, machine: str, t_from: float | None = None) -> list[HealthView]:
        """The machine's health messages on the time line that ends with its last stored
        window, oldest first: read back across runs while each window ends before the one
        saved after it starts (the reading stops where the clock went back) and ends at or
        after ``t_from`` [s, plant time]. What a restart resumes the trends from."""
        lower = float(t_from) if t_from is not None and math.isfinite(t_from) else -math.inf
        docs = self._read("cannot read the history",
                          lambda conn: queries.timeline_docs(conn, machine, lower))
        return [read_health(d) for d in reversed(docs)]

    def latest_health(self, machine: str | None = None) -> HealthView | None:
        """The last health message saved, through its typed view."""
        doc = self._read("cannot read the history",
                         lambda conn: queries.latest_doc(conn, machine))
        return None if doc is None else read_health(doc)

    def last_docs(self, machine: str, run: str, limit: int) -> list[str]:
        """The last ``limit`` health messages of ``machine``'s run ``run``, as saved (JSON
        text), oldest first (:meth:`twinwatch.daemon.pipeline.WindowPipeline.recent`). Also
        after :meth:`close`, read-only: a run's history is asked for after its daemon stopped.

        Raises:
            StoreError: the database cannot be read (the message says why).
        """
        if self._closed_for_good:
            try:
                conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True,
                                       timeout=self.busy_timeout)
                try:
                    return queries.last_docs(conn, machine, run, limit)
                finally:
                    conn.close()
            except sqlite3.Error as exc:
                raise self._error("cannot read the history", exc) from exc
        docs: list[str] = self._read("cannot read the history",
                                     lambda conn: queries.last_docs(conn, machine, run, limit))
        return docs

    def count(self) -> int:
        """Health rows stored."""
        return int(self._read("cannot count the history", queries.count))

    # -- the outbox of a store-and-forward output ------------------------------------------------
    def outbox(self, output: str, machine: str) -> StoreOutbox:
        """The outbox of ``output`` for ``machine``'s windows (see :class:`StoreOutbox`)."""
        return StoreOutbox(self, output, machine)

    def _write(self, what: str, fn: Any) -> None:
        """Run ``fn(connection)`` in one write transaction, under the write lock.

        Raises:
            StoreError: the database cannot be written (nothing of ``fn`` is committed).
        """
        with self._write_lock:
            self._check_file()
            if self._file_gone is not None:
                raise StoreError(f"state database {self.path} was {self._file_gone}: not "
                                 f"written yet ({self.file_event})")
            conn = self._connect()
            try:
                conn.execute("BEGIN IMMEDIATE")
                fn(conn)
                conn.execute("COMMIT")
            except sqlite3.Error as exc:
                _rollback(conn)
                raise self._error(what, exc) from exc

    # -- lifecycle ----------------------------------------------------------------------------
    def _close_all(self) -> None:
        with self._conns_lock:
            conns, self._conns = [c for _, c in self._conns], []
        for c in conns:
            try:
                c.close()
            except sqlite3.Error:  # pragma: no cover
                logger.debug("error closing a state database connection", exc_info=True)
        self._local = threading.local()

    def close(self) -> None:
        """Write any delayed windows (one last try), then close every connection. Idempotent."""
        if self._closed:
            return
        with self._write_lock:
            self._check_file()
            if self._pending or self._state_pending:
                if self._file_gone is not None or not self._flush():
                    self.lost += len(self._pending)
                    logger.error("state database %s: %d windows could not be written and are "
                                 "lost", self.path, len(self._pending))
                    self._pending.clear()
        self._close_all()
        self._release()
        self._closed_for_good = True
        self._closed = True


def _packed(row: tuple[Any, ...]) -> tuple[Any, ...]:
    """A saved ``health`` row as kept in ``_recent``: its message zlib-compressed (level 1:
    9 KB of JSON -> about 2.8 KB)."""
    return (*row[:6], zlib.compress(row[6].encode(), 1))


def _unpacked(row: tuple[Any, ...]) -> tuple[Any, ...]:
    return (*row[:6], zlib.decompress(row[6]).decode())


def _rollback(conn: sqlite3.Connection) -> None:
    """Roll back the transaction a failure left open (a failing rollback is ignored)."""
    if conn.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            conn.execute("ROLLBACK")
