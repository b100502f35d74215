"""The sink contract: what every output receives for each processed window, and what the daemon
asks of it.

Modelled on python-can's ``BusABC``: one abstract base, :class:`Sink`, that every output
subclasses, built-in or a plug-in of the entry-point group ``twinwatch.sinks``. A sink declares
its table (:attr:`Sink.config_class`, a :class:`SinkConfig`), how it opens
(:meth:`Sink.from_config`), its :attr:`Sink.role` and what it does with a window
(:meth:`Sink.write`); the reporting and reload hooks default to nothing. A new output, step by
step: docs/extending.md ("Where a new output plugs in").
"""

from __future__ import annotations

import abc
import threading
from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Protocol, Self

from pydantic import Field

from twinwatch._lifecycle import Closeable
from twinwatch._table import StrictTable
from twinwatch.plugins import commented_table

if TYPE_CHECKING:  # annotations only: opening a sink does not load the twin's estimation
    from twinwatch.twin.adaptation import AdaptationResult, TwinState
    from twinwatch.twin.health import HealthMessage, HealthView
    from twinwatch.twin.model import WindowData

__all__ = [
    "AlarmBands",
    "Gate",
    "HistoryPage",
    "HistoryQuery",
    "Outbox",
    "OutboxRow",
    "ProcessedWindow",
    "SharedResources",
    "Role",
    "Sink",
    "SinkConfig",
    "SinkContext",
]

Role = Literal["gate", "publisher", "recorder"]
"""What a sink is to the pipeline: the ``gate`` (stores first; a window it cannot take is not
published), a ``publisher`` (gets only stored windows) or a ``recorder`` (gets every window)."""


@dataclass(frozen=True)
class ProcessedWindow:
    """Everything the sinks need about one processed window.

    Attributes:
        window: the acquisition window (times, channels, index).
        result: what adaptation did (estimate, terms, residuals, discovery).
        health: the window's typed health message (README "The health message"), ``alarms``
            included.
        health_json: ``health`` encoded, once, by the one encoder
            (:meth:`~twinwatch.twin.health.HealthMessage.to_json`): the text every sink writes.
        events: alarm-state changes this window caused (published on ``<machine>/alarm``).
        twin_state: the accepted twin to persist (``TwinAdapter.state()``, with the diagnosis'
            when there is a diagnoser) when this window was trusted or a diagnoser runs, else
            None (the stored twin is kept).
    """

    window: WindowData
    result: AdaptationResult
    health: HealthMessage
    health_json: str
    events: list[dict[str, Any]]
    twin_state: TwinState | None


class HistoryPage(list["HealthView"]):
    """One page of stored health messages (a list, oldest first) and the cursor of the next
    page: ``next_after``, the ``after`` to ask next (by wall time the stamp the gate saved the
    last window with, which the message does not carry), None when the page is empty."""

    def __init__(self, windows: Iterable[HealthView] = (), *,
                 next_after: float | None = None) -> None:
        super().__init__(windows)
        self.next_after = next_after


class HistoryQuery(Protocol):
    """The stored health messages of the running machine in a time range, oldest first (the
    gate's :meth:`Gate.history`, bound to the machine); ``run``: one run's, None every run's;
    ``after``: the paging cursor."""

    def __call__(self, t_from: float | None, t_to: float | None, limit: int | None,
                 by: Literal["plant", "wall"], run: str | None = None,
                 after: float | None = None) -> list[HealthView]: ...


@dataclass(frozen=True)
class AlarmBands:
    """One parameter's ``[alarms]`` thresholds as signed deviations from nominal [%] (None:
    the rule has no such threshold; a symmetric rule gives both sides)."""

    warning_high: float | None = None
    warning_low: float | None = None
    alarm_high: float | None = None
    alarm_low: float | None = None


@dataclass(frozen=True)
class OutboxRow:
    """One stored window as an outbox gives it to a publisher (:meth:`Outbox.pending`).

    Attributes:
        id: the gate's row id (increasing in the order the windows were stored).
        run: the run that stored it (the gate's run id).
        window: the window index within that run.
        wall: when it was stored [s since the epoch].
        doc: the health message, byte for byte as stored (its one encoding).
    """

    id: int
    run: str
    window: int
    wall: float
    doc: str


class Outbox(Protocol):
    """The gate's record of which stored windows one output has delivered (store-and-forward:
    the state database is the outbox). Bound to one output name and one machine; its methods
    may be called from the output's own thread and raise
    :class:`~twinwatch.errors.StoreError` when the gate cannot answer.

    A window is *delivered* once :meth:`ack` recorded it. ``position`` is a row id such that
    every stored window of the machine at or below it is delivered (or was stored before the
    output first opened); the delivered windows above it are recorded one by one.
    """

    @property
    def dropped(self) -> int:
        """Windows the gate's retention deleted before they were delivered (this run)."""
        ...

    def start(self) -> int:
        """The delivered position (at first open: the newest stored window; older history is
        not sent)."""
        ...

    def pending(self, after: int, limit: int) -> list[OutboxRow]:
        """Stored windows above row id ``after`` not delivered yet, oldest first, at most
        ``limit``."""
        ...

    def count(self, position: int) -> int:
        """How many stored windows above ``position`` are not delivered."""
        ...

    def latest_id(self) -> int | None:
        """The newest stored window's row id (None: nothing stored)."""
        ...

    def doc_at_or_before(self, health_id: int) -> str | None:
        """The health message of the newest stored window at or below ``health_id``."""
        ...

    def ack(self, delivered: list[OutboxRow], position: int) -> None:
        """Record ``delivered`` and the new ``position`` in one transaction (idempotent)."""
        ...


@dataclass(frozen=True)
class SinkContext:
    """What a sink needs from the daemon that opens it (not the whole configuration).

    Attributes:
        machine: the machine name (``[machine] name``: one Zenoh key chunk).
        model: the twin model's registry name (``dc_motor``, ...).
        outputs: the twin's outputs, in order (``("ia", "omega", "Va")``).
        parameters: parameter name -> SI unit, in the twin's order.
        base_dir: the configuration file's directory (files the configuration names).
        cwd: the working directory (files the daemon creates: the state database, the
            recording; the unit's ``StateDirectory``).
        history: the stored windows (the gate's history for this machine), or None when no
            gate is open; a publisher may serve it (the Zenoh history query).
        recent_windows: the windows the daemon keeps in memory (``[acquisition] history``):
            the gate keeps as many of those it wrote, to write them again to a database file
            deleted or replaced under it.
        output_units: output -> SI unit (``{"ia": "A", "omega": "rad/s"}``).
        nominal: parameter -> the nominal value the deviations are measured from [SI].
        estimated: the parameters the twin estimates (``[estimation] estimate``), in
            priority order; the others are tied or fixed.
        alarm_bands: parameter -> its ``[alarms]`` thresholds, for an output that draws them
            (empty when alarms are off).
        run: the run id every health message of the daemon carries (one per start of the
            daemon, kept across a reload; empty outside a daemon).
        outbox: the gate's :class:`Outbox` for an output name (``outbox("mqtt")``), or None
            when no gate is open or it keeps none: a publisher that delivers every stored
            window (store-and-forward) asks it again after a reload.
        shared: what the daemons of one process share (a gateway: one Zenoh session for every
            machine whose ``[zenoh]`` session settings are the same), or None (one daemon per
            process: every output opens its own).
    """

    machine: str
    model: str = ""
    outputs: tuple[str, ...] = ()
    parameters: Mapping[str, str] = field(default_factory=dict)
    base_dir: Path = field(default_factory=Path.cwd)
    cwd: Path = field(default_factory=Path.cwd)
    history: HistoryQuery | None = None
    recent_windows: int = 1000
    output_units: Mapping[str, str] = field(default_factory=dict)
    nominal: Mapping[str, float] = field(default_factory=dict)
    estimated: tuple[str, ...] = ()
    alarm_bands: Mapping[str, AlarmBands] = field(default_factory=dict)
    run: str = ""
    outbox: Callable[[str], Outbox | None] | None = None
    shared: SharedResources | None = None


class SharedResources:
    """Connections the daemons of one process share (``twinwatch run DIR``, the gateway): one
    object per key, opened by the first output that asks for it and closed when the last one
    releases it (reference-counted). An output keys it by the settings that make it (a Zenoh
    session: mode, endpoints, TLS, authentication).

    Thread-safe. Opening holds the lock: a second machine asking for the same session waits
    for the first to open it instead of opening a second one on the same port.

    Args:
        directory: the process's working root (the gateway's ``--work-root``): where a shared
            object keeps its own small files (the Sparkplug edge node's ``bdSeq``); None: each
            output's ``SinkContext.cwd``.
    """

    def __init__(self, directory: Path | None = None) -> None:
        self.directory = directory
        self._lock = threading.Lock()
        self._items: dict[str, list[Any]] = {}  # key -> [object, references, close]

    def acquire(self, key: str, open_: Callable[[], Any], close: Callable[[Any], None]) -> Any:
        """The object for ``key``: the open one (one more reference), or ``open_()``'s.

        Raises:
            Whatever ``open_`` raises (nothing is kept then).
        """
        with self._lock:
            item = self._items.get(key)
            if item is None:
                item = self._items[key] = [open_(), 0, close]
            item[1] += 1
            return item[0]

    @staticmethod
    def hold(shared: SharedResources | None, key: str, open_: Callable[[], Any],
             close: Callable[[Any], None]) -> tuple[Any, Callable[[], None]]:
        """The object for ``key`` (:meth:`acquire`; without ``shared``, ``open_()``'s own)
        and the call that lets it go (:meth:`release`; the own one, ``close(obj)``)."""
        if shared is None:
            obj = open_()
            return obj, lambda: close(obj)
        return shared.acquire(key, open_, close), lambda: shared.release(key)

    def release(self, key: str) -> None:
        """Drop one reference to ``key``'s object; the last closes it (``close(obj)``)."""
        with self._lock:
            item = self._items.get(key)
            if item is None:
                return
            item[1] -= 1
            if item[1] > 0:
                return
            del self._items[key]
        item[2](item[0])

    def references(self, key: str) -> int:
        """How many outputs hold ``key``'s object (0: none open)."""
        with self._lock:
            item = self._items.get(key)
            return 0 if item is None else int(item[1])

    def keys(self) -> list[str]:
        """The keys of the open objects."""
        with self._lock:
            return list(self._items)


class SinkConfig(StrictTable):
    """Base of every output's table model (``[state]``, ``[zenoh]``, ``[recording]``,
    ``[outputs.<name>]``): unknown keys are refused (an error naming the full key).

    The hooks below let ``check-config``, ``run`` and the loader check what the table needs
    from the machine without knowing the output; each key they return is relative to the
    table (``tls.root_ca_certificate``) and reported with the table's path in front.
    """

    enabled: bool = Field(True, description="false: the output is not opened")

    def input_files(self) -> dict[str, str]:
        """Files the output reads when it opens (certificates, keys): key -> path. A missing
        or unreadable one is refused before anything is opened. Default: none."""
        return {}

    def secret_input_files(self) -> dict[str, str]:
        """The :meth:`input_files` that hold secrets (private keys, passwords): refused when
        other users can read them. Default: none."""
        return {}

    def inline_secret_keys(self) -> list[str]:
        """Keys holding a secret in the configuration itself: the configuration file is then
        refused when other users can read it. Default: none."""
        return []

    def output_files(self, cwd: Path) -> dict[str, Path]:
        """Files the output creates: key -> absolute path (relative ones against ``cwd``, the
        working directory); their directory must exist and be writable. Default: none."""
        return {}

    def resolve_paths(self, base_dir: Path) -> None:
        """Make the paths of :meth:`input_files` absolute against ``base_dir`` (the
        configuration file's directory; ``~`` expanded). Default: each key of
        :meth:`input_files` read as the dotted key of its value (``tls.ca_certs``,
        ``trusted_clients.0``)."""
        for key, value in self.input_files().items():
            *parents, last = key.split(".")
            obj: Any = self
            for part in parents:
                obj = getattr(obj, part)
            path = Path(value).expanduser()
            resolved = str(path if path.is_absolute() else (base_dir / path).resolve())
            if isinstance(obj, list):
                obj[int(last)] = resolved
            else:
                setattr(obj, last, resolved)

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """What an output on this table holds exclusively while open (the files it locks, the
        endpoints it listens on): a reload that changes its table but not these must wait for
        the running output to release them. Default: the :meth:`output_files`, resolved."""
        return {str(p.resolve()) for p in self.output_files(cwd).values()}


class Sink(Closeable, abc.ABC):
    """Base class of every output (see the module docstring for the contract).

    Subclasses set :attr:`config_class` (and :attr:`role`, :attr:`counter_prefix`,
    :attr:`open_order` where the defaults do not fit) and implement :meth:`from_config`,
    :meth:`write` and :meth:`close` (and set ``self._closed = False`` once open, so an output
    never closed warns).

    Attributes:
        name: the registry name it was opened as (set by :meth:`open`).
        context: the daemon's :class:`SinkContext` (set by :meth:`open`, re-bound by
            :meth:`attach`).
    """

    #: The pydantic model of this output's table.
    config_class: ClassVar[type[SinkConfig]]
    #: What the sink is to the pipeline (see :data:`Role`).
    role: ClassVar[Role] = "publisher"
    #: Prefix of its health counters (``<prefix>_<counter>``); None: the registry name.
    counter_prefix: ClassVar[str | None] = None
    #: Lower opens first. The daemon takes every exclusive resource before it touches a file:
    #: a network port (10) before a file lock (20, 30); plug-ins open after the built-ins.
    open_order: ClassVar[int] = 100

    name: str = ""
    context: SinkContext | None = None
    _reload_key: Hashable | None = None
    #: Windows given to it that it lost for good: a nonzero value makes ``twinwatch run``
    #: exit 74.
    lost: int = 0

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run (or when the output is disabled: never opened)."""
        return self._closed

    # -- opening ------------------------------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def from_config(cls, config: Any, context: SinkContext) -> Self:
        """Open the output.

        Args:
            config: its validated table (a :attr:`config_class` instance).
            context: what it needs from the daemon.

        Raises:
            twinwatch.errors.SinkError: it cannot open (a port in use, a file locked, a broker
                absent); the message says what to change (``twinwatch run`` exits 1 with it).
        """

    @classmethod
    def open(cls, name: str, config: Any, context: SinkContext) -> Self:
        """:meth:`from_config`, then remember the registry name, the context and the
        :meth:`reload_key` it was opened with (what the daemon calls)."""
        sink = cls.from_config(config, context)
        sink.name = name
        sink.context = context
        sink._reload_key = cls.reload_key(config, context)
        return sink

    @classmethod
    def reload_key(cls, config: Any, context: SinkContext) -> Hashable:
        """What the open sink depends on: a reload whose key is equal keeps it open, another
        closes and reopens it. Default: the machine name and the table's values."""
        return (context.machine, _frozen(config.model_dump()))

    def keeps(self, config: Any, context: SinkContext) -> bool:
        """True if a daemon on ``config`` and ``context`` may adopt this open sink."""
        return self._reload_key is not None and (
            self._reload_key == type(self).reload_key(config, context))

    def attach(self, context: SinkContext) -> None:
        """A new daemon adopts this open sink (a reload): use its context from now on."""
        self.context = context

    def detach(self) -> None:
        """The daemon that opened the sink stops (a reload hands it over): until
        :meth:`attach`, nothing of that daemon may be used (the stored history)."""
        if self.context is not None:
            self.context = replace(self.context, history=None, outbox=None)

    # -- the windows --------------------------------------------------------------------------
    @abc.abstractmethod
    def write(self, out: ProcessedWindow) -> bool | None:
        """Take one processed window (called from the adaptation worker, one at a time).

        Returns:
            For the gate: False when it could not take the window (it is then not given to
            the publishers); anything for the others. Never raises for a failing output: a
            failure is counted, logged once and reported by :attr:`problem`.
        """

    @abc.abstractmethod
    def close(self) -> None:
        """Release the output (flush, footer, sessions). Idempotent; the counters stay
        readable for the final accounting."""

    # -- what it reports ----------------------------------------------------------------------
    @property
    def publishes(self) -> bool:
        """It makes windows visible to others: it gets only the windows the gate stored."""
        return self.role == "publisher"

    @property
    def prefix(self) -> str:
        """The prefix of its health counters."""
        return self.counter_prefix or self.name

    def counters(self) -> dict[str, int]:
        """Its counters (without prefix: the daemon publishes them as
        ``<counter_prefix>_<name>``). Default: none."""
        return {}

    @property
    def problem(self) -> str | None:
        """What is degraded right now, one line for systemd's ``STATUS`` and the log; None
        when it works."""
        return None

    @property
    def status(self) -> str | None:
        """What it serves, a part of systemd's ``STATUS`` line (``health on ...``); None."""
        return None

    def summary(self) -> list[str]:
        """Lines for the run's summary: where the windows went, what was lost."""
        return []

    @classmethod
    def sample(cls, table: str) -> str:
        """The commented-out sample of its table for ``twinwatch sample-config``. Default:
        generated from :attr:`config_class`."""
        return commented_table(cls.config_class, table, commented=True)


class Gate(Sink):
    """The gate role: the sink that must take a window before the publishers get it (the
    state store), and what the daemon resumes from at start."""

    role: ClassVar[Role] = "gate"

    #: Where it stores (named in messages: "resumed from <path>").
    path: Path
    #: Windows :meth:`write` could not take when they were processed (hence not published).
    not_stored: int = 0
    #: How many times a corrupt store was moved aside (nothing is resumed from it).
    recovered: int = 0

    #: The last write failed because another process holds the write lock (a backup tool):
    #: the pipeline then holds the windows and publishes them once :meth:`retry` stored them.
    locked: bool = False

    @abc.abstractmethod
    def write(self, out: ProcessedWindow) -> bool:
        """Store the window; False when it waits (it is then not published)."""

    def hold(self, out: ProcessedWindow) -> None:
        """Keep the window to be stored with the next successful write, without trying now
        (the database is :attr:`locked`). Default: :meth:`write` (it waits there)."""
        self.write(out)

    def retry(self) -> bool:
        """Try once more to store the windows waiting (after :attr:`locked`); True when they
        are all stored. Default: False (nothing to retry)."""
        return False

    def save_state(self, machine: str, window: int, t_end: float,
                   twin_state: Mapping[str, Any]) -> bool:
        """Store the twin to resume from (as a window's, ``twin_state``) without a window: a
        daemon's last, at its stop. True if stored. Default: False (nothing stored)."""
        return False

    @abc.abstractmethod
    def load_twin_state(self, machine: str | None = None) -> dict[str, Any] | None:
        """The last accepted twin of ``machine``, as saved, or None."""

    @abc.abstractmethod
    def latest_health(self, machine: str | None = None) -> HealthView | None:
        """The last stored health message of ``machine`` through its typed view
        (:func:`~twinwatch.twin.health.read_health`), or None."""

    @abc.abstractmethod
    def history(self, t_from: float | None = None, t_to: float | None = None,
                limit: int | None = 1000, *, by: Literal["plant", "wall"] = "plant",
                machine: str | None = None, run: str | None = None,
                after: float | None = None) -> list[HealthView]:
        """Stored health messages in a time range (of one run when ``run`` is given), oldest
        first, each through its typed view; ``after``: only those ending strictly after it
        (the paging cursor)."""

    def timeline(self, machine: str, t_from: float | None = None) -> list[HealthView]:
        """``machine``'s stored messages on the time line that ends with its last one, from
        ``t_from`` [s, plant time] on, oldest first: what a restart resumes the trends from.
        Default: the last stored run's windows (the state store follows the line across
        restarts)."""
        last = self.latest_health(machine)
        if last is None or last.t_end is None:
            return []
        out: list[HealthView] = []
        after: float | None = None
        while True:
            page = self.history(t_from, float(last.t_end), 1000, by="plant", machine=machine,
                                run=last.run, after=after)
            out += page
            if len(page) < 1000 or page[-1].t_end is None:
                return out
            after = float(page[-1].t_end)

    def outbox(self, output: str, machine: str) -> Outbox | None:
        """The :class:`Outbox` of ``output`` for ``machine``'s windows; None (the default):
        this gate keeps none."""
        return None


def _frozen(value: Any) -> Hashable:
    """``value`` (JSON-like) as a hashable, comparable key."""
    if isinstance(value, Mapping):
        return tuple(sorted((str(k), _frozen(v)) for k, v in value.items()))
    if isinstance(value, list | tuple):
        return tuple(_frozen(v) for v in value)
    return value  # type: ignore[no-any-return]
