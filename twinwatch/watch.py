"""See health without writing code: ``twinwatch watch`` (the fleet at a glance) and ``twinwatch
tail MACHINE`` (one line per health message as it arrives).

Every daemon's Zenoh output (:mod:`twinwatch.sinks.zenoh`) declares, with ``P =
<key_prefix>/<machine>``, the liveliness token ``P/alive`` while it runs, publishes each window's
health on ``P/health`` and alarm changes on ``P/alarm``, and answers ``get(P/health)`` with the
latest window. A watcher opens one Zenoh session (explicit endpoints, multicast and gossip
scouting off: :func:`open_session`), connected to a daemon directly (it is a peer listening on
``tcp/127.0.0.1:7447`` by default) or to a router the daemons connect to, and

* finds the machines by liveliness (a subscriber on ``<prefix>/*/alive`` with the tokens that
  exist already): a machine appears when its daemon starts and is marked gone when its token
  goes (a stop, a crash, a lost link: the router drops a dead session's tokens);
* follows ``<prefix>/*/health`` and ``<prefix>/*/alarm`` with ``zenoh.ext`` advanced
  subscribers: each machine's last windows come at once from its publisher's cache (also for a
  daemon that starts later), a loss on the way (a router restarting) is recovered from that
  cache, and what the cache no longer holds is reported by the sample-miss listener and asked
  from the machine's history (its state database, ``<prefix>/<machine>/history``): no window is
  lost for the watcher, and none is delivered twice (:class:`FleetWatcher`);
* asks a machine that gave nothing from a cache (plain publishers) for its latest window
  (``get(<prefix>/<machine>/health)``).

:class:`Fleet` holds what the network showed (thread-safe: Zenoh's threads update it), and
:meth:`Fleet.snapshot` is the one summary every view reads: the JSON of ``watch --once
--json`` (README, "Watching the fleet"), the rich table of ``watch`` (:func:`render`). The
health message is read as the JSON it is published as, not through the typed model, so that a
watcher shows daemons of other twinwatch versions: a field it does not know is ignored, one that
is missing is shown as absent (the prognostics' ``rul``, when the message carries it).

This room imports the ground floor only (zenoh through :mod:`twinwatch._lazy`, rich inside
:func:`render`): never the daemon, the sinks or the twin's estimation (``watch`` starts in well
under a second).
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol

from twinwatch._lazy import lazy_module
from twinwatch.errors import WatchError

if TYPE_CHECKING:
    import zenoh
    from rich.console import RenderableType
    from rich.text import Text
    from zenoh import ext as zenoh_ext

    from twinwatch.twin.health import DiagnosisView, HealthView
else:  # imported when a session opens
    zenoh = lazy_module("zenoh")
    zenoh_ext = lazy_module("zenoh.ext")

__all__ = [
    "DEFAULT_CONNECT",
    "Delivery",
    "Fleet",
    "FleetWatcher",
    "Gap",
    "MachineState",
    "Mode",
    "WatchError",
    "Tail",
    "health_line",
    "open_session",
    "render",
    "watching",
]

DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)
"""Where a watcher connects by default: a daemon (a peer listening there by default) or a
router on this host."""

Mode = Literal["client", "peer"]

MachineState = Literal["alive", "stale", "gone", "unknown"]
"""``alive``: its liveliness token is present (and a window came recently); ``stale``: the token
is present but no window for longer than the stale time (a silent source, a stuck worker);
``gone``: the token went (the daemon stopped or died, or the link to it is lost); ``unknown``:
heard only through a health message, no token seen."""

_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*)"
                          r":[0-9]{1,5}$")
_CHUNKS_RE = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")

#: Counters that report a loss or a fault (nonzero: shown under data quality, "losses"). Not
#: the driver's activity (``driver_polls``, ``driver_duplicates``: a poll that found the
#: sample already read, nothing lost; ``driver_reconnects``, ``driver_remote_frames``, the
#: frames and samples delivered), which the column listed before (issue 24).
PROBLEM_COUNTERS = ("windows_abandoned", "overruns", "numeric_failures", "samples_lost",
                    "bad_samples", "windows_not_stored", "store_waiting", "store_lost",
                    "store_history_lost", "store_errors", "recording_lost", "zenoh_errors",
                    "driver_bad_frames", "driver_bad_values", "driver_gaps", "driver_errors",
                    "driver_dropped", "driver_error_frames", "driver_incomplete_syncs",
                    "driver_outages", "mqtt_lost")

SETTLE_S = 0.5
"""Tokens that arrive this soon after a watcher starts [s] existed before it."""


# -- the session -------------------------------------------------------------------------------
def check_endpoints(connect: Sequence[str]) -> list[str]:
    """The endpoints, checked (``proto/host:port``).

    Raises:
        WatchError: none given, or one is malformed (named).
    """
    if not connect:
        raise WatchError("give at least one endpoint to connect to, e.g. --connect "
                         "tcp/127.0.0.1:7447")
    for e in connect:
        if _ENDPOINT_RE.match(e) is None:
            raise WatchError(f"endpoint {e!r} is not of the form proto/host:port (proto one of "
                             "tcp, udp, tls, quic, ws), e.g. tcp/127.0.0.1:7447")
    return list(connect)


def check_prefix(prefix: str) -> str:
    """The key prefix, checked: ``/``-separated plain chunks (as ``[zenoh] key_prefix``).

    Raises:
        WatchError: it is empty or has wildcards or reserved characters.
    """
    if _CHUNKS_RE.match(prefix) is None:
        raise WatchError(f"key prefix {prefix!r} must be chunks of letters, digits, '_', '-' or "
                         "'.' separated by '/' (the daemons' [zenoh] key_prefix)")
    return prefix


def open_session(connect: Sequence[str] = DEFAULT_CONNECT, mode: Mode = "client"
                 ) -> zenoh.Session:
    """A Zenoh session that talks only to ``connect``: no listening, multicast and gossip
    scouting off (a watcher never discovers or is discovered by anything it was not told).

    Args:
        connect: endpoints of a daemon (a peer) or a router, ``tcp/127.0.0.1:7447``.
        mode: ``client`` (default: through the router or peer it connects to) or ``peer``.

    Raises:
        WatchError: an endpoint is malformed, or nothing answers there (client mode).
    """
    endpoints = check_endpoints(connect)
    conf = zenoh.Config()
    try:
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
    except zenoh.ZError as exc:
        raise WatchError(f"invalid zenoh settings (mode={mode}, connect={endpoints}): "
                         f"{exc}") from exc
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        msg = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()
        if "unable to connect" in msg.lower():
            raise WatchError(f"cannot connect to {', '.join(endpoints)}: nothing answers there; "
                             "start a daemon (twinwatch run) or a zenoh router there, or give "
                             f"--connect (zenoh: {msg})") from exc
        raise WatchError(f"cannot open a zenoh session (mode={mode}, connect={endpoints}): "
                         f"{msg}") from exc


def _machine_of(key: str, prefix: str, suffix: str) -> str | None:
    """``<prefix>/<machine>/<suffix>`` -> machine (None for another key)."""
    head, tail = f"{prefix}/", f"/{suffix}"
    if key.startswith(head) and key.endswith(tail):
        machine = key[len(head):-len(tail)]
        return machine if machine and "/" not in machine else None
    return None


def _decode(payload: Any) -> dict[str, Any] | None:
    """A JSON object from a Zenoh payload (an alarm event, a history page), or None (a
    non-object or bad JSON is ignored)."""
    try:
        doc = json.loads(payload.to_string())
    except (ValueError, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


def _health_view(doc: HealthView | Mapping[str, Any]) -> HealthView:
    """A health message as its typed view (:func:`~twinwatch.twin.health.read_health`)."""
    from twinwatch.twin.health import HealthView, read_health

    return doc if isinstance(doc, HealthView) else read_health(doc)


def _decode_health(payload: Any) -> tuple[HealthView, str] | None:
    """A health message from a Zenoh payload: its typed view and its text, or None (bad JSON
    or not an object is ignored)."""
    from twinwatch.twin.health import read_health

    try:
        text = payload.to_string()
        return read_health(text), text
    except (ValueError, UnicodeDecodeError):
        return None


# -- the fleet ---------------------------------------------------------------------------------
@dataclass
class _Machine:
    name: str
    token: bool | None = None  # None: never seen a token
    since: float | None = None  # wall time of the last token change seen (None: before us)
    health: HealthView | None = None
    received: float | None = None  # wall time the last health arrived
    events: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=5))
    missed: int = 0  # windows zenoh reported missed
    recovered: int = 0  # windows then got from the history
    gap_error: str | None = None  # why the last gap could not be asked from the history


class Fleet:
    """The machines of one key prefix as the network shows them.

    Args:
        stale_after: seconds without a window (at least 3 window lengths) before a machine
            whose token is present is shown ``stale``.
        forget_after: seconds after which a gone machine is no longer listed (None: never).
        clock: wall clock [s since the epoch].

    Thread-safe: Zenoh's threads call :meth:`token`, :meth:`health`, :meth:`alarm`; a view
    reads :meth:`snapshot`.
    """

    def __init__(self, *, stale_after: float = 10.0, forget_after: float | None = 600.0,
                 clock: Callable[[], float] = time.time) -> None:
        self.stale_after = stale_after
        self.forget_after = forget_after
        self._clock = clock
        self._lock = threading.Lock()
        self._machines: dict[str, _Machine] = {}
        self.changed = threading.Event()
        self.started = clock()

    def _get(self, name: str) -> _Machine:
        m = self._machines.get(name)
        if m is None:
            m = self._machines[name] = _Machine(name)
        return m

    def token(self, machine: str, present: bool) -> None:
        """The machine's liveliness token appeared (``present``) or went. A token present
        within :data:`SETTLE_S` of the start was there before the watcher (since unknown)."""
        now = self._clock()
        with self._lock:
            m = self._get(machine)
            if m.token != present:
                before = present and m.token is None and now - self.started < SETTLE_S
                m.token, m.since = present, None if before else now
        self.changed.set()

    def health(self, machine: str, doc: HealthView | Mapping[str, Any]) -> bool:
        """A health message of ``machine`` (the latest, or one published: its typed view, or
        decoded). An older window of the same run than the one held (a late reply to the first
        query) is ignored.

        Returns:
            True if it is now the machine's latest.
        """
        doc = _health_view(doc)
        with self._lock:
            m = self._get(machine)
            old = m.health
            if old is not None and old.run == doc.run and isinstance(
                    doc.window, int) and isinstance(old.window, int) and (
                    doc.window <= old.window):
                return False
            m.health, m.received = doc, self._clock()
        self.changed.set()
        return True

    def alarm(self, machine: str, event: Mapping[str, Any]) -> None:
        """An alarm event of ``machine`` (``<prefix>/<machine>/alarm``)."""
        with self._lock:
            self._get(machine).events.append(dict(event))
        self.changed.set()

    def gap(self, gap: Gap) -> None:
        """Windows of a machine zenoh reported missed, and what its history returned."""
        with self._lock:
            m = self._get(gap.machine)
            m.missed += gap.missed
            m.recovered += len(gap.recovered)
            m.gap_error = gap.error
        self.changed.set()

    def machines(self) -> list[str]:
        """The machines listed now, sorted."""
        return [m["machine"] for m in self.snapshot()["machines"]]

    def snapshot(self) -> dict[str, Any]:
        """What the network shows now, as plain JSON types (``watch --once --json``)::

            {"t": <wall s>, "machines": [{"machine", "state", "token", "state_since_s",
              "last_window_age_s", "model", "run", "window", "t_start", "t_end",
              "parameters": {name: {"value", "unit", "nominal", "deviation_pct", "status",
                                    "alarm", "rul_s", "rul_status"}},
              "alarms": {name: {"level", "since_t", "deviation_pct"}},
              "terms": [{"equation", "meaning"}],
              "diagnosis": {"fault", "probability", "action"} | null,
              "quality": {"nrmse", "model_check", "trusted", "elapsed_ms", "problems"},
              "delivery": {"missed", "recovered", "error"},
              "last_event": {...} | null}, ...]}

        ``state_since_s``: since the watcher saw the token appear or go (null: it was there
        before the watcher started). Parameters that are ``tied`` or ``fixed`` are left out
        (not estimated); ``alarm`` is
        the parameter's alarm level when it has a rule; ``rul_s`` the median remaining useful
        life to the alarm threshold [s] when the message carries a prediction. ``delivery``:
        the windows zenoh reported this watcher missed (a router outage, a lost link: beyond
        what the publisher's cache gave back), how many of them the daemon's history query
        then returned, and why the last such query failed (null: it did not).
        """
        now = self._clock()
        with self._lock:
            if self.forget_after is not None:
                for name in [n for n, m in self._machines.items()
                             if m.token is False and m.since is not None
                             and now - m.since > self.forget_after]:
                    del self._machines[name]
            machines = [self._view(m, now) for _, m in sorted(self._machines.items())]
        return {"t": now, "machines": machines}

    def _view(self, m: _Machine, now: float) -> dict[str, Any]:
        h = m.health
        age = None if m.received is None else max(now - m.received, 0.0)
        window_s = (_num(h.t_end, 0.0) - _num(h.t_start, 0.0)) if h is not None else 0.0
        state: MachineState
        if m.token is False:
            state = "gone"
        elif m.token is None:
            state = "unknown"
        elif age is not None and age > max(self.stale_after, 3.0 * window_s):
            state = "stale"
        else:
            state = "alive"
        return {
            "machine": m.name,
            "state": state,
            "token": m.token,
            "state_since_s": None if m.since is None else max(now - m.since, 0.0),
            "last_window_age_s": age,
            "model": h.model if h is not None else None,
            "run": h.run if h is not None else None,
            "window": h.window if h is not None else None,
            "t_start": h.t_start if h is not None else None,
            "t_end": h.t_end if h is not None else None,
            "parameters": _parameters(h) if h is not None else {},
            "alarms": {k: {"level": a.level, "since_t": a.since_t,
                           "deviation_pct": a.deviation_pct,
                           "rul": ({"level": a.rul.level, "since_t": a.rul.since_t,
                                    "rul_s": a.rul.rul_s} if a.rul is not None else None)}
                       for k, a in ((h.alarms if h is not None else None) or {}).items()},
            "terms": [{"equation": t.equation, "meaning": t.meaning}
                      for t in (h.terms if h is not None else None) or []],
            "diagnosis": _diagnosis(h.diagnosis if h is not None else None),
            "quality": _quality(h) if h is not None else None,
            "delivery": {"missed": m.missed, "recovered": m.recovered, "error": m.gap_error},
            "last_event": m.events[-1] if m.events else None,
        }


def _num(x: Any, default: float | None = None) -> Any:
    return x if isinstance(x, int | float) and not isinstance(x, bool) else default


def _parameters(h: HealthView) -> dict[str, dict[str, Any]]:
    alarms = h.alarms or {}
    out: dict[str, dict[str, Any]] = {}
    for name, p in (h.parameters or {}).items():
        if p.status in ("tied", "fixed"):
            continue
        crossing = p.rul.alarm if p.rul is not None else None
        alarm = alarms.get(name)
        out[name] = {"value": _num(p.value), "unit": p.unit,
                     "nominal": _num(p.nominal),
                     "deviation_pct": _num(p.deviation_pct), "status": p.status,
                     "alarm": alarm.level if alarm is not None else None,
                     "rul_s": _num(crossing.rul_s if crossing is not None else None),
                     "rul_status": crossing.status if crossing is not None else None}
    return out


def _problems(h: HealthView) -> dict[str, int]:
    """The counters of losses that are not zero."""
    return {k: v for k, v in (h.counters or {}).items()
            if k in PROBLEM_COUNTERS and isinstance(v, int) and v}


def _quality(h: HealthView) -> dict[str, Any]:
    counters = h.counters or {}
    problems = _problems(h)
    check = h.model_check
    elapsed = _num(h.elapsed_s)
    return {"nrmse": _num(h.nrmse),
            "model_check": check.passed if check is not None else None,
            "trusted": h.trusted,
            "elapsed_ms": None if elapsed is None else round(elapsed * 1e3, 1),
            "windows_estimated": counters.get("windows_estimated"),
            "problems": problems}


# -- the watcher -------------------------------------------------------------------------------
Delivery = Literal["live", "history"]
"""How a health message reached the watcher: ``live`` (published, or from a daemon's cache:
the latest at start, a late joiner's history, a loss zenoh recovered) or ``history`` (asked from
the daemon's state database after zenoh reported windows missed)."""

LATEST_AFTER_S = 0.3
"""A machine whose token is there but whose publisher's cache gave no window this long after
the watcher started is asked for its latest window (a daemon with plain publishers: [zenoh]
cache = 0, or an older twinwatch) [s]."""

HISTORY_TIMEOUT_S = 10.0
"""How long one history query may take to answer [s]."""

HISTORY_ATTEMPTS = 3
"""Tries of the history query for a gap (1 s, then 2 s apart) before it is given up."""


@dataclass
class Gap:
    """Windows of one machine zenoh reported missed, and what the history query got back.

    Attributes:
        machine: the machine.
        missed: windows zenoh's sample-miss detection counted (not received live, not
            recovered from the publisher's cache).
        recovered: the windows the history query returned that this watcher had not seen,
            oldest first (their window numbers).
        error: why the history could not be asked (after every attempt), or None.
    """

    machine: str
    missed: int
    recovered: list[int] = field(default_factory=list)
    error: str | None = None


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

    Health and alarm events are followed with ``zenoh.ext`` advanced subscribers: at start (and
    when a daemon appears later) each machine's last ``history`` windows come from its
    publisher's cache (``[zenoh] cache``), a loss on the way (a router restarting, a dropped
    link) is recovered from that cache, and what the cache no longer holds is reported by the
    sample-miss listener: those windows are then asked from the machine's state database
    (``<prefix>/<machine>/history?run=<run>;t_from=<the last window before the gap>``, target
    ALL so a storage declared complete on the prefix does not capture it), delivered with
    ``delivery="history"``, counted in the fleet (``missed``, ``recovered``) and reported
    through ``on_gap``. A machine whose token is there but whose cache gave nothing within
    :data:`LATEST_AFTER_S` (plain publishers: ``cache = 0``, an older daemon) is asked for its
    latest window (``get(<prefix>/*/health)``). Each window is delivered once.

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
        WatchError: the prefix or the machine name is malformed, or ``history`` < 1.

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
        if machine != "*" and (_CHUNKS_RE.match(machine) is None or "/" in machine):
            raise WatchError(f"machine {machine!r}: give the daemon's [machine] name (letters, "
                             "digits, '_', '-', '.') or * for every machine")
        if history < 1 or alarm_history < 0:
            raise WatchError(f"history {history}: ask at least the latest window (1)")
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

    def key(self, suffix: str) -> str:
        return f"{self.prefix}/{self.machine}/{suffix}"

    def resume(self, machine: str, run: str | None, window: int,
               t_end: float | None) -> None:
        """Go on from where an earlier subscriber stopped (a central store restarted): the
        windows of ``machine``'s ``run`` up to ``window`` count as delivered, and the ones
        after it (plant time after ``t_end`` [s]) are asked from its history once started,
        delivered with ``delivery="history"`` and told through ``on_gap`` (``missed`` 0: zenoh
        did not count them). A later run of that machine (its daemon restarted meanwhile) is
        followed from what its cache holds. Call before :meth:`start`.

        Raises:
            WatchError: ``machine`` is not a machine name.
        """
        if _CHUNKS_RE.match(machine) is None or "/" in machine:
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
            if all(m["window"] is not None for m in self.fleet.snapshot()["machines"]
                   if m["token"]):
                return
            for reply in self.session.get(self.key("health"), timeout=5.0):
                if reply.ok is None:
                    continue
                machine = _machine_of(str(reply.ok.key_expr), self.prefix, "health")
                with self._lock:  # only a machine nothing came from: never out of order
                    if machine is not None and machine not in self._seq:
                        self._health(str(reply.ok.key_expr), reply.ok.payload, "live")
        except zenoh.ZError:  # the session closed under the query
            pass
        finally:
            self.queried.set()
            self.fleet.changed.set()

    def _on_token(self, sample: zenoh.Sample) -> None:
        machine = _machine_of(str(sample.key_expr), self.prefix, "alive")
        if machine is None:
            return
        present = sample.kind == zenoh.SampleKind.PUT
        self.fleet.token(machine, present)
        if self.on_token is not None:
            self.on_token(machine, present)

    def _on_health(self, sample: zenoh.Sample) -> None:
        machine = self._health(str(sample.key_expr), sample.payload, "live")
        info = sample.source_info
        if machine is not None and info is not None:
            source = info.source_id
            with self._lock:
                self._sources[(str(source.zid), int(source.eid))] = machine

    def _health(self, key: str, payload: Any, delivery: Delivery) -> str | None:
        """Deliver one health message unless it was delivered before; its machine."""
        machine = _machine_of(key, self.prefix, "health")
        got = _decode_health(payload)
        if machine is None or got is None:
            return None
        self._deliver(machine, *got, delivery)
        return machine

    def _deliver(self, machine: str, doc: HealthView, text: str,
                 delivery: Delivery) -> bool:
        window, t_end = doc.window, _num(doc.t_end)
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
        machine = _machine_of(str(sample.key_expr), self.prefix, "alarm")
        doc = _decode(sample.payload)
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
                    page = _decode(reply.ok.payload)
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
                    doc = _health_view(raw)
                    if self._deliver(machine, doc, text, "history"):
                        gap.recovered.append(doc.window)
                    t_end = _num(doc.t_end)
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
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        threads, self._threads = self._threads, []
        for thread in threads:
            thread.join(timeout=HISTORY_TIMEOUT_S + 1)

    def __enter__(self) -> FleetWatcher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def watching(connect: Sequence[str], mode: Mode, prefix: str, fleet: Fleet,
             machine: str = "*", **options: Any) -> Iterator[Settling]:
    """A session on ``connect`` and a started :class:`FleetWatcher` on it (``options``: its
    ``history``, ``alarm_history`` and ``on_*``), closed on exit.

    Raises:
        WatchError: see :func:`open_session` and :class:`FleetWatcher`.
    """
    check_prefix(prefix)
    # A client session talks to one of its endpoints only (the first that answers): with
    # `--connect A --connect B` the machines behind B never showed although the header
    # listed both (issue 24). In client mode each endpoint gets a session of its own, all
    # feeding the one fleet; a peer session connects to every endpoint itself.
    groups = ([[e] for e in connect] if mode == "client" and len(connect) > 1
              else [list(connect)])
    with contextlib.ExitStack() as stack:
        watchers: list[FleetWatcher] = []
        for group in groups:
            session = open_session(group, mode)
            stack.callback(session.close)
            watchers.append(stack.enter_context(
                FleetWatcher(session, fleet, prefix=prefix, machine=machine, **options)))
        yield watchers[0] if len(watchers) == 1 else _Watchers(watchers)


class Settling(Protocol):
    """What :func:`watching` yields: one :class:`FleetWatcher`, or several as one."""

    def settle(self, timeout: float) -> None:
        """Wait until every machine with a token has reported a window, or ``timeout`` [s]
        has passed (:meth:`FleetWatcher.settle`)."""


class _Watchers:
    """Several :class:`FleetWatcher` (one per endpoint in client mode) as one."""

    def __init__(self, watchers: Sequence[FleetWatcher]) -> None:
        self.watchers = list(watchers)

    def settle(self, timeout: float) -> None:
        """:meth:`FleetWatcher.settle` on each, within one ``timeout`` [s] in all."""
        deadline = time.monotonic() + timeout
        for w in self.watchers:
            w.settle(max(0.0, deadline - time.monotonic()))


# -- formatting --------------------------------------------------------------------------------
def age(seconds: float | None) -> str:
    """A duration for a person: ``0.4 s``, ``12 s``, ``3.5 min``, ``2.1 h``, ``3.0 d``."""
    if seconds is None or not math.isfinite(seconds):
        return "-"
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} d"


def _value(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.6g}"


def _dev(v: float | None) -> str:
    return "n/a" if v is None else f"{v:+.2f} %"


def _rul(p: Mapping[str, Any]) -> str | None:
    status = p.get("rul_status")
    if status == "predicted" and p.get("rul_s") is not None:
        return f"RUL {age(p['rul_s'])}"
    if status == "crossed":
        return "RUL: crossed"
    return None


def health_line(doc: HealthView | Mapping[str, Any], *, wall: float | None = None) -> str:
    """One line for ``twinwatch tail``: when it arrived, machine, window and its plant time,
    each parameter the window concerns (value, deviation from nominal, ``=`` held, ``~``
    fused), the fit, the model check and the raised alarms. ``doc``: the health message's
    typed view (:func:`~twinwatch.twin.health.read_health`), or decoded.

    Example::

        10:15:31 dc-motor-sim #540 [1080.00-1081.99 s] Ra 5.82987 -10.31 % D 0.00143 +0.02 %
        ... nRMSE 1.6e-05 check ok  ALARM Ra (run 20261122T101530Z-3f9a2c)
    """
    doc = _health_view(doc)
    stamp = time.strftime("%H:%M:%S", time.localtime(time.time() if wall is None else wall))
    parts = [stamp, str("?" if doc.machine is None else doc.machine),
             f"#{'?' if doc.window is None else doc.window}"]
    t0, t1 = _num(doc.t_start), _num(doc.t_end)
    if t0 is not None and t1 is not None:
        parts.append(f"[{t0:.2f}-{t1:.2f} s]")
    parts += _parameter_words(doc) + _fit_words(doc) + _alarm_words(doc)
    n = len(doc.terms or [])
    if n:
        parts.append(f"+{n} term{'s' if n > 1 else ''}")
    problems = _problems(doc)
    if problems:
        parts.append("losses " + ", ".join(f"{k} {v}" for k, v in problems.items()))
    if doc.run:
        parts.append(f"(run {doc.run})")
    return " ".join(parts)


def _parameter_words(doc: HealthView) -> list[str]:
    """:func:`health_line`'s parameters: ``Ra 5.82987 -10.31 %`` each (``Ra=`` held, ``Ra~``
    fused), the tied and fixed ones left out."""
    marks = {"held": "=", "fused": "~"}
    return [f"{name}{marks.get(str(p.status), ' ')}{_value(_num(p.value))} "
            f"{_dev(_num(p.deviation_pct))}"
            for name, p in (doc.parameters or {}).items() if p.status not in ("tied", "fixed")]


def _fit_words(doc: HealthView) -> list[str]:
    """:func:`health_line`'s fit: ``nRMSE 1.6e-05``, ``check ok`` / ``check FAILED`` (none
    without a model check), ``untrusted``."""
    nrmse, check = _num(doc.nrmse), doc.model_check
    passed = check.passed if check is not None else None
    words = [f"nRMSE {nrmse:.1e}" if nrmse is not None else "nRMSE n/a"]
    if passed is not None:
        words.append("check ok" if passed else "check FAILED")
    if doc.trusted is False:
        words.append("untrusted")
    return words


def _alarm_words(doc: HealthView) -> list[str]:
    """:func:`health_line`'s raised alarms, alarms first: `` ALARM Ra``, `` WARNING D, J``."""
    raised = [(k, a.level) for k, a in (doc.alarms or {}).items()
              if a.level in ("warning", "alarm")]
    words = []
    for lvl in ("alarm", "warning"):
        names = [k for k, v in raised if v == lvl]
        if names:
            words.append(f" {lvl.upper()} {', '.join(names)}")
    return words


def _diagnosis(d: DiagnosisView | None) -> dict[str, Any] | None:
    """The message's diagnosis in short: the most probable fault (``no_fault``, ``unknown``,
    ``check_function``: the twin does not fit), its probability and action; null without one
    (a daemon before schema 8, or it is off)."""
    if d is None:
        return None
    faults = d.faults or []
    top = faults[0] if d.status == "fault" and faults else None
    action = top.action if top is not None else None
    if d.status == "check_function":
        since = d.check_function_since
        action = ("the twin does not describe this machine"
                  + (f" since {since:.0f} s" if isinstance(since, int | float) else "")
                  + ": check the sensors and the model")
    return {"fault": (top.id if top is not None else None) or d.status,
            "probability": d.probability,
            "action": action}


_LEVEL_STYLE = {"alarm": "bold red", "warning": "yellow", "normal": "green"}
_SHORT = {"estimated": "est", "fused": "fused", "held": "held"}
_STATE_STYLE = {"alive": "green", "stale": "yellow", "gone": "red", "unknown": "dim"}
_STATE_MARK = {"alive": "●", "stale": "◐", "gone": "✕", "unknown": "?"}


FILE_WIDTH = 180
"""Columns of the table written to a file or a pipe (on a terminal: the terminal's width).
The columns' least widths add up to about 110: at rich's default 80 for a non-terminal every
column was folded (issue 24)."""


def console(file: Any = None) -> Any:
    """A rich console for ``file`` (standard output by default): the terminal's width on a
    terminal, :data:`FILE_WIDTH` columns into a file or a pipe."""
    import sys as _sys

    from rich.console import Console

    stream = file if file is not None else _sys.stdout
    tty = bool(getattr(stream, "isatty", lambda: False)())
    return Console(file=stream) if tty else Console(file=stream, width=FILE_WIDTH)


def render(snapshot: Mapping[str, Any], *, title: str = "twinwatch fleet") -> RenderableType:
    """The rich table of :meth:`Fleet.snapshot`: one row per machine with its state (alive /
    stale / gone, for how long), its last window (age, index, plant time, run), each parameter's
    value, deviation from nominal, status, alarm level and RUL, the raised alarms and the last
    event, the discovered terms, the most probable fault and its probability, and the data
    quality (fit, model check, losses). Each cell is its own function (``_<column>_cell``),
    given the machine's entry of the snapshot."""
    from rich.table import Table
    from rich.text import Text

    machines = snapshot.get("machines", [])
    table = Table(title=f"{title}: {len(machines)} machine{'s' if len(machines) != 1 else ''}",
                  title_justify="left", expand=True, show_lines=True)
    for header, ratio, least in (("machine", 2, 8), ("state", 2, 9), ("last window", 3, 24),
                                 ("parameters (vs nominal)", 5, 24), ("alarms", 3, 12),
                                 ("terms (DT'')", 3, 10), ("diagnosis", 2, 10),
                                 ("data quality", 3, 16)):
        table.add_column(header, ratio=ratio, min_width=least, overflow="fold")
    if not machines:
        table.add_row("no machine on the network yet", "", "", "", "", "", "", "")
    for m in machines:
        terms = Text("\n".join(str(t["equation"]) for t in m["terms"]) or "none",
                     style="" if m["terms"] else "dim")
        table.add_row(Text(str(m["machine"]), style="bold"), _state_cell(m), _last_cell(m),
                      _parameters_cell(m), _alarms_cell(m), terms, _diagnosis_cell(m),
                      _quality_cell(m))
    return table


def _state_cell(m: Mapping[str, Any]) -> Text:
    """``● alive`` / ``◐ stale`` / ``✕ gone``, and since when (for how long it has been so
    while the token is there, how long ago it went)."""
    from rich.text import Text

    state = str(m["state"])
    st = Text(f"{_STATE_MARK.get(state, '?')} {state}", style=_STATE_STYLE.get(state, ""))
    since = m["state_since_s"]
    if since is not None:
        st.append("\n" + (f"for {age(since)}" if m["token"] else f"{age(since)} ago"),
                  style="dim")
    return st


def _last_cell(m: Mapping[str, Any]) -> Text:
    """The last window: how long ago, its index, its plant time and its run."""
    from rich.text import Text

    if m["window"] is None:
        return Text("no window yet", style="dim")
    last = Text(f"{age(m['last_window_age_s'])} ago\n#{m['window']}")
    if m["t_start"] is not None and m["t_end"] is not None:
        last.append(f" [{m['t_start']:.0f}-{m['t_end']:.0f} s]")
    if m["run"]:
        last.append(f"\nrun {m['run']}", style="dim")
    return last


def _parameters_cell(m: Mapping[str, Any]) -> Text:
    """One line per parameter: its deviation from nominal (in its alarm level's style), its
    status, its RUL."""
    from rich.text import Text

    params = Text()
    for name, p in m["parameters"].items():
        if params:
            params.append("\n")
        level = p.get("alarm")
        params.append(f"{name:<3} {_dev(p['deviation_pct']):>9} ",
                      style=_LEVEL_STYLE.get(str(level), ""))
        status = str(p["status"])
        params.append(_SHORT.get(status, status), style="dim" if status == "held" else "")
        rul = _rul(p)
        if rul:
            params.append(f" {rul}", style="cyan")
    return params


def _alarms_cell(m: Mapping[str, Any]) -> Text:
    """The raised alarms (the deviation's and the RUL's, each said as what it is, since when)
    or ``none`` / ``no rules``, then the last alarm event."""
    from rich.text import Text

    alarms = Text()
    for name, a in m["alarms"].items():
        for kind, lv in (("", a), ("RUL ", a.get("rul") or {})):
            if lv.get("level") in ("warning", "alarm"):
                if alarms:
                    alarms.append("\n")
                since = (f" since t={lv['since_t']:.0f} s"
                         if lv.get("since_t") is not None else "")
                alarms.append(f"{name} {kind}{str(lv['level']).upper()}{since}",
                              style=_LEVEL_STYLE[str(lv["level"])])
    if not alarms:
        alarms.append("none" if m["alarms"] else "no rules", style="green dim")
    event = m.get("last_event")
    if event and event.get("parameter"):
        kind = "RUL " if event.get("kind") == "rul" else ""
        alarms.append(f"\nlast: {event.get('parameter')} {kind}{event.get('previous')} -> "
                      f"{event.get('level')} at {_num(event.get('t'), 0.0):.0f} s",
                      style="dim")
    return alarms


def _diagnosis_cell(m: Mapping[str, Any]) -> Text:
    """The most probable fault and its probability (``n/a`` without a diagnosis)."""
    from rich.text import Text

    dg = m.get("diagnosis")
    diag = Text("n/a" if dg is None else str(dg["fault"]).replace("_", " "),
                style="dim" if dg is None or dg["fault"] == "no_fault" else "bold yellow")
    if dg is not None and isinstance(dg.get("probability"), int | float):
        diag.append(f" {dg['probability']:.2f}")
    return diag


def _quality_cell(m: Mapping[str, Any]) -> Text:
    """The fit, the model check, trust, the time per window, the losses; the windows the
    watcher missed and got back from the history."""
    from rich.text import Text

    quality = Text()
    q = m["quality"]
    if q is not None:
        quality.append(f"nRMSE {q['nrmse']:.1e}" if q["nrmse"] is not None else "nRMSE n/a")
        if q["model_check"] is not None:
            quality.append(", check ok" if q["model_check"] else ", check FAILED",
                           style="" if q["model_check"] else "yellow")
        if q["trusted"] is False:
            quality.append(", untrusted", style="yellow")
        if q["elapsed_ms"] is not None:
            quality.append(f"\n{q['elapsed_ms']:.0f} ms/window", style="dim")
        if q["problems"]:
            quality.append("\n" + ", ".join(f"{k} {v}" for k, v in q["problems"].items()),
                           style="yellow")
        else:
            quality.append("\nno losses", style="green dim")
    d = m.get("delivery") or {}
    if d.get("missed") or d.get("recovered") or d.get("error"):
        quality.append(("\n" if quality else "") + _gap_words(d),
                       style="yellow" if d.get("error") or
                       d.get("recovered", 0) < d.get("missed", 0) else "dim")
    return quality


def _gap_words(d: Mapping[str, Any]) -> str:
    """What the watcher missed and got back: ``missed 10, 10 from the history``."""
    text = f"missed {d.get('missed', 0)}, {d.get('recovered', 0)} from the history"
    return text + (f" (history failed: {d['error']})" if d.get("error") else "")


def gap_line(gap: Gap) -> str:
    """One line on a gap for ``tail`` (stderr): ``m1: 10 windows missed (a router outage or a
    lost link), 10 got from its history (windows 8-17)``."""
    text = f"{gap.machine}: "
    if gap.missed:
        text += (f"{gap.missed} window{'s' if gap.missed != 1 else ''} missed (a router "
                 "outage or a lost link), ")
    n = len(gap.recovered)
    text += f"{n} got from its history"
    if gap.recovered:
        ws = sorted(w for w in gap.recovered if isinstance(w, int))
        span = f"window {ws[0]}" if len(ws) == 1 else f"windows {ws[0]}-{ws[-1]}"
        text += f" ({span})" if ws else ""
    if gap.error:
        text += f"; the history query failed: {gap.error}"
    return text


class Tail:
    """``twinwatch tail``: one line per health message as it arrives (the machine's last
    windows first: the latest, or ``--history N``), and, in text, each alarm event; the machine
    appearing and going, and the windows missed and got back from its history, are noted
    aside. Each window is printed once; a window got from the history after a gap comes when
    it is got (after the live ones that revealed the gap), marked ``[from the history]`` in
    text.

    Give its :meth:`on_health`, :meth:`on_alarm`, :meth:`on_token` and :meth:`on_gap` to the
    :class:`FleetWatcher` (:func:`watching`), then :meth:`run`.

    Args:
        emit: where a line goes (stdout).
        as_json: each health message as one line of JSON, exactly as published (no alarm
            events).
        note: where the machine's appearing and going are said (stderr), or None.
    """

    def __init__(self, emit: Callable[[str], None], *, as_json: bool = False,
                 note: Callable[[str], None] | None = None) -> None:
        self.emit = emit
        self.as_json = as_json
        self.note = note
        self._lines: deque[tuple[bool, str]] = deque()
        self._cond = threading.Condition()
        self._tokens = 0

    def _put(self, is_health: bool, line: str) -> None:
        with self._cond:
            self._lines.append((is_health, line))
            self._cond.notify()

    def on_health(self, machine: str, doc: HealthView, text: str,
                  delivery: Delivery = "live") -> None:
        if self.as_json:
            self._put(True, text)
        else:
            mark = "  [from the history]" if delivery == "history" else ""
            self._put(True, health_line(doc) + mark)

    def on_gap(self, gap: Gap) -> None:
        if self.note is not None:
            self.note(gap_line(gap))

    def on_alarm(self, machine: str, event: dict[str, Any]) -> None:
        if not self.as_json:
            self._put(False, f"{time.strftime('%H:%M:%S')} {event.get('message', event)}")

    def on_token(self, machine: str, present: bool) -> None:
        self._tokens += present
        if self.note is not None:
            self.note(f"{machine}: " + ("on the network" if present else
                                        "gone (its daemon stopped, or the link was lost)"))

    def run(self, count: int | None = None, stop: threading.Event | None = None,
            waiting: str | None = None) -> int:
        """Print until ``count`` health messages or ``stop``.

        Args:
            waiting: said aside once if no machine has appeared within 1 s (what is awaited).

        Returns:
            The number of health messages printed.
        """
        printed = 0
        t0 = time.monotonic()
        said_waiting = waiting is None
        while (count is None or printed < count) and not (stop is not None and stop.is_set()):
            with self._cond:
                if not self._lines:
                    self._cond.wait(0.2)
                batch = list(self._lines)
                self._lines.clear()
            for is_health, line in batch:
                if is_health and count is not None and printed >= count:
                    break
                self.emit(line)
                printed += is_health
            if not said_waiting and not self._tokens and time.monotonic() - t0 > 1.0:
                said_waiting = True
                if self.note is not None:
                    self.note(f"waiting for {waiting} (not on the network yet)")
        return printed
