"""The subscription: :class:`FleetWatcher` feeds a :class:`~twinwatch.watch.fleet.Fleet` from a
Zenoh session (liveliness, health and alarm events through ``zenoh.ext`` advanced subscribers,
the windows missed asked from the machine's history, each window delivered once), and
:func:`watching` opens the sessions and the watchers for ``watch`` and ``tail``.
"""

from __future__ import annotations

import contextlib
import json
import queue
import threading
import time
from collections.abc import Callable, Collection, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from twinwatch._lazy import lazy_module
from twinwatch.errors import WatchError
from twinwatch.io.keys import BOX_TOKENS
from twinwatch.watch.fleet import Delivery, Fleet, Gap
from twinwatch.watch.session import (
    CHUNKS_RE,
    Mode,
    check_prefix,
    decode_health,
    decode_json,
    health_view,
    machine_of,
    sessions_watched,
)
from twinwatch.watch.view import number

if TYPE_CHECKING:
    import zenoh
    from zenoh import ext as zenoh_ext

    from twinwatch.twin.health import HealthView
else:  # imported when a session opens
    zenoh = lazy_module("zenoh")
    zenoh_ext = lazy_module("zenoh.ext")


LATEST_AFTER_S = 0.3
"""A machine whose token is there but whose publisher's cache gave no window this long after
the watcher started is asked for its latest window (a daemon with plain publishers: [zenoh]
cache = 0, or an older twinwatch) [s]."""


BOX_LIST_TIMEOUT_S = 5.0
"""How long a get of a box's machines (on its token's key, ``[zenoh] presence = "box"``) may
take [s]."""

BOX_LIST_EVERY_S = 1.0
"""A window of a machine no token stands for, while boxes' tokens are present, asks the boxes'
machines again (a machine added to a gateway after its box's token came), at most this often
[s]."""


HISTORY_TIMEOUT_S = 10.0
"""How long one history query may take to answer [s]."""


HISTORY_ATTEMPTS = 3
"""Tries of the history query for a gap (1 s, then 2 s apart) before it is given up."""


@dataclass
class _Sequence:
    """The windows of one run of one machine delivered so far: every window from the first
    delivered to ``contiguous``, and the ones above it in ``above`` (window -> t_end)."""

    run: Any
    contiguous: int
    t_end: float | None  # plant time [s] at the end of window ``contiguous``
    above: dict[int, float | None] = field(default_factory=dict)

    def add(self, window: int, t_end: float | None) -> bool:
        """Record ``window``; False when it was delivered already."""
        if window <= self.contiguous or window in self.above:
            return False
        self.above[window] = t_end
        while self.contiguous + 1 in self.above:
            self.contiguous += 1
            self.t_end = self.above.pop(self.contiguous)
        return True

    def settle(self) -> None:
        """After a gap was filled from the history: what it did not return was never published
        (an overrun, a failed window), so the sequence goes on from the highest delivered."""
        if self.above:
            self.contiguous = max(self.above)
            self.t_end = self.above[self.contiguous]
            self.above.clear()


class FleetWatcher:
    """Feeds a :class:`Fleet` from a Zenoh session: liveliness, health, alarm events.

    How (:mod:`twinwatch.watch`): ``zenoh.ext`` advanced subscribers on health and alarms; the
    windows the publisher's cache no longer holds are asked from the machine's history
    (``<prefix>/<machine>/history?run=<run>;t_from=<the last window before the gap>``, target
    ALL), delivered with ``delivery="history"``, counted in the fleet (``missed``,
    ``recovered``) and reported through ``on_gap``; a machine whose cache gave nothing within
    :data:`LATEST_AFTER_S` is asked for its latest window. Each window is delivered once. A box
    token (``[zenoh] presence = "box"``) is asked for the machines it stands for
    (:class:`~twinwatch.sinks.zenoh.QueryDispatch`): shown present while a box token names them.

    Args:
        session: an open session (:func:`open_session`); the caller closes it.
        fleet: what to feed.
        prefix: the daemons' ``[zenoh] key_prefix``.
        machine: only this machine (``*``: every machine).
        history: windows per machine asked from the publishers' caches at start, and again
            when a publisher is seen anew after a router outage (at most their ``[zenoh]
            cache``; 1: the latest; what a gap needs beyond it comes from the history).
        alarm_history: alarm events per machine asked at start (0: only new ones).
        on_health: called with the machine, a health message not delivered before (its typed
            view, :func:`~twinwatch.twin.health.read_health`), its text as published and its
            delivery (``live`` or ``history``).
        on_alarm, on_token: called with the machine and an alarm event, a token's presence.
        on_gap: called with a :class:`Gap` once the history was asked for it.

    Callbacks run on Zenoh's threads or the watcher's (never two at once for health).

    Raises:
        WatchError: the prefix or the machine name is malformed, ``history`` < 1 or
            ``alarm_history`` < 0.

    Use as a context manager (the subscribers are undeclared on exit).
    """

    def __init__(self, session: zenoh.Session, fleet: Fleet, *, prefix: str = "twinwatch",
                 machine: str = "*", history: int = 1, alarm_history: int = 5,
                 on_health: Callable[[str, HealthView, str, Delivery], None] | None = None,
                 on_alarm: Callable[[str, dict[str, Any]], None] | None = None,
                 on_token: Callable[[str, bool], None] | None = None,
                 on_gap: Callable[[Gap], None] | None = None) -> None:
        # the health message's typed view (pydantic): loaded here, before any subscriber (a
        # first import in a callback can let a live window overtake the cached ones)
        import twinwatch.twin.health  # noqa: F401

        self.session = session
        self.fleet = fleet
        self.prefix = check_prefix(prefix)
        if machine != "*" and (CHUNKS_RE.match(machine) is None or "/" in machine):
            raise WatchError(f"machine {machine!r}: give the daemon's [machine] name (letters, "
                             "digits, '_', '-', '.') or * for every machine")
        if history < 1:
            raise WatchError(f"history {history}: ask at least the latest window (1)")
        if alarm_history < 0:
            raise WatchError(f"alarm_history {alarm_history}: ask 0 (only new events) or more")
        self.machine = machine
        self.history = history
        self.alarm_history = alarm_history
        self._subs: list[Any] = []
        self._threads: list[threading.Thread] = []
        self.queried = threading.Event()
        self.on_health = on_health
        self.on_alarm = on_alarm
        self.on_token = on_token
        self.on_gap = on_gap
        self._lock = threading.RLock()  # one health delivery at a time, in order
        self._seq: dict[str, _Sequence] = {}
        self._sources: dict[tuple[str, int], str] = {}  # publisher (zid, eid) -> machine
        self._gaps: queue.Queue[tuple[str | None, int] | None] = queue.Queue()
        self._closing = threading.Event()
        # boxes' presence ([zenoh] presence = "box")
        self._box_lock = threading.Lock()
        self._box_members: dict[str, set[str]] = {}  # box token's key -> the machines it names
        self._boxed: set[str] = set()  # every machine a box token present names
        self._tokened: set[str] = set()  # machines whose own token was seen
        self._box_listing = 0  # gets of boxes' machines not ended yet
        self._box_idle = threading.Event()
        self._box_idle.set()
        self._box_asked = -float("inf")  # monotonic time of the last ask for unknown machines

    def key(self, suffix: str) -> str:
        return f"{self.prefix}/{self.machine}/{suffix}"

    def resume(self, machine: str, run: str | None, window: int,
               t_end: float | None) -> None:
        """Go on from where an earlier subscriber stopped (a central store restarted): the
        windows of ``machine``'s ``run`` up to ``window`` count as delivered, the ones after
        ``t_end`` [s] are asked from its history once started (``delivery="history"``,
        ``on_gap`` with ``missed`` 0); a later run is followed from the publisher's cache.
        Call before :meth:`start`.

        Raises:
            WatchError: ``machine`` is not a machine name.
        """
        if CHUNKS_RE.match(machine) is None or "/" in machine:
            raise WatchError(f"machine {machine!r}: give the daemon's [machine] name")
        with self._lock:
            self._seq[machine] = _Sequence(run, window, t_end)
        self._gaps.put((machine, 0))

    def start(self) -> FleetWatcher:
        """Declare the subscribers (the tokens that exist and the caches' windows arrive at
        once), then ask the machines that gave nothing for their latest window in the
        background (:attr:`queried` is set once done)."""
        live = self.session.liveliness()
        self._subs.append(live.declare_subscriber(self.key("alive"), self._on_token,
                                                  history=True))
        self._subs.append(live.declare_subscriber(f"{self.prefix}/{BOX_TOKENS}/*/*",
                                                  self._on_box_token, history=True))
        recovery = zenoh_ext.RecoveryConfig(periodic_queries=None, heartbeat=True)
        health = zenoh_ext.declare_advanced_subscriber(
            self.session, self.key("health"), self._on_health, recovery=recovery,
            history=zenoh_ext.HistoryConfig(detect_late_publishers=True,
                                            max_samples=self.history))
        self._subs.append(health)
        self._subs.append(health.sample_miss_listener(self._on_miss))
        alarm_history = (zenoh_ext.HistoryConfig(detect_late_publishers=True,
                                                 max_samples=self.alarm_history)
                         if self.alarm_history else None)
        self._subs.append(zenoh_ext.declare_advanced_subscriber(
            self.session, self.key("alarm"), self._on_alarm, recovery=recovery,
            history=alarm_history))
        for target, name in ((self._ask_latest, "twinwatch-watch-query"),
                             (self._fill_gaps, "twinwatch-watch-history")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    # -- arriving ------------------------------------------------------------------------------
    def _ask_latest(self) -> None:
        try:
            if self._closing.wait(LATEST_AFTER_S):
                return
            self._box_idle.wait(BOX_LIST_TIMEOUT_S)  # the machines of the boxes there
            if all(m["window"] is not None for m in self.fleet.snapshot()["machines"]
                   if m["token"]):
                return
            for reply in self.session.get(self.key("health"), timeout=5.0):
                if reply.ok is None:
                    continue
                machine = machine_of(str(reply.ok.key_expr), self.prefix, "health")
                with self._lock:  # only a machine nothing came from: never out of order
                    if machine is not None and machine not in self._seq:
                        self._health(str(reply.ok.key_expr), reply.ok.payload, "live")
        except zenoh.ZError:  # the session closed under the query
            pass
        finally:
            self.queried.set()
            self.fleet.changed.set()

    def _on_token(self, sample: zenoh.Sample) -> None:
        machine = machine_of(str(sample.key_expr), self.prefix, "alive")
        if machine is None:
            return
        present = sample.kind == zenoh.SampleKind.PUT
        if present:
            with self._box_lock:
                self._tokened.add(machine)
        self._token(machine, present)

    def _token(self, machine: str, present: bool) -> None:
        """``machine``'s presence (its token's or its box's) changed."""
        self.fleet.token(machine, present)
        if self.on_token is not None:
            self.on_token(machine, present)

    # -- boxes' presence ([zenoh] presence = "box") --------------------------------------------
    def _on_box_token(self, sample: zenoh.Sample) -> None:
        """A box's token appeared (its machines are asked from it: :meth:`_list_boxes`) or
        went (the machines it named are gone, unless another box's token names them)."""
        key = str(sample.key_expr)
        if sample.kind == zenoh.SampleKind.PUT:
            with self._box_lock:
                self._box_members.setdefault(key, set())
            self._list_boxes(key)
            return
        with self._box_lock:
            members = self._box_members.pop(key, set())
            self._boxed = set().union(*self._box_members.values())
            gone = sorted(members - self._boxed)
        for m in gone:
            self._token(m, False)

    def _list_boxes(self, key: str) -> None:
        """Ask the box tokens' queryables reaching ``key`` for their machines (replies on
        Zenoh's threads: :meth:`_on_box_reply`)."""
        with self._box_lock:
            self._box_listing += 1
            self._box_idle.clear()
        try:
            self.session.get(key, zenoh.handlers.Callback(self._on_box_reply,
                                                          self._box_listed),
                             target=zenoh.QueryTarget.ALL, timeout=BOX_LIST_TIMEOUT_S)
        except zenoh.ZError:  # the session closed
            self._box_listed()

    def _box_listed(self) -> None:
        with self._box_lock:
            self._box_listing -= 1
            if self._box_listing <= 0:
                self._box_listing = 0
                self._box_idle.set()

    def _on_box_reply(self, reply: zenoh.Reply) -> None:
        """A box's machines (``{"box", "machines"}``): the new ones are present, those it no
        longer names (and no other box does) gone."""
        if reply.ok is None:
            return
        key = str(reply.ok.key_expr)
        doc = decode_json(reply.ok.payload)
        names = doc.get("machines") if doc is not None else None
        if not isinstance(names, list):
            return
        machines = {m for m in names if isinstance(m, str) and CHUNKS_RE.match(m) is not None
                    and "/" not in m and self.machine in ("*", m)}
        with self._box_lock:
            old = self._box_members.get(key)
            if old is None:  # its token went meanwhile, or is not here yet
                return
            self._box_members[key] = machines
            self._boxed = set().union(*self._box_members.values())
            came, went = sorted(machines - old), sorted(old - self._boxed)
        for m in came:
            self._token(m, True)
        for m in went:
            self._token(m, False)

    def _unnamed(self, machine: str) -> None:
        """A window of ``machine``: if no token stands for it while boxes' tokens are
        present, ask the boxes' machines again (at most every :data:`BOX_LIST_EVERY_S`)."""
        with self._box_lock:
            if (not self._box_members or machine in self._boxed or machine in self._tokened
                    or time.monotonic() - self._box_asked < BOX_LIST_EVERY_S):
                return
            self._box_asked = time.monotonic()
        self._list_boxes(f"{self.prefix}/{BOX_TOKENS}/*/*")

    def _on_health(self, sample: zenoh.Sample) -> None:
        machine = self._health(str(sample.key_expr), sample.payload, "live")
        if machine is not None:
            self._unnamed(machine)
        info = sample.source_info
        if machine is not None and info is not None:
            source = info.source_id
            with self._lock:
                self._sources[(str(source.zid), int(source.eid))] = machine

    def _health(self, key: str, payload: Any, delivery: Delivery) -> str | None:
        """Deliver one health message unless it was delivered before; its machine."""
        machine = machine_of(key, self.prefix, "health")
        got = decode_health(payload)
        if machine is None or got is None:
            return None
        self._deliver(machine, *got, delivery)
        return machine

    def _deliver(self, machine: str, doc: HealthView, text: str,
                 delivery: Delivery) -> bool:
        window, t_end = doc.window, number(doc.t_end)
        with self._lock:
            if isinstance(window, int) and not isinstance(window, bool):
                seq = self._seq.get(machine)
                if seq is None or seq.run != doc.run:
                    self._seq[machine] = _Sequence(doc.run, window, t_end)
                elif not seq.add(window, t_end):
                    return False
            self.fleet.health(machine, doc)
            if self.on_health is not None:
                self.on_health(machine, doc, text, delivery)
        return True

    def _on_alarm(self, sample: zenoh.Sample) -> None:
        machine = machine_of(str(sample.key_expr), self.prefix, "alarm")
        doc = decode_json(sample.payload)
        if machine is None or doc is None:
            return
        self.fleet.alarm(machine, doc)
        if self.on_alarm is not None:
            self.on_alarm(machine, doc)

    # -- gaps ----------------------------------------------------------------------------------
    def _on_miss(self, miss: Any) -> None:
        """Zenoh's sample-miss listener (its thread): ``miss.nb`` windows of the publisher
        ``miss.source`` were neither received nor recovered from its cache."""
        source = miss.source
        with self._lock:
            machine = self._sources.get((str(source.zid), int(source.eid)))
        self._gaps.put((machine, int(miss.nb)))

    def _fill_gaps(self) -> None:
        while True:
            item = self._gaps.get()
            if item is None or self._closing.is_set():
                return
            machine, missed = item
            with self._lock:
                machines = [machine] if machine is not None else sorted(self._seq)
            for m in machines:  # a publisher not heard yet: every machine is asked
                gap = self._fill(m, missed if machine is not None else 0)
                if gap is not None:
                    self.fleet.gap(gap)
                    if self.on_gap is not None:
                        self.on_gap(gap)

    def _fill(self, machine: str, missed: int) -> Gap | None:
        """Ask ``machine``'s history for the windows after the last one delivered without a
        gap; deliver those not delivered. None when nothing was missed or returned."""
        gap = Gap(machine, missed)
        with self._lock:
            seq = self._seq.get(machine)
            if seq is None:
                return gap if missed else None
            run, t_from = seq.run, seq.t_end
        params = [f"run={run}"] if isinstance(run, str) and run else []
        if t_from is not None:
            params.append(f"t_from={t_from!r}")
        for attempt in range(HISTORY_ATTEMPTS):
            if attempt and self._closing.wait(float(attempt)):
                return None
            try:
                self._page(machine, params, gap)
            except (WatchError, zenoh.ZError) as exc:
                gap.error = str(exc)
                continue
            gap.error = None
            break
        with self._lock:
            seq = self._seq.get(machine)
            if seq is not None and seq.run == run and gap.error is None:
                seq.settle()
        return gap if (gap.missed or gap.recovered or gap.error) else None

    def _page(self, machine: str, params: list[str], gap: Gap) -> None:
        """Deliver the history after ``params``' ``t_from``, page by page.

        Raises:
            WatchError: the daemon refused the query or did not answer.
        """
        key = f"{self.prefix}/{machine}/history"
        while True:
            selector = f"{key}?{';'.join(params)}" if params else key
            pages = []
            for reply in self.session.get(selector, target=zenoh.QueryTarget.ALL,
                                          timeout=HISTORY_TIMEOUT_S):
                if reply.ok is not None:
                    page = decode_json(reply.ok.payload)
                    if page is not None and isinstance(page.get("windows"), list):
                        pages.append(page)
                else:
                    err = reply.err
                    raise WatchError(f"{key}: " + (err.payload.to_string() if err is not None
                                                   else "an error without a message"))
            if not pages:
                raise WatchError(f"{key}: no answer within {HISTORY_TIMEOUT_S:g} s (the "
                                 "daemon is not reachable, or keeps no state database)")
            last_t = None
            for page in pages:  # {"windows": [health message, ...], "more": bool}
                for raw in page["windows"]:
                    if not isinstance(raw, dict):
                        continue
                    text = json.dumps(raw, separators=(",", ":"))  # as published
                    doc = health_view(raw)
                    if self._deliver(machine, doc, text, "history"):
                        gap.recovered.append(doc.window)
                    t_end = number(doc.t_end)
                    if t_end is not None:
                        last_t = t_end if last_t is None else max(last_t, t_end)
            if not any(p.get("more") for p in pages) or last_t is None:
                return
            # the next page: windows ending after the last one (t_from is inclusive and
            # returned that window again)
            params = [p for p in params if not p.startswith("after=")]
            params.append(f"after={last_t!r}")

    # -- waiting and closing -------------------------------------------------------------------
    def settle(self, timeout: float) -> None:
        """Wait until every machine with a token has reported a window and the machines that
        gave nothing were asked for their latest, or ``timeout`` [s] has passed (what ``watch
        --once`` prints)."""
        deadline = time.monotonic() + timeout
        time.sleep(min(0.2, timeout))  # the tokens that exist arrive within milliseconds
        while time.monotonic() < deadline:
            snap = self.fleet.snapshot()["machines"]
            tokens = [m for m in snap if m["token"]]
            if all(m["window"] is not None for m in tokens) and (
                    tokens or self.queried.is_set()):
                return
            self.fleet.changed.wait(max(min(0.05, deadline - time.monotonic()), 0.0))
            self.fleet.changed.clear()

    def close(self) -> None:
        """Undeclare the subscribers and stop the watcher's threads (idempotent)."""
        self._closing.set()
        self._gaps.put(None)
        subs, self._subs = self._subs, []
        for sub in reversed(subs):
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        threads, self._threads = self._threads, []
        for thread in threads:
            thread.join(timeout=HISTORY_TIMEOUT_S + 1)

    def __enter__(self) -> FleetWatcher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def watching(connect: Sequence[str], mode: Mode, prefix: str, fleet: Fleet,
             machine: str = "*", *, optional: Collection[str] = (),
             on_skip: Callable[[str, str], None] | None = None,
             **options: Any) -> Iterator[_Watchers]:
    """Sessions on ``connect`` and a started :class:`FleetWatcher` on each (``options``: its
    ``history``, ``alarm_history`` and ``on_*``), yielded as one (its ``settle``), closed on
    exit.

    Args:
        optional, on_skip: as :func:`~twinwatch.watch.session.sessions_watched`'s.

    Raises:
        WatchError: see :func:`open_session` and :class:`FleetWatcher`; every endpoint was
            skipped.
    """
    check_prefix(prefix)
    with sessions_watched(
            connect, mode,
            lambda session: FleetWatcher(session, fleet, prefix=prefix, machine=machine,
                                         **options),
            optional=optional, on_skip=on_skip) as watchers:
        yield _Watchers(watchers)


class _Watchers:
    """The :class:`FleetWatcher` of each session (one per endpoint in client mode) as one."""

    def __init__(self, watchers: Sequence[FleetWatcher]) -> None:
        self.watchers = list(watchers)

    def settle(self, timeout: float) -> None:
        """:meth:`FleetWatcher.settle` on each, within one ``timeout`` [s] in all."""
        deadline = time.monotonic() + timeout
        for w in self.watchers:
            w.settle(max(0.0, deadline - time.monotonic()))
