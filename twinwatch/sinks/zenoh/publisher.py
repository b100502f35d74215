"""The Zenoh output itself: :class:`HealthPublisher`, one machine's health, alarms and fleet
summary on zenoh, with its latest values and history answered (see the package docstring).
"""

from __future__ import annotations

import logging
import math
import random
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Self

from twinwatch.errors import PublisherError
from twinwatch.io.encoding import to_json
from twinwatch.sinks.base import AlarmBands, ProcessedWindow, SharedResources, Sink, SinkContext
from twinwatch.sinks.zenoh.config import ZenohConfig, check_key, zenoh, zenoh_ext
from twinwatch.sinks.zenoh.queries import (
    QUERY_LOG_INTERVAL,
    QueryDispatch,
    RateLimitedLog,
    client_name,
    history_parameters,
)
from twinwatch.sinks.zenoh.session import declare_publisher, open_session, session_key
from twinwatch.twin.summary import fleet_summary, summary_changed

logger = logging.getLogger(__package__)


UNRULED_THRESHOLD_PCT = 5.0
"""A parameter without an alarm rule is measured against this deviation [% of nominal] for
the fleet summary's ``worst`` (:func:`worst_parameter`)."""


class HealthPublisher(Sink):
    """Publishes one machine's health (and other JSON topics) on zenoh: the built-in output
    ``zenoh`` (table ``[zenoh]``, a publisher: it gets only the windows the state store stored).

    Thread-safe against :meth:`close`; a failing put is logged once, counted in
    :attr:`errors`, and never raised. After :meth:`close`, or with ``config.enabled`` false,
    publishing is a no-op.

    Args:
        config: the ``[zenoh]`` configuration.
        machine: machine name, one key chunk (letters, digits, ``_``, ``-``, ``.``).

    Raises:
        ValueError: ``machine`` is not a valid key chunk.
        PublisherError: the session or a declaration could not be created.
    """

    config_class: ClassVar[type[ZenohConfig]] = ZenohConfig
    counter_prefix: ClassVar[str | None] = "zenoh"
    open_order: ClassVar[int] = 10  # the port first: a second daemon fails before any file

    def __init__(self, config: ZenohConfig, machine: str, *,
                 retry_connect: bool = False, shared: SharedResources | None = None) -> None:
        self._closed = True  # until fully open, so __del__ and close() are safe
        if "/" in machine:
            raise ValueError(f"machine {machine!r} must be a single key chunk (no '/')")
        check_key(machine, what="machine")
        self.config = config
        self.machine = machine
        self.base_key = f"{config.key_prefix}/{machine}"
        self.health_key = f"{self.base_key}/health"
        self.summary_key = f"{self.base_key}/summary"
        self.alive_key = f"{self.base_key}/alive"
        self.box = config.box or socket.gethostname() or "localhost"
        self.summaries = 0
        self.summaries_resent = 0
        self._matching: zenoh.MatchingListener | None = None
        self._summary_matching = False  # a subscriber of P/summary was reachable last
        self._summary: dict[str, Any] | None = None  # the last summary published
        self._summary_at = -math.inf  # monotonic time it was published [s]
        self.published = 0
        self.errors = 0
        self.not_connected = 0
        self._lock = threading.Lock()
        self._failing = False
        self._latest: dict[str, str] = {}
        self._handlers: dict[str, Callable[[zenoh.Query], Any]] = {}
        self._publishers: dict[str, zenoh.Publisher | zenoh_ext.AdvancedPublisher] = {}
        self._session: zenoh.Session | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._queryable: zenoh.Queryable[None] | None = None
        self._give_up = threading.Event()
        self._connector: threading.Thread | None = None
        self._query_log = RateLimitedLog(logger, QUERY_LOG_INTERVAL)
        self._detached = False
        self._shared = shared
        self._shared_key: str | None = None
        self._release_session: Callable[[], None] = lambda: None
        # in a gateway, the queryable every machine of the shared session answers through
        self._dispatch: QueryDispatch | None = None
        self._dispatch_key: str | None = None
        if not config.enabled:
            logger.info("zenoh publishing disabled for %s", machine)
            return
        try:
            session = self._open_session()
        except PublisherError as exc:
            unreachable = "nothing answers there" in str(exc)
            if not (retry_connect and unreachable):
                raise
            logger.warning("%s; twinwatch runs on (estimation, state database) and keeps "
                           "trying every %g s at most; subscribers catch up on the missed "
                           "windows with the history query", exc, config.retry_max)
            self._closed = False
            self._connector = threading.Thread(target=self._connect_loop,
                                               name="twinwatch-zenoh-connect", daemon=True)
            self._connector.start()
            return
        self._attach(session)
        self._closed = False

    def _open_session(self) -> zenoh.Session:
        """This publisher's session: its own (:func:`open_session`), or in a gateway the one
        shared by every machine with the same :func:`session_key`. Let go with
        ``_release_session``.

        Raises:
            PublisherError: as :func:`open_session`.
        """
        key = session_key(self.config)
        session, self._release_session = SharedResources.hold(
            self._shared, key, lambda: open_session(self.config), lambda s: s.close())
        self._shared_key = key if self._shared is not None else None
        return session

    def _attach(self, session: zenoh.Session) -> None:
        """Declare the health publisher, queryable and token on ``session`` and use it."""
        queryable: zenoh.Queryable[None] | None = None
        try:
            publisher = declare_publisher(session, self.health_key, self.config)
            if self._shared is not None and self._shared_key is not None:
                key = f"{self._shared_key}|queryable|{self.config.key_prefix}"
                dispatch: QueryDispatch = self._shared.acquire(
                    key, lambda: QueryDispatch(session, self.config.key_prefix),
                    QueryDispatch.close)
                self._dispatch, self._dispatch_key = dispatch, key  # released on failure
                by_box = self.config.presence == "box"
                dispatch.add(self.machine, self._answer, self.resend_summary,
                             box=self.box if by_box else None)
            else:
                by_box = False  # a session of its own: the machine's token is the box's
                queryable = session.declare_queryable(f"{self.base_key}/**", self._on_query)
            token = None if by_box else session.liveliness().declare_token(self.alive_key)
        except zenoh.ZError as exc:
            self._leave_dispatch()
            self._release_session()
            raise PublisherError(f"cannot declare zenoh entities under {self.base_key}: {exc}"
                                 ) from exc
        with self._lock:
            self._publishers[self.health_key] = publisher
            self._queryable, self._token, self._session = queryable, token, session
        cfg = self.config
        logger.info("publishing health of %s on %s (mode=%s, listen=%s, connect=%s)",
                    self.machine, self.health_key, cfg.mode,
                    cfg.listen if cfg.mode != "client" else [], cfg.connect)

    def _connect_loop(self) -> None:
        """Open the session in the background until it works or :meth:`close` is called;
        the delay doubles from 0.5 s up to ``retry_max``, with +-20 % jitter."""
        delay = 0.5
        while not self._give_up.wait(delay * random.uniform(0.8, 1.2)):
            try:
                session = self._open_session()
            except PublisherError as exc:
                logger.debug("zenoh still unreachable: %s", exc)
                delay = min(2 * delay, self.config.retry_max)
                continue
            if self._give_up.is_set():
                self._release_session()
                return
            try:
                self._attach(session)
            except PublisherError as exc:
                logger.error("%s", exc)
                return
            logger.warning("zenoh reached (%s) after %d windows were not published: "
                           "publishing resumes", ", ".join(self.config.connect),
                           self.not_connected)
            return

    # -- the sink contract ---------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: ZenohConfig, context: SinkContext) -> Self:
        """The daemon's publisher: a router unreachable at start is retried in the background.

        Raises:
            PublisherError: the session or a declaration could not be created.
            ValueError: the machine name is not a key chunk.
        """
        publisher = cls(config, context.machine, retry_connect=True, shared=context.shared)
        publisher.attach(context)
        return publisher

    def attach(self, context: SinkContext) -> None:
        """Serve the history of ``context`` (a new daemon after a reload adopts the session)."""
        super().attach(context)
        self._detached = False
        if context.history is not None and f"{self.base_key}/history" not in self._handlers:
            self.add_query_handler("history", self._on_history_query)

    def detach(self) -> None:
        """A reload hands the session over: history queries are answered "reloading"."""
        super().detach()
        self._detached = True

    def _on_history_query(self, query: Any) -> dict[str, Any]:
        """``get("P/history?t_from=..;t_to=..;by=plant|wall;limit=..;run=..")`` (zenoh
        thread): one reply ``{"count", "more", "windows": [health, ...]}``, oldest first
        (``run``: a run id, or ``current``).

        Raises:
            ValueError: a bad parameter (replied as an error naming it), or no history to
                serve (reloading; no state database).
        """
        history = self.context.history if self.context is not None else None
        if self._detached:
            raise ValueError("the daemon is reloading: ask again in a moment")
        if history is None:
            raise ValueError("this daemon keeps no history (no state database: [state])")
        t_from, t_to, limit, by, run, after = history_parameters(query.parameters)
        if run == "current":
            run = self.context.run if self.context is not None and self.context.run else None
            if run is None:
                raise ValueError("run='current': this daemon has no run id")
        # ``after`` only when asked: a HistoryQuery without it still serves
        windows = (history(t_from, t_to, limit, by, run) if after is None
                   else history(t_from, t_to, limit, by, run, after))
        more = len(windows) == limit
        # the cursor of the next page: the gate's, else by plant time the last window's end
        nxt = getattr(windows, "next_after", None) if more and windows else None
        if nxt is None and more and windows and by == "plant":
            nxt = windows[-1].t_end
        return {"machine": self.machine, "by": by, "t_from": t_from, "t_to": t_to, "run": run,
                "after": after, "count": len(windows), "more": more, "next_after": nxt,
                # each message with the fields it was stored with, no others
                "windows": [w.model_dump(by_alias=True, exclude_unset=True) for w in windows]}

    def counters(self) -> dict[str, int]:
        """``published`` (puts), ``summaries``, ``summaries_resent``, ``errors`` (failed
        puts), ``not_connected`` (windows before the router was reached)."""
        return {"published": int(self.published), "summaries": int(self.summaries),
                "summaries_resent": int(self.summaries_resent),
                "errors": int(self.errors), "not_connected": int(self.not_connected)}

    @property
    def status(self) -> str:
        return f"health on {self.health_key}"

    def summary(self) -> list[str]:
        if self.config.mode == "client":
            where = f"a client of {', '.join(self.config.connect)}"
        else:
            where = f"listening on {', '.join(self.config.listen) or 'nothing'}"
        return [f"health was published on {self.health_key} (zenoh, {where})"]

    @property
    def connected(self) -> bool:
        """A session is open (False while the router is still being reached at start)."""
        return self._session is not None

    def add_query_handler(self, key_suffix: str, handler: Callable[[zenoh.Query], Any]) -> None:
        """Answer gets on ``P/{key_suffix}`` with ``handler(query)`` (called on a zenoh thread):
        a mapping is replied as JSON on that key; a :class:`ValueError` is replied as an error
        with its message.

        Raises:
            ValueError: ``key_suffix`` is not a plain key.
        """
        check_key(key_suffix, what="key_suffix")
        self._handlers[f"{self.base_key}/{key_suffix}"] = handler

    @property
    def session(self) -> zenoh.Session | None:
        """The underlying zenoh session (``None`` when disabled)."""
        return self._session

    def publish(self, health: Mapping[str, Any]) -> None:
        """Publish one health document on ``P/health`` and keep it as the latest.

        Args:
            health: JSON-serialisable mapping (see :func:`to_json`).
        """
        self._put(self.health_key, health)

    def publish_json(self, key_suffix: str, payload: Mapping[str, Any]) -> None:
        """Publish ``payload`` as JSON on ``P/{key_suffix}`` and keep it as the latest.

        Args:
            key_suffix: one or more ``/``-separated key chunks, e.g. ``"alarm"``; not
                ``"alive"`` (reserved for liveliness).
            payload: JSON-serialisable mapping (see :func:`to_json`).

        Raises:
            ValueError: ``key_suffix`` is not a plain key or is ``"alive"``.
        """
        check_key(key_suffix, what="key_suffix")
        if key_suffix == "alive":
            raise ValueError("key_suffix 'alive' is reserved for the liveliness token")
        self._put(f"{self.base_key}/{key_suffix}", payload)

    def write(self, out: ProcessedWindow) -> None:
        """The window's health on ``P/health``, its alarm events on ``P/alarm``, then its
        fleet summary (:meth:`publish_summary`) with :func:`worst_parameter` as ``worst``."""
        self._put(self.health_key, out.health_json)
        for event in out.events:
            self.publish_json("alarm", event)
        summary = fleet_summary(out.health, box=self.box, wall=time.time())
        bands = self.context.alarm_bands if self.context is not None else {}
        summary["worst"] = worst_parameter(out.health, bands)
        self.publish_summary(summary)

    def publish_summary(self, summary: Mapping[str, Any], *, now: float | None = None
                        ) -> bool:
        """Publish a fleet summary (:func:`~twinwatch.twin.summary.fleet_summary`) on
        ``P/summary`` if it changed since the last one published
        (:func:`~twinwatch.twin.summary.summary_changed`) or ``[zenoh] summary_interval``
        seconds passed since; kept as the latest, which a get returns to a late joiner (the
        summary's publisher is a plain one).

        Args:
            summary: the summary (plain JSON types).
            now: monotonic time [s] (default: :func:`time.monotonic`).

        Returns:
            True if it was published.
        """
        now = time.monotonic() if now is None else now
        doc = dict(summary)
        if not summary_changed(self._summary, doc) and not _worst_changed(
                self._summary, doc) and now - self._summary_at < self.config.summary_interval:
            return False
        self._summary, self._summary_at = doc, now
        self._put(self.summary_key, doc)
        self.summaries += 1
        return True

    def _put(self, key: str, payload: Mapping[str, Any] | str) -> None:
        with self._lock:
            if self._closed:
                logger.debug("publisher closed, dropping %s", key)
                return
            if self._session is None:  # router not reached yet (retry_connect)
                if key != self.summary_key:  # windows and events, not their summaries
                    self.not_connected += 1
                self._latest[key] = payload if isinstance(payload, str) else to_json(payload)
                return
            try:
                text = payload if isinstance(payload, str) else to_json(payload)
                publisher = self._publishers.get(key)
                if publisher is None:
                    # the summary's publisher is a plain one: its latest is this queryable's
                    # (an advanced one per machine does not scale: docs/fleet.md)
                    cfg = (self.config if key != self.summary_key else self.config.model_copy(
                        update={"cache": 0}))
                    publisher = declare_publisher(self._session, key, cfg)
                    self._publishers[key] = publisher
                    if (key == self.summary_key and self._dispatch is None
                            and isinstance(publisher, zenoh.Publisher)):
                        # its own session's listener (a gateway's: QueryDispatch's)
                        self._matching = publisher.declare_matching_listener(
                            self._on_summary_matching)
                publisher.put(text)
            except (zenoh.ZError, TypeError, ValueError) as exc:
                self.errors += 1
                if not self._failing:
                    logger.error("publishing on %s failed: %s", key, exc)
                    self._failing = True
                else:
                    logger.debug("publishing on %s failed again: %s", key, exc)
                return
            self._latest[key] = text
            if key != self.summary_key:  # the summaries are counted in summaries
                self.published += 1
            if self._failing:
                logger.info("publishing on %s works again", key)
                self._failing = False

    def _on_summary_matching(self, status: zenoh.MatchingStatus) -> None:
        """When a subscriber of the summary becomes reachable again, send the latest summary
        again (:meth:`resend_summary`): at a failover it reaches the watcher before a get
        would. On a zenoh thread, never under the lock (it may run inside the declaration)."""
        matching = bool(status.matching)
        was, self._summary_matching = self._summary_matching, matching
        if matching and not was:
            self.resend_summary()

    def resend_summary(self) -> None:
        """Send the latest summary again (none yet, or closed: nothing); counted in
        ``summaries_resent``. Called on a zenoh thread, without the lock."""
        if self._closed:
            return
        text = self._latest.get(self.summary_key)
        publisher = self._publishers.get(self.summary_key)
        if text is None or publisher is None:
            return
        try:
            publisher.put(text)
        except zenoh.ZError as exc:
            logger.debug("sending %s again failed: %s", self.summary_key, exc)
            return
        self.summaries_resent += 1
        logger.debug("%s sent again: a subscriber is reachable again", self.summary_key)

    def _leave_dispatch(self) -> None:
        dispatch, key = self._dispatch, self._dispatch_key
        self._dispatch = self._dispatch_key = None
        if dispatch is not None:
            dispatch.remove(self.machine)
        if self._shared is not None and key is not None:
            self._shared.release(key)

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._answer(query)
        finally:
            query.drop()

    def _answer(self, query: zenoh.Query) -> None:
        """Answer a get with the latest payload of every topic its key expression intersects
        and the handlers' answers (the query is not dropped: the caller does)."""
        with self._lock:
            latest = list(self._latest.items())
        try:
            for key, text in latest:
                if query.key_expr.intersects(key):
                    query.reply(key, text, encoding=zenoh.Encoding.APPLICATION_JSON)
            for key, handler in self._handlers.items():
                if not query.key_expr.intersects(key):
                    continue
                try:
                    answer = handler(query)
                except ValueError as exc:
                    query.reply_err(str(exc))
                    self._query_log.log(client_name(query), logging.WARNING,
                                        "query %s refused: %s", query.selector, exc)
                    continue
                except Exception as exc:  # noqa: BLE001 - a query must not kill zenoh's thread
                    query.reply_err(f"internal error: {exc}")
                    self._query_log.log(client_name(query), logging.ERROR,
                                        "answering %s failed: %s: %s", query.selector,
                                        type(exc).__name__, exc)
                    logger.debug("answering %s failed", query.selector, exc_info=True)
                    continue
                query.reply(key, to_json(answer), encoding=zenoh.Encoding.APPLICATION_JSON)
        except zenoh.ZError as exc:
            logger.debug("replying to query %s failed: %s", query.selector, exc)

    def close(self) -> None:
        """Undeclare the token, queryable and publishers, then close the session. Idempotent."""
        self._give_up.set()
        connector, self._connector = self._connector, None
        if connector is not None:
            connector.join(timeout=30)
        with self._lock:
            if self._closed:
                return
            self._closed = True
            token, queryable, session = self._token, self._queryable, self._session
            publishers = list(self._publishers.values())
            matching, self._matching = self._matching, None
            self._token = self._queryable = None
            self._publishers.clear()
        # Outside the lock: undeclaring the queryable waits for a running _on_query callback.
        steps: list[tuple[str, Callable[[], Any]]] = []
        if token is not None:
            steps.append(("liveliness token", token.undeclare))
        if queryable is not None:
            steps.append(("queryable", queryable.undeclare))
        steps.append(("gateway's queryable", self._leave_dispatch))
        if matching is not None:
            steps.append(("summary's matching listener", matching.undeclare))
        steps += [("publisher", p.undeclare) for p in publishers]
        if session is not None:
            steps.append(("session", self._release_session))
        for what, step in steps:
            try:
                step()
            except zenoh.ZError as exc:
                logger.warning("closing zenoh %s of %s failed: %s", what, self.machine, exc)
        logger.info("zenoh publisher of %s closed (%d published, %d errors)", self.machine,
                    self.published, self.errors)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"HealthPublisher({self.health_key!r}, {state}, published={self.published})"


def worst_parameter(health: Any, bands: Mapping[str, AlarmBands]) -> dict[str, Any] | None:
    """The parameter furthest off nominal by its own threshold, for the fleet summary's
    ``worst``.

    Each parameter with a finite deviation (not ``tied`` nor ``fixed``) is measured as
    ``|deviation| / threshold``: its alarm rule's warning threshold on the side it deviates to
    (else the alarm threshold; share 0 when the rule does not watch that side), or
    :data:`UNRULED_THRESHOLD_PCT` without a rule.

    Args:
        health: the window's typed message (its ``parameters``).
        bands: the ``[alarms]`` thresholds by parameter [% of nominal]
            (:attr:`~twinwatch.sinks.base.SinkContext.alarm_bands`).

    Returns:
        ``{"parameter", "deviation_pct", "threshold_pct" (null without a rule), "share"
        (|deviation| / threshold)}``, or None when no parameter has a deviation.
    """
    best: tuple[float, dict[str, Any]] | None = None
    for name, p in (health.parameters or {}).items():
        if p is None or p.status in ("tied", "fixed"):
            continue
        dev = p.deviation_pct
        if not isinstance(dev, int | float) or not math.isfinite(dev):
            continue
        b = bands.get(name)
        if b is None:
            threshold: float | None = None
            share = abs(dev) / UNRULED_THRESHOLD_PCT
        else:
            if dev >= 0:
                th = b.warning_high if b.warning_high is not None else b.alarm_high
            else:
                th = b.warning_low if b.warning_low is not None else b.alarm_low
            threshold = None if th is None else abs(float(th))
            share = abs(dev) / threshold if threshold else 0.0
        if best is None or share > best[0]:
            best = (share, {"parameter": name, "deviation_pct": float(f"{dev:.4g}"),
                            "threshold_pct": threshold, "share": round(share, 3)})
    return best[1] if best is not None else None


def _worst_changed(old: Mapping[str, Any] | None, new: Mapping[str, Any]) -> bool:
    """The worst parameter is another one than in the summary published last."""
    def name(doc: Mapping[str, Any] | None) -> Any:
        worst = doc.get("worst") if doc is not None else None
        return worst.get("parameter") if isinstance(worst, Mapping) else None

    return old is not None and name(old) != name(new)
