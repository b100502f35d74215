"""HealthPublisher against a real zenoh node in another process, on loopback only.

The observer is a separate Python process (``python -c``) with its own zenoh session, scouting
off, explicit endpoints: it subscribes to the health topic and to liveliness changes, and
answers ``get``/``alive`` commands read on stdin with JSON lines on stdout. Every port is picked
free at run time (never 7447), so the tests run next to a live daemon.
"""

from __future__ import annotations

import json
import logging
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from pydantic import ValidationError

from twinwatch.sinks.zenoh import (
    HealthPublisher,
    PublisherError,
    ZenohConfig,
    open_session,
    to_json,
    to_zenoh_config,
)

from .helpers.net import endpoint, free_port

TIMEOUT = 10.0  # upper bound of any single wait; the tests take well under a second each

OBSERVER = r"""
import json, sys, threading, zenoh

mode, listen, connect, base = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
conf = zenoh.Config()
conf.insert_json5("mode", json.dumps(mode))
conf.insert_json5("listen/endpoints", listen)
conf.insert_json5("connect/endpoints", connect)
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("scouting/gossip/enabled", "false")
lock = threading.Lock()

def out(**event):
    with lock:
        sys.stdout.write(json.dumps(event) + "\n")
        sys.stdout.flush()

def on_sample(s):
    out(event="sample", key=str(s.key_expr), encoding=str(s.encoding),
        payload=json.loads(s.payload.to_string()))

def on_alive(s):
    out(event="alive", key=str(s.key_expr), kind=str(s.kind))

with zenoh.open(conf) as session:
    sub = session.declare_subscriber(base + "/health", on_sample)
    live = session.liveliness().declare_subscriber(base + "/alive", on_alive, history=True)
    out(event="ready")
    for line in sys.stdin:
        cmd = line.split()
        if not cmd or cmd[0] == "quit":
            break
        if cmd[0] == "get":
            replies = []
            for r in session.get(cmd[1], timeout=2.0):
                if r.ok is not None:
                    replies.append({"key": str(r.ok.key_expr), "encoding": str(r.ok.encoding),
                                    "payload": json.loads(r.ok.payload.to_string())})
            out(event="get", replies=replies)
        elif cmd[0] == "alive":
            keys = [str(r.ok.key_expr) for r in session.liveliness().get(base + "/alive",
                                                                        timeout=2.0)
                    if r.ok is not None]
            out(event="tokens", keys=keys)
    sub.undeclare()
    live.undeclare()
"""


class Observer:
    """A zenoh node in a child process, driven through stdin/stdout JSON lines."""

    def __init__(self, mode: str, *, listen: list[str], connect: list[str], base: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", OBSERVER, mode, json.dumps(listen), json.dumps(connect), base],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._stash: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, name="observer-reader", daemon=True)
        self._reader.start()
        self.expect("ready")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.events.put(json.loads(line))

    def send(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(
        self,
        event: str,
        predicate: Callable[[dict[str, Any]], bool] = lambda e: True,
        *,
        timeout: float = TIMEOUT,
    ) -> dict[str, Any]:
        """The next event of kind ``event`` matching ``predicate``; fails after ``timeout``."""
        for i, item in enumerate(self._stash):
            if item["event"] == event and predicate(item):
                return self._stash.pop(i)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                item = self.events.get(timeout=min(left, 0.1))
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            if item["event"] == event and predicate(item):
                return item
            self._stash.append(item)  # kept for a later expect()
        stderr = (
            self.proc.stderr.read() if self.proc.poll() is not None and self.proc.stderr else ""
        )
        pytest.fail(f"observer: no {event!r} event within {timeout} s {stderr}")

    def ask(self, command: str, event: str) -> dict[str, Any]:
        self.send(command)
        return self.expect(event)

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:
                self.send("quit")
                self.proc.wait(timeout=TIMEOUT)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(timeout=TIMEOUT)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        self._reader.join(timeout=TIMEOUT)


@pytest.fixture
def observers() -> Iterator[Callable[..., Observer]]:
    started: list[Observer] = []

    def start(mode: str, *, listen: list[str], connect: list[str], base: str) -> Observer:
        obs = Observer(mode, listen=listen, connect=connect, base=base)
        started.append(obs)
        return obs

    yield start
    for obs in started:
        obs.stop()


@pytest.fixture
def publishers() -> Iterator[Callable[..., HealthPublisher]]:
    """Open HealthPublishers; all closed at teardown, and their sessions checked closed."""
    opened: list[HealthPublisher] = []

    def open_(config: ZenohConfig, machine: str = "m1") -> HealthPublisher:
        pub = HealthPublisher(config, machine)
        opened.append(pub)
        return pub

    yield open_
    for pub in opened:
        pub.close()
        assert pub.session is None or pub.session.is_closed()


def eventually(ask: Callable[[], Any], expected: Any, *, timeout: float = TIMEOUT) -> Any:
    """Repeat ``ask()`` until it returns ``expected`` (declarations propagate asynchronously)."""
    deadline = time.monotonic() + timeout
    while (got := ask()) != expected and time.monotonic() < deadline:
        time.sleep(0.02)
    return got


def alive_keys(obs: Observer) -> list[str]:
    keys: list[str] = obs.ask("alive", "tokens")["keys"]
    return keys


def publish_until_received(pub: HealthPublisher, obs: Observer) -> None:
    """Publish until the observer gets one sample: subscriptions propagate asynchronously."""
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        pub.publish({"warmup": True})
        try:
            obs.expect("sample", timeout=0.1)
            return
        except pytest.fail.Exception:
            continue
    pytest.fail("observer never received a health sample")


def test_external_client_receives_health_queries_latest_and_sees_liveliness(
    publishers: Callable[..., HealthPublisher], observers: Callable[..., Observer]
) -> None:
    port = free_port()
    pub = publishers(ZenohConfig(listen=[endpoint(port)]), "motor1")
    obs = observers("client", listen=[], connect=[endpoint(port)], base="twinwatch/motor1")

    publish_until_received(pub, obs)
    for seq in range(3):
        pub.publish({"seq": seq, "theta_error": 0.01 * seq, "status": "ok"})
    got = [obs.expect("sample", lambda e: "seq" in e["payload"]) for _ in range(3)]
    assert [e["payload"]["seq"] for e in got] == [0, 1, 2]
    assert {e["key"] for e in got} == {"twinwatch/motor1/health"}
    assert {e["encoding"] for e in got} == {"application/json"}

    reply = obs.ask("get twinwatch/motor1/health", "get")
    assert reply["replies"] == [
        {
            "key": "twinwatch/motor1/health",
            "encoding": "application/json",
            "payload": {"seq": 2, "theta_error": 0.02, "status": "ok"},
        }
    ]

    pub.publish_json("alarm", {"level": "warning", "parameter": "Ra"})
    everything = obs.ask("get twinwatch/motor1/**", "get")["replies"]
    assert {r["key"]: r["payload"] for r in everything} == {
        "twinwatch/motor1/health": {"seq": 2, "theta_error": 0.02, "status": "ok"},
        "twinwatch/motor1/alarm": {"level": "warning", "parameter": "Ra"},
    }

    alive = ["twinwatch/motor1/alive"]
    assert eventually(lambda: alive_keys(obs), alive) == alive
    assert pub.published >= 5 and pub.errors == 0


def test_liveliness_token_disappears_after_close(
    publishers: Callable[..., HealthPublisher], observers: Callable[..., Observer]
) -> None:
    """Through a router (standing in for zenohd): the observer outlives the publisher."""
    router = endpoint(free_port())
    obs = observers("router", listen=[router], connect=[], base="twinwatch/m1")
    pub = publishers(ZenohConfig(mode="client", connect=[router]), "m1")

    obs.expect("alive", lambda e: e["kind"] == "SampleKind.PUT")
    assert eventually(lambda: alive_keys(obs), ["twinwatch/m1/alive"]) == ["twinwatch/m1/alive"]
    pub.publish({"status": "ok"})
    assert obs.ask("get twinwatch/m1/health", "get")["replies"][0]["payload"] == {"status": "ok"}

    pub.close()
    obs.expect("alive", lambda e: e["kind"] == "SampleKind.DELETE")
    assert eventually(lambda: alive_keys(obs), []) == []
    assert obs.ask("get twinwatch/m1/health", "get")["replies"] == []


def test_no_reply_before_first_publish(
    publishers: Callable[..., HealthPublisher], observers: Callable[..., Observer]
) -> None:
    port = free_port()
    pub = publishers(ZenohConfig(listen=[endpoint(port)]), "m1")
    obs = observers("client", listen=[], connect=[endpoint(port)], base="twinwatch/m1")
    pub.publish_json("alarm", {"level": "info"})

    def answered() -> list[str]:
        return [r["key"] for r in obs.ask("get twinwatch/m1/**", "get")["replies"]]

    # The queryable is reachable (it answers for the alarm) but has no health to give yet.
    assert eventually(answered, ["twinwatch/m1/alarm"]) == ["twinwatch/m1/alarm"]
    assert obs.ask("get twinwatch/m1/health", "get")["replies"] == []


def test_port_in_use_raises_publisher_error(publishers: Callable[..., HealthPublisher]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as squatter:
        squatter.bind(("127.0.0.1", 0))
        squatter.listen()
        port = squatter.getsockname()[1]
        with pytest.raises(PublisherError, match=rf"port {port} already in use on 127\.0\.0\.1"):
            publishers(ZenohConfig(listen=[endpoint(port)]))

    port = free_port()
    publishers(ZenohConfig(listen=[endpoint(port)]), "m1")
    with pytest.raises(PublisherError, match=r"set \[zenoh\]\.listen to another port"):
        publishers(ZenohConfig(listen=[endpoint(port)]), "m2")


def test_client_with_nothing_to_connect_to_raises_publisher_error() -> None:
    target = endpoint(free_port())
    with pytest.raises(PublisherError, match=rf"cannot connect to {target}"):
        HealthPublisher(ZenohConfig(mode="client", connect=[target]), "m1")


def test_failing_put_is_counted_and_logged_once(
    publishers: Callable[..., HealthPublisher], caplog: pytest.LogCaptureFixture
) -> None:
    pub = publishers(ZenohConfig(listen=[endpoint(free_port())]))
    with caplog.at_level(logging.DEBUG, logger="twinwatch.sinks.zenoh"):
        pub.publish({"bad": object()})
        pub.publish({"bad": object()})
        pub.publish({"good": 1.0})
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "twinwatch/m1/health" in errors[0].getMessage()
    assert (pub.published, pub.errors) == (1, 2)


def test_publish_from_worker_while_main_thread_closes(
    publishers: Callable[..., HealthPublisher],
) -> None:
    pub = publishers(ZenohConfig(listen=[endpoint(free_port())]))
    failures: list[BaseException] = []
    started = threading.Event()

    def worker() -> None:
        try:
            for seq in range(5000):
                pub.publish({"seq": seq})
                pub.publish_json("alarm", {"seq": seq})
                started.set()
        except BaseException as exc:  # noqa: BLE001 - any escape is the failure under test
            failures.append(exc)

    thread = threading.Thread(target=worker, name="publish-worker")
    thread.start()
    assert started.wait(TIMEOUT)
    pub.close()
    thread.join(TIMEOUT)
    assert not thread.is_alive() and failures == []
    assert pub.closed and pub.session is not None and pub.session.is_closed()
    pub.close()  # idempotent
    published = pub.published
    pub.publish({"after": "close"})  # a silent no-op
    assert pub.published == published and pub.errors == 0


def test_disabled_publisher_opens_nothing() -> None:
    with HealthPublisher(ZenohConfig(enabled=False), "m1") as pub:
        pub.publish({"status": "ok"})
        assert pub.session is None and pub.published == 0


def test_config_validation() -> None:
    assert ZenohConfig().listen == ["tcp/127.0.0.1:7447"]
    bad_configs: list[dict[str, Any]] = [
        {"listen": ["127.0.0.1:7447"]},
        {"listen": ["tcp/127.0.0.1"]},
        {"listen": ["tcp/127.0.0.1:70000"]},
        {"connect": ["serial/dev:1"]},
        {"mode": "client"},
        {"mode": "client", "connect": ["tcp/127.0.0.1:7447"], "listen": ["tcp/127.0.0.1:1"]},
        {"key_prefix": "twin/*"},
        {"key_prefix": "/twinwatch"},
        {"listen": [], "connect": []},
        {"lisen": ["tcp/127.0.0.1:7447"]},
    ]
    for bad in bad_configs:
        with pytest.raises(ValidationError):
            ZenohConfig.model_validate(bad)
    with pytest.raises(ValueError):
        HealthPublisher(ZenohConfig(enabled=False), "a/b")


def test_zenoh_config_has_scouting_off_and_explicit_endpoints() -> None:
    conf = to_zenoh_config(ZenohConfig(listen=["tcp/127.0.0.1:17447"], connect=[]))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:17447"]
    client = to_zenoh_config(ZenohConfig(mode="client", connect=["tcp/127.0.0.1:17447"]))
    assert json.loads(client.get_json("listen/endpoints")) == []


def test_open_session_is_usable_by_tools() -> None:
    with open_session(ZenohConfig(listen=[endpoint(free_port())])) as session:
        assert not session.is_closed()


def test_to_json_is_strict_json() -> None:
    import numpy as np

    text = to_json({"x": np.float32(0.5), "v": np.array([1.0, np.nan]), "inf": float("inf")})
    assert json.loads(text) == {"x": 0.5, "v": [1.0, None], "inf": None}
