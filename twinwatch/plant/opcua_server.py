"""Serve a simulated plant's samples as OPC UA variables (asyncua server, 127.0.0.1).

:class:`PlantOpcUaServer` runs an asyncua :class:`~asyncua.Server` in a background thread
(``twinwatch-opcua-server``) with its own asyncio loop. The address space holds one object,
``<ns>:<object_name>`` under Objects, with one Double variable per served channel
(NodeId ``ns=<ns>;s=<object_name>.<channel>``, browse name ``<ns>:<channel>``, namespace
:data:`NAMESPACE`), each with its ``EngineeringUnits`` property (an ``EUInformation`` with the
UNECE code of the unit, OPC UA Part 8). Every plant sample is written to every variable as a
``DataValue`` whose SourceTimestamp is the sample's time on a wall-clock base (the server's
start, POSIX, plus plant time) and whose ServerTimestamp is the wall clock.

Pacing: ``"realtime"``, a timer writes each sample when the wall clock reaches its plant time
(from the first ``may_advance()``; the plant's clock runs on while the server is stopped);
``"lockstep"``, bursts of ``burst`` samples, one per ``publishing_interval``, while
``may_advance()`` says the consumer keeps up (docs/opcua-input.md: a subscription cannot make
a server wait).

All variables are read-only (AccessLevel CurrentRead); the server offers security None only
and listens on the loopback interface.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable, Mapping
from datetime import UTC, datetime, timedelta
from typing import Any, Literal, cast

from twinwatch.io.sample import Sample
from twinwatch.io.threadlog import demote_thread_records
from twinwatch.plant._server import Pacing, PlantSource, ServerThread, free_tcp_port

__all__ = ["NAMESPACE", "PlantOpcUaServer", "PlantSource", "UNECE"]

#: The namespace URI of the simulated plants' variables.
NAMESPACE = "urn:twinwatch:simulated-plant"
#: unit -> (UNECE common code, display name) for the EngineeringUnits of the served variables
UNECE: Mapping[str, tuple[str, str]] = {
    "V": ("VLT", "V"), "A": ("AMP", "A"), "rad/s": ("2A", "rad/s"), "N m": ("NU", "N m"),
    "m": ("MTR", "m"), "Pa": ("PAL", "Pa"), "N": ("NEW", "N"), "m^2": ("MTK", "m^2"),
}
_UNECE_URI = "http://www.opcfoundation.org/UA/units/un/cefact"
_THREAD_NAME = "twinwatch-opcua-server"
_START_TIMEOUT = 20.0  # [s]: asyncua's server loads the standard address space at start
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


# asyncua's server records from the plant's server thread at DEBUG: a loopback server with
# security None warns at every start that it offers no signing (on purpose here), and a port
# already taken is logged with its traceback: PlantOpcUaServer.start says it in one line
demote_thread_records(_THREAD_NAME, (
    "asyncua.server.server", "asyncua.server.internal_server",
    "asyncua.server.binary_server_asyncio", "asyncua.server.address_space"))


def _node_id(identifier: str, ns: int) -> Any:
    """A string NodeId (asyncua's typed constructor)."""
    from asyncua import ua

    return ua.NodeId(ua.String(identifier), ua.Int16(ns))


class PlantOpcUaServer(ServerThread):
    """An OPC UA server serving a plant's samples on 127.0.0.1.

    Args:
        plant: the sample source.
        units: served channel -> unit (a key of :data:`UNECE`, or any text: then only the
            display name is set); channels not listed are not served.
        object_name: the object holding the variables (``"Motor"``).
        pacing: ``"realtime"`` or ``"lockstep"`` (module docstring).
        port: TCP port; 0 picks a free one (read :attr:`port` after :meth:`start`; a restart
            reuses it).
        publishing_interval: lock-step: seconds between bursts.
        burst: lock-step: samples per burst (at most a monitored item's queue).
        may_advance: lock-step: returns False while the consumer is behind.

    Attributes:
        samples_served: samples written so far. finished: the plant reached its end.
        base: POSIX time of plant time 0 (the source timestamps' base).
        cpu_seconds: CPU time [s] the server's thread has used in all its starts, the
            address space's set-up included (asyncua loads the standard nodes: ~1.5 s).
        serving_cpu_seconds: CPU time [s] the thread has used serving, all starts together
            (plant steps and writes, the subscriptions' publishing): updated after each write.
    """

    kind = "OPC UA"
    thread_name = _THREAD_NAME
    start_timeout = _START_TIMEOUT
    listen_verb = "listen on"

    def __init__(self, plant: PlantSource, units: Mapping[str, str], *,
                 object_name: str = "Motor", pacing: Pacing = "realtime",
                 host: Literal["127.0.0.1"] = "127.0.0.1", port: int = 0,
                 publishing_interval: float = 0.05, burst: int = 10,
                 may_advance: Callable[[], bool] | None = None) -> None:
        unknown = [ch for ch in units if ch not in plant.channels]
        if unknown or not units:
            raise ValueError(f"units: {', '.join(unknown) or 'nothing'} not plant channels "
                             f"({', '.join(plant.channels)})")
        super().__init__(plant, pacing, host, port)
        self.units = dict(units)
        self.object_name = object_name
        self.publishing_interval = publishing_interval
        self.burst = max(1, burst)
        self.may_advance = may_advance or (lambda: True)
        self.base = time.time()
        self.serving_cpu_seconds = 0.0
        self._cpu_ready = 0.0
        self._serving_before = 0.0
        self._t0_mono: float | None = None
        self._nodes: dict[str, Any] = {}
        self._server: Any = None
        self.ns = 2

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}"

    def node_id(self, channel: str) -> str:
        """The NodeId string of a served channel's variable."""
        return f"ns={self.ns};s={self.object_name}.{channel}"

    def _before_start(self) -> None:
        """Port 0: a free port picked now (the endpoint names it before the server starts)."""
        if self.port == 0:
            self.port = free_tcp_port()

    # -- the server thread ------------------------------------------------------------------
    async def _serve(self) -> None:
        from asyncua import Server, ua

        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        server = Server()
        self._server = server
        await server.init()
        server.set_endpoint(f"{self.endpoint}/twinwatch/")
        server.set_server_name("twinwatch simulated plant")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        self.ns = await server.register_namespace(NAMESPACE)
        obj = await server.nodes.objects.add_object(
            _node_id(self.object_name, self.ns), ua.QualifiedName(self.object_name, self.ns))
        self._nodes = {}
        for ch, unit in self.units.items():
            var = await obj.add_variable(_node_id(f"{self.object_name}.{ch}", self.ns),
                                         ua.QualifiedName(ch, self.ns),
                                         ua.Variant(0.0, ua.VariantType.Double))
            code, name = UNECE.get(unit, ("", unit))
            unit_id = int.from_bytes(code.encode("ascii"), "big") if code else -1
            eu = ua.EUInformation(NamespaceUri=_UNECE_URI, UnitId=unit_id,
                                  DisplayName=ua.LocalizedText(name),
                                  Description=ua.LocalizedText(name))
            await var.add_property(_node_id(f"{self.object_name}.{ch}.EngineeringUnits",
                                            self.ns),
                                   ua.QualifiedName("EngineeringUnits", 0),
                                   ua.Variant(eu, ua.VariantType.ExtensionObject))
            self._nodes[ch] = var.nodeid
            # no sample yet: the value says so (a subscriber skips it)
            await server.write_attribute_value(var.nodeid, ua.DataValue(
                ua.Variant(0.0, ua.VariantType.Double),
                StatusCode=ua.StatusCode(ua.UInt32(ua.StatusCodes.BadWaitingForInitialData))))
        if self.last_sample is not None:  # a restart serves the last sample again first
            await self._write(self.last_sample)
        await server.start()
        try:
            self._cpu_ready = time.thread_time()
            self._serving_before = self.serving_cpu_seconds
            self._ready.set()
            if self.pacing == "realtime":
                await self._realtime()
            else:
                await self._lockstep()
        finally:
            with contextlib.suppress(Exception):
                await server.stop()
        self._server = None

    async def _wait_stop(self, delay: float) -> bool:
        assert self._stop_event is not None
        try:
            await asyncio.wait_for(self._stop_event.wait(), max(0.0, delay))
        except TimeoutError:
            return False
        return True

    async def _realtime(self) -> None:
        while self._t0_mono is None and not self.may_advance():  # the plant's clock starts
            if await self._wait_stop(0.01):                        # with its first subscriber
                return
        if self._t0_mono is None:
            self._t0_mono = time.monotonic()
            self.base = time.time()
        while not self._finished:
            due = int((time.monotonic() - self._t0_mono) / self.sample_period + 1e-9) + 1
            while self.samples_served < due and not self._finished:
                await self._advance_one()
            nxt = self._t0_mono + self.samples_served * self.sample_period
            if await self._wait_stop(nxt - time.monotonic()):
                return
        await self._wait_stop(1e9)

    async def _lockstep(self) -> None:
        while not self._finished:
            if self.may_advance():
                for _ in range(self.burst):
                    await self._advance_one()
            if await self._wait_stop(self.publishing_interval):
                return
        await self._wait_stop(1e9)

    async def _advance_one(self) -> None:
        sample = self._next_from_plant()
        if sample is None:
            return
        await self._write(sample)
        self.serving_cpu_seconds = (self._serving_before + time.thread_time()
                                    - self._cpu_ready)

    async def _write(self, sample: Sample) -> None:
        from asyncua import ua

        source = cast("ua.DateTime", _EPOCH + timedelta(seconds=self.base + sample.t))
        now = cast("ua.DateTime", datetime.now(UTC))
        server = self._server
        for ch, nodeid in self._nodes.items():
            dv = ua.DataValue(ua.Variant(float(sample.values[ch]), ua.VariantType.Double),
                              SourceTimestamp=source, ServerTimestamp=now)
            await server.write_attribute_value(nodeid, dv)
