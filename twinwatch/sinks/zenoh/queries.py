"""The queries a daemon answers on zenoh: one queryable per session and key prefix
(:class:`QueryDispatch`, a gateway's machines sharing it), the box's presence token, rate-limited
log lines about bad queries, and the history query's parameters.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from typing import Any, Literal

from twinwatch.io.keys import box_chunk, box_token_key
from twinwatch.sinks.zenoh.config import zenoh

logger = logging.getLogger(__package__)


QUERY_LOG_INTERVAL = 60.0
"""Seconds between two log lines about one client's bad or failing queries [s]."""


class RateLimitedLog:
    """At most one log line per key every ``interval`` seconds; the next line says how many
    were suppressed (any peer on the network can send queries).

    Args:
        log: the logger to write to.
        interval: seconds between two lines of one key.
        max_keys: keys remembered (the oldest is forgotten beyond it).
    """

    def __init__(self, log: logging.Logger, interval: float, max_keys: int = 1000) -> None:
        self._log = log
        self.interval = interval
        self.max_keys = max_keys
        self._last: dict[str, tuple[float, int]] = {}
        self._lock = threading.Lock()

    def log(self, key: str, level: int, msg: str, *args: object) -> bool:
        """Log ``msg % args`` at ``level`` unless ``key`` logged less than ``interval`` ago.

        Returns:
            True if the line was written.
        """
        now = time.monotonic()
        with self._lock:
            last, suppressed = self._last.get(key, (-math.inf, 0))
            if now - last < self.interval:
                self._last[key] = (last, suppressed + 1)
                return False
            self._last.pop(key, None)
            self._last[key] = (now, 0)
            while len(self._last) > self.max_keys:
                self._last.pop(next(iter(self._last)))
        if suppressed:
            msg += " (%d similar from %s suppressed in the last %.0f s)"
            args = (*args, suppressed, key, self.interval)
        self._log.log(level, msg, *args)
        return True


def client_name(query: zenoh.Query) -> str:
    """Who sent ``query``: its source's zenoh id when the peer sent one, else "a peer"."""
    info = query.source_info
    source = getattr(info, "source_id", None) if info is not None else None
    zid = getattr(source, "zid", None)
    return f"peer {zid}" if zid is not None else "a peer"


@dataclasses.dataclass
class _BoxPresence:
    """A box's presence in :class:`QueryDispatch` (``[zenoh] presence = "box"``): its name, the
    key of its token and queryable (:func:`~twinwatch.io.keys.box_token_key`), the two
    entities, and the machines it stands for."""

    name: str
    key: str
    token: zenoh.LivelinessToken
    queryable: zenoh.Queryable[None]
    machines: set[str] = dataclasses.field(default_factory=set)


class QueryDispatch:
    """One queryable on ``<key_prefix>/**`` answering the gets of every machine that shares a
    session in a gateway, each asked only when the get's key expression reaches its
    ``<key_prefix>/<machine>/**``; one per box instead of one per machine keeps the routers'
    key matching small (docs/fleet.md).

    One matching listener for the session: a publisher that never puts, on the first
    machine's summary key, whose matching status turning true again (a failover) sends every
    machine's latest summary again.

    With ``[zenoh] presence = "box"`` it also holds the box's presence: one liveliness token
    on :func:`~twinwatch.io.keys.box_token_key`, declared with the box's first machine and
    undeclared with its last, and a queryable on the same key answering ``{"box": <name>,
    "machines": [<machine>, ...]}`` (what ``twinwatch watch`` reads).

    Args:
        session: the shared session.
        prefix: the machines' ``[zenoh] key_prefix``.

    Raises:
        zenoh.ZError: the queryable could not be declared (the session closed).
    """

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.prefix = prefix
        self._session = session
        self._lock = threading.Lock()
        self._machines: dict[str, tuple[zenoh.KeyExpr, Callable[[zenoh.Query], None]]] = {}
        self._resend: dict[str, Callable[[], None]] = {}
        self._probe: zenoh.Publisher | None = None
        self._listener: zenoh.MatchingListener | None = None
        self._matching = False
        self._boxes: dict[str, _BoxPresence] = {}  # box chunk -> its token and machines
        self._queryable = session.declare_queryable(f"{prefix}/**", self._on_query)

    def add(self, machine: str, answer: Callable[[zenoh.Query], None],
            resend: Callable[[], None] | None = None, *, box: str | None = None) -> None:
        """Answer the gets reaching ``<prefix>/<machine>/**`` with ``answer(query)`` (which
        does not drop the query); call ``resend()`` when a subscriber of the summaries is
        reachable again; with ``box``, the machine's presence is that box's token.

        Raises:
            zenoh.ZError: the first machine's probe, or its box's token, could not be declared.
        """
        with self._lock:
            self._machines[machine] = (zenoh.KeyExpr(f"{self.prefix}/{machine}/**"), answer)
            if resend is not None:
                self._resend[machine] = resend
            if box is not None:
                self._add_to_box(machine, box)
            probe = None
            if self._probe is None and resend is not None:
                probe = self._probe = self._session.declare_publisher(
                    f"{self.prefix}/{machine}/summary")
        if probe is not None:
            # outside the lock: the listener's first status may come in its declaration
            self._listener = probe.declare_matching_listener(self._on_matching)

    def _add_to_box(self, machine: str, box: str) -> None:
        """``machine`` is present through ``box``'s token, declared now if it is the box's
        first (under the lock: a query on the box's key waits for it)."""
        chunk = box_chunk(box)
        entry = self._boxes.get(chunk)
        if entry is None:
            key = box_token_key(self.prefix, box, str(self._session.zid()))
            queryable = self._session.declare_queryable(key, self._on_box_query)
            try:
                token = self._session.liveliness().declare_token(key)
            except zenoh.ZError:
                queryable.undeclare()
                raise
            entry = self._boxes[chunk] = _BoxPresence(box, key, token, queryable)
            logger.info("presence of the machines of box %s: the liveliness token %s", box, key)
        entry.machines.add(machine)

    def _on_box_query(self, query: zenoh.Query) -> None:
        """A get on a box's token key: ``{"box", "machines"}`` of every box it reaches."""
        try:
            with self._lock:
                boxes = [(e.key, e.name, sorted(e.machines)) for e in self._boxes.values()]
            for key, name, machines in boxes:
                if query.key_expr.intersects(key):
                    query.reply(key, json.dumps({"box": name, "machines": machines}),
                                encoding=zenoh.Encoding.APPLICATION_JSON)
        except zenoh.ZError as exc:
            logger.debug("replying to query %s failed: %s", query.selector, exc)
        finally:
            query.drop()

    def remove(self, machine: str) -> None:
        """Stop answering for ``machine`` (a get running meanwhile may still reach it); the
        last machine of a box undeclares its token."""
        gone: list[_BoxPresence] = []
        with self._lock:
            self._machines.pop(machine, None)
            self._resend.pop(machine, None)
            for chunk, entry in list(self._boxes.items()):
                entry.machines.discard(machine)
                if not entry.machines:
                    gone.append(self._boxes.pop(chunk))
        for entry in gone:  # outside the lock: the queryable waits for a running callback
            self._undeclare_box(entry)

    def _undeclare_box(self, entry: _BoxPresence) -> None:
        for what, entity in (("liveliness token", entry.token), ("queryable", entry.queryable)):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.warning("closing the zenoh %s of box %s failed: %s", what, entry.name,
                               exc)

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        """The probe's matching listener (on a zenoh thread): a subscriber reachable again
        sends every machine's latest summary again."""
        matching = bool(status.matching)
        was, self._matching = self._matching, matching
        if not matching or was:
            return
        with self._lock:
            resend = list(self._resend.values())
        for send in resend:
            send()

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            machines = list(self._machines.values())
        try:
            for key, answer in machines:
                if query.key_expr.intersects(key):
                    answer(query)
        finally:
            query.drop()

    def close(self) -> None:
        """Undeclare the queryable, the matching listener and its probe (each waits for a
        running callback), and the boxes' tokens left."""
        with self._lock:
            boxes, self._boxes = list(self._boxes.values()), {}
        for entry in boxes:
            self._undeclare_box(entry)
        entities = (("queryable", self._queryable), ("matching listener", self._listener),
                    ("summary probe", self._probe))
        for what, entity in entities:
            if entity is None:
                continue
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.warning("closing the zenoh %s on %s/** failed: %s", what, self.prefix,
                               exc)


HISTORY_LIMIT = 1000
"""Most windows one history query returns (page on with ``after`` = the reply's
``next_after``)."""

HISTORY_PARAMETERS = ("t_from", "t_to", "by", "limit", "run", "after")

_RUN_RE = re.compile(r"^[A-Za-z0-9_.:-]{1,64}$")


def history_parameters(params: Any) -> tuple[float | None, float | None, int,
                                              Literal["plant", "wall"], str | None,
                                              float | None]:
    """The history query's parameters, checked: ``t_from`` and ``t_to`` finite seconds (either
    may be absent), ``t_from <= t_to``, ``by`` ``plant`` or ``wall``, ``limit`` a whole number
    from 1 (at most :data:`HISTORY_LIMIT`), ``run`` a run id or ``current`` (absent: every
    run), ``after`` finite seconds (the paging cursor, the previous reply's ``next_after``).

    Args:
        params: the selector's parameters (a mapping with ``get``, zenoh's ``Parameters``).

    Returns:
        ``(t_from, t_to, limit, by, run, after)``.

    Raises:
        ValueError: naming the bad parameter.
    """
    unknown = [k for k, _ in _items(params) if k not in HISTORY_PARAMETERS]
    if unknown:
        raise ValueError(f"unknown parameter {unknown[0]!r}: use "
                         f"{', '.join(HISTORY_PARAMETERS)}")

    def num(key: str) -> float | None:
        raw = params.get(key)
        if raw in (None, ""):
            return None
        try:
            value = float(raw)
        except ValueError:
            raise ValueError(f"{key}={raw!r} is not a number [s]") from None
        if not math.isfinite(value):
            raise ValueError(f"{key}={raw!r}: give a finite time [s], or leave it out for "
                             f"an open end")
        return value

    raw_by = params.get("by") or "plant"
    if raw_by not in ("plant", "wall"):
        raise ValueError(f"by={raw_by!r}: use by=plant (source time) or by=wall (epoch s)")
    by: Literal["plant", "wall"] = "wall" if raw_by == "wall" else "plant"
    t_from, t_to = num("t_from"), num("t_to")
    if t_from is not None and t_to is not None and t_from > t_to:
        raise ValueError(f"t_from={t_from:g} is after t_to={t_to:g}")
    lim = num("limit")
    if lim is not None and (lim < 1 or not lim.is_integer()):
        raise ValueError(f"limit={params.get('limit')!r}: give a whole number from 1 "
                         f"(at most {HISTORY_LIMIT} are returned)")
    limit = HISTORY_LIMIT if lim is None else min(int(lim), HISTORY_LIMIT)
    run = params.get("run")
    if run in (None, ""):
        run = None
    elif _RUN_RE.match(str(run)) is None:
        raise ValueError(f"run={run!r}: give a run id as the health messages carry it "
                         f"(e.g. run=20261122T101530Z-3f9a2c), or run=current")
    return t_from, t_to, limit, by, (None if run is None else str(run)), num("after")


def _items(params: Any) -> list[tuple[str, str]]:
    if isinstance(params, dict):
        return list(params.items())
    return [(str(k), str(v)) for k, v in params]
