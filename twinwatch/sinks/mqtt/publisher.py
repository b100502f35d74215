"""The MQTT output itself: the paho client in its own thread (an :class:`MqttSession`),
connecting and reconnecting, delivering the outbox's windows oldest first and recording their
acknowledgements (a :class:`Delivery`; the delivery contract: docs/architecture.md).
"""

from __future__ import annotations

import json
import logging
import random
import threading
import time
from typing import TYPE_CHECKING, Any, ClassVar

from twinwatch.sinks.base import OutboxRow, ProcessedWindow, SinkContext
from twinwatch.sinks.mqtt.config import MqttConfig, check_topic
from twinwatch.sinks.mqtt.delivery import DeliveringSink, Delivery
from twinwatch.sinks.mqtt.encoding import (
    components,
    discovery_payload,
    flat_values,
    ha_device_id,
    health_view,
    levels,
    reconstructed_events,
)
from twinwatch.sinks.mqtt.session import CLOSE_RETRY_S, MqttSession, mqtt, read_password

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView

logger = logging.getLogger(__package__)  # the output's name in its log lines: twinwatch.sinks.mqtt


class MqttPublisher(DeliveringSink):
    """The MQTT output (see the module docstring): the built-in ``mqtt``, ``[outputs.mqtt]``.

    Args:
        config: the validated table.
        context: the daemon's context (machine, model, parameters; the gate's outbox).

    Attributes:
        session: the connection to the broker (:class:`MqttSession`).
        delivery: the windows delivered and pending (:class:`Delivery`).

    Raises:
        PublisherError: a TLS or password file cannot be read, or the TLS setup fails. An
            unreachable broker is not an error: it is tried again in the background while
            the windows wait in the outbox.
    """

    config_class: ClassVar[type[MqttConfig]] = MqttConfig
    counter_prefix: ClassVar[str | None] = "mqtt"

    config: MqttConfig

    def __init__(self, config: MqttConfig, context: SinkContext) -> None:
        self._closed = True  # until fully open
        self.config = config
        self.machine = context.machine
        self.model = context.model
        self.parameters = dict(context.parameters)
        self.base = f"{config.topic_prefix}/{context.machine}"
        check_topic(self.base, "topic_prefix/machine")
        self.health_topic = f"{self.base}/health"
        self.availability_topic = f"{self.base}/availability"
        ha = config.home_assistant
        self.discovery_topic = f"{ha.prefix}/device/{ha_device_id(context.machine)}/config"
        self._events: dict[str, list[dict[str, Any]]] = {}
        self._events_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._discovery_sent: str | None = None
        self._discovery_due: float | None = None
        self.delivery = Delivery(config, in_memory=context.outbox is None,
                                 outbox_name=lambda: self.name or "mqtt", send=self._send,
                                 ready=lambda: self.session.connected, machine=self.machine)
        self.context = context
        self._bind(context)
        self.session = MqttSession(
            config, self, table="mqtt",
            client_id=config.client_id or f"twinwatch-{context.machine}",
            password=read_password(config, "mqtt"),
            will=lambda: (self.availability_topic, "offline", True), log=logger,
            paho_log=f"{__name__}.paho", stopping=self._stop.is_set,
            conflict="give each daemon its own [outputs.mqtt] client_id (or machine name); "
                     "connecting less often meanwhile, windows wait in the outbox")
        self.client_id = self.session.client_id
        self.session.client.connect_async(config.host, config.port, keepalive=config.keepalive)
        self._thread = threading.Thread(target=self._run, name="twinwatch-mqtt", daemon=True)
        self._closed = False
        self._thread.start()

    # -- the session's calls ------------------------------------------------------------------
    def session_up(self, client: mqtt.Client, again: bool) -> None:
        """Connected: ``online`` on the availability topic, the discovery (or its clearing)."""
        if again:
            logger.warning("MQTT broker %s reached: %d windows pending are sent now",
                           self.session.broker, self.delivery.pending)
        else:
            logger.info("publishing health of %s on %s (MQTT broker %s)", self.machine,
                        self.health_topic, self.session.broker)
        client.publish(self.availability_topic, "online", qos=1, retain=True)
        ha = self.config.home_assistant
        if ha.discovery:
            client.subscribe(f"{ha.prefix}/status", qos=1)
            self._discovery_sent = None
            self._send_discovery(force=True)
        else:
            client.publish(self.discovery_topic, b"", qos=1, retain=True)
        self._wake.set()

    def session_down(self) -> bool:
        """A lost connection is never our own doing: False."""
        return False

    def session_refused(self, reason: Any) -> None:
        """Nothing to add to the session's line."""

    def in_flight(self) -> str:
        """``3 windows in flight``."""
        return f"{len(self.delivery.inflight)} windows in flight"

    def on_message(self, client: mqtt.Client, userdata: Any, msg: Any) -> None:
        """Home Assistant's birth message: send the discovery again after a short random
        delay (its documentation asks for one, to spread the load)."""
        if msg.payload.strip().lower() == b"online":
            self._discovery_due = time.monotonic() + random.uniform(0.0, 1.0)

    def on_publish(self, client: mqtt.Client, userdata: Any, mid: int, reason: Any,
                   properties: Any) -> None:
        """paho's acknowledgement of a message: its window is delivered with the last."""
        self.delivery.acknowledged(mid)

    # -- the sink contract --------------------------------------------------------------------
    def attach(self, context: SinkContext) -> None:
        """A reload's daemon adopts the output: its outbox from now on."""
        super().attach(context)
        self._bind(context)

    def _bind(self, context: SinkContext) -> None:
        self.context = context
        self.delivery.bind(context)
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
        if self.delivery.memory is not None:
            self.delivery.memory.add(out.health_json, out.health.window)
        self._wake.set()

    def counters(self) -> dict[str, int]:
        """``delivered`` (windows acknowledged by the broker), ``pending`` (stored, not yet
        delivered), ``dropped`` (deleted by the retention, or pushed out of the memory outbox,
        before delivery), ``connects``, ``disconnects``, ``errors`` (publishes refused,
        outbox reads or writes that failed)."""
        d, s = self.delivery, self.session
        return {"delivered": int(d.delivered), "pending": int(d.pending),
                "dropped": d.dropped, "connects": int(s.connects),
                "disconnects": int(s.disconnects), "errors": int(d.errors)}

    @property
    def connected(self) -> bool:
        """The broker has accepted the connection (CONNACK) and it is not known lost."""
        return self.session.connected

    @property
    def problem(self) -> str | None:
        out = [] if self._closed else self.session.problems(self.pending)
        unacked = self.delivery.unacknowledged(self.session.broker,
                                               self.connected and not self._closed)
        if unacked is not None:
            out.append(unacked)
        if self.dropped:
            out.append(f"MQTT: {self.dropped} windows dropped undelivered")
        return "; ".join(out) or None

    @property
    def status(self) -> str:
        return f"health on mqtt://{self.config.host}:{self.config.port}/{self.health_topic}"

    def summary(self) -> list[str]:
        where = ("kept in the state database for the next start" if self.delivery.memory is None
                 else "lost (no state database)")
        line = (f"health was published on {self.health_topic} (MQTT, broker "
                f"{self.config.host}:{self.config.port}): {self.delivered} windows delivered")
        return [self._with_pending(line, f" ({where})")]

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
                self.delivery.errors += 1
                logger.exception("the MQTT output of %s failed; it goes on in 1 s",
                                 self.machine)
                if self._stop.wait(1.0):
                    self._finish()
                    return

    def _loop(self) -> None:
        session = self.session
        self._last_poll = self._last_count = self._close_attempt = 0.0
        deadline: float | None = None
        while True:
            now = time.monotonic()
            if self.delivery.rebind.is_set():
                self.delivery.rebind_outbox()
            if self._stop.is_set():  # closing: deliver what is pending, for a while
                if deadline is None:
                    deadline = now + self.config.close_timeout
                step = self._closing(now, deadline)
                if step == "done":
                    break
                if step == "wait":
                    continue
            if not session.connected and not self._offline(now):
                continue
            session.client.loop(timeout=0.05)
            if session.connected:
                self._online(now)
        self._finish()

    def _closing(self, now: float, deadline: float) -> str:
        """A turn while closing: ``"done"`` once every window is delivered or the deadline
        [s, monotonic] passed; ``"wait"`` while unconnected (an attempt at once and then
        every :data:`CLOSE_RETRY_S`); ``"go"``: deliver."""
        session, delivery = self.session, self.delivery
        if now >= deadline:
            return "done"
        if not session.connected:
            # while windows wait: an attempt at once and then every CLOSE_RETRY_S until the
            # deadline (the backoff may be sleeping through a broker that is back)
            if not (delivery.inflight or delivery.has_pending()):
                return "done"
            if now >= self._close_attempt:
                session.attempt()
                self._close_attempt = time.monotonic() + CLOSE_RETRY_S
            if not session.connected:
                delivery.flush_acks()
                time.sleep(max(0.0, min(0.2, deadline - time.monotonic())))
            return "wait"
        if not delivery.inflight:
            delivery.feed(now, all_rows=True)
            if not delivery.inflight and not delivery.has_pending():
                return "done"
        return "go"

    def _offline(self, now: float) -> bool:
        """A turn without a connection: an attempt when due (capped exponential backoff);
        else the deliveries recorded and counted while waiting for a window stored or the
        next attempt. True when connected."""
        session, delivery = self.session, self.delivery
        if session.due(now):
            session.attempt()
            if not session.connected:
                session.backoff()
        if session.connected:
            return True
        delivery.flush_acks()
        if now - self._last_count > 1.0:
            delivery.count()
            self._last_count = now
        if self._wake.wait(min(0.2, max(session.next_attempt - time.monotonic(), 0.01))):
            self._wake.clear()
            delivery.count()  # a window stored: one more pending
            self._last_count = time.monotonic()
        return False

    def _online(self, now: float) -> None:
        """A connected turn: feed on a wake-up (or every 0.5 s), the discovery when Home
        Assistant asked, the deliveries recorded and counted."""
        delivery = self.delivery
        woken = self._wake.is_set()
        self._wake.clear()
        if woken or self._stop.is_set() or now - self._last_poll > 0.5:
            delivery.feed(now, all_rows=woken or self._stop.is_set())
            self._last_poll = now
        if self._discovery_due is not None and now >= self._discovery_due:
            self._send_discovery(force=True)
        delivery.flush_acks()
        if now - self._last_count > 1.0:
            delivery.count()
            self._last_count = now

    # -- sending ------------------------------------------------------------------------------
    def _send_discovery(self, force: bool = False) -> None:
        self._discovery_due = None
        ha = self.config.home_assistant
        if not ha.discovery or not self.session.connected:
            return
        ctx = self.context
        payload = json.dumps(discovery_payload(
            self.machine, self.model, self.base, self.delivery.latest_doc, self.parameters,
            qos=self.config.qos, device_name=ha.device_name,
            rules=set(ctx.alarm_bands) if ctx is not None else None,
            nominal=dict(ctx.nominal) if ctx is not None and ctx.nominal else None),
            separators=(",", ":"))
        if payload == self._discovery_sent and not force:
            return
        self.session.client.publish(self.discovery_topic, payload, qos=1, retain=True)
        self._discovery_sent = payload

    def _send(self, row: OutboxRow, newest: bool) -> bool:
        """Publish one window's messages (always True: a refusal is counted, the window stays
        in flight until the connection's loss sends it again)."""
        qos = self.config.qos
        delivery = self.delivery
        doc: HealthView | None
        try:
            doc = health_view(row.doc)
        except ValueError:
            doc = None
        mids = []
        for topic, payload, retain in self._messages(row, doc, newest):
            info = self.session.client.publish(topic, payload, qos=qos, retain=retain)
            if info.rc != mqtt.MQTT_ERR_SUCCESS and info.rc != mqtt.MQTT_ERR_NO_CONN:
                delivery.errors += 1
                logger.debug("publishing on %s refused: %s", topic, mqtt.error_string(info.rc))
            mids.append(info.mid)
        delivery.sent(row, mids)
        delivery.previous_levels = levels(doc)
        if newest and doc is not None and doc.model_fields_set:
            had = delivery.latest_doc
            delivery.latest_doc = doc
            if self.config.home_assistant.discovery and (
                    had is None or components(had) != components(doc)):
                self._send_discovery()
        return True

    def _messages(self, row: OutboxRow, doc: HealthView | None, newest: bool
                  ) -> list[tuple[str, str | bytes, bool]]:
        """A window's messages, ``(topic, payload, retain)``: the health message, its alarm
        events (the evaluator's, else read from two stored messages), and for the newest
        window the retained plain values."""
        messages: list[tuple[str, str | bytes, bool]] = [(self.health_topic, row.doc, False)]
        with self._events_lock:
            events = self._events.pop(row.doc, None)
        if events is None:
            events = reconstructed_events(doc, self.delivery.previous_levels or {})
        messages += [(f"{self.base}/alarm", json.dumps(e), False) for e in events]
        if newest and doc is not None:
            messages += [(f"{self.base}/{k}", v, True) for k, v in flat_values(doc).items()]
        return messages

    def _finish(self) -> None:
        """Leaving the thread: record the deliveries, go offline, disconnect."""
        self.delivery.flush_acks()
        self.delivery.count()
        self.session.leave(self.availability_topic, "offline", retain=True)
        self.delivery.finish()

    def __repr__(self) -> str:
        state = ("closed" if self._closed else
                 ("connected" if self.session.connected else "connecting"))
        return f"MqttPublisher({self.health_topic!r}, {state}, delivered={self.delivered})"
