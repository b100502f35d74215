"""One MQTT session with a broker, as the MQTT output and a Sparkplug B edge node both hold it:
the paho client, connection attempts with a capped, jittered backoff, the connection lost,
another client taking the client id over, and what is wrong with the session for STATUS.

The owner (:class:`~twinwatch.sinks.mqtt.publisher.MqttPublisher`, the Sparkplug
:class:`~twinwatch.sinks.sparkplug.node.EdgeNode`) drives the session from one
:class:`SessionThread` loop.
"""

from __future__ import annotations

import logging
import random
import ssl
import threading
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from twinwatch._forward import Forward
from twinwatch._lazy import lazy_module
from twinwatch.errors import PublisherError

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt
    from paho.mqtt.client import Client  # in SessionThread, ``mqtt`` is its session

    from twinwatch.sinks.mqtt.config import MqttConnectionConfig
    from twinwatch.sinks.mqtt.delivery import DeliveringSink
else:  # imported when the output opens: loading a configuration does not load paho
    mqtt = lazy_module("paho.mqtt.client")

__all__ = ["CLOSE_RETRY_S", "TAKEOVERS", "TAKEOVER_S", "MqttSession",
           "SessionThread", "read_password"]

#: At stop, with windows still to deliver and no connection: the spacing of the connection
#: attempts until ``close_timeout`` [s].
CLOSE_RETRY_S = 1.0

TAKEOVERS = 3
"""Connections lost in a row, each within :data:`TAKEOVER_S` of being made, that name a
client-id conflict (another client connecting with the same id takes the session over)."""

TAKEOVER_S = 10.0
"""A connection lost within this many seconds of being made counts as taken over [s]."""


class MqttSession:
    """The session (see the module docstring).

    Args:
        config: the output's table (its broker connection keys).
        owner: the thread that holds it (:class:`SessionThread`: its session calls).
        table: the output's table in messages (``outputs.<table>.tls``).
        client_id: the MQTT client id.
        password: read from ``password_file`` (or ``password``), or None.
        will: the last will's ``(topic, payload, retain)``, asked at each new client.
        log: the owner's logger.
        paho_log: the logger paho's own lines go to.
        conflict: what the client-id conflict's ERROR line tells the user to do.
        stopping: whether the owner is closing (a lost connection is then not a take-over).

    Attributes:
        client: the paho client (:meth:`new_client` replaces it).
        connected: the broker accepted the connection (CONNACK) and it is not known lost.
        connects, disconnects: connections made and lost so far.

    Raises:
        PublisherError: the TLS setup fails.
    """

    def __init__(self, config: MqttConnectionConfig, owner: SessionThread[Any], *, table: str,
                 client_id: str, password: str | None,
                 will: Callable[[], tuple[str, str | bytes, bool]],
                 log: logging.Logger, paho_log: str, conflict: str,
                 stopping: Callable[[], bool]) -> None:
        self.config = config
        self.owner = owner
        self.table = table
        self.client_id = client_id
        self._password = password
        self._will = will
        self._log = log
        self._paho_log = paho_log
        self._conflict = conflict
        self._stopping = stopping
        self.connected = False
        self.connects = 0
        self.disconnects = 0
        self.down_since: float | None = time.monotonic()
        self.connected_at = 0.0
        self.last_error: str | None = None
        self.refused = False  # the last attempt's CONNACK refused the connection
        self.takeovers = 0  # connections lost soon after they were made, in a row
        self.takeover_total = 0
        self.hold_until = 0.0  # no connection attempt before (a client-id conflict)
        self.next_attempt = 0.0
        self._delay = config.reconnect_min
        self.client = self.new_client()

    @property
    def broker(self) -> str:
        """``host:port`` of the broker."""
        return f"{self.config.host}:{self.config.port}"

    def new_client(self) -> mqtt.Client:
        """A paho client with the credentials, the TLS setup, the will and the owner's
        callbacks (:meth:`attempt` connects it).

        Raises:
            PublisherError: the TLS setup fails.
        """
        cfg = self.config
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=self.client_id,
                             clean_session=True, protocol=mqtt.MQTTv311)
        client.connect_timeout = cfg.connect_timeout
        client.max_inflight_messages_set(0)   # the inflight limit is the owner's, in windows
        client.max_queued_messages_set(0)
        client.enable_logger(logging.getLogger(self._paho_log))
        if cfg.username:
            client.username_pw_set(cfg.username, self._password)
        if cfg.tls is not None:
            tls = cfg.tls
            try:
                client.tls_set(ca_certs=tls.ca_certs, certfile=tls.certfile,
                               keyfile=tls.keyfile, cert_reqs=ssl.CERT_REQUIRED,
                               tls_version=ssl.PROTOCOL_TLS_CLIENT)
            except (OSError, ssl.SSLError, ValueError) as exc:
                raise PublisherError(f"outputs.{self.table}.tls: cannot set up TLS: "
                                     f"{exc}; check the certificate and key files") from exc
            client.tls_insecure_set(not tls.verify_hostname)
        topic, payload, retain = self._will()
        client.will_set(topic, payload, qos=1, retain=retain)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self.owner.on_publish
        client.on_message = self.owner.on_message
        self.client = client
        return client

    # -- connecting ---------------------------------------------------------------------------
    def due(self, now: float) -> bool:
        """A connection attempt is due at ``now`` [s, monotonic]: the backoff and a
        take-over's hold have passed."""
        return now >= self.next_attempt and now >= self.hold_until

    def backoff(self) -> None:
        """The attempt failed: the next one after a capped exponential backoff, +-25 %
        jitter (``reconnect_min`` doubling up to ``reconnect_max`` [s])."""
        self.next_attempt = time.monotonic() + self._delay * random.uniform(0.75, 1.25)
        self._delay = min(2 * self._delay, self.config.reconnect_max)

    def attempt(self) -> None:
        """One connection attempt: connect, then wait for the CONNACK (not past a refusal:
        its socket is closed, and polling it makes paho log an error)."""
        self.refused = False
        try:
            self.client.reconnect()
        except (OSError, ssl.SSLError, ValueError) as exc:
            self.unreachable(str(exc) or type(exc).__name__)
            return
        # the CONNACK is waited for while closing too: the closing loop's attempts are how a
        # backlog reaches a broker that is back after the run's end
        end = time.monotonic() + self.config.connect_timeout
        while not self.connected and not self.refused and time.monotonic() < end:
            if self.client.loop(timeout=0.05) != mqtt.MQTT_ERR_SUCCESS:
                break

    def unreachable(self, why: str) -> None:
        """An attempt failed: said once at WARNING per cause (a new cause at DEBUG)."""
        if self.last_error != why:
            level = logging.WARNING if self.last_error is None else logging.DEBUG
            self._log.log(level, "MQTT broker %s unreachable (%s); windows wait in the state "
                          "database and are sent once it answers", self.broker, why)
        self.last_error = why

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                    properties: Any) -> None:
        if reason.is_failure:
            self.owner.session_refused(reason)
            self.unreachable(f"connection refused: {reason}")
            self.refused = True
            client.disconnect()
            return
        self.connected = True
        self.connected_at = time.monotonic()
        self.down_since = None
        self.connects += 1
        self._delay = self.config.reconnect_min
        self.owner.session_up(client, self.last_error is not None or self.connects > 1)
        self.last_error = None

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                       properties: Any) -> None:
        own = self.owner.session_down()
        was, self.connected = self.connected, False
        if was:
            self.disconnects += 1
        if was and not own and not self._stopping():
            self._taken_over(time.monotonic() - self.connected_at)
            if self.takeovers >= TAKEOVERS:
                self._log.debug("MQTT connection of client id %r taken over again",
                                self.client_id)
            else:
                self._log.warning("MQTT connection to %s lost (%s): %s are sent again on "
                                  "reconnection", self.broker, reason, self.owner.in_flight())
        if self.down_since is None or own:
            self.down_since = time.monotonic()

    def _taken_over(self, lasted: float) -> None:
        """A connection lost ``lasted`` seconds after it was made. The broker closes a
        session when another client connects with the same client id (MQTT 3.1.1: no reason
        given). :data:`TAKEOVERS` such losses in a row: named once, and the next attempts
        wait longer (doubling from 5 s to 60 s); a connection that lasts resets it."""
        if lasted > TAKEOVER_S:
            if self.takeovers >= TAKEOVERS:
                self._log.warning("MQTT client id %r: the connection has lasted %.0f s, no "
                                  "longer taken over", self.client_id, lasted)
            self.takeovers = 0
            return
        self.takeovers += 1
        self.takeover_total += 1
        if self.takeovers < TAKEOVERS:
            return
        if self.takeovers == TAKEOVERS:
            self._log.error("another client uses client id %r on MQTT broker %s: the "
                            "connection was taken over %d times in a row, each within %.0f s: "
                            "%s", self.client_id, self.broker, self.takeovers, TAKEOVER_S,
                            self._conflict)
        hold = min(5.0 * 2 ** (self.takeovers - TAKEOVERS), 60.0) * random.uniform(0.75, 1.25)
        self.hold_until = time.monotonic() + hold

    def leave(self, topic: str, payload: str | bytes, retain: bool = False) -> None:
        """A clean stop: ``payload`` on ``topic`` (what the will says: ``offline``, NDEATH),
        given 2 s to be acknowledged, then disconnect."""
        if self.connected:
            info = self.client.publish(topic, payload, qos=1, retain=retain)
            end = time.monotonic() + 2.0
            while self.connected and not info.is_published() and time.monotonic() < end:
                self.client.loop(timeout=0.05)
            self.client.disconnect()
        self.connected = False

    # -- for STATUS ---------------------------------------------------------------------------
    def problems(self, pending: int) -> list[str]:
        """The session's part of the output's problem line, with ``pending`` windows."""
        out = []
        if not self.connected and self.down_since is not None and not self._stopping():
            since = time.monotonic() - self.down_since
            if since > 2 * self.config.connect_timeout or self.connects:
                why = f" ({self.last_error})" if self.last_error else ""
                out.append(f"MQTT broker {self.broker} unreachable for {since:.0f} s{why}: "
                           f"{pending} windows pending, sent when it is back")
        if self.takeovers >= TAKEOVERS and not self._stopping():
            out.append(f"another client uses MQTT client id {self.client_id!r} on "
                       f"{self.broker} ({self.takeover_total} connections taken over): "
                       f"{pending} windows pending")
        return out


def read_password(config: Any, table: str) -> str | None:
    """The password of an MQTT output's table: ``password_file``'s first line, or
    ``password``.

    Raises:
        PublisherError: the file cannot be read (naming ``outputs.<table>.password_file``).
    """
    if config.password_file is None:
        return config.password  # type: ignore[no-any-return]
    try:
        with open(config.password_file, encoding="utf-8") as f:
            return f.readline().rstrip("\r\n")
    except OSError as exc:
        raise PublisherError(f"cannot read outputs.{table}.password_file = "
                             f"{config.password_file}"
                             f": {exc.strerror or exc}; fix the path or the file's "
                             f"permissions (the service user must read it)") from exc


M = TypeVar("M", bound="DeliveringSink")


class SessionThread(Generic[M]):
    """The thread that drives an :class:`MqttSession` and the deliveries of its members (the
    MQTT output: itself; a Sparkplug edge node: its devices).

    A subclass sets :attr:`mqtt`, :attr:`wake`, ``_stop`` and ``_thread`` (``target``
    :meth:`_run`) and implements the hooks below.
    """

    mqtt: MqttSession
    wake: threading.Event
    _stop: threading.Event
    _thread: threading.Thread

    connected: Forward[bool] = Forward(
        "mqtt.connected", "The broker accepted the connection (CONNACK), not known lost.")

    # -- the session's calls (from paho's callbacks, in the thread) ---------------------------
    def session_up(self, client: Client, again: bool) -> None:
        """Connected (``again``: after an outage or a previous connection): announce."""
        raise NotImplementedError

    def session_down(self) -> bool:
        """The connection is gone; True when the owner closed it itself (not a loss).
        Default: never."""
        return False

    def session_refused(self, reason: Any) -> None:
        """The broker refused the connection (CONNACK ``reason``). Default: nothing to add to
        the session's line."""

    def in_flight(self) -> str:
        """What a lost connection sends again, for its log line (``3 windows in flight``)."""
        raise NotImplementedError

    def on_publish(self, client: Client, userdata: Any, mid: int, reason: Any,
                   properties: Any) -> None:
        """paho's acknowledgement of message ``mid``."""
        raise NotImplementedError

    def on_message(self, client: Client, userdata: Any, msg: Any) -> None:
        """A message on a topic the owner subscribed to."""
        raise NotImplementedError

    def _members(self) -> Sequence[M]:
        """The members served now."""
        raise NotImplementedError

    def _retire(self, member: M) -> None:
        """``member`` has left (delivered, or past its ``leave_by``)."""
        raise NotImplementedError

    def _failed(self) -> None:
        """An unexpected error in the thread: counted and logged with its traceback."""
        raise NotImplementedError

    def _finish(self) -> None:
        """The thread ends: the session closed."""
        raise NotImplementedError

    def _connect(self) -> None:
        """One connection attempt."""
        self.mqtt.attempt()

    def _ready(self, member: M) -> bool:
        """``member`` may be fed in this connected turn."""
        return True

    def _turn_done(self, now: float) -> None:
        """What a connected turn does after its members' turns."""

    def _stop_thread(self, timeout: float) -> bool:
        """Stop the thread (it delivers what its members' ``leave_by`` allows): True when it
        ended within ``timeout`` [s]."""
        self._stop.set()
        self.wake.set()
        self._thread.join(timeout=timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        """The thread: :meth:`_loop`, restarted 1 s after an unexpected error (the output
        must not die silently)."""
        while True:
            try:
                self._loop()
                return
            except Exception:  # noqa: BLE001 - logged; the loop goes on
                self._failed()
                if self._stop.wait(1.0):
                    for member in self._members():
                        self._retire(member)
                    self._finish()
                    return

    def _loop(self) -> None:
        self._last_poll = self._last_count = self._close_attempt = 0.0
        while True:
            now = time.monotonic()
            members = self._members()
            for m in members:
                if m.delivery.rebind.is_set():
                    m.delivery.rebind_outbox()
            if not members:
                if self._stop.is_set():
                    break
                if not self.mqtt.connected:  # no member yet (the first is joining)
                    self.wake.wait(0.05)
                    self.wake.clear()
                    continue
            if not self.mqtt.connected:
                self._offline(now, members)
                if not self.mqtt.connected:
                    continue
            self.mqtt.client.loop(timeout=0.05)
            if self.mqtt.connected:
                self._online(now, members)
        self._finish()

    def _offline(self, now: float, members: Sequence[M]) -> None:
        """A turn without a connection: closing members retired when done, a connection
        attempted when due (while a closing member's windows wait, every
        :data:`CLOSE_RETRY_S`); waits for a window stored or the next attempt."""
        waiting = [m for m in members if not self._left(m, now) and m.leave_by is not None]
        closing = self._stop.is_set()  # the whole session closes: only the closing attempts
        if waiting and now >= self._close_attempt:
            # a closing member's windows wait (the backoff may sleep through a broker back)
            self._connect()
            self._close_attempt = time.monotonic() + CLOSE_RETRY_S
        elif not closing and self.mqtt.due(now):
            self._connect()
            if not self.mqtt.connected:
                self.mqtt.backoff()
        if self.mqtt.connected:
            return
        for m in self._members():  # without the ones retired just now
            m.delivery.flush_acks()
        self._count(now)
        until = self._close_attempt if closing else self.mqtt.next_attempt
        if self.wake.wait(min(0.2, max(until - time.monotonic(), 0.01))):
            self.wake.clear()
            self._count(now, force=True)  # a window stored: one more pending

    def _online(self, now: float, members: Sequence[M]) -> None:
        """A connected turn: each member fed (on a wake-up, every 0.5 s, while it leaves),
        retired when done, its acknowledgements recorded."""
        woken = self.wake.is_set()
        self.wake.clear()
        poll = woken or now - self._last_poll > 0.5
        if poll:
            self._last_poll = now
        for m in members:
            leaving = m.leave_by is not None
            if self._ready(m) and (poll or leaving):
                m.delivery.feed(now, all_rows=woken or leaving)
            if not self._left(m, now):
                m.delivery.flush_acks()
        self._turn_done(now)
        self._count(now)

    def _left(self, m: M, now: float) -> bool:
        """``m`` closes and is delivered or past its ``leave_by``: retired (True)."""
        if m.leave_by is None or (now < m.leave_by and m.has_undelivered()):
            return False
        self._retire(m)
        return True

    def _count(self, now: float, force: bool = False) -> None:
        """Count each member's pending windows, at most once a second unless ``force``."""
        if force or now - self._last_count > 1.0:
            for m in self._members():
                m.delivery.count()
            self._last_count = time.monotonic() if force else now
