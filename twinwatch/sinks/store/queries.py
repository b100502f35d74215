"""The state database's read side, as functions over one :mod:`sqlite3` connection.
:class:`~twinwatch.sinks.store.database.StateStore` runs them behind its file checks and
corruption recovery; nothing here writes, locks or recovers.
"""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Sequence
from typing import Any, Literal

from twinwatch.sinks.base import HistoryPage
from twinwatch.twin.health import read_health

__all__ = ["count", "history_page", "history_query", "last_docs", "latest_doc",
           "timeline_docs", "twin_state"]


def history_query(t_from: float | None, t_to: float | None, limit: int | None, *,
                  by: Literal["plant", "wall"], machine: str | None, run: str | None,
                  after: float | None) -> tuple[str, list[Any]]:
    """The SQL and its arguments of :meth:`StateStore.history
    <twinwatch.sinks.store.database.StateStore.history>` (see it for the arguments): each row
    is ``(doc, cursor)``, the cursor the window's ``t_end`` by plant time, its stored wall
    stamp by wall time.

    Raises:
        ValueError: ``by`` is neither ``"plant"`` nor ``"wall"``.
    """
    if by not in ("plant", "wall"):
        raise ValueError(f"by must be 'plant' or 'wall', not {by!r}")
    lo, hi = ("t_end", "t_start") if by == "plant" else ("wall", "wall")
    terms: list[tuple[str, Any]] = [
        (c, v) for c, v in (("machine = ?", machine), ("run = ?", run)) if v is not None]
    terms += [(c, float(v)) for c, v in ((f"{lo} >= ?", t_from), (f"{hi} <= ?", t_to),
                                         (f"{lo} > ?", after))
              if v is not None and math.isfinite(v)]
    where = [c for c, _ in terms]
    args = [v for _, v in terms]
    sql = f"SELECT doc, {lo} FROM health"
    if where:
        sql += " WHERE " + " AND ".join(where)
    sql += " ORDER BY id"
    if limit is not None:
        sql += " LIMIT ?"
        args.append(int(limit))
    return sql, args


def history_page(rows: Sequence[tuple[str, float]]) -> HistoryPage:
    """The rows of :func:`history_query` as a page of typed views, with the cursor of the next
    page in the time asked (by wall time the stamp the store keeps)."""
    return HistoryPage((read_health(r[0]) for r in rows),
                       next_after=float(rows[-1][1]) if rows else None)


def timeline_docs(conn: sqlite3.Connection, machine: str, lower: float) -> list[str]:
    """The messages (JSON text) of ``machine``'s time line that ends with its last stored
    window, newest first, ending at or after ``lower`` [s, plant time]
    (:meth:`StateStore.timeline <twinwatch.sinks.store.database.StateStore.timeline>`)."""
    docs: list[str] = []
    after: float | None = None  # t_start of the window saved after this one
    cur = conn.execute("SELECT doc, t_start, t_end FROM health WHERE machine = ? "
                       "ORDER BY id DESC", (machine,))
    for doc, t_start, t_end in cur:
        if (after is not None and not t_end < after) or t_end < lower:
            break
        docs.append(doc)
        after = t_start
    cur.close()
    return docs


def latest_doc(conn: sqlite3.Connection, machine: str | None) -> str | None:
    """The last message saved (of ``machine``; None: of any), JSON text, or None."""
    sql = "SELECT doc FROM health"
    args: tuple[Any, ...] = ()
    if machine is not None:
        sql += " WHERE machine = ?"
        args = (machine,)
    row = conn.execute(sql + " ORDER BY id DESC LIMIT 1", args).fetchone()
    return None if row is None else str(row[0])


def last_docs(conn: sqlite3.Connection, machine: str, run: str, limit: int) -> list[str]:
    """The last ``limit`` messages (JSON text) of ``machine``'s run ``run``, oldest first."""
    rows = conn.execute("SELECT doc FROM health WHERE machine = ? AND run = ? ORDER BY id DESC "
                        "LIMIT ?", (machine, run, int(limit))).fetchall()
    return [r[0] for r in reversed(rows)]


def twin_state(conn: sqlite3.Connection, machine: str | None
               ) -> tuple[str, str | None] | None:
    """The saved twin (JSON text) of ``machine`` (None: the most recently saved one) and the
    diagnosis evidence saved by the same run (JSON text, or None), or None."""
    if machine is None:
        row = conn.execute("SELECT machine, run, state FROM twin ORDER BY wall DESC "
                           "LIMIT 1").fetchone()
    else:
        row = conn.execute("SELECT machine, run, state FROM twin WHERE machine = ?",
                           (machine,)).fetchone()
    if row is None:
        return None
    diag = conn.execute("SELECT state FROM diagnosis WHERE machine = ? AND run = ?",
                        (row[0], row[1])).fetchone()
    return str(row[2]), None if diag is None else str(diag[0])


def count(conn: sqlite3.Connection) -> int:
    """Health rows stored."""
    return int(conn.execute("SELECT COUNT(*) FROM health").fetchone()[0])
