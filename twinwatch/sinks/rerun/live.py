"""The recording's live view (:class:`LiveServer`): a second recording stream, with the same
recording id and blueprint as the file's, whose only sink is Rerun's gRPC server. The file's
stream never touches it: the file's faults never disturb the viewers, and a server that fails
stops only the live view. A gRPC server does not stop while a viewer is connected (Rerun SDK
0.41), so a closed recorder parks its server (:data:`_LIVE`) for the next recorder on the same
address; it ends with the process.

Also here, the streams whose file writer died (:func:`bury`).
"""

from __future__ import annotations

import logging
import socket
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

from twinwatch.errors import RecorderError
from twinwatch.sinks.rerun.style import Op, rr, rrb
from twinwatch.sinks.rerun.views import emit

logger = logging.getLogger(__package__)  # the log lines name the package

__all__ = ["LiveServer", "bury"]

_LIVE: dict[tuple[str, int], tuple[Any, str]] = {}
"""Live servers of closed recorders, by address, with their URL."""
_LIVE_LOCK = threading.Lock()

_GRAVEYARD: list[Any] = []
"""Recording streams whose file writer died: kept referenced so that nothing frees them."""


def bury(rec: rr.RecordingStream) -> None:
    """Abandon a stream whose file writer died. With the Rerun SDK 0.41 every later flush,
    disconnect or new file on it, its ``__del__`` and the SDK's exit hook wait forever for the
    dead writer: disable the instance's helpers, keep it referenced for the life of the
    process, and unregister the exit hook (each recorder disconnects its own stream)."""
    rec._flush = lambda *args, **kwargs: None
    rec._disconnect_orphaned_recordings = lambda *args, **kwargs: None
    _GRAVEYARD.append((rec, getattr(rec, "inner", None)))
    rr.unregister_shutdown()


class LiveServer:
    """One recorder's live view on ``bind:port``.

    Args:
        machine: whose recording (for the log).
        bind, port: the gRPC server's address (``[recording] serve_bind``, ``serve_port``).
        memory_limit: the history the server keeps for late viewers
            (``server_memory_limit``, e.g. ``"25%"``).

    Attributes:
        stream: the live recording stream, None before :meth:`open` and once stopped or
            parked.
        url: where a viewer connects (``rerun+http://127.0.0.1:9876/proxy``) once open.
        problem: why the live view stopped (None while it runs).
    """

    def __init__(self, machine: str, bind: str, port: int, memory_limit: str) -> None:
        self.machine = machine
        self.bind = bind
        self.port = port
        self.memory_limit = memory_limit
        self.stream: rr.RecordingStream | None = None
        self.url: str | None = None
        self.problem: str | None = None

    def probe(self) -> None:
        """The live server's address is free.

        Raises:
            RecorderError: naming the address and the key to change.
        """
        bind, port = self.bind, self.port
        with _LIVE_LOCK:
            if (bind, port) in _LIVE:
                return  # this process's server, kept from a recorder closed before
        family = socket.AF_INET6 if ":" in bind else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((bind, port))
            except OSError as exc:
                raise RecorderError(
                    f"cannot serve the recording live on {bind}:{port}: {exc.strerror or exc} "
                    "(another viewer or twinwatch?); set [recording] serve_port") from None

    def open(self, application_id: str, recording_id: uuid.UUID, blueprint: rrb.Blueprint,
             log_static: Callable[[rr.RecordingStream], None], timeout: float) -> None:
        """Open :attr:`stream` with the blueprint and what ``log_static`` sends once; a server
        parked by a closed recorder (:meth:`park`) is taken over, with its viewers.

        Raises:
            RecorderError: the server does not listen within ``timeout`` [s].
        """
        bind, port = self.bind, self.port
        with _LIVE_LOCK:
            parked = _LIVE.pop((bind, port), None)
        if parked is not None:
            live, self.url = parked
            live.send_blueprint(blueprint, make_active=True, make_default=True)
            log_static(live)
            logger.info("recording of %s served live (the server goes on): rerun %s",
                        self.machine, self.url)
            self.stream = live
            return
        live = rr.RecordingStream(application_id, recording_id=recording_id)
        sink = rr.GrpcServerSink(bind_ip=bind, port=port, server_memory_limit=self.memory_limit)
        live.set_sinks(sink, default_blueprint=blueprint)
        url = sink.uri
        del sink  # the stream owns the server
        log_static(live)
        deadline = time.monotonic() + timeout
        while True:
            try:
                with socket.create_connection((bind if bind not in ("0.0.0.0", "::") else
                                               "127.0.0.1", port), timeout=0.5):
                    break
            except OSError as exc:
                if time.monotonic() > deadline:
                    live.disconnect()
                    raise RecorderError(f"the live recording server on {bind}:{port} does not "
                                        f"listen ({exc})") from None
                time.sleep(0.05)
        self.url = url
        logger.info("recording of %s served live: rerun %s", self.machine, self.url)
        self.stream = live

    def emit(self, ops: list[Op]) -> None:
        """Send one window to the live server; a failure stops the live view only."""
        live = self.stream
        if live is None:
            return
        try:
            emit(live, ops)
        except Exception as exc:  # noqa: BLE001 - the file goes on whatever the server does
            self.stream = None
            self.problem = f"live recording server stopped: {exc}"
            logger.error("%s; the file goes on", self.problem)
            bury(live)

    def park(self, flush_timeout: float) -> None:
        """Flush the live stream and keep it, with its server, for the next recorder on its
        address (it ends with the process)."""
        live, self.stream = self.stream, None
        if live is None:
            return
        try:
            live.flush(timeout_sec=flush_timeout)
        except Exception as exc:  # noqa: BLE001 - the file still closes
            logger.warning("flushing the live recording server: %s", exc)
        assert self.url is not None
        with _LIVE_LOCK:  # a later recorder on this address goes on with it
            _LIVE[(self.bind, self.port)] = (live, self.url)
