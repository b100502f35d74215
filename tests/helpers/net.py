"""Loopback networking for the tests: free ports, Zenoh sessions and routers (scouting off),
and waiting for a condition."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import pytest
import zenoh


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now (bound then released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    assert port != 7447
    return port


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def zsession(mode: str, *, listen: list[str] = (), connect: list[str] = ()) -> zenoh.Session:
    """A zenoh session on loopback, scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def wait_for(pred: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.05)
    pytest.fail(f"timed out after {timeout} s waiting for {what}")


def get_json(session: zenoh.Session, selector: str) -> list[Any]:
    out = []
    for r in session.get(selector, timeout=5.0):
        if r.ok is not None:
            out.append(json.loads(r.ok.payload.to_string()))
        else:
            out.append({"error": r.err.payload.to_string()})
    return out


class Collector:
    """Health messages received by a subscriber on the test's router."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.items: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, smp: zenoh.Sample) -> None:
        with self._lock:
            self.items.append(json.loads(smp.payload.to_string()))

    def snapshot(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.items)


class Router:
    """A zenoh router on ``ep`` that can be stopped and started again on the same port."""

    def __init__(self, ep: str) -> None:
        self.ep = ep
        self.session: zenoh.Session | None = None

    def start(self) -> None:
        deadline = time.monotonic() + 10
        while True:  # the port of the router just closed may take a moment to be free
            try:
                self.session = zsession("router", listen=[self.ep])
                return
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def stop(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


@contextmanager
def router_on(ep: str) -> Iterator[Router]:
    router = Router(ep)
    router.start()
    try:
        yield router
    finally:
        router.stop()
