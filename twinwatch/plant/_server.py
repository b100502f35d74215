"""The thread a simulated device's server runs in (the plant's Modbus and OPC UA servers): its
own asyncio loop, a start that returns once the server listens (or says why it could not), a
stop that joins it, as a context manager; and what both servers keep of the plant they serve."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
import time
from typing import ClassVar, Literal, Protocol, Self

from twinwatch._lifecycle import Closeable
from twinwatch.io.sample import EndOfStream, Sample

__all__ = ["Pacing", "PlantSource", "ServerThread", "free_tcp_port"]

Pacing = Literal["realtime", "lockstep"]
"""How a plant's server steps the plant: in real time, or as fast as its client keeps up."""


class PlantSource(Protocol):
    """What the server needs from a plant (e.g. :class:`~twinwatch.plant.dcmotor.DCMotorPlant`)."""

    @property
    def sample_period(self) -> float:
        """Seconds between samples."""
        ...

    @property
    def channels(self) -> tuple[str, ...]:
        """Names of the values in each sample."""
        ...

    def next_sample(self) -> Sample:
        """The next sample; raises EndOfStream after the last one."""
        ...


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerThread(Closeable):
    """A server of a plant's samples serving in a thread of its own (subclasses:
    :meth:`_serve`, a coroutine that sets ``_loop``, ``_stop_event`` and ``_ready`` once it
    listens and returns once ``_stop_event`` is set; ``__init__`` calls this one's).

    Args:
        plant: the sample source.
        pacing: ``"realtime"`` or ``"lockstep"``.
        host, port: where it listens (port 0: a free one, chosen at the first start).

    Attributes:
        cpu_seconds: CPU time [s] the server's thread has used in all its starts.
        sample_period: the plant's [s].
        samples_served: samples taken from the plant so far.
        last_sample: the last sample served (None before the first).
    """

    #: the device in messages (``"Modbus"``, ``"OPC UA"``)
    kind: ClassVar[str]
    #: its thread's name
    thread_name: ClassVar[str]
    #: seconds :meth:`start` waits for the server to listen
    start_timeout: ClassVar[float] = 5.0
    #: ``could not <listen_verb> <endpoint>`` when it fails to start
    listen_verb: ClassVar[str] = "start on"

    def __init__(self, plant: PlantSource, pacing: Pacing, host: str, port: int) -> None:
        self.plant = plant
        self.pacing: Pacing = pacing
        self.host = host
        self.port = port
        self.sample_period = float(plant.sample_period)
        self.samples_served = 0
        self.last_sample: Sample | None = None
        self._finished = False
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self.cpu_seconds = 0.0
        self._log = logging.getLogger(type(self).__module__)

    @property
    def endpoint(self) -> str:
        """Where it listens, for a person."""
        raise NotImplementedError

    @property
    def finished(self) -> bool:
        """True once the plant raised EndOfStream (the last sample stays served)."""
        return self._finished

    def _next_from_plant(self) -> Sample | None:
        """The plant's next sample, counted in :attr:`samples_served` and kept as
        :attr:`last_sample`; None once the plant has ended (logged when it ends)."""
        if self._finished:
            return None
        try:
            sample = self.plant.next_sample()
        except EndOfStream:
            self._finished = True
            self._log.info("plant finished after %d samples; serving the last one",
                           self.samples_served)
            return None
        self.samples_served += 1
        self.last_sample = sample
        return sample

    @property
    def running(self) -> bool:
        """The server's thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def _before_start(self) -> None:
        """What to settle before the thread starts (a free port)."""

    def start(self) -> Self:
        """Start serving (returns once the server listens).

        Raises:
            RuntimeError: already running, or the server could not listen (port in use, serial
                device missing: the message names it); the thread is joined before raising.
        """
        if self.running:
            raise RuntimeError(f"{type(self).__name__} is already running")
        self._before_start()
        self._ready.clear()
        self._start_error = None
        self._thread = threading.Thread(target=self._thread_main, name=self.thread_name,
                                        daemon=True)
        self._thread.start()
        if not self._ready.wait(self.start_timeout):
            self.stop()
            raise RuntimeError(f"{self.kind} server did not start within {self.start_timeout} s")
        if self._start_error is not None:
            err = self._start_error
            self.stop()
            raise RuntimeError(f"{self.kind} server could not {self.listen_verb} "
                               f"{self.endpoint}: {err}") from err
        self._log.info("plant %s server on %s (%s pacing)", self.kind, self.endpoint,
                       self.pacing)
        return self

    def stop(self) -> None:
        """Stop serving and join the thread. Idempotent; :meth:`start` may be called again."""
        thread, loop, stop_event = self._thread, self._loop, self._stop_event
        if thread is None:
            return
        if loop is not None and stop_event is not None and thread.is_alive():
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(stop_event.set)
        thread.join(self.start_timeout)
        if thread.is_alive():  # pragma: no cover - the loop is stuck
            self._log.warning("plant %s server thread did not stop in time", self.kind)
        self._thread = None
        self._log.debug("plant %s server on %s stopped", self.kind, self.endpoint)

    close = stop

    def __enter__(self) -> Self:
        if not self.running:
            self.start()
        return self

    def _thread_main(self) -> None:
        cpu0 = time.thread_time()
        try:
            with asyncio.Runner() as runner:
                runner.run(self._serve())
        except BaseException as exc:  # noqa: BLE001 - reported to start() or logged
            if not self._ready.is_set():
                self._start_error = exc
            else:
                self._log.error("plant %s server failed: %s", self.kind, exc)
        finally:
            self.cpu_seconds += time.thread_time() - cpu0
            self._loop = None
            self._ready.set()

    async def _serve(self) -> None:
        raise NotImplementedError
