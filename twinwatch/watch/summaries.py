"""The fleet's summaries (:mod:`twinwatch.twin.summary`) as a Zenoh network shows them
(:class:`SummaryWatcher`); what it holds is read by :mod:`twinwatch.watch.ranking`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Collection, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from twinwatch._lazy import lazy_module
from twinwatch.errors import WatchError
from twinwatch.io.keys import BOX_TOKENS, box_chunk
from twinwatch.watch.ranking import Received
from twinwatch.watch.session import (
    CHUNKS_RE,
    Mode,
    Unreachable,
    check_fleet_prefix,
    decode_health,
    decode_json,
    prefix_base,
    sessions_watched,
)

if TYPE_CHECKING:
    import zenoh

    from twinwatch.twin.health import HealthView
else:  # imported when a session opens
    zenoh = lazy_module("zenoh")

logger = logging.getLogger(__name__)

LATEST_TIMEOUT_S = 20.0
"""How long one ask of every machine's latest summary may take [s] (10 000 replies through
routers on a loaded box take about 2 s: docs/fleet.md)."""

REASK_TIMEOUT_S = 5.0
"""How long an ask of machines back may take [s]; those that did not answer by then are asked
again (:data:`REASK_RETRIES_S`)."""

REASK_QUIET_S = 0.5
"""Machines' tokens that appear again (a router back) are waited for until none came for this
long [s], then the latest summaries are asked once."""

REASK_ONE_BY_ONE = 20
"""At most this many machines back at once are asked one by one (:data:`REASK_BOXES`)."""

REASK_BOXES = 100
"""More machines back at once under a prefix with ``*`` are asked one get per box (the chunks
before the machine's name), for at most this many boxes; more: one get for all."""

REASK_RETRIES_S = (1.0, 2.0, 4.0, 8.0)
"""A machine back that did not answer the ask is asked again after these delays [s], one
after the other: after a router restart its token may reach the watcher before the routers
know its queryable (docs/fleet.md)."""

SWEEP_AFTER_S = 10.0
"""A sweep asks every machine's latest summary again this long [s] after the last token of a
burst came back (a router died or restarted): it recovers the summaries the mesh lost while
recomputing its routes. Not sooner: the replies would cross a mesh still busy (docs/fleet.md)."""

SWEEP_MIN_MACHINES = 20
"""A sweep (:data:`SWEEP_AFTER_S`) follows a burst of at least this many machines back; one
daemon restarted is asked for its own latest only."""

SETTLE_QUIET_S = 1.0
""":meth:`SummaryWatcher.settle`: the fleet counts as complete once no new machine came for
this long [s]."""


def machines_key(prefix: str, machines: str) -> str:
    """``<prefix>/<machines>/summary``, ``machines`` one key-expression chunk: a machine's
    name, ``*`` (every machine), or a pattern such as ``line1-$*`` (every machine whose name
    starts with ``line1-``; ``$*`` is zenoh's wildcard inside a chunk). ``prefix`` may hold
    ``*`` chunks after its first (:func:`~twinwatch.watch.session.check_fleet_prefix`).

    Raises:
        WatchError: the prefix or the pattern is not a key expression (named).
    """
    check_fleet_prefix(prefix)
    key = f"{prefix}/{machines}/summary"
    if not machines or "/" in machines or "**" in machines:
        raise WatchError(f"machines {machines!r}: give one chunk of a key expression: a "
                         "machine's name, * or a pattern like line1-$*")
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise WatchError(f"machines {machines!r}: not a zenoh key expression chunk ({exc}); "
                         "use * for every machine or $* inside a name (line1-$*)") from None
    return key


class SummaryWatcher:
    """Each machine's latest fleet summary on a Zenoh session.

    Args:
        session: an open session (:func:`~twinwatch.watch.session.open_session`); the caller
            closes it.
        prefix: the daemons' ``[zenoh] key_prefix``; ``*`` chunks after the first follow
            several (``twinwatch/*``: the gateways' ``twinwatch/<box>``). A machine is then
            named by its key's chunks after the prefix's plain ones (``gw-line1/m17``).
        machines: one key-expression chunk selecting the machines (:func:`machines_key`).
        clock: wall clock [s since the epoch].
        on_summary: called with the machine and a summary newer than the one held (zenoh's
            thread).
        exact: declare a do-nothing subscriber on each machine's own summary key
            (:meth:`_declare_exact`): fewer route computations at the router delivering to
            this watcher, one more declaration per machine for every router. None (default):
            only when the prefix has no ``*`` (under boxes' chunks they starve a far client:
            docs/fleet.md).

    Thread-safe; use as a context manager (the subscriber is undeclared on exit).

    Raises:
        WatchError: a bad prefix or pattern.
    """

    def __init__(self, session: zenoh.Session, *, prefix: str = "twinwatch",
                 machines: str = "*", clock: Callable[[], float] = time.time,
                 on_summary: Callable[[str, dict[str, Any]], None] | None = None,
                 exact: bool | None = None) -> None:
        self.session = session
        self.prefix = prefix
        self.key = machines_key(prefix, machines)
        self.machines = machines
        self.base = prefix_base(prefix)  # a machine's key is <base>/<its name>/<topic>
        self._clock = clock
        self._lock = threading.Lock()
        self._received: dict[str, Received] = {}
        self.delivered = 0  # summaries received (a repeat of the held one not counted)
        self.changed = threading.Event()
        self.on_summary = on_summary
        self._sub: Any = None
        #: start() began: a summary may come before declare_subscriber returns (a publisher's
        #: matching listener republishes its latest at once), so this, not ``_sub``, says so
        self._started = False
        self._live: Any = None
        self._boxes: Any = None  # the liveliness subscriber on the boxes' tokens
        #: machine -> a subscriber on its own summary key, which does nothing (:meth:`put`)
        self._exact: dict[str, Any] = {}
        self.exact = "*" not in prefix.split("/") if exact is None else exact
        self._last_new = time.monotonic()
        self._token_at = -1e9
        self._ask = threading.Event()
        self._pending: set[str] = set()  # machines whose tokens appeared again
        self._retries: dict[str, int] = {}  # machine back, not answering -> asks repeated
        self._sweep_at: float | None = None  # monotonic time of the next sweep
        self._burst = 0  # machines back since the last ask (tokens that appeared again)
        self._closing = threading.Event()
        self._asker: threading.Thread | None = None
        self.queried = threading.Event()  # the first ask of the latest summaries ended
        self.asked = 0  # asks of the latest summaries that ended
        self.swept = 0  # asks of every machine's latest after machines came back (sweeps)

    def start(self) -> SummaryWatcher:
        """Declare the subscribers (live summaries; the machines' and the boxes' liveliness
        tokens) and start the asking thread (``twinwatch-watch-summaries``: :meth:`_ask_loop`),
        which first asks every machine's latest summary; :attr:`queried` is set once it ended."""
        self._started = True
        self._sub = self.session.declare_subscriber(self.key, self._on_sample)
        alive = self.key.removesuffix("/summary") + "/alive"
        live = self.session.liveliness()
        self._live = live.declare_subscriber(alive, self._on_token)
        self._boxes = live.declare_subscriber(f"{self.prefix}/{BOX_TOKENS}/*/*",
                                              self._on_box_token)
        self._last_new = time.monotonic()
        self._asker = threading.Thread(target=self._ask_loop, name="twinwatch-watch-summaries",
                                       daemon=True)
        self._ask.set()
        self._asker.start()
        return self

    def _on_token(self, sample: zenoh.Sample) -> None:
        """A machine's token: one this watcher holds a summary of that appears again (its
        daemon reached anew: a router back, a restart) is asked for its latest; a new machine's
        first summary comes live. A token that goes marks the machine gone at once
        (:meth:`_gone`): shown stale, not after the summaries' ``stale_after``."""
        machine = str(sample.key_expr)[len(self.base) + 1:-len("/alive")]
        if sample.kind != zenoh.SampleKind.PUT:
            self._gone({machine})
            return
        with self._lock:
            if machine not in self._received:
                return
            self._alive({machine})
        self._back({machine})

    def _gone(self, machines: Collection[str]) -> None:
        """The presence of ``machines`` went (their tokens, or their box's): each held is
        marked gone (:attr:`Received.gone_at`, now) until its token or a summary comes
        again."""
        now = self._clock()
        with self._lock:
            marked = [m for m in machines if (r := self._received.get(m)) is not None
                      and r.gone_at is None]
            for m in marked:
                self._received[m] = dataclasses.replace(self._received[m], gone_at=now)
        if marked:
            logger.debug("%d machines gone (their presence token went): %s", len(marked),
                         ", ".join(sorted(marked)[:5]))
            self.changed.set()

    def _alive(self, machines: Collection[str]) -> None:
        """Their presence is back: no longer gone (the caller holds the lock)."""
        for m in machines:
            r = self._received.get(m)
            if r is not None and r.gone_at is not None:
                self._received[m] = dataclasses.replace(r, gone_at=None)
                self.changed.set()

    def _on_box_token(self, sample: zenoh.Sample) -> None:
        """A box's token (``<base>/<chunks>/@box/<box>/<zid>``, ``[zenoh] presence =
        "box"``): the machines held under those chunks whose summary names that box are back
        (:meth:`_back`) when it appears, gone when it goes. A new box's machines' first
        summaries come live."""
        chunks = str(sample.key_expr)[len(self.base) + 1:].split("/")
        if len(chunks) < 3 or chunks[-3] != BOX_TOKENS:
            return
        where, box = "/".join(chunks[:-3]), chunks[-2]
        with self._lock:
            machines = {m for m, r in self._received.items()
                        if m.rpartition("/")[0] == where
                        and box_chunk(str(r.summary.get("box"))) == box}
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive(machines)
        if sample.kind != zenoh.SampleKind.PUT:
            self._gone(machines)
            return
        if machines:
            logger.debug("box %s back (%s): its %d machines are asked again", box,
                         sample.key_expr, len(machines))
            self._back(machines)

    def _back(self, machines: set[str]) -> None:
        """``machines`` held came back (their tokens or their box's): ask them again once the
        tokens stopped coming, and sweep after a burst of :data:`SWEEP_MIN_MACHINES`."""
        self._token_at = time.monotonic()
        with self._lock:
            self._pending |= machines
            self._burst += len(machines)
            if self._burst >= SWEEP_MIN_MACHINES:
                self._sweep_at = self._token_at + SWEEP_AFTER_S
        self._ask.set()

    def _ask_loop(self) -> None:
        """Ask the latest summaries when :attr:`_ask` is set (at start without waiting; after
        tokens appeared, once they stopped coming for :data:`REASK_QUIET_S`; machines back
        that did not answer, again after :data:`REASK_RETRIES_S`); and every machine's latest
        when a sweep (:data:`SWEEP_AFTER_S`) is due."""
        first = True
        while True:
            with self._lock:
                due = self._sweep_at
            if not self._ask.wait(None if due is None else max(due - time.monotonic(), 0.0)):
                if self._closing.is_set() or not self._sweep():
                    return
                continue
            if self._closing.is_set():
                return
            if not first:  # tokens come in a burst: ask once it ended
                while time.monotonic() - self._token_at < REASK_QUIET_S:
                    if self._closing.wait(REASK_QUIET_S / 2):
                        return
            self._ask.clear()
            with self._lock:
                pending, self._pending = self._pending, set()
                self._burst = 0
            keys = [self.key] if first else self._reask_keys(pending)
            t0 = time.monotonic()
            try:
                answered = self._get_all(keys, LATEST_TIMEOUT_S if first else REASK_TIMEOUT_S)
                self.asked += 1
            except zenoh.ZError:  # the session closed under the query
                return
            finally:
                if first:
                    self.queried.set()
                    self.changed.set()
            again = set() if first else self._retry(pending - answered, answered)
            logger.debug("asked the latest summaries (%s): %d answered in %.1f s; %d machines "
                         "back that did not answer asked again", "all" if first else
                         f"{len(pending)} machines back, {len(keys)} gets", len(answered),
                         time.monotonic() - t0, len(again))
            first = False

    def _sweep(self) -> bool:
        """Ask every machine's latest summary once (a sweep, :data:`SWEEP_AFTER_S`); the
        replies newer than what is held replace it, the others are dropped (:meth:`put`).
        Returns False when the session closed under the query."""
        with self._lock:
            self._sweep_at = None
            delivered = self.delivered
        t0 = time.monotonic()
        try:
            answered = self._get_all([self.key], LATEST_TIMEOUT_S)
        except zenoh.ZError:
            return False
        self.swept += 1
        logger.debug("asked every machine's latest summary again after machines came back: "
                     "%d answered in %.1f s, %d summaries newer than held meanwhile",
                     len(answered), time.monotonic() - t0, self.delivered - delivered)
        return True

    def _get_all(self, keys: list[str], timeout: float) -> set[str]:
        """Send a get (target ALL) on each of ``keys`` at once, hold every summary replied
        until each ended or ``timeout`` [s] passed; returns the machines that answered.

        Raises:
            zenoh.ZError: the session closed.
        """
        answered: set[str] = set()
        lock = threading.Lock()  # replies come on zenoh's threads, also after the deadline
        ended = [threading.Event() for _ in keys]

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                machine = self._on_sample(reply.ok)
                if machine is not None:
                    with lock:
                        answered.add(machine)

        for key, end in zip(keys, ended, strict=True):
            self.session.get(key, zenoh.handlers.Callback(on_reply, end.set),
                             target=zenoh.QueryTarget.ALL, timeout=timeout)
        deadline = time.monotonic() + timeout + 1.0
        for end in ended:
            if not end.wait(max(deadline - time.monotonic(), 0.0)):
                break
        with lock:
            return set(answered)

    def _retry(self, missing: set[str], answered: set[str]) -> set[str]:
        """Ask ``missing`` machines again after the next of :data:`REASK_RETRIES_S` (each at
        most that many times); returns those asked again."""
        for m in answered:
            self._retries.pop(m, None)
        again = {m for m in missing if self._retries.get(m, 0) < len(REASK_RETRIES_S)}
        for m in missing - again:
            self._retries.pop(m, None)
        if not again:
            return again
        delay = REASK_RETRIES_S[min(self._retries.get(m, 0) for m in again)]
        for m in again:
            self._retries[m] = self._retries.get(m, 0) + 1
        with self._lock:
            self._pending |= again
        # the loop asks once REASK_QUIET_S passed since _token_at: delay from now
        self._token_at = max(self._token_at, time.monotonic() + delay - REASK_QUIET_S)
        self._ask.set()
        return again

    def _reask_keys(self, pending: set[str]) -> list[str]:
        """The gets that ask ``pending`` machines' latest summaries again: a few machines
        (:data:`REASK_ONE_BY_ONE`), each its own; more, under a prefix with ``*``, one get per
        box whose machines came back (not every box answering for machines already held);
        else one get for all."""
        if len(pending) <= REASK_ONE_BY_ONE:
            return [f"{self.base}/{m}/summary" for m in sorted(pending)]
        boxes = {m.rpartition("/")[0] for m in pending}
        if "" in boxes or len(boxes) > REASK_BOXES:
            return [self.key]
        return [f"{self.base}/{b}/{self.machines}/summary" for b in sorted(boxes)]

    def _on_sample(self, sample: zenoh.Sample) -> str | None:
        """Hold a summary's sample (:meth:`put`); returns its machine (None: not a summary)."""
        doc = decode_json(sample.payload)
        if doc is None:
            return None
        key = str(sample.key_expr)
        machine = key[len(self.base) + 1:-len("/summary")]
        self.put(machine, doc)
        return machine

    def put(self, machine: str, summary: dict[str, Any]) -> bool:
        """Hold ``summary`` as ``machine``'s latest (``machine`` the name its key gives) unless
        it is older than the one held (the same run, an earlier window) or the same.

        Returns:
            True if it is now the machine's latest.
        """
        if summary.get("machine") != machine:  # named by its key (<box>/<machine>: prefix *)
            summary = {**summary, "machine": machine}
        now = self._clock()
        with self._lock:
            old = self._received.get(machine)
            if old is not None and old.summary.get("run") == summary.get("run"):
                ow, nw = old.summary.get("window"), summary.get("window")
                if isinstance(ow, int) and isinstance(nw, int) and (
                        nw < ow or (nw == ow and old.summary.get("wall") == summary.get(
                            "wall"))):
                    return False
            if old is None:
                self._last_new = time.monotonic()
            self._received[machine] = Received(summary, now)
            self.delivered += 1
            exact = (self.exact and old is None and self._started
                     and machine not in self._exact
                     and not self._closing.is_set())
            if exact:
                self._exact[machine] = None   # declared below, once
        if exact:
            self._declare_exact(machine)
        self.changed.set()
        if self.on_summary is not None:
            self.on_summary(machine, summary)
        return True

    def _declare_exact(self, machine: str) -> None:
        """A subscriber on ``machine``'s own summary key, doing nothing: a Zenoh router
        precomputes and caches the route of a key that has a subscriber on that very key, and
        computes the route of every other put anew, matching it against every key it holds
        (``Resource::get_matches``, zenoh PR #1717; the cost: docs/fleet.md). The wildcard
        subscriber still finds new machines and receives every summary once."""
        try:
            sub = self.session.declare_subscriber(f"{self.base}/{machine}/summary",
                                                  lambda sample: None)
        except zenoh.ZError:  # the session closed meanwhile
            return
        with self._lock:
            closing = self._closing.is_set()
            if not closing:
                self._exact[machine] = sub
        if closing:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()

    @property
    def received(self) -> dict[str, Received]:
        """machine -> its latest summary and when it arrived (a copy)."""
        with self._lock:
            return dict(self._received)

    def __len__(self) -> int:
        with self._lock:
            return len(self._received)

    def settle(self, timeout: float, *, expected: int | None = None,
               quiet: float = SETTLE_QUIET_S) -> None:
        """Wait until ``expected`` machines are held, or (without it) no new machine came for
        ``quiet`` [s] after the first, or ``timeout`` [s] passed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            n = len(self)
            if expected is not None and n >= expected:
                return
            if expected is None and n and self.queried.is_set() and (
                    time.monotonic() - self._last_new >= quiet):
                return
            if expected is None and not n and self.queried.is_set():
                return  # nobody answered
            self.changed.wait(min(0.05, max(deadline - time.monotonic(), 0.0)))
            self.changed.clear()

    def health(self, machine: str, timeout: float = 5.0) -> HealthView | None:
        """``machine``'s full health: its latest window, asked from its daemon
        (``get(<prefix>/<machine>/health)``) only now; None when nothing answered.

        Raises:
            WatchError: ``machine`` is not a machine's name.
        """
        if CHUNKS_RE.match(machine) is None:
            raise WatchError(f"machine {machine!r}: give one machine's name")
        for reply in self.session.get(f"{self.base}/{machine}/health", timeout=timeout,
                                      target=zenoh.QueryTarget.ALL):
            if reply.ok is not None:
                got = decode_health(reply.ok.payload)
                if got is not None:
                    return got[0]
        return None

    def close(self) -> None:
        """Undeclare the subscribers and stop asking (idempotent)."""
        self._closing.set()
        self._ask.set()
        subs = [self._boxes, self._live, self._sub]
        self._boxes = self._live = self._sub = None
        with self._lock:
            exact, self._exact = self._exact, {}
        for sub in [*subs, *exact.values()]:
            if sub is not None:
                with contextlib.suppress(zenoh.ZError):
                    sub.undeclare()
        asker, self._asker = self._asker, None
        if asker is not None:
            asker.join(timeout=LATEST_TIMEOUT_S + 1)

    def __enter__(self) -> SummaryWatcher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


class Summaries:
    """Several :class:`SummaryWatcher` (one per endpoint in client mode) read as one."""

    def __init__(self, watchers: list[SummaryWatcher]) -> None:
        self.watchers = watchers

    @property
    def received(self) -> dict[str, Received]:
        """machine -> its latest summary over every watcher (the one that arrived last)."""
        out: dict[str, Received] = {}
        for w in self.watchers:
            for m, r in w.received.items():
                if m not in out or r.at > out[m].at:
                    out[m] = r
        return out

    def settle(self, timeout: float, *, expected: int | None = None,
               quiet: float = SETTLE_QUIET_S) -> None:
        """:meth:`SummaryWatcher.settle` on each, within one ``timeout`` [s]."""
        deadline = time.monotonic() + timeout
        for w in self.watchers:
            w.settle(max(0.0, deadline - time.monotonic()), expected=expected, quiet=quiet)

    def wait(self, timeout: float) -> None:
        """Wait until a summary arrives or ``timeout`` [s] passed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(w.changed.is_set() for w in self.watchers):
                break
            time.sleep(min(0.05, max(deadline - time.monotonic(), 0.0)))
        for w in self.watchers:
            w.changed.clear()

    def health(self, machine: str, timeout: float = 5.0) -> HealthView | None:
        """:meth:`SummaryWatcher.health` through each watcher until one answers."""
        for w in self.watchers:
            got = w.health(machine, timeout)
            if got is not None:
                return got
        return None


@contextmanager
def following(connect: Sequence[str], mode: Mode, prefix: str, machines: str = "*", *,
              optional: Collection[str] = (),
              on_skip: Callable[[str, str], None] | None = None) -> Iterator[Summaries]:
    """Sessions on ``connect`` (one per endpoint in client mode, as
    :func:`~twinwatch.watch.subscription.watching`) and a started :class:`SummaryWatcher` on
    each, closed on exit.

    Raises:
        WatchError: a bad endpoint, prefix or pattern; nothing answers (``optional``
            endpoints may be skipped, each told to ``on_skip``).
    """
    machines_key(prefix, machines)
    with sessions_watched(
            connect, mode,
            lambda session: SummaryWatcher(session, prefix=prefix, machines=machines),
            optional=optional, on_skip=on_skip, unreachable=Unreachable) as watchers:
        yield Summaries(watchers)
