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
* asks every machine for its latest window once (``get(<prefix>/*/health)``), then follows
  ``<prefix>/*/health`` and ``<prefix>/*/alarm``.

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

import json
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from twinwatch._lazy import lazy_module
from twinwatch.errors import WatchError

if TYPE_CHECKING:
    import zenoh
    from rich.console import RenderableType
else:  # imported when a session opens
    zenoh = lazy_module("zenoh")

__all__ = [
    "DEFAULT_CONNECT",
    "Fleet",
    "FleetWatcher",
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

#: Counters that report a loss or a fault (nonzero: shown under data quality), besides every
#: ``driver_*`` counter other than the frames and samples delivered.
PROBLEM_COUNTERS = ("windows_abandoned", "overruns", "numeric_failures", "samples_lost",
                    "bad_samples", "windows_not_stored", "store_waiting", "store_lost",
                    "store_history_lost", "store_errors", "recording_lost", "zenoh_errors")
_DRIVER_TOTALS = ("driver_frames", "driver_samples")

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
    """A JSON object from a Zenoh payload, or None (a non-object or bad JSON is ignored)."""
    try:
        doc = json.loads(payload.to_string())
    except (ValueError, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


# -- the fleet ---------------------------------------------------------------------------------
@dataclass
class _Machine:
    name: str
    token: bool | None = None  # None: never seen a token
    since: float | None = None  # wall time of the last token change seen (None: before us)
    health: dict[str, Any] | None = None
    received: float | None = None  # wall time the last health arrived
    events: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=5))


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

    def health(self, machine: str, doc: Mapping[str, Any]) -> bool:
        """A health message of ``machine`` (the latest, or one published). An older window of
        the same run than the one held (a late reply to the first query) is ignored.

        Returns:
            True if it is now the machine's latest.
        """
        with self._lock:
            m = self._get(machine)
            old = m.health
            if old is not None and old.get("run") == doc.get("run") and isinstance(
                    doc.get("window"), int) and isinstance(old.get("window"), int) and (
                    doc["window"] <= old["window"]):
                return False
            m.health, m.received = dict(doc), self._clock()
        self.changed.set()
        return True

    def alarm(self, machine: str, event: Mapping[str, Any]) -> None:
        """An alarm event of ``machine`` (``<prefix>/<machine>/alarm``)."""
        with self._lock:
            self._get(machine).events.append(dict(event))
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
              "quality": {"nrmse", "model_check", "trusted", "elapsed_ms", "problems"},
              "last_event": {...} | null}, ...]}

        ``state_since_s``: since the watcher saw the token appear or go (null: it was there
        before the watcher started). Parameters that are ``tied`` or ``fixed`` are left out
        (not estimated); ``alarm`` is
        the parameter's alarm level when it has a rule; ``rul_s`` the median remaining useful
        life to the alarm threshold [s] when the message carries a prediction.
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
        h = m.health or {}
        age = None if m.received is None else max(now - m.received, 0.0)
        window_s = _num(h.get("t_end"), 0.0) - _num(h.get("t_start"), 0.0)
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
            "model": h.get("model"),
            "run": h.get("run"),
            "window": h.get("window"),
            "t_start": h.get("t_start"),
            "t_end": h.get("t_end"),
            "parameters": _parameters(h),
            "alarms": {k: {"level": a.get("level"), "since_t": a.get("since_t"),
                           "deviation_pct": a.get("deviation_pct")}
                       for k, a in _dict(h.get("alarms")).items() if isinstance(a, dict)},
            "terms": [{"equation": t.get("equation"), "meaning": t.get("meaning")}
                      for t in _list(h.get("terms")) if isinstance(t, dict)],
            "quality": _quality(h) if m.health is not None else None,
            "last_event": m.events[-1] if m.events else None,
        }


def _dict(x: Any) -> dict[str, Any]:
    return x if isinstance(x, dict) else {}


def _list(x: Any) -> list[Any]:
    return x if isinstance(x, list) else []


def _num(x: Any, default: float | None = None) -> Any:
    return x if isinstance(x, int | float) and not isinstance(x, bool) else default


def _parameters(h: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    alarms = _dict(h.get("alarms"))
    out: dict[str, dict[str, Any]] = {}
    for name, p in _dict(h.get("parameters")).items():
        if not isinstance(p, dict) or p.get("status") in ("tied", "fixed"):
            continue
        rul = _dict(_dict(p.get("rul")).get("alarm"))
        out[name] = {"value": _num(p.get("value")), "unit": p.get("unit"),
                     "nominal": _num(p.get("nominal")),
                     "deviation_pct": _num(p.get("deviation_pct")), "status": p.get("status"),
                     "alarm": _dict(alarms.get(name)).get("level"),
                     "rul_s": _num(rul.get("rul_s")), "rul_status": rul.get("status")}
    return out


def _quality(h: Mapping[str, Any]) -> dict[str, Any]:
    counters = _dict(h.get("counters"))
    problems = {k: v for k, v in counters.items()
                if (k in PROBLEM_COUNTERS or (k.startswith("driver_")
                                              and k not in _DRIVER_TOTALS))
                and isinstance(v, int) and v}
    check = h.get("model_check")
    elapsed = _num(h.get("elapsed_s"))
    return {"nrmse": _num(h.get("nrmse")),
            "model_check": check.get("passed") if isinstance(check, dict) else None,
            "trusted": h.get("trusted"),
            "elapsed_ms": None if elapsed is None else round(elapsed * 1e3, 1),
            "windows_estimated": counters.get("windows_estimated"),
            "problems": problems}


# -- the watcher -------------------------------------------------------------------------------
class FleetWatcher:
    """Feeds a :class:`Fleet` from a Zenoh session: liveliness, health, alarm events, and one
    query for every machine's latest window.

    Args:
        session: an open session (:func:`open_session`); the caller closes it.
        fleet: what to feed.
        prefix: the daemons' ``[zenoh] key_prefix``.
        machine: only this machine (``*``: every machine).
        on_health, on_alarm, on_token: also called (on Zenoh's threads) with the machine and
            a health message that is its new latest (decoded, and its text as published), an
            alarm event, a token's presence.

    Raises:
        WatchError: the prefix or the machine name is malformed.

    Use as a context manager (the subscribers are undeclared on exit).
    """

    def __init__(self, session: zenoh.Session, fleet: Fleet, *, prefix: str = "twinwatch",
                 machine: str = "*",
                 on_health: Callable[[str, dict[str, Any], str], None] | None = None,
                 on_alarm: Callable[[str, dict[str, Any]], None] | None = None,
                 on_token: Callable[[str, bool], None] | None = None) -> None:
        self.session = session
        self.fleet = fleet
        self.prefix = check_prefix(prefix)
        if machine != "*" and (_CHUNKS_RE.match(machine) is None or "/" in machine):
            raise WatchError(f"machine {machine!r}: give the daemon's [machine] name (letters, "
                             "digits, '_', '-', '.') or * for every machine")
        self.machine = machine
        self._subs: list[Any] = []
        self._query: threading.Thread | None = None
        self.queried = threading.Event()
        self.on_health = on_health
        self.on_alarm = on_alarm
        self.on_token = on_token

    def key(self, suffix: str) -> str:
        return f"{self.prefix}/{self.machine}/{suffix}"

    def start(self) -> FleetWatcher:
        """Declare the subscribers (the tokens that exist arrive at once) and ask for the
        latest windows in the background (:attr:`queried` is set once answered)."""
        live = self.session.liveliness()
        self._subs.append(live.declare_subscriber(self.key("alive"), self._on_token,
                                                  history=True))
        self._subs.append(self.session.declare_subscriber(self.key("health"), self._on_health))
        self._subs.append(self.session.declare_subscriber(self.key("alarm"), self._on_alarm))
        self._query = threading.Thread(target=self._ask_latest, name="twinwatch-watch-query",
                                       daemon=True)
        self._query.start()
        return self

    def _ask_latest(self) -> None:
        try:
            for reply in self.session.get(self.key("health"), timeout=5.0):
                if reply.ok is not None:
                    self._health(str(reply.ok.key_expr), reply.ok.payload)
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
        self._health(str(sample.key_expr), sample.payload)

    def _health(self, key: str, payload: Any) -> None:
        machine = _machine_of(key, self.prefix, "health")
        doc = _decode(payload)
        if machine is None or doc is None:
            return
        if self.fleet.health(machine, doc) and self.on_health is not None:
            self.on_health(machine, doc, payload.to_string())

    def _on_alarm(self, sample: zenoh.Sample) -> None:
        machine = _machine_of(str(sample.key_expr), self.prefix, "alarm")
        doc = _decode(sample.payload)
        if machine is None or doc is None:
            return
        self.fleet.alarm(machine, doc)
        if self.on_alarm is not None:
            self.on_alarm(machine, doc)

    def settle(self, timeout: float) -> None:
        """Wait until every machine with a token has reported a window and the latest-window
        query is answered, or ``timeout`` [s] has passed (what ``watch --once`` prints)."""
        deadline = time.monotonic() + timeout
        time.sleep(min(0.2, timeout))  # the tokens that exist arrive within milliseconds
        while time.monotonic() < deadline:
            snap = self.fleet.snapshot()["machines"]
            if self.queried.is_set() and all(m["window"] is not None for m in snap
                                              if m["token"]):
                return
            self.fleet.changed.wait(max(min(0.05, deadline - time.monotonic()), 0.0))
            self.fleet.changed.clear()

    def close(self) -> None:
        """Undeclare the subscribers (idempotent)."""
        subs, self._subs = self._subs, []
        for sub in subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass

    def __enter__(self) -> FleetWatcher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def watching(connect: Sequence[str], mode: Mode, prefix: str, fleet: Fleet,
             machine: str = "*", **callbacks: Any) -> Iterator[FleetWatcher]:
    """A session on ``connect`` and a started :class:`FleetWatcher` on it (``callbacks``: its
    ``on_*``), closed on exit.

    Raises:
        WatchError: see :func:`open_session` and :class:`FleetWatcher`.
    """
    check_prefix(prefix)
    session = open_session(connect, mode)
    try:
        with FleetWatcher(session, fleet, prefix=prefix, machine=machine,
                          **callbacks) as watcher:
            yield watcher
    finally:
        session.close()


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


def health_line(doc: Mapping[str, Any], *, wall: float | None = None) -> str:
    """One line for ``twinwatch tail``: when it arrived, machine, window and its plant time,
    each parameter the window concerns (value, deviation from nominal, ``=`` held, ``~``
    fused), the fit, the model check and the raised alarms.

    Example::

        10:15:31 dc-motor-sim #540 [1080.00-1081.99 s] Ra 5.82987 -10.31 % D 0.00143 +0.02 %
        ... nRMSE 1.6e-05 check ok  ALARM Ra (run 20261122T101530Z-3f9a2c)
    """
    stamp = time.strftime("%H:%M:%S", time.localtime(time.time() if wall is None else wall))
    parts = [stamp, str(doc.get("machine", "?")), f"#{doc.get('window', '?')}"]
    t0, t1 = _num(doc.get("t_start")), _num(doc.get("t_end"))
    if t0 is not None and t1 is not None:
        parts.append(f"[{t0:.2f}-{t1:.2f} s]")
    marks = {"held": "=", "fused": "~"}
    for name, p in _parameters(doc).items():
        parts.append(f"{name}{marks.get(str(p['status']), ' ')}{_value(p['value'])} "
                     f"{_dev(p['deviation_pct'])}")
    q = _quality(doc)
    parts.append(f"nRMSE {q['nrmse']:.1e}" if q["nrmse"] is not None else "nRMSE n/a")
    if q["model_check"] is not None:
        parts.append("check ok" if q["model_check"] else "check FAILED")
    if q["trusted"] is False:
        parts.append("untrusted")
    raised = [(k, a.get("level")) for k, a in _dict(doc.get("alarms")).items()
              if isinstance(a, dict) and a.get("level") in ("warning", "alarm")]
    for lvl in ("alarm", "warning"):
        names = [k for k, v in raised if v == lvl]
        if names:
            parts.append(f" {lvl.upper()} {', '.join(names)}")
    n = len(_list(doc.get("terms")))
    if n:
        parts.append(f"+{n} term{'s' if n > 1 else ''}")
    if q["problems"]:
        parts.append("losses " + ", ".join(f"{k} {v}" for k, v in q["problems"].items()))
    if doc.get("run"):
        parts.append(f"(run {doc['run']})")
    return " ".join(parts)


_LEVEL_STYLE = {"alarm": "bold red", "warning": "yellow", "normal": "green"}
_SHORT = {"estimated": "est", "fused": "fused", "held": "held"}
_STATE_STYLE = {"alive": "green", "stale": "yellow", "gone": "red", "unknown": "dim"}
_STATE_MARK = {"alive": "●", "stale": "◐", "gone": "✕", "unknown": "?"}


def render(snapshot: Mapping[str, Any], *, title: str = "twinwatch fleet") -> RenderableType:
    """The rich table of :meth:`Fleet.snapshot`: one row per machine with its state (alive /
    stale / gone, for how long), its last window (age, index, plant time, run), each parameter's
    value, deviation from nominal, status, alarm level and RUL, the raised alarms and the last
    event, the discovered terms, and the data quality (fit, model check, losses)."""
    from rich.table import Table
    from rich.text import Text

    machines = snapshot.get("machines", [])
    table = Table(title=f"{title}: {len(machines)} machine{'s' if len(machines) != 1 else ''}",
                  title_justify="left", expand=True, show_lines=True)
    for header, ratio, least in (("machine", 2, 8), ("state", 2, 9), ("last window", 3, 24),
                                 ("parameters (vs nominal)", 5, 24), ("alarms", 3, 12),
                                 ("terms (DT'')", 3, 10), ("data quality", 3, 16)):
        table.add_column(header, ratio=ratio, min_width=least, overflow="fold")
    if not machines:
        table.add_row("no machine on the network yet", "", "", "", "", "", "")
    for m in machines:
        state = str(m["state"])
        st = Text(f"{_STATE_MARK.get(state, '?')} {state}", style=_STATE_STYLE.get(state, ""))
        since = m["state_since_s"]
        if since is not None:
            st.append("\n" + (f"for {age(since)}" if m["token"] else f"{age(since)} ago"),
                      style="dim")
        if m["window"] is None:
            last = Text("no window yet", style="dim")
        else:
            last = Text(f"{age(m['last_window_age_s'])} ago\n#{m['window']}")
            if m["t_start"] is not None and m["t_end"] is not None:
                last.append(f" [{m['t_start']:.0f}-{m['t_end']:.0f} s]")
            if m["run"]:
                last.append(f"\nrun {m['run']}", style="dim")
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
        alarms = Text()
        for name, a in m["alarms"].items():
            if a["level"] in ("warning", "alarm"):
                if alarms:
                    alarms.append("\n")
                since = f" since t={a['since_t']:.0f} s" if a["since_t"] is not None else ""
                alarms.append(f"{name} {str(a['level']).upper()}{since}",
                              style=_LEVEL_STYLE[str(a["level"])])
        if not alarms:
            alarms.append("none" if m["alarms"] else "no rules", style="green dim")
        event = m.get("last_event")
        if event and event.get("parameter"):
            alarms.append(f"\nlast: {event.get('parameter')} {event.get('previous')} -> "
                          f"{event.get('level')} at {_num(event.get('t'), 0.0):.0f} s",
                          style="dim")
        terms = Text("\n".join(str(t["equation"]) for t in m["terms"]) or "none",
                     style="" if m["terms"] else "dim")
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
        table.add_row(Text(str(m["machine"]), style="bold"), st, last, params, alarms, terms,
                      quality)
    return table


class Tail:
    """``twinwatch tail``: one line per health message as it arrives (the latest window first,
    when the daemon answers the first query), and, in text, each alarm event; the machine
    appearing and going are noted aside.

    Give its :meth:`on_health`, :meth:`on_alarm` and :meth:`on_token` to the
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

    def on_health(self, machine: str, doc: dict[str, Any], text: str) -> None:
        self._put(True, text if self.as_json else health_line(doc))

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
