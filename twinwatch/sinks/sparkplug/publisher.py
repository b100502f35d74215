"""The Sparkplug B output of one machine: a device of its edge node.

Each machine's output keeps its delivery over its own outbox (a
:class:`~twinwatch.sinks.mqtt.delivery.Delivery`) and its device's metrics and aliases; the
:class:`~twinwatch.sinks.sparkplug.node.EdgeNode` it joins (one per broker, group and edge node
id in the process) holds the MQTT session and the thread that drives every device's delivery.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import TYPE_CHECKING, Any, ClassVar

from twinwatch.errors import PublisherError
from twinwatch.sinks.base import OutboxRow, SharedResources, SinkContext
from twinwatch.sinks.mqtt.delivery import DeliveringSink, Delivery
from twinwatch.sinks.mqtt.encoding import health_view
from twinwatch.sinks.mqtt.session import mqtt, read_password
from twinwatch.sinks.sparkplug.config import SparkplugConfig, check_id, node_key
from twinwatch.sinks.sparkplug.metrics import metric_specs, metric_values
from twinwatch.sinks.sparkplug.node import EdgeNode
from twinwatch.sinks.sparkplug.session import DeviceSession, now_ms

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthView

logger = logging.getLogger(__package__)

__all__ = ["SparkplugPublisher"]


class SparkplugPublisher(DeliveringSink):
    """The Sparkplug B output (docs/sparkplug.md): the built-in ``sparkplug``,
    ``[outputs.sparkplug]``; the machine is the device ``device_id`` (unset: its name) of the
    edge node ``edge_node_id`` (unset: its name).

    Args:
        config: the validated table.
        context: the daemon's context (``shared``: the process's edge nodes).

    Raises:
        PublisherError: one line naming ``outputs.sparkplug.<key>``: the machine name is no
            Sparkplug id, two metrics differ only in case, a TLS or password file cannot be
            read, the edge node's other devices set a session key otherwise, the device id is
            taken.
    """

    config_class: ClassVar[type[SparkplugConfig]] = SparkplugConfig
    counter_prefix: ClassVar[str | None] = "sparkplug"

    config: SparkplugConfig

    def __init__(self, config: SparkplugConfig, context: SinkContext) -> None:
        self._closed = True  # until fully open
        for key, value in (("edge_node_id", config.edge_node_id),
                           ("device_id", config.device_id)):
            if value is None:
                try:
                    check_id(context.machine, "the machine name")
                except ValueError as exc:
                    raise PublisherError(f"outputs.sparkplug.{key}: {exc}; set {key}") from None
        self.config = config
        self.machine = context.machine
        self.model = context.model
        self.parameters = dict(context.parameters)
        self.rules = set(context.alarm_bands)
        self.device_births = 0
        self.device_born = False
        self.left = threading.Event()        # the node has retired this device
        self.delivery = Delivery(
            config, in_memory=context.outbox is None, outbox_name=lambda: self.name or
            "sparkplug", send=self._send, machine=self.machine,
            ready=lambda: self._node.connected and self._node.born)  # DDATA may go out
        password = read_password(config, "sparkplug")
        edge = config.edge_node_id or context.machine
        directory = getattr(context.shared, "directory", None) or context.cwd

        def open_node() -> EdgeNode:
            return EdgeNode(config, edge, password, directory, context.machine)

        node: EdgeNode
        self._key = node_key(config, context.machine)
        node, self._release = SharedResources.hold(context.shared, self._key, open_node,
                                                   EdgeNode.close)
        self._node = node
        self.wake = node.wake
        try:
            self.client_id = node.client_id
            self.device = DeviceSession(node.session, config.device_id or context.machine)
            try:
                self.device.declare(metric_specs(context.parameters, self.rules, None))
            except ValueError as exc:
                raise PublisherError(f"outputs.sparkplug: {exc}; rename a parameter") from None
            self.attach(context)
            node.join(self, config, context.machine)
        except BaseException:
            self._release()
            raise
        self._closed = False

    # -- the device's state ----------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """The edge node is connected and born (the host online): DDATA may go out."""
        return self._node.connected and self._node.born

    @property
    def latest_doc(self) -> HealthView | None:
        """The newest stored window of this run's typed message (a DBIRTH's values), or None:
        a new run never births with the previous run's last window."""
        doc = self.delivery.latest_doc
        return doc if doc is not None and self._this_run(doc) else None

    def _this_run(self, doc: HealthView) -> bool:
        run = self.context.run if self.context is not None else ""
        return not run or getattr(doc, "run", None) == run

    def reset_connection(self) -> None:
        """A new connection: the windows in flight are sent again from the outbox."""
        self.delivery.reset_connection()
        self.device_born = False

    # -- the device's messages (in the node's thread) ----------------------------------------
    def device_birth(self) -> None:
        """DBIRTH: every metric with the newest stored window of this run's values (none yet:
        nulls)."""
        doc = self.latest_doc
        values: dict[str, Any] = {}
        if doc is not None:
            with contextlib.suppress(ValueError):  # named when the window is sent
                self.device.declare(metric_specs(self.parameters, self.rules, doc))
            values = metric_values(doc)
        self._node.client.publish(self.device.dbirth_topic,
                                  self.device.dbirth(values, now_ms()), qos=self.config.qos)
        self.device_born = True
        self.device_births += 1

    def _send(self, row: OutboxRow, newest: bool) -> bool:
        """One window's DDATA (historical when stored before this connection's births); a
        metric the birth did not announce makes a new DBIRTH of the device first."""
        delivery = self.delivery
        try:
            doc = health_view(row.doc)
        except ValueError:
            doc = None
        if doc is None:  # a stored row that is no health message: nothing to send
            delivery.errors += 1
            delivery.sent(row, [])
            return True
        try:
            grew = self.device.declare(metric_specs(self.parameters, self.rules, doc))
        except ValueError as exc:
            logger.error("outputs.sparkplug: %s; the new metric is left out", exc)
            grew = False
        if self._this_run(doc) and (newest or self.latest_doc is None):
            delivery.latest_doc = doc
        if grew or not self.device_born:
            self.device_birth()
        node = self._node
        payload = self.device.ddata(metric_values(doc), now_ms(), int(row.wall * 1000),
                                    historical=row.wall < node.live_since)
        info = node.client.publish(self.device.ddata_topic, payload, qos=self.config.qos)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            delivery.errors += 1
            logger.debug("publishing on %s refused: %s", self.device.ddata_topic,
                         mqtt.error_string(info.rc))
            return False
        delivery.sent(row, [info.mid])
        node.track(info.mid, self)
        if self.config.qos == 0 and info.is_published():
            node.on_publish(None, None, info.mid, None, None)
        return True

    # -- the sink contract ------------------------------------------------------------------
    def close(self) -> None:
        """Deliver what is pending for up to ``close_timeout`` s, DDEATH, leave the edge node.
        Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._node.leave(self)
        if not self.left.wait(timeout=self.config.close_timeout
                              + self.config.connect_timeout + 10):
            logger.warning("the Sparkplug device %s did not leave its edge node in time",
                           self.device.device_id)
        self._release()
        logger.info("Sparkplug output of %s closed (%d windows delivered, %d pending)",
                    self.machine, self.delivered, self.pending)

    def counters(self) -> dict[str, int]:
        """The MQTT output's, and ``births`` (NBIRTHs), ``device_births``, ``rebirths``,
        ``commands_refused`` (commands that tried to write a metric)."""
        node = self._node
        return {"delivered": int(self.delivered), "pending": int(self.pending),
                "dropped": self.dropped, "connects": int(node.connects),
                "disconnects": int(node.disconnects),
                "errors": int(self.delivery.errors + node.errors), "births": int(node.births),
                "device_births": int(self.device_births), "rebirths": int(node.rebirths),
                "commands_refused": int(node.commands_refused)}

    @property
    def births(self) -> int:
        """NBIRTHs of the edge node so far."""
        return self._node.births

    @property
    def problem(self) -> str | None:
        parts = [self._node.problem(self.pending), self.delivery.unacknowledged(
            self._node.mqtt.broker, self.connected and not self._closed)]
        if self.dropped:
            parts.append(f"Sparkplug: {self.dropped} windows dropped undelivered")
        return "; ".join(p for p in parts if p) or None

    @property
    def status(self) -> str:
        return (f"Sparkplug B on mqtt://{self.config.host}:{self.config.port}/"
                f"{self.device.ddata_topic}")

    def summary(self) -> list[str]:
        line = (f"Sparkplug B was published on {self.device.ddata_topic} (broker "
                f"{self.config.host}:{self.config.port}): {self.delivered} windows delivered, "
                f"{self.device_births} device births")
        return [self._with_pending(line)]

    def __repr__(self) -> str:
        state = ("closed" if self._closed else
                 ("connected" if self._node.connected else "connecting"))
        return (f"SparkplugPublisher({self.device.ddata_topic!r}, {state}, "
                f"delivered={self.delivered})")
