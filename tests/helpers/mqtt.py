"""A real Mosquitto broker and an MQTT subscriber for the MQTT output's tests (no mock broker).

:class:`Broker` runs Debian's ``/usr/sbin/mosquitto`` on 127.0.0.1 and a free port, from a
generated configuration (anonymous clients, persistence in the test's directory, so a stop and
a start keep the retained messages and a persistent subscriber's queue). ``.ci/run`` installs the
package where it can; without it the tests skip, saying so.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from .net import free_port
from .paths import ROOT

MOSQUITTO = shutil.which("mosquitto") or (
    "/usr/sbin/mosquitto" if os.path.exists("/usr/sbin/mosquitto") else None)

needs_mosquitto = pytest.mark.skipif(
    MOSQUITTO is None, reason="Mosquitto is not installed (Debian: apt-get install mosquitto; "
    ".ci/run installs it when it runs as root)")


class Broker:
    """A Mosquitto broker on 127.0.0.1:``port`` with its files in ``directory``."""

    def __init__(self, directory: Path, port: int | None = None, *, extra: str = "",
                 anonymous: bool = True) -> None:
        assert MOSQUITTO is not None
        self.directory = directory
        self.port = port or free_port()
        directory.mkdir(parents=True, exist_ok=True)
        self.conf = directory / "mosquitto.conf"
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            f"allow_anonymous {'true' if anonymous else 'false'}\n"
            f"{extra}"
            "persistence true\n"
            f"persistence_location {directory}/\n"
            "autosave_interval 1\n"
            "max_queued_messages 100000\n"
            "max_inflight_messages 0\n")
        if os.geteuid() == 0:
            # started as root, mosquitto runs as the user "mosquitto", who cannot enter the
            # test's private directory (its persistence, password file, certificates)
            self.conf.write_text(self.conf.read_text() + "user root\n")
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self) -> None:
        assert self.proc is None
        log = (self.directory / f"mosquitto.{self.starts}.log").open("wb")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=log,
                                     stderr=subprocess.STDOUT)
        self.starts += 1
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return
            except OSError:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"mosquitto exited: see {log.name}") from None
                time.sleep(0.05)
        raise RuntimeError("mosquitto did not listen within 10 s")

    def stop(self) -> None:
        """SIGTERM (mosquitto saves its persistence database) and wait."""
        proc, self.proc = self.proc, None
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def running_broker(directory: Path) -> Iterator[Broker]:
    """A started broker, stopped at the end (the tests' ``broker`` fixture)."""
    if MOSQUITTO is None:
        pytest.skip("Mosquitto is not installed (Debian: apt-get install mosquitto)")
    b = Broker(directory)
    b.start()
    try:
        yield b
    finally:
        for sub in list(Subscriber.open):  # also after a failed assertion: no thread leaks
            sub.close()
        b.stop()


@dataclass
class Message:
    topic: str
    payload: bytes
    retain: bool
    dup: bool


class Subscriber:
    """A paho client collecting every message of ``topics`` (QoS 1). ``persistent``: a session
    the broker keeps while it is away (its messages are queued for it, also across a broker
    restart with persistence)."""

    open: list[Subscriber] = []

    def __init__(self, port: int, topics: list[str], *, client_id: str | None = None,
                 persistent: bool = False, username: str | None = None,
                 password: str | None = None) -> None:
        import paho.mqtt.client as mqtt

        self.messages: list[Message] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2,
                                  client_id=client_id or f"test-sub-{free_port()}",
                                  clean_session=not persistent)
        self.client.reconnect_delay_set(0.1, 0.5)
        if username is not None:
            self.client.username_pw_set(username, password)
        self.topics = topics
        self.subscribed = threading.Event()
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        self.client.on_subscribe = lambda *a: self.subscribed.set()
        self.client.connect("127.0.0.1", port, keepalive=5)
        self.client.loop_start()
        Subscriber.open.append(self)
        assert self.subscribed.wait(10), "the subscriber was not subscribed within 10 s"

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any,
                    properties: Any) -> None:
        client.subscribe([(t, 1) for t in self.topics])

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        with self.lock:
            self.messages.append(Message(msg.topic, bytes(msg.payload), bool(msg.retain),
                                         bool(msg.dup)))

    def on(self, topic: str) -> list[Message]:
        with self.lock:
            return [m for m in self.messages if m.topic == topic]

    def wait(self, predicate: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout} s waiting for {what}")
            time.sleep(0.05)

    def close(self) -> None:
        if self in Subscriber.open:
            Subscriber.open.remove(self)
            self.client.disconnect()
            self.client.loop_stop()


def retained(port: int, topic: str, timeout: float = 2.0, *,
             expect: tuple[str, ...] = ()) -> dict[str, bytes]:
    """The retained messages under ``topic`` (a new clean subscriber: what a tool that
    connects now gets), collected for ``timeout`` s; with ``expect``, only until each of those
    topics has had its retained message (a topic keeps one: it is final)."""
    sub = Subscriber(port, [topic])
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not (
            expect and all(any(m.retain for m in sub.on(t)) for t in expect)):
        time.sleep(0.02)
    sub.close()
    return {m.topic: m.payload for m in sub.messages if m.retain}


def twinwatch(config: Path, *args: str, cwd: Path) -> subprocess.Popen[str]:
    """``twinwatch run CONFIG ARGS`` as a user runs it, in a subprocess."""
    env = dict(os.environ, CI="true", PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "twinwatch", "run", str(config),
                             "--no-progress", *args], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def mqtt_table(port: int, extra: str = "") -> str:
    return f"\n[outputs.mqtt]\nport = {port}\nkeepalive = 5\nreconnect_max = 1.0\n{extra}"


def make_pki(d: Path) -> None:
    """A CA, a certificate for the broker (127.0.0.1) and one for twinwatch, in ``d`` (openssl
    CLI; the keys 0600)."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl CLI is not installed")

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True, timeout=30)

    d.mkdir(parents=True, exist_ok=True)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
            "-subj", "/CN=twinwatch-test-ca")
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n"
                               "basicConstraints=CA:FALSE\nkeyUsage=digitalSignature\n"
                               "extendedKeyUsage=serverAuth,clientAuth\n")
    for name, cn in (("broker", "localhost"), ("twinwatch", "twinwatch")):
        openssl("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={cn}")
        openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", "ext.cnf")
        (d / f"{name}.key").chmod(0o600)


def finish(proc: subprocess.Popen[str], sig: int | None = None,
           timeout: float = 300) -> tuple[int, str, str]:
    if sig is not None:
        proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, out, err


def stored_window(store: Any, w: int, machine: str = "m1") -> Any:
    """Store one small health message as the gate does and return what write() gets."""
    from types import SimpleNamespace

    doc = json.dumps({"machine": machine, "window": w, "t_start": 2.0 * w,
                      "t_end": 2.0 * w + 1.99, "parameters": {"Ra": {
                          "value": 6.5 - 0.01 * w, "unit": "ohm", "deviation_pct": -0.15 * w,
                          "status": "estimated"}}, "alarms": {}})
    if store is not None:
        assert store.save_window({"machine": machine, "window": w, "t_start": 2.0 * w,
                                  "t_end": 2.0 * w + 1.99}, None, doc=doc)
    return SimpleNamespace(health=SimpleNamespace(window=w), health_json=doc, events=[])
