"""The outbox of a store-and-forward output in the state database (:class:`StoreOutbox`,
the gate's :class:`~twinwatch.sinks.base.Outbox`): which stored windows an output has
delivered, read and written through the store's connections and its write lock."""

from __future__ import annotations

import sqlite3
import time
from typing import TYPE_CHECKING, Any

from twinwatch.sinks.base import OutboxRow

if TYPE_CHECKING:
    from twinwatch.sinks.store.database import StateStore

__all__ = ["StoreOutbox"]


class StoreOutbox:
    """One output's outbox in the state database (:class:`~twinwatch.sinks.base.Outbox`): the
    ``health`` table holds the windows, this records which of them the output has delivered.

    Two tables, one transaction per call under the store's write lock: ``outbox_position``
    (output, machine -> a ``health`` row id at or below which every window is delivered) and
    ``outbox_ack`` (output, machine, run, window -> delivered, for the windows above the
    position).

    Args:
        store: the open state store.
        output: the output's registry name (``mqtt``).
        machine: whose windows.

    Every method raises :class:`~twinwatch.errors.StoreError` when the database cannot be
    read or written (nothing is then recorded: call again).
    """

    # The queries read the health table by row id ranges (``+machine``: not through the
    # machine's time indexes, which would visit every row of the machine).

    def __init__(self, store: StateStore, output: str, machine: str) -> None:
        self.store = store
        self.output = output
        self.machine = machine
        self.generation = store.generation

    @property
    def changed(self) -> bool:
        """The store has opened another database file since this outbox was made: its row
        ids and position are stale; ask the gate for a new outbox."""
        return self.store.generation != self.generation

    def _same_file(self, conn: sqlite3.Connection) -> sqlite3.Connection:
        """``conn`` if the store still writes the file of this outbox; else raises."""
        if self.changed:
            raise sqlite3.OperationalError("the state database file changed: its outbox is "
                                           "read again")
        return conn

    def _one(self, sql: str, args: tuple[Any, ...]) -> Any:
        return self.store._read("cannot read the outbox",
                                lambda conn: self._same_file(conn).execute(sql, args).fetchone())

    @property
    def dropped(self) -> int:
        """Windows deleted by the retention before they were delivered."""
        return self.store.outbox_dropped.get((self.output, self.machine), 0)

    def start(self) -> int:
        """The delivered position; on the output's first open, the newest stored window of
        the machine (0 if none): the history before the output existed is not sent."""
        row = self._one("SELECT health_id FROM outbox_position WHERE output = ? AND machine = ?",
                        (self.output, self.machine))
        if row is not None:
            return int(row[0])
        position = self.latest_id() or 0

        def create(conn: sqlite3.Connection) -> None:
            self._same_file(conn).execute(
                "INSERT OR IGNORE INTO outbox_position (output, machine, health_id, wall) "
                "VALUES (?, ?, ?, ?)", (self.output, self.machine, position, time.time()))

        self.store._write("cannot create the outbox", create)
        return self.start()

    def pending(self, after: int, limit: int) -> list[OutboxRow]:
        """Stored windows of the machine above row id ``after`` not delivered, oldest first."""
        rows = self.store._read("cannot read the outbox", lambda conn: self._same_file(
            conn).execute(
            "SELECT h.id, h.run, h.window, h.wall, h.doc FROM health h WHERE h.id > ? AND "
            "+h.machine = ? AND NOT EXISTS (SELECT 1 FROM outbox_ack a WHERE a.output = ? AND "
            "a.machine = h.machine AND a.run = h.run AND a.window = h.window) ORDER BY h.id "
            "LIMIT ?", (int(after), self.machine, self.output, int(limit))).fetchall())
        return [OutboxRow(int(i), str(r), int(w), float(t), str(d)) for i, r, w, t, d in rows]

    def count(self, position: int) -> int:
        """Stored windows of the machine above ``position`` not delivered."""
        def read(conn: sqlite3.Connection) -> int:
            stored = self._same_file(conn).execute(
                "SELECT COUNT(*) FROM health WHERE id > ? AND +machine = ?",
                (int(position), self.machine)).fetchone()[0]
            acked = conn.execute(
                "SELECT COUNT(*) FROM outbox_ack a WHERE a.output = ? AND a.machine = ? AND "
                "a.health_id > ? AND EXISTS (SELECT 1 FROM health h WHERE h.id = a.health_id)",
                (self.output, self.machine, int(position))).fetchone()[0]
            return max(int(stored) - int(acked), 0)

        return int(self.store._read("cannot count the outbox", read))

    def latest_id(self) -> int | None:
        """The newest stored window's row id of the machine, None if none."""
        row = self._one("SELECT id FROM health WHERE +machine = ? ORDER BY id DESC LIMIT 1",
                        (self.machine,))
        return None if row is None else int(row[0])

    def doc_at_or_before(self, health_id: int) -> str | None:
        """The health message of the newest window of the machine at or below ``health_id``."""
        row = self._one("SELECT doc FROM health WHERE +machine = ? AND id <= ? ORDER BY id DESC "
                        "LIMIT 1", (self.machine, int(health_id)))
        return None if row is None else str(row[0])

    def ack(self, delivered: list[OutboxRow], position: int) -> None:
        """Record the ``delivered`` windows and the new delivered ``position`` (the marks at
        or below it are no longer needed) in one transaction."""
        wall = time.time()

        def write(conn: sqlite3.Connection) -> None:
            self._same_file(conn).executemany(
                "INSERT OR IGNORE INTO outbox_ack (output, machine, run, window, health_id, "
                "wall) VALUES (?, ?, ?, ?, ?, ?)",
                [(self.output, self.machine, r.run, r.window, r.id, wall) for r in delivered
                 if r.id > position])
            conn.execute(
                "INSERT INTO outbox_position (output, machine, health_id, wall) VALUES "
                "(?, ?, ?, ?) ON CONFLICT (output, machine) DO UPDATE SET health_id = "
                "MAX(health_id, excluded.health_id), wall = excluded.wall",
                (self.output, self.machine, int(position), wall))
            conn.execute("DELETE FROM outbox_ack WHERE output = ? AND machine = ? AND "
                         "health_id <= (SELECT health_id FROM outbox_position WHERE output = ? "
                         "AND machine = ?)", (self.output, self.machine, self.output,
                                              self.machine))

        self.store._write("cannot record the delivered windows", write)

    def __repr__(self) -> str:
        return f"StoreOutbox({self.output!r}, {self.machine!r}, {self.store.path})"
