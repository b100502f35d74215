"""The MQTT output itself: the paho client in its own thread (an :class:`MqttSession`),
delivering the outbox's windows oldest first (a :class:`Delivery`).
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
from twinwatch.sinks.mqtt.session import MqttSession, SessionThread, mqtt, read_password

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView

logger = logging.getLogger(__package__)  # twinwatch.sinks.mqtt


class MqttPublisher(DeliveringSink, SessionThread["MqttPublisher"]):
    """The MQTT output (see the module docstring): the built-in ``mqtt``, ``[outputs.mqtt]``.

    Args:
        config: the validated table.
        context: the daemon's context (machine, model, parameters; the gate's outbox).

    Attributes:
        mqtt: the connection to the broker (:class:`MqttSession`).
        delivery: the windows delivered and pending (:class:`Delivery`).

    Raises:
        PublisherError: a TLS or password file cannot be read, or the TLS setup fails (an
            unreachable broker is not an error: it is tried again in the background).
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
        self.wake = threading.Event()
        self._stop = threading.Event()
        self._discovery_sent: str | None = None
        self._discovery_due: float | None = None
        self.delivery = Delivery(config, in_memory=context.outbox is None,
                                 outbox_name=lambda: self.name or "mqtt", send=self._send,
                                 ready=lambda: self.mqtt.connected, machine=self.machine)
        self.attach(context)
        self.mqtt = MqttSession(
            config, self, table="mqtt",
            client_id=config.client_id or f"twinwatch-{context.machine}",
            password=read_password(config, "mqtt"),
            will=lambda: (self.availability_topic, "offline", True), log=logger,
            paho_log=f"{__name__}.paho", stopping=self._stop.is_set,
            conflict="give each daemon its own [outputs.mqtt] client_id (or machine name); "
                     "connecting less often meanwhile, windows wait in the outbox")
        self.client_id = self.mqtt.client_id
        self.mqtt.client.connect_async(config.host, config.port, keepalive=config.keepalive)
        self._thread = threading.Thread(target=self._run, name="twinwatch-mqtt", daemon=True)
        self._closed = False
        self._thread.start()

    # -- the session's calls ------------------------------------------------------------------
    def session_up(self, client: mqtt.Client, again: bool) -> None:
        """Connected: ``online`` on the availability topic, the discovery (or its clearing)."""
        if again:
            logger.warning("MQTT broker %s reached: %d windows pending are sent now",
                           self.mqtt.broker, self.delivery.pending)
        else:
            logger.info("publishing health of %s on %s (MQTT broker %s)", self.machine,
                        self.health_topic, self.mqtt.broker)
        client.publish(self.availability_topic, "online", qos=1, retain=True)
        ha = self.config.home_assistant
        if ha.discovery:
            client.subscribe(f"{ha.prefix}/status", qos=1)
            self._discovery_sent = None
            self._send_discovery(force=True)
        else:
            client.publish(self.discovery_topic, b"", qos=1, retain=True)
        self.wake.set()

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
    def write(self, out: ProcessedWindow) -> None:
        """Remember the window's alarm events, then :meth:`DeliveringSink.write`."""
        if out.events and not self._closed:
            with self._events_lock:
                self._events[out.health_json] = list(out.events)
                while len(self._events) > 1000:
                    self._events.pop(next(iter(self._events)))
        super().write(out)

    def counters(self) -> dict[str, int]:
        """``delivered``, ``pending``, ``dropped`` (as :class:`Delivery`), ``connects``,
        ``disconnects``, ``errors``."""
        d, s = self.delivery, self.mqtt
        return {"delivered": int(d.delivered), "pending": int(d.pending),
                "dropped": d.dropped, "connects": int(s.connects),
                "disconnects": int(s.disconnects), "errors": int(d.errors)}

    @property
    def problem(self) -> str | None:
        out = [] if self._closed else self.mqtt.problems(self.pending)
        unacked = self.delivery.unacknowledged(self.mqtt.broker,
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
        self.leave_by = time.monotonic() + self.config.close_timeout
        if not self._stop_thread(self.config.close_timeout + self.config.connect_timeout + 10):
            logger.warning("the MQTT thread of %s did not stop in time", self.machine)
        logger.info("MQTT output of %s closed (%d windows delivered, %d pending)",
                    self.machine, self.delivered, self.pending)

    # -- the thread (a SessionThread of one member: the output) -------------------------------
    def _members(self) -> list[MqttPublisher]:
        return [self] if self.leave_by is None or time.monotonic() < self.leave_by else []

    def _retire(self, member: MqttPublisher) -> None:
        self.leave_by = 0.0  # delivered: the thread finishes

    def _failed(self) -> None:
        self.delivery.errors += 1
        logger.exception("the MQTT output of %s failed; it goes on in 1 s", self.machine)

    def _turn_done(self, now: float) -> None:
        if self._discovery_due is not None and now >= self._discovery_due:
            self._send_discovery(force=True)

    # -- sending ------------------------------------------------------------------------------
    def _send_discovery(self, force: bool = False) -> None:
        self._discovery_due = None
        ha = self.config.home_assistant
        if not ha.discovery or not self.mqtt.connected:
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
        self.mqtt.client.publish(self.discovery_topic, payload, qos=1, retain=True)
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
            info = self.mqtt.client.publish(topic, payload, qos=qos, retain=retain)
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
        events, and for the newest window the retained plain values."""
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
        self.delivery.flush_acks()
        self.delivery.count()
        self.mqtt.leave(self.availability_topic, "offline", retain=True)
        self.delivery.finish()

    def __repr__(self) -> str:
        state = ("closed" if self._closed else
                 ("connected" if self.mqtt.connected else "connecting"))
        return f"MqttPublisher({self.health_topic!r}, {state}, delivered={self.delivered})"
