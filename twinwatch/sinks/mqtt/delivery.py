"""An MQTT output's delivery over its outbox, as the MQTT and the Sparkplug B outputs both keep
it: which stored windows were handed to the broker, which it acknowledged, which are pending,
at most ``inflight`` unacknowledged and ``rate`` a second (docs/architecture.md). Everything
here runs in the output's thread.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import threading
import time
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Self

from twinwatch._forward import Forward
from twinwatch.errors import StoreError
from twinwatch.sinks.base import Outbox, OutboxRow, ProcessedWindow, Sink, SinkContext
from twinwatch.sinks.mqtt.encoding import health_view, levels
from twinwatch.sinks.mqtt.outbox import MemoryOutbox, Window

if TYPE_CHECKING:
    from twinwatch.sinks.mqtt.config import MqttConnectionConfig
    from twinwatch.twin.health import HealthView

logger = logging.getLogger(__package__)

__all__ = ["DeliveringSink", "Delivery"]


class Delivery:
    """The delivery state of one output over its outbox.

    Args:
        config: the output's table (``inflight``, ``rate``, ``ack_timeout``,
            ``memory_outbox``).
        in_memory: no state database: the outbox is a :class:`MemoryOutbox`.
        outbox_name: the output's name, the outbox's key in the state database.
        send: hands one row's messages to paho (``newest``: the newest stored window); False
            when paho refused (the connection is gone).
        ready: the session may send now (connected, and for Sparkplug born).
        machine: the machine's name, in the log.

    Attributes:
        delivered: windows acknowledged by the broker.
        pending: windows stored and not delivered yet.
        errors: publishes refused, outbox reads or writes that failed.
        inflight: health row id -> the window handed to paho, not acknowledged yet.
        latest_doc: the newest window stored or sent, typed (None before one).
        previous_levels: the alarm levels of the window before the next one sent (None: to
            read from the outbox).
        rebind: set when the outbox is to be bound again (at start, after a reload).
    """

    def __init__(self, config: MqttConnectionConfig, *, in_memory: bool,
                 outbox_name: Callable[[], str], send: Callable[[OutboxRow, bool], bool],
                 ready: Callable[[], bool], machine: str) -> None:
        self.config = config
        self.memory = MemoryOutbox(config.memory_outbox) if in_memory else None
        self._outbox_name = outbox_name
        self._send = send
        self._ready = ready
        self.machine = machine
        self.context: SinkContext | None = None
        self.delivered = 0
        self.pending = 0
        self.errors = 0
        self.outbox: Outbox | None = None
        self.rebind = threading.Event()
        self.inflight: dict[int, Window] = {}  # health row id -> window
        self.mids: dict[int, int] = {}          # message id -> health row id
        self.acked: list[OutboxRow] = []        # delivered, not yet recorded
        self.position = 0
        self.cursor = 0
        self.latest_doc: HealthView | None = None
        self.previous_levels: dict[str, str] | None = None
        self._tokens = float(config.inflight)
        self._token_time = time.monotonic()
        self._failing_store = False
        self._unacked_logged = False

    @property
    def dropped(self) -> int:
        """Windows deleted by the retention, or pushed out of the memory outbox, undelivered."""
        box = self.outbox
        return int(getattr(box, "dropped", 0) or 0) if box is not None else 0

    def lost(self, closed: bool) -> int:
        """Windows that will never be delivered: dropped, and without a state database the
        windows still pending once ``closed``."""
        return self.dropped + (self.pending if self.memory is not None and closed else 0)

    def bind(self, context: SinkContext) -> None:
        """Deliver from ``context``'s outbox; the thread binds it (:meth:`rebind_outbox`)."""
        self.context = context
        if context.outbox is not None:
            # The delivered position exists before the output's thread first runs (created
            # there, the windows stored meanwhile would be taken for old history, never sent)
            try:
                box = context.outbox(self._outbox_name())
                if box is not None:
                    box.start()
            except StoreError:
                pass  # the thread binds again and reports it (store_failed)
        self.rebind.set()

    def rebind_outbox(self) -> None:
        """Use the outbox of the current context (at start, and after a reload)."""
        self.rebind.clear()
        self.flush_acks()
        ctx = self.context
        getter = ctx.outbox if ctx is not None else None
        box: Outbox | None = self.memory
        try:
            if box is None and getter is not None:
                box = getter(self._outbox_name())
            if box is None:
                self.outbox = None  # detached (a reload): wait for attach()
                return
            if box is self.outbox and not getattr(box, "changed", False):
                return
            position = box.start()
            latest = box.doc_at_or_before(box.latest_id() or position)
        except (StoreError, ValueError) as exc:
            self.store_failed(exc)
            self.rebind.set()
            return
        self.outbox = box
        self.position = position
        self.cursor = max(position, max(self.inflight, default=position))
        if latest is not None and self.latest_doc is None:
            try:
                self.latest_doc = health_view(latest)
            except ValueError:
                pass
        self.count()

    def has_pending(self) -> bool:
        """A stored window beyond the ones handed to paho is not delivered yet."""
        box = self.outbox
        try:
            return box is not None and bool(box.pending(self.cursor, 1))
        except StoreError:
            return False

    def feed(self, now: float, all_rows: bool) -> None:
        """Hand paho the next pending windows, within the inflight limit and the rate
        (``all_rows`` false: leave the newest second's windows to the window's own wake-up,
        which carries its alarm events)."""
        self.file_changed()
        box = self.outbox
        if box is None or not self._ready():
            return
        self._tokens = min(float(self.config.inflight),
                           self._tokens + (now - self._token_time) * self.config.rate)
        self._token_time = now
        room = min(self.config.inflight - len(self.inflight), int(self._tokens))
        if room <= 0:
            return
        try:
            rows = box.pending(self.cursor, room)
            latest = box.latest_id() if rows else None
            if rows and self.previous_levels is None:
                before = box.doc_at_or_before(rows[0].id - 1)
                self.previous_levels = levels(health_view(before)) if before else {}
        except (StoreError, ValueError) as exc:
            self.store_failed(exc)
            return
        if self._failing_store:
            logger.info("the MQTT outbox in the state database can be read again")
            self._failing_store = False
        if not all_rows:  # a poll: leave the newest windows to write() (their events)
            settled = time.time() - 1.0
            rows = list(itertools.takewhile(lambda r: r.wall < settled, rows))
        for row in rows:
            if row.id in self.inflight:
                continue
            if not self._send(row, row.id == latest):
                break
            self.cursor = max(self.cursor, row.id)
            self._tokens -= 1.0

    def sent(self, row: OutboxRow, mids: list[int]) -> None:
        """``row`` handed to paho as the messages ``mids``: in flight until each is
        acknowledged (none: delivered at once, nothing to send)."""
        window = Window(row)
        window.mids.update(mids)
        for mid in mids:
            self.mids[mid] = row.id
        self.inflight[row.id] = window
        if not mids:
            del self.inflight[row.id]
            self.acked.append(row)

    def acknowledged(self, mid: int) -> None:
        """paho's acknowledgement of message ``mid``: its window is delivered with the last."""
        row_id = self.mids.pop(mid, None)
        window = self.inflight.get(row_id) if row_id is not None else None
        if window is None:
            return
        window.mids.discard(mid)
        if not window.mids:
            del self.inflight[window.row.id]
            self.acked.append(window.row)
            self.delivered += 1

    def position_now(self) -> int:
        """The outbox position up to which every window is delivered."""
        if self.inflight:
            return min(self.inflight) - 1
        return self.cursor

    def reset_connection(self) -> None:
        """A new connection that does not resend paho's messages: the windows in flight are
        sent again from the outbox."""
        self.flush_acks()
        position = self.position_now()
        self.inflight.clear()
        self.mids.clear()
        self.cursor = position

    def flush_acks(self) -> None:
        """Record the delivered windows and the position in the outbox (a failure keeps them
        for the next try)."""
        box = self.outbox
        if box is None or not self.acked:
            return
        acked, position = list(self.acked), self.position_now()
        try:
            box.ack(acked, position)
        except StoreError as exc:
            self.store_failed(exc)
            return
        del self.acked[:len(acked)]
        self.position = position
        self.count()

    def count(self) -> None:
        """Count the windows pending (stored beyond the position, not acknowledged)."""
        self.file_changed()
        box = self.outbox
        if box is None:
            return
        try:
            stored = box.count(self.position)
        except StoreError as exc:
            self.store_failed(exc)
            return
        self.pending = max(stored - len(self.acked), 0)

    def finish(self) -> None:
        """The output stops: record the deliveries; in memory, what stays pending."""
        self.flush_acks()
        self.count()
        if self.memory is not None:
            self.pending = self.memory.count(self.position_now())

    def file_changed(self) -> bool:
        """The store has opened a new database file: the outbox's row ids are stale. The
        windows in flight and delivered but not yet recorded are forgotten (sent again from
        the new file: at least once), and the outbox is bound again."""
        box = self.outbox
        if box is None or not getattr(box, "changed", False):
            return False
        logger.warning("the MQTT output of %s goes on with the state database's new file "
                       "(%d windows in flight or acknowledged and not yet recorded are sent "
                       "again from it)", self.machine, len(self.inflight) + len(self.acked))
        self.inflight.clear()
        self.mids.clear()
        self.acked.clear()
        self.previous_levels = None
        self.outbox = None
        self.rebind_outbox()
        return True

    def store_failed(self, exc: BaseException) -> None:
        """The outbox cannot be read or written: counted, said once, tried again."""
        if self.file_changed():
            return
        self.errors += 1
        if not self._failing_store:
            logger.error("the MQTT output cannot use the outbox in the state database (%s): "
                         "tried again", exc)
            self._failing_store = True

    def unacknowledged(self, broker: str, connected: bool) -> str | None:
        """Connected, but the oldest window handed to the broker waits for its
        acknowledgement longer than ``ack_timeout``. Logged once per episode."""
        if not connected:
            self._unacked_logged = False
            return None
        sent = [w.sent for w in list(self.inflight.values())]
        age_s = time.monotonic() - min(sent) if sent else 0.0
        if age_s <= self.config.ack_timeout:
            self._unacked_logged = False
            return None
        line = (f"MQTT broker {broker} has not acknowledged {len(sent)} windows for "
                f"{age_s:.0f} s (ack_timeout {self.config.ack_timeout:g} s): {self.pending} "
                f"windows pending")
        if not self._unacked_logged:
            self._unacked_logged = True
            logger.warning("%s; they are kept and sent again on the next connection", line)
        return line


class DeliveringSink(Sink):
    """What an output that delivers through a :class:`Delivery` answers (the MQTT and the
    Sparkplug B outputs). A subclass sets :attr:`delivery`, ``_closed`` and :attr:`wake`; its
    close sets :attr:`leave_by`."""

    delivery: Delivery
    _closed: bool
    wake: threading.Event
    leave_by: float | None = None  # closing: deliver until then (monotonic)

    def attach(self, context: SinkContext) -> None:
        """Deliver from ``context``'s outbox."""
        super().attach(context)
        self.delivery.bind(context)
        self.wake.set()

    def write(self, out: ProcessedWindow) -> None:
        """Wake the thread (keep the window in memory without a state database). Never
        blocks on the broker."""
        if self._closed:
            return
        if self.delivery.memory is not None:
            self.delivery.memory.add(out.health_json, out.health.window)
        self.wake.set()

    def has_undelivered(self) -> bool:
        """Windows in flight or pending in the outbox."""
        return bool(self.delivery.inflight) or self.delivery.has_pending()

    @classmethod
    def from_config(cls, config: Any, context: SinkContext) -> Self:
        """Open the output; the broker is connected to in the background."""
        return cls(config, context)  # type: ignore[call-arg]

    @classmethod
    def reload_key(cls, config: Any, context: SinkContext) -> Hashable:
        """The table's values and what its files hold now: a SIGHUP after a password or a
        certificate was renewed opens the output again with them."""
        files = []
        for key, path in sorted(config.input_files().items()):
            try:
                files.append((key, hashlib.sha256(Path(path).read_bytes()).hexdigest()))
            except OSError as exc:  # the reload's own open names it
                files.append((key, f"unreadable: {exc.strerror or exc}"))
        return (super().reload_key(config, context), tuple(files))

    def detach(self) -> None:
        """Nothing new is read from the outbox until :meth:`attach`."""
        super().detach()
        self.delivery.rebind.set()

    def _with_pending(self, line: str, where: str = "") -> str:
        """A summary ``line`` with the windows pending (and ``where`` they are kept) and those
        dropped undelivered, when there are any."""
        if self.pending:
            line += f", {self.pending} pending{where}"
        if self.dropped:
            line += f", {self.dropped} dropped undelivered"
        return line

    delivered: Forward[int] = Forward("delivery.delivered", "Windows acknowledged by the broker.")
    pending: Forward[int] = Forward("delivery.pending", "Windows stored and not delivered yet.")
    dropped: Forward[int] = Forward(
        "delivery.dropped", "Windows deleted by the retention, or pushed out of the memory "
        "outbox, undelivered.")

    @property
    def lost(self) -> int:  # type: ignore[override]
        """:meth:`Delivery.lost`."""
        return self.delivery.lost(self._closed)
