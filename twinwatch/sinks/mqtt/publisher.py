"""The MQTT output itself: the paho client in its own thread, connecting and reconnecting,
delivering the outbox's windows oldest first and recording their acknowledgements (the
delivery contract: docs/architecture.md).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import random
import ssl
import threading
import time
from collections.abc import Hashable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self

from twinwatch._lazy import lazy_module
from twinwatch.errors import PublisherError, StoreError
from twinwatch.sinks.base import (
    Outbox,
    OutboxRow,
    ProcessedWindow,
    Sink,
    SinkContext,
)

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

    from twinwatch.twin.health import HealthView
else:  # imported when the output opens: loading a configuration does not load paho
    mqtt = lazy_module("paho.mqtt.client")
from twinwatch.sinks.mqtt.config import MqttConfig, _check_topic
from twinwatch.sinks.mqtt.encoding import (
    _components,
    _levels,
    _view,
    discovery_payload,
    flat_values,
    ha_device_id,
    reconstructed_events,
)
from twinwatch.sinks.mqtt.outbox import MemoryOutbox, _Window

logger = logging.getLogger(__package__)  # the output's name in its log lines: twinwatch.sinks.mqtt


#: At stop, with windows still to deliver and no connection: the spacing of the connection
#: attempts until ``close_timeout`` [s].
CLOSE_RETRY_S = 1.0

TAKEOVERS = 3
"""Connections lost in a row, each within :data:`TAKEOVER_S` of being made, that name a
client-id conflict (another client connecting with the same id takes the session over)."""

TAKEOVER_S = 10.0
"""A connection lost within this many seconds of being made counts as taken over [s]."""


class MqttPublisher(Sink):
    """The MQTT output (see the module docstring): the built-in ``mqtt``, ``[outputs.mqtt]``.

    Args:
        config: the validated table.
        context: the daemon's context (machine, model, parameters; the gate's outbox).

    Raises:
        PublisherError: a TLS or password file cannot be read, or the TLS setup fails. An
            unreachable broker is not an error: it is tried again in the background while
            the windows wait in the outbox.
    """

    config_class: ClassVar[type[MqttConfig]] = MqttConfig
    counter_prefix: ClassVar[str | None] = "mqtt"
    #: the table's name in messages (``outputs.<table>.<key>``)
    table: ClassVar[str] = "mqtt"
    #: the default client id is ``<client_prefix>-<machine>``
    client_prefix: ClassVar[str] = "twinwatch"

    config: MqttConfig

    def __init__(self, config: MqttConfig, context: SinkContext) -> None:
        self._closed = True  # until fully open
        self.config = config
        self.machine = context.machine
        self.model = context.model
        self.parameters = dict(context.parameters)
        self.client_id = config.client_id or f"{self.client_prefix}-{context.machine}"
        self._topics(context)
        # counters (written by the thread, read by the worker and the main thread)
        self.delivered = 0
        self.pending = 0
        self.errors = 0
        self.connects = 0
        self.disconnects = 0
        self._memory: MemoryOutbox | None = None
        self._outbox: Outbox | None = None
        self._events: dict[str, list[dict[str, Any]]] = {}
        self._events_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._rebind = threading.Event()
        self._connected = False
        self._down_since: float | None = time.monotonic()
        self._unacked_logged = False
        self._connected_at = 0.0
        self._takeovers = 0          # connections lost soon after they were made, in a row
        self._takeover_total = 0
        self._hold_until = 0.0       # no connection attempt before (a client-id conflict)
        self._last_error: str | None = None
        self._refused = False  # the last attempt's CONNACK refused the connection
        self._failing_store = False
        self._inflight: dict[int, _Window] = {}  # health row id -> window
        self._mids: dict[int, int] = {}          # message id -> health row id
        self._acked: list[OutboxRow] = []        # delivered, not yet recorded
        self._position = 0
        self._cursor = 0
        self._latest_doc: HealthView | None = None
        self._previous_levels: dict[str, str] | None = None
        self._discovery_sent: str | None = None
        self._discovery_due: float | None = None
        self._tokens = float(config.inflight)
        self._token_time = time.monotonic()
        self._password = self._read_password()
        if context.outbox is None:  # no state database: the outbox is in memory
            self._memory = MemoryOutbox(config.memory_outbox)
        self.context = context
        self._bind(context)
        self.client = self._make_client()
        self.client.connect_async(config.host, config.port, keepalive=config.keepalive)
        self._thread = threading.Thread(target=self._run, name=f"twinwatch-{self.table}",
                                        daemon=True)
        self._closed = False
        self._thread.start()

    def _topics(self, context: SinkContext) -> None:
        """The topics (set before the client is made; a subclass publishes others)."""
        config = self.config
        self.base = f"{config.topic_prefix}/{context.machine}"
        _check_topic(self.base, "topic_prefix/machine")
        self.health_topic = f"{self.base}/health"
        self.availability_topic = f"{self.base}/availability"
        ha = config.home_assistant
        self.discovery_topic = f"{ha.prefix}/device/{ha_device_id(context.machine)}/config"

    # -- opening ------------------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: MqttConfig, context: SinkContext) -> Self:
        """Open the output; the broker is connected to in the background."""
        return cls(config, context)

    @classmethod
    def reload_key(cls, config: MqttConfig, context: SinkContext) -> Hashable:
        """The table's values and what its files hold now (the password file, the TLS
        certificates and key): a SIGHUP after a password or a certificate was renewed opens
        the output again with them; the same table and files keep it connected. (Before,
        only the table counted: a fixed password file was read again only by a restart.)"""
        files = []
        for key, path in sorted(config.input_files().items()):
            try:
                files.append((key, hashlib.sha256(Path(path).read_bytes()).hexdigest()))
            except OSError as exc:  # the reload's own open names it
                files.append((key, f"unreadable: {exc.strerror or exc}"))
        return (super().reload_key(config, context), tuple(files))

    def _read_password(self) -> str | None:
        cfg = self.config
        if cfg.password_file is None:
            return cfg.password
        try:
            with open(cfg.password_file, encoding="utf-8") as f:
                return f.readline().rstrip("\r\n")
        except OSError as exc:
            raise PublisherError(f"cannot read outputs.{self.table}.password_file = "
                                 f"{cfg.password_file}"
                                 f": {exc.strerror or exc}; fix the path or the file's "
                                 f"permissions (the service user must read it)") from exc

    def _make_client(self) -> mqtt.Client:
        cfg = self.config
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id,
                             clean_session=True, protocol=mqtt.MQTTv311)
        client.connect_timeout = cfg.connect_timeout
        client.max_inflight_messages_set(0)   # the inflight limit is ours, in windows
        client.max_queued_messages_set(0)
        client.enable_logger(logging.getLogger(f"{__name__}.paho"))
        if cfg.username:
            client.username_pw_set(cfg.username, self._password)
        if cfg.tls is not None:
            tls = cfg.tls
            try:
                client.tls_set(ca_certs=tls.ca_certs, certfile=tls.certfile,
                               keyfile=tls.keyfile, cert_reqs=ssl.CERT_REQUIRED,
                               tls_version=ssl.PROTOCOL_TLS_CLIENT)
            except (OSError, ssl.SSLError, ValueError) as exc:
                raise PublisherError(f"outputs.{self.table}.tls: cannot set up TLS: {exc}; "
                                     f"check the certificate and key files") from exc
            client.tls_insecure_set(not tls.verify_hostname)
        client.will_set(self.availability_topic, "offline", qos=1, retain=True)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish
        client.on_message = self._on_message
        return client

    # -- the sink contract --------------------------------------------------------------------
    def attach(self, context: SinkContext) -> None:
        """A reload's daemon adopts the output: its outbox from now on."""
        super().attach(context)
        self._bind(context)

    def detach(self) -> None:
        """The daemon that opened it stops (a reload): nothing new is read from its outbox
        until :meth:`attach`."""
        super().detach()
        self._rebind.set()

    def _bind(self, context: SinkContext) -> None:
        self.context = context
        if context.outbox is not None:
            # The delivered position exists before the output's thread first runs: created
            # there, lazily, it was placed at the newest stored window, and the windows the
            # daemon stored meanwhile were taken for old history and never sent (issue 26;
            # the reload hand-over test lost its first 3 windows in 4 of 8 runs).
            try:
                box = context.outbox(self.name or self.table)
                if box is not None:
                    box.start()
            except StoreError:
                pass  # the thread binds again and reports it (_store_failed)
        self._rebind.set()
        self._wake.set()

    def write(self, out: ProcessedWindow) -> None:
        """The window pipeline's call (a stored window): remember its alarm events, keep it
        in memory when there is no state database, wake the thread. Never blocks on the
        broker."""
        if self._closed:
            return
        if out.events:
            with self._events_lock:
                self._events[out.health_json] = list(out.events)
                while len(self._events) > 1000:
                    self._events.pop(next(iter(self._events)))
        if self._memory is not None:
            self._memory.add(out.health_json, out.health.window)
        self._wake.set()

    def counters(self) -> dict[str, int]:
        """``delivered`` (windows acknowledged by the broker), ``pending`` (stored, not yet
        delivered), ``dropped`` (deleted by the retention, or pushed out of the memory outbox,
        before delivery), ``connects``, ``disconnects``, ``errors`` (publishes refused,
        outbox reads or writes that failed)."""
        return {"delivered": int(self.delivered), "pending": int(self.pending),
                "dropped": self.dropped, "connects": int(self.connects),
                "disconnects": int(self.disconnects), "errors": int(self.errors)}

    @property
    def dropped(self) -> int:
        box = self._outbox
        return int(getattr(box, "dropped", 0) or 0) if box is not None else 0

    @property
    def lost(self) -> int:  # type: ignore[override]
        """Windows that will never be delivered: dropped, and without a state database the
        windows still pending when it closed."""
        lost = self.dropped
        if self._memory is not None and self._closed:
            lost += self.pending
        return lost

    @property
    def connected(self) -> bool:
        """The broker has accepted the connection (CONNACK) and it is not known lost."""
        return self._connected

    @property
    def problem(self) -> str | None:
        out = []
        if not self._connected and self._down_since is not None and not self._closed:
            since = time.monotonic() - self._down_since
            if since > 2 * self.config.connect_timeout or self.connects:
                why = f" ({self._last_error})" if self._last_error else ""
                out.append(f"MQTT broker {self.config.host}:{self.config.port} unreachable for "
                           f"{since:.0f} s{why}: {self.pending} windows pending, sent when it "
                           f"is back")
        unacked = self._unacknowledged()
        if unacked is not None:
            out.append(unacked)
        if self._takeovers >= TAKEOVERS and not self._closed:
            out.append(f"another client uses MQTT client id {self.client_id!r} on "
                       f"{self.config.host}:{self.config.port} ({self._takeover_total} "
                       f"connections taken over): {self.pending} windows pending")
        if self.dropped:
            out.append(f"MQTT: {self.dropped} windows dropped undelivered")
        return "; ".join(out) or None

    def _unacknowledged(self) -> str | None:
        """Connected, but the oldest window handed to the broker waits for its
        acknowledgement longer than ``ack_timeout``: a broker that accepts and never
        acknowledges (issue 26: 36 windows pending for 70 s, STATUS never said DEGRADED, not
        one log line). Logged once per episode."""
        if not self._connected or self._closed:
            self._unacked_logged = False
            return None
        sent = [w.sent for w in list(self._inflight.values())]
        age_s = time.monotonic() - min(sent) if sent else 0.0
        if age_s <= self.config.ack_timeout:
            self._unacked_logged = False
            return None
        line = (f"MQTT broker {self.config.host}:{self.config.port} has not acknowledged "
                f"{len(sent)} windows for {age_s:.0f} s (ack_timeout "
                f"{self.config.ack_timeout:g} s): {self.pending} windows pending")
        if not self._unacked_logged:
            self._unacked_logged = True
            logger.warning("%s; they are kept and sent again on the next connection", line)
        return line

    @property
    def status(self) -> str:
        return f"health on mqtt://{self.config.host}:{self.config.port}/{self.health_topic}"

    def summary(self) -> list[str]:
        where = ("kept in the state database for the next start" if self._memory is None
                 else "lost (no state database)")
        line = (f"health was published on {self.health_topic} (MQTT, broker "
                f"{self.config.host}:{self.config.port}): {self.delivered} windows delivered")
        if self.pending:
            line += f", {self.pending} pending ({where})"
        if self.dropped:
            line += f", {self.dropped} dropped undelivered"
        return [line]

    def close(self) -> None:
        """Deliver what is pending for up to ``close_timeout`` s, record the deliveries,
        publish ``offline`` and disconnect. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=self.config.close_timeout + self.config.connect_timeout + 10)
        if self._thread.is_alive():
            logger.warning("the MQTT thread of %s did not stop in time", self.machine)
        logger.info("MQTT output of %s closed (%d windows delivered, %d pending)",
                    self.machine, self.delivered, self.pending)

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        """The thread: :meth:`_loop`, restarted after an unexpected error (logged with its
        traceback, counted in ``errors``): the output must not die silently."""
        while True:
            try:
                self._loop()
                return
            except Exception:  # noqa: BLE001 - logged; the loop goes on
                self.errors += 1
                logger.exception("the MQTT output of %s failed; it goes on in 1 s",
                                 self.machine)
                if self._stop.wait(1.0):
                    self._finish()
                    return

    def _loop(self) -> None:
        delay = self.config.reconnect_min
        next_attempt = 0.0
        last_poll = 0.0
        last_count = 0.0
        deadline: float | None = None
        close_attempt = 0.0
        while True:
            now = time.monotonic()
            if self._rebind.is_set():
                self._rebind_outbox()
            if self._stop.is_set():  # closing: deliver what is pending, for a while
                if deadline is None:
                    deadline = now + self.config.close_timeout
                if now >= deadline:
                    break
                if not self._connected:
                    # while windows wait: an attempt at once and then every
                    # CLOSE_RETRY_S until the deadline (the backoff may be sleeping through a
                    # broker that is back; a single attempt gave up on a broker started a
                    # second after a short run's end, its backlog left for the next start)
                    if not (self._inflight or self._has_pending()):
                        break
                    if now >= close_attempt:
                        self._connect()
                        close_attempt = time.monotonic() + CLOSE_RETRY_S
                    if not self._connected:
                        self._flush_acks()
                        time.sleep(max(0.0, min(0.2, deadline - time.monotonic())))
                    continue
                if not self._inflight:
                    self._feed(now, all_rows=True)
                    if not self._inflight and not self._has_pending():
                        break
            if not self._connected:
                if now >= next_attempt and now >= self._hold_until:
                    self._connect()
                    if not self._connected:  # capped exponential backoff, +-25 % jitter
                        next_attempt = time.monotonic() + delay * random.uniform(0.75, 1.25)
                        delay = min(2 * delay, self.config.reconnect_max)
                if not self._connected:
                    self._flush_acks()
                    if now - last_count > 1.0:
                        self._count()
                        last_count = now
                    if self._wake.wait(min(0.2, max(next_attempt - time.monotonic(), 0.01))):
                        self._wake.clear()
                        self._count()  # a window stored: one more pending
                        last_count = time.monotonic()
                    continue
            delay = self.config.reconnect_min
            self.client.loop(timeout=0.05)
            if not self._connected:
                continue
            woken = self._wake.is_set()
            self._wake.clear()
            if woken or self._stop.is_set() or now - last_poll > 0.5:
                self._feed(now, all_rows=woken or self._stop.is_set())
                last_poll = now
            if self._discovery_due is not None and now >= self._discovery_due:
                self._send_discovery(force=True)
            self._flush_acks()
            if now - last_count > 1.0:
                self._count()
                last_count = now
        self._finish()

    def _has_pending(self) -> bool:
        """A stored window beyond the ones handed to paho is not delivered yet."""
        box = self._outbox
        try:
            return box is not None and bool(box.pending(self._cursor, 1))
        except StoreError:
            return False

    def _rebind_outbox(self) -> None:
        """Use the outbox of the current context (at start, and after a reload)."""
        self._rebind.clear()
        self._flush_acks()
        ctx = self.context
        getter = ctx.outbox if ctx is not None else None
        box: Outbox | None = self._memory
        try:
            if box is None and getter is not None:
                box = getter(self.name or self.table)
            if box is None:
                self._outbox = None  # detached (a reload): wait for attach()
                return
            if box is self._outbox and not getattr(box, "changed", False):
                return
            position = box.start()
            latest = box.doc_at_or_before(box.latest_id() or position)
        except (StoreError, ValueError) as exc:
            self._store_failed(exc)
            self._rebind.set()
            return
        self._outbox = box
        self._position = position
        self._cursor = max(position, max(self._inflight, default=position))
        if latest is not None and self._latest_doc is None:
            try:
                self._latest_doc = _view(latest)
            except ValueError:
                pass
        self._count()

    def _connect(self) -> None:
        """One connection attempt: TCP (and TLS), CONNECT, then wait for the CONNACK (not
        past a refusal: its socket is closed, and polling it made paho log an error on every
        retry)."""
        self._refused = False
        try:
            self.client.reconnect()
        except (OSError, ssl.SSLError, ValueError) as exc:
            self._unreachable(str(exc) or type(exc).__name__)
            return
        # the CONNACK is waited for while closing too: the closing loop's attempts are how a
        # backlog reaches a broker that is back after the run's end (leaving at once, each
        # attempt's socket was closed by the next before its CONNACK was read: a broker back
        # 25 s after an outage, during the stop, saw a connection a second and got nothing)
        end = time.monotonic() + self.config.connect_timeout
        while not self._connected and not self._refused and time.monotonic() < end:
            if self.client.loop(timeout=0.05) != mqtt.MQTT_ERR_SUCCESS:
                break

    def _unreachable(self, why: str) -> None:
        if self._last_error != why:
            level = logging.WARNING if self._last_error is None else logging.DEBUG
            logger.log(level, "MQTT broker %s:%d unreachable (%s); windows wait in the "
                       "state database and are sent once it answers", self.config.host,
                       self.config.port, why)
        self._last_error = why

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                    properties: Any) -> None:
        if reason.is_failure:
            self._unreachable(f"connection refused: {reason}")
            self._refused = True
            client.disconnect()
            return
        self._connected = True
        self._connected_at = time.monotonic()
        self._down_since = None
        self.connects += 1
        if self._last_error is not None or self.connects > 1:
            logger.warning("MQTT broker %s:%d reached: %d windows pending are sent now",
                           self.config.host, self.config.port, self.pending)
        else:
            logger.info("publishing health of %s on %s (MQTT broker %s:%d)", self.machine,
                        self.health_topic, self.config.host, self.config.port)
        self._last_error = None
        self._announce(client)
        self._wake.set()

    def _announce(self, client: mqtt.Client) -> None:
        """Connected: ``online`` on the availability topic, the discovery (or its clearing)."""
        client.publish(self.availability_topic, "online", qos=1, retain=True)
        ha = self.config.home_assistant
        if ha.discovery:
            client.subscribe(f"{ha.prefix}/status", qos=1)
            self._discovery_sent = None
            self._send_discovery(force=True)
        else:
            client.publish(self.discovery_topic, b"", qos=1, retain=True)

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                       properties: Any) -> None:
        if self._connected and not self._stop.is_set():
            self._taken_over(time.monotonic() - self._connected_at)
        if self._connected:
            self.disconnects += 1
            if self._takeovers >= TAKEOVERS:
                logger.debug("MQTT connection of client id %r taken over again", self.client_id)
            elif not self._stop.is_set():
                logger.warning("MQTT connection to %s:%d lost (%s): %d windows in flight are "
                               "sent again on reconnection", self.config.host, self.config.port,
                               reason, len(self._inflight))
        self._connected = False
        if self._down_since is None:
            self._down_since = time.monotonic()

    def _taken_over(self, lasted: float) -> None:
        """A connection lost ``lasted`` seconds after it was made. The broker closes a
        session when another client connects with the same client id (MQTT 3.1.1: no reason
        given); two daemons with one id take it from each other in turn (issue 26: 78
        take-overs in 45 s, 13 of 39 windows never received, about 80 warnings per daemon and
        no line naming the cause). :data:`TAKEOVERS` such losses in a row, each within
        :data:`TAKEOVER_S` of the connection: named once, and the next attempts wait longer
        (doubling from 5 s to 60 s); a connection that lasts resets it."""
        if lasted > TAKEOVER_S:
            if self._takeovers >= TAKEOVERS:
                logger.warning("MQTT client id %r: the connection has lasted %.0f s, no longer "
                               "taken over", self.client_id, lasted)
            self._takeovers = 0
            return
        self._takeovers += 1
        self._takeover_total += 1
        if self._takeovers < TAKEOVERS:
            return
        if self._takeovers == TAKEOVERS:
            logger.error("another client uses client id %r on MQTT broker %s:%d: the "
                         "connection was taken over %d times in a row, each within %.0f s: "
                         "give each daemon its own [outputs.%s] client_id (or machine "
                         "name); connecting less often meanwhile, windows wait in the outbox",
                         self.client_id, self.config.host, self.config.port, self._takeovers,
                         TAKEOVER_S, self.table)
        hold = min(5.0 * 2 ** (self._takeovers - TAKEOVERS), 60.0) * random.uniform(0.75, 1.25)
        self._hold_until = time.monotonic() + hold

    def _on_message(self, client: mqtt.Client, userdata: Any, msg: Any) -> None:
        """Home Assistant's birth message: send the discovery again after a short random
        delay (its documentation asks for one, to spread the load)."""
        if msg.payload.strip().lower() == b"online":
            self._discovery_due = time.monotonic() + random.uniform(0.0, 1.0)

    def _on_publish(self, client: mqtt.Client, userdata: Any, mid: int, reason: Any,
                    properties: Any) -> None:
        row_id = self._mids.pop(mid, None)
        if row_id is None:
            return
        window = self._inflight.get(row_id)
        if window is None:
            return
        window.mids.discard(mid)
        if not window.mids:
            del self._inflight[row_id]
            self._acked.append(window.row)
            self.delivered += 1

    # -- sending ------------------------------------------------------------------------------
    def _send_discovery(self, force: bool = False) -> None:
        self._discovery_due = None
        ha = self.config.home_assistant
        if not ha.discovery or not self._connected:
            return
        ctx = self.context
        payload = json.dumps(discovery_payload(
            self.machine, self.model, self.base, self._latest_doc, self.parameters,
            qos=self.config.qos, device_name=ha.device_name,
            rules=set(ctx.alarm_bands) if ctx is not None else None,
            nominal=dict(ctx.nominal) if ctx is not None and ctx.nominal else None),
            separators=(",", ":"))
        if payload == self._discovery_sent and not force:
            return
        self.client.publish(self.discovery_topic, payload, qos=1, retain=True)
        self._discovery_sent = payload

    def _feed(self, now: float, all_rows: bool) -> None:
        """Hand paho the next pending windows, within the inflight limit and the rate."""
        self._file_changed()
        box = self._outbox
        if box is None or not self._connected:
            return
        self._tokens = min(float(self.config.inflight),
                           self._tokens + (now - self._token_time) * self.config.rate)
        self._token_time = now
        room = min(self.config.inflight - len(self._inflight), int(self._tokens))
        if room <= 0:
            return
        try:
            rows = box.pending(self._cursor, room)
            latest = box.latest_id() if rows else None
            if rows and self._previous_levels is None:
                before = box.doc_at_or_before(rows[0].id - 1)
                self._previous_levels = _levels(_view(before)) if before else {}
        except (StoreError, ValueError) as exc:
            self._store_failed(exc)
            return
        if self._failing_store:
            logger.info("the MQTT outbox in the state database can be read again")
            self._failing_store = False
        if not all_rows:  # a poll: leave the newest windows to write() (their events)
            settled = time.time() - 1.0
            rows = list(itertools.takewhile(lambda r: r.wall < settled, rows))
        for row in rows:
            if row.id in self._inflight:
                continue
            if not self._send(row, newest=row.id == latest):
                break
            self._cursor = max(self._cursor, row.id)
            self._tokens -= 1.0

    def _send(self, row: OutboxRow, newest: bool) -> bool:
        """Publish one window's messages; False if paho refused (the connection is gone)."""
        qos = self.config.qos
        doc: HealthView | None
        try:
            doc = _view(row.doc)
        except ValueError:
            doc = None
        window = _Window(row)
        messages: list[tuple[str, str | bytes, bool]] = [(self.health_topic, row.doc, False)]
        with self._events_lock:
            events = self._events.pop(row.doc, None)
        if events is None:
            events = reconstructed_events(doc, self._previous_levels or {})
        messages += [(f"{self.base}/alarm", json.dumps(e), False) for e in events]
        if newest:
            messages += [(f"{self.base}/{k}", v, True)
                         for k, v in (flat_values(doc) if doc is not None else {}).items()]
        for topic, payload, retain in messages:
            info = self.client.publish(topic, payload, qos=qos, retain=retain)
            if info.rc != mqtt.MQTT_ERR_SUCCESS and info.rc != mqtt.MQTT_ERR_NO_CONN:
                self.errors += 1
                logger.debug("publishing on %s refused: %s", topic, mqtt.error_string(info.rc))
            window.mids.add(info.mid)
            self._mids[info.mid] = row.id
        self._inflight[row.id] = window
        self._previous_levels = _levels(doc)
        if newest and doc is not None and doc.model_fields_set:
            had = self._latest_doc
            self._latest_doc = doc
            if self.config.home_assistant.discovery and (
                    had is None or _components(had) != _components(doc)):
                self._send_discovery()
        return True

    def _position_now(self) -> int:
        if self._inflight:
            return min(self._inflight) - 1
        return self._cursor

    def _flush_acks(self) -> None:
        """Record the delivered windows and the position in the outbox (a failure keeps them
        for the next try)."""
        box = self._outbox
        if box is None or not self._acked:
            return
        acked, position = list(self._acked), self._position_now()
        try:
            box.ack(acked, position)
        except StoreError as exc:
            self._store_failed(exc)
            return
        del self._acked[:len(acked)]
        self._position = position
        self._count()

    def _count(self) -> None:
        self._file_changed()
        box = self._outbox
        if box is None:
            return
        try:
            stored = box.count(self._position)
        except StoreError as exc:
            self._store_failed(exc)
            return
        self.pending = max(stored - len(self._acked), 0)

    def _file_changed(self) -> bool:
        """The state database's file was deleted, replaced or moved away and the store has
        opened the one at the path (noticed by the store at the next window or read): the
        outbox's row ids are stale. The windows in flight and delivered but not yet recorded
        are forgotten (sent again from the new file: at least once), the outbox is bound
        again: the windows the store wrote to the new file and this output had not
        delivered are pending there (delivery went on silently nowhere before, issue 26)."""
        box = self._outbox
        if box is None or not getattr(box, "changed", False):
            return False
        logger.warning("the MQTT output of %s goes on with the state database's new file "
                       "(%d windows in flight or acknowledged and not yet recorded are sent "
                       "again from it)", self.machine, len(self._inflight) + len(self._acked))
        self._inflight.clear()
        self._mids.clear()
        self._acked.clear()
        self._previous_levels = None
        self._outbox = None
        self._rebind_outbox()
        return True

    def _store_failed(self, exc: BaseException) -> None:
        if self._file_changed():
            return
        self.errors += 1
        if not self._failing_store:
            logger.error("the MQTT output cannot use the outbox in the state database (%s): "
                         "tried again", exc)
            self._failing_store = True

    def _finish(self) -> None:
        """Leaving the thread: record the deliveries, go offline, disconnect."""
        self._flush_acks()
        self._count()
        if self._connected:
            infos = self._farewell()
            end = time.monotonic() + 2.0
            while (self._connected and not all(i.is_published() for i in infos)
                   and time.monotonic() < end):
                self.client.loop(timeout=0.05)
            self.client.disconnect()
        self._connected = False
        self._flush_acks()
        if self._memory is not None:
            self.pending = self._memory.count(self._position_now())

    def _farewell(self) -> list[mqtt.MQTTMessageInfo]:
        """A clean stop, still connected: ``offline`` on the availability topic."""
        return [self.client.publish(self.availability_topic, "offline", qos=1, retain=True)]

    def __repr__(self) -> str:
        state = "closed" if self._closed else ("connected" if self._connected else "connecting")
        return f"MqttPublisher({self.health_topic!r}, {state}, delivered={self.delivered})"
