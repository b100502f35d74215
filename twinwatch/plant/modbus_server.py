"""Serve a simulated plant's samples as a Modbus device (pymodbus server, TCP or RTU).

:class:`PlantModbusServer` runs a pymodbus async server in a background thread
(``twinwatch-modbus-server``) with its own asyncio loop. Each plant sample is encoded into
registers with the *same* register map model the driver decodes with
(:class:`~twinwatch.drivers.modbus.ModbusChannelMap`,
:class:`~twinwatch.drivers.modbus.ModbusCounterMap`), using pymodbus'
:meth:`~pymodbus.client.mixin.ModbusClientMixin.convert_to_registers`:
``raw = (value - offset) / scale``, integers rounded and saturated (logged once). A sample
counter register (``round(t / sample_period)``, wrapping) lets a client tell new samples from
repeated ones.

Pacing:

* ``"realtime"``: a timer advances the plant at the wall-clock rate, one sample every
  ``sample_period``. The plant's clock keeps running while the server is stopped: after a
  restart the plant catches up with the wall clock and the counter jumps (a client sees the gap).
* ``"lockstep"``: the plant advances exactly once each time a client reads a register block
  that holds (part of) the counter, and that read already returns the new sample (the first
  such read returns sample 0). A client that reads the counter block first in every poll
  (as :class:`~twinwatch.drivers.modbus.ModbusDriver` does) sees every sample exactly once,
  however fast or slow it polls (:meth:`PlantModbusServer._on_request`).

When the plant raises :class:`~twinwatch.drivers.base.EndOfStream` the server keeps serving
the last sample (the counter stops; :attr:`PlantModbusServer.finished` becomes True).

Faults on a schedule (tests): while :attr:`PlantModbusServer.exception_code` is set, every read
is answered with that Modbus exception (2: ILLEGAL DATA ADDRESS, what a PLC answers while its
program is downloaded; 6: SERVER DEVICE BUSY, ...) instead of its registers; the plant goes on.

All registers are read-only: a write request is answered with ILLEGAL DATA ADDRESS.
Registers between mapped ones (in the span of a table) read as 0.

For RTU tests without hardware, :class:`PtyLink` is a virtual null-modem cable: two
pseudo-terminals whose master sides a thread cross-connects (what ``socat pty pty`` does).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import select
import threading
import time
import tty
from collections.abc import Mapping

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from twinwatch._lifecycle import Closeable
from twinwatch.io.modbus_registers import (
    FUNCTION_CODES,
    ModbusChannelMap,
    ModbusCounterMap,
    ModbusRegister,
    check_overlaps,
)
from twinwatch.io.sample import Sample
from twinwatch.plant._server import Pacing, PlantSource, ServerThread, free_tcp_port

logger = logging.getLogger(__name__)

__all__ = ["PlantModbusServer", "PlantSource", "PtyLink", "free_tcp_port"]

class PlantModbusServer(ServerThread):
    """A Modbus TCP (or RTU) device serving a plant's samples.

    Args:
        plant: the sample source (``sample_period``, ``channels``, ``next_sample()``).
        registers: plant channel -> register map (the driver's model); every channel must be
            one of ``plant.channels``; a subset is fine.
        counter: the sample-counter register; None serves no counter (then ``"lockstep"``
            is not possible).
        pacing: ``"realtime"`` or ``"lockstep"`` (see the module docstring).
        host: TCP address to listen on.
        port: TCP port; 0 picks a free one (read it from :attr:`port` after :meth:`start`;
            a restart reuses it).
        serial_port: serve Modbus RTU on this serial device instead of TCP.
        baudrate, parity, stopbits, bytesize: RTU line settings.
        device_id: the unit id served (requests for another id get an exception response).

    Raises:
        ValueError: a mapped channel is not a plant channel, registers overlap, or lock-step
            without a counter.
    """

    kind = "Modbus"
    thread_name = "twinwatch-modbus-server"

    def __init__(
        self,
        plant: PlantSource,
        registers: Mapping[str, ModbusChannelMap],
        *,
        counter: ModbusCounterMap | None = None,
        pacing: Pacing = "realtime",
        host: str = "127.0.0.1",
        port: int = 0,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        stopbits: int = 1,
        bytesize: int = 8,
        device_id: int = 1,
    ) -> None:
        unknown = [ch for ch in registers if ch not in plant.channels]
        if unknown:
            raise ValueError(
                f"registers: {', '.join(unknown)} not plant channels "
                f"({', '.join(plant.channels)})"
            )
        if not registers:
            raise ValueError("registers: at least one channel")
        if pacing == "lockstep" and counter is None:
            raise ValueError("lockstep pacing needs a counter register")
        entries: dict[str, ModbusRegister] = {f"registers.{k}": v for k, v in registers.items()}
        if counter is not None:
            entries["counter"] = counter
        check_overlaps(entries)
        super().__init__(plant, pacing, host, port)
        self.registers = dict(registers)
        self.counter = counter
        self.serial_port = serial_port
        self.baudrate, self.parity, self.stopbits, self.bytesize = (
            baudrate, parity, stopbits, bytesize)
        self.device_id = device_id
        # register image per table: table -> (first address, registers)
        self._spans: dict[str, tuple[int, list[int]]] = {}
        for reg in entries.values():
            lo, hi = reg.address, reg.end
            if reg.table in self._spans:
                start, regs = self._spans[reg.table]
                lo, hi = min(lo, start), max(hi, start + len(regs))
            self._spans[reg.table] = (lo, [0] * (hi - lo))
        self._inexact_logged: set[str] = set()
        self._t0_wall: float | None = None  # monotonic time of sample 0 (realtime)
        self._lock = threading.Lock()  # guards the plant and the register image
        #: answer every read with this Modbus exception code while set (None: serve)
        self.exception_code: int | None = None

    # -- lifecycle --------------------------------------------------------------------------
    @property
    def endpoint(self) -> str:
        if self.serial_port is not None:
            return f"rtu {self.serial_port}"
        return f"tcp {self.host}:{self.port}"

    # -- the server thread ------------------------------------------------------------------
    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        device = SimDevice(id=self.device_id, simdata=self._simdata(), action=self._on_request)
        server: ModbusTcpServer | ModbusSerialServer
        if self.serial_port is not None:
            server = ModbusSerialServer(
                device,
                port=self.serial_port,
                baudrate=self.baudrate,
                parity=self.parity,
                stopbits=self.stopbits,
                bytesize=self.bytesize,
                reconnect_delay=0.0,
            )
        else:
            server = ModbusTcpServer(device, address=(self.host, self.port))
        await server.serve_forever(background=True)
        try:
            if self.serial_port is None:
                listener = server.transport
                sockets = getattr(listener, "sockets", None) or []
                if sockets:
                    self.port = int(sockets[0].getsockname()[1])
            timer = None
            if self.pacing == "realtime":
                self._advance_realtime()
                timer = asyncio.create_task(self._realtime_timer(), name="twinwatch-plant-timer")
            self._ready.set()
            await self._stop_event.wait()
            if timer is not None:
                timer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await timer
        finally:
            await server.shutdown()

    def _simdata(
        self,
    ) -> tuple[list[SimData], list[SimData], list[SimData], list[SimData]]:
        """pymodbus blocks: (coils, discrete inputs, holding, input); all read-only."""

        def table(name: str) -> list[SimData]:
            if name not in self._spans:  # a table we do not serve: one invalid register
                return [SimData(0, datatype=DataType.INVALID)]
            start, regs = self._spans[name]
            return [
                SimData(start, count=len(regs), values=0, datatype=DataType.REGISTERS,
                        readonly=True)
            ]

        bits = [SimData(0, values=False, datatype=DataType.BITS, readonly=True)]
        return (bits, list(bits), table("holding"), table("input"))

    async def _on_request(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus' SimDevice action, awaited before each request is answered.

        Lock-step: a read of the counter's block advances the plant first. Then the request's
        table is refreshed from the register image (``registers`` is pymodbus' live list for
        that table, modified in place).
        """
        table = next((t for t, fc in FUNCTION_CODES.items() if fc == function_code), None)
        if table is None or set_values is not None:
            return None  # coils / writes: pymodbus refuses them (read-only)
        code = self.exception_code
        if code is not None:
            return ExcCodes(code)
        with self._lock:
            c = self.counter
            if (
                self.pacing == "lockstep"
                and c is not None
                and c.table == table
                and address < c.end
                and c.address < address + count
            ):
                self._advance_one()
            span = self._spans.get(table)
            if span is not None and span[0] == start_address:
                registers[: len(span[1])] = span[1]
        return None

    async def _realtime_timer(self) -> None:
        while True:
            assert self._t0_wall is not None
            k_next = self.samples_served
            due = self._t0_wall + k_next * self.sample_period
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            with self._lock:
                self._advance_realtime()
            if self._finished:
                return

    # -- plant stepping (under self._lock or from the loop thread) --------------------------
    def _advance_realtime(self) -> None:
        """Step the plant up to the sample due now (more than one after a stall)."""
        now = time.monotonic()
        if self._t0_wall is None:
            self._t0_wall = now
        due = int((now - self._t0_wall) / self.sample_period + 1e-9) + 1  # samples due by now
        while self.samples_served < due and not self._finished:
            self._advance_one()

    def _advance_one(self) -> None:
        sample = self._next_from_plant()
        if sample is not None:
            self._write(sample)

    def _write(self, sample: Sample) -> None:
        for ch, m in self.registers.items():
            value = sample.values[ch]
            raw = (value - m.offset) / m.scale if m.scale != 0 else math.nan
            regs, exact = m.encode(raw)
            if not exact and ch not in self._inexact_logged:
                self._inexact_logged.add(ch)
                logger.warning(
                    "%s = %s does not fit %s (scale %s, offset %s): saturated",
                    ch, value, m.describe(), m.scale, m.offset,
                )
            self._put(m, regs)
        if self.counter is not None:
            k = int(round(sample.t / self.sample_period)) % self.counter.modulus
            self._put(self.counter, self.counter.encode(k)[0])

    def _put(self, reg: ModbusRegister, regs: list[int]) -> None:
        start, image = self._spans[reg.table]
        image[reg.address - start : reg.end - start] = regs


class PtyLink(Closeable):
    """A virtual null-modem cable: two pseudo-terminals cross-connected by a thread.

    Bytes written to :attr:`port_a` come out of :attr:`port_b` and vice versa, like
    ``socat -d -d pty,raw,echo=0 pty,raw,echo=0``. Open each end with pyserial (pymodbus'
    serial client and server do). Use as a context manager; :meth:`close` joins the thread.

    Raises:
        OSError: no pseudo-terminals on this system.
    """

    def __init__(self) -> None:
        self._fds: list[int] = []
        self._masters: tuple[int, int]
        master_a, slave_a = os.openpty()
        self._fds += [master_a, slave_a]
        master_b, slave_b = os.openpty()
        self._fds += [master_b, slave_b]
        for fd in (slave_a, slave_b):
            tty.setraw(fd)  # no echo, no line discipline until pyserial configures the port
        self.port_a = os.ttyname(slave_a)
        self.port_b = os.ttyname(slave_b)
        self._masters = (master_a, master_b)
        self._wake_r, self._wake_w = os.pipe()
        self._fds += [self._wake_r, self._wake_w]
        self._thread = threading.Thread(target=self._pump, name="twinwatch-pty-link", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        a, b = self._masters
        other = {a: b, b: a}
        while True:
            ready, _, _ = select.select([a, b, self._wake_r], [], [], 1.0)
            if self._wake_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:  # EIO: the other side's slave is not open right now
                    time.sleep(0.01)
                    continue
                if data:
                    os.write(other[fd], data)

    def close(self) -> None:
        """Stop the pump thread and close the terminals. Idempotent."""
        if not self._fds:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(2.0)
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds = []
