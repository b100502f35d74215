"""Modbus driver: poll a device's registers (TCP or RTU) into twin samples; never writes.

A background thread (``twinwatch-modbus-poll``) owns the pymodbus client. It polls the
configured registers every ``poll_period`` (default: ``sample_period``), decodes them with
pymodbus' own :meth:`~pymodbus.client.mixin.ModbusClientMixin.convert_from_registers` and
hands complete samples to :meth:`~twinwatch.drivers.base.Driver.read` through a queue. The
thread exists so that ``read(timeout)`` never blocks much longer than ``timeout``: a pymodbus
sync request cannot be given a per-call deadline, and a device that stops answering holds a
request for ``timeout * (retries + 1)`` seconds.

Register map and requests
    ``[driver.registers]`` maps each twin channel to a register (:class:`ModbusChannelMap`:
    address, table, type, word order; :mod:`twinwatch.io.modbus_registers`); the twin value is
    ``raw * scale + offset``. The registers of one table are read as one block from the lowest
    to the highest mapped address (:func:`~twinwatch.io.modbus_registers.plan_blocks`: the
    device must answer reads of the unmapped registers between them); the block holding the
    counter is read first in each poll.

Time source (``time_source``)
    ``"clock"``: t [s] is :func:`time.monotonic` at the middle of the poll's first request
    (the acquisition computer's clock); a poll that falls more than one period behind its
    schedule counts the missed polls in ``stats.gaps``. ``"counter"``: t = counter *
    ``sample_period`` where ``counter`` is a uint16/uint32 register the device increments once
    per sample, i.e. the device's own clock. A configured counter (with either time source)
    counts duplicate polls, stale answers, gaps and restarts as
    :meth:`~twinwatch.drivers.base.Driver._count` says.

Lock-step (``lockstep = true``)
    For a simulated device that advances one sample each time its counter block is read
    (:class:`~twinwatch.plant.modbus_server.PlantModbusServer` with ``pacing="lockstep"``): the
    driver polls as fast as the caller consumes (one sample queued) and nothing is lost;
    ``live`` is then False. Needs ``time_source = "counter"``.

Failures
    A request that times out, a refused or dropped connection, and an exception response a
    device gives for a while (02, 04, 05, 06, 0A/0B: :data:`_TRANSIENT_EXCEPTION_CODES`) count
    in ``stats.errors`` (and ``stats.extra``: ``timeouts``, ``connect_failures``,
    ``exception_responses``). The client is then reopened after a jittered exponential backoff
    (0.1 s doubling up to ``backoff_max``), the outage logged as
    :class:`~twinwatch.drivers.base.QueuedDriver` does; :attr:`ModbusDriver.waiting` says since
    when and why. An exception response ILLEGAL FUNCTION or ILLEGAL DATA VALUE means the
    register map does not match the device: the polling stops and ``read`` raises
    :class:`~twinwatch.drivers.base.DriverOperationError` (the daemon reopens the driver with a
    longer backoff). A decoded NaN or infinite value counts in ``stats.bad_values`` and is
    delivered as it is; a response with the wrong number of registers in ``stats.bad_frames``.

Monitoring only: the driver sends read requests (function codes 3 and 4) and nothing else.

A commented ``[driver]`` table: ``twinwatch/config/samples/driver_modbus.toml``
(``twinwatch sample-config --driver modbus``).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, StrictFloat, StrictInt, model_validator
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse

from twinwatch.drivers.base import (
    DriverConfig,
    DriverInitializationError,
    QueuedDriver,
    Sample,
)
from twinwatch.io.counter import SampleCounter
from twinwatch.io.modbus_registers import (
    ModbusChannelMap,
    ModbusCounterMap,
    ModbusRegister,
    check_overlaps,
    plan_blocks,
)
from twinwatch.io.threadlog import demote_thread_records

logger = logging.getLogger(__name__)

__all__ = ["ModbusDriver", "ModbusDriverConfig"]

#: exception codes that mean "the register map does not fit this device" (not transient)
_FATAL_EXCEPTION_CODES = {1: "ILLEGAL FUNCTION", 3: "ILLEGAL DATA VALUE"}
#: exception codes a device answers for a while (a PLC being reprogrammed answers 02 for its
#: registers, a gateway 0A/0B for a device behind it): retried with backoff, never fatal
_TRANSIENT_EXCEPTION_CODES = {2: "ILLEGAL DATA ADDRESS", 4: "SERVER DEVICE FAILURE",
                              5: "ACKNOWLEDGE", 6: "SERVER DEVICE BUSY",
                              10: "GATEWAY PATH UNAVAILABLE",
                              11: "GATEWAY TARGET DEVICE FAILED TO RESPOND"}
_BACKOFF_INITIAL = 0.1  # [s]
_POLL_THREAD_NAME = "twinwatch-modbus-poll"


# -- configuration ----------------------------------------------------------------------------


class ModbusDriverConfig(DriverConfig):
    """Configuration of :class:`ModbusDriver` (the ``[driver]`` table with ``type = "modbus"``).

    Attributes:
        type: always ``"modbus"``.
        transport: ``"tcp"`` (Modbus TCP) or ``"rtu"`` (Modbus RTU on a serial line).
        host: TCP: the device's address (default the loopback 127.0.0.1).
        port: TCP: the device's port (default 502).
        serial_port: RTU: serial device path (``/dev/ttyUSB0``, a pseudo-terminal, ...).
        baudrate: RTU: line speed [bit/s].
        parity: RTU: ``"N"``, ``"E"`` or ``"O"``.
        stopbits: RTU: 1 or 2.
        bytesize: RTU: 7 or 8 data bits.
        device_id: Modbus unit / slave id (0-247).
        timeout: seconds to wait for one response (and for a TCP connect).
        retries: times pymodbus re-sends a request that timed out (0: the next poll retries).
        backoff_max: cap [s] of the reconnect delay (starts at 0.1 s, doubles, jittered).
        sample_period: nominal sample period [s] of the device's data (> 0).
        poll_period: seconds between polls; default ``sample_period``. With a counter, polling
            faster than the device samples (e.g. half the period) catches every sample; the
            extra polls are skipped as duplicates.
        time_source: ``"clock"`` or ``"counter"`` (see the module docstring).
        counter: the sample-counter register (uint16 or uint32); required by
            ``time_source = "counter"`` and by ``lockstep``.
        lockstep: poll only when the caller has taken the previous sample, as fast as it reads
            (for a simulated device that advances on each read of its counter block).
        registers: twin channel -> :class:`ModbusChannelMap`, at least one; the table order is
            the order of :attr:`ModbusDriver.channels`.
    """

    type: Literal["modbus"]
    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = Field(default="127.0.0.1", min_length=1)
    port: StrictInt = Field(default=502, ge=1, le=65535)
    serial_port: str | None = Field(default=None, min_length=1)
    baudrate: StrictInt = Field(default=19200, gt=0)
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    bytesize: Literal[7, 8] = 8
    device_id: StrictInt = Field(default=1, ge=0, le=247)
    timeout: StrictFloat = Field(default=1.0, gt=0, allow_inf_nan=False)
    retries: StrictInt = Field(default=0, ge=0, le=10)
    backoff_max: StrictFloat = Field(default=5.0, ge=_BACKOFF_INITIAL, allow_inf_nan=False)
    sample_period: StrictFloat = Field(gt=0, allow_inf_nan=False)
    poll_period: StrictFloat | None = Field(default=None, gt=0, allow_inf_nan=False)
    time_source: Literal["clock", "counter"] = "clock"
    counter: ModbusCounterMap | None = None
    lockstep: bool = False
    registers: dict[str, ModbusChannelMap] = Field(min_length=1)

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels this driver delivers (``registers``)."""
        return tuple(self.registers)

    @model_validator(mode="after")
    def _consistent(self) -> ModbusDriverConfig:
        if self.transport == "rtu" and self.serial_port is None:
            raise ValueError("serial_port is required with transport = 'rtu'")
        if self.transport == "tcp" and self.serial_port is not None:
            raise ValueError("serial_port is only for transport = 'rtu'")
        if self.time_source == "counter" and self.counter is None:
            raise ValueError("time_source = 'counter' needs counter = { address = ..., ... }")
        if self.lockstep and self.time_source != "counter":
            raise ValueError("lockstep = true needs time_source = 'counter'")
        if any(not name for name in self.registers):
            raise ValueError("registers: empty channel name")
        entries: dict[str, ModbusRegister] = {
            f"registers.{k}": v for k, v in self.registers.items()
        }
        if self.counter is not None:
            entries["counter"] = self.counter
        check_overlaps(entries)
        return self

    @property
    def effective_poll_period(self) -> float:
        """``poll_period``, or ``sample_period`` when not set [s]."""
        return self.sample_period if self.poll_period is None else self.poll_period

    def describe_endpoint(self) -> str:
        """``"tcp 127.0.0.1:502 device 1"`` / ``"rtu /dev/ttyUSB0 19200 8N1 device 1"``."""
        if self.transport == "tcp":
            return f"tcp {self.host}:{self.port} device {self.device_id}"
        return (
            f"rtu {self.serial_port} {self.baudrate} {self.bytesize}{self.parity}{self.stopbits}"
            f" device {self.device_id}"
        )


# -- pymodbus log noise -------------------------------------------------------------------------


# pymodbus logs every failed connect and every timeout at ERROR from the polling threads: at
# DEBUG, the driver reports an outage itself
demote_thread_records(_POLL_THREAD_NAME, ("pymodbus.logging",), critical=True)


# -- the driver -------------------------------------------------------------------------------


class _DeviceFailure(Exception):
    """A recoverable failure of one poll; ``kind`` names the stats.extra counter."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class _FatalConfigError(Exception):
    """The device refused the register map (ILLEGAL FUNCTION or ILLEGAL DATA VALUE)."""


_EXTRA_COUNTERS = (
    "polls",
    "duplicates",
    "reordered",
    "counter_resets",
    "timeouts",
    "connect_failures",
    "exception_responses",
    "outages",
    "reconnects",
    "dropped",
)
#: samples a live driver keeps for a caller that does not read (older ones are dropped)
_LIVE_QUEUE = 1024


class ModbusDriver(QueuedDriver):
    """Twin samples polled from a Modbus TCP or RTU device; read requests only.

    Args:
        base_dir: accepted for the driver contract; no path in this config is relative.

    Attributes:
        live: False in lock-step mode, True otherwise.
        blocks: the read requests of one poll, in order.
        client: the pymodbus sync client (owned by the polling thread; do not use it).

    Raises:
        DriverInitializationError: the client cannot be created (e.g. pyserial missing for
            RTU). An unreachable device is *not* an error here: the driver keeps trying.
    """

    config_class = ModbusDriverConfig
    sample_model = "hydraulic_actuator"
    sample_machine = "hydraulic-modbus"
    sample_title = "a hydraulic actuator read from a Modbus device"
    driver_name = "Modbus"

    @classmethod
    def probe(cls, config: DriverConfig, *, base_dir: Path | None = None) -> str | None:
        """``check-config``: connect to the device (TCP) or open the serial port (RTU), send
        nothing, close.

        Raises:
            DriverInitializationError: the device does not accept a connection.
        """
        assert isinstance(config, ModbusDriverConfig)
        client = cls._make_client(config)
        try:
            if not client.connect():
                raise DriverInitializationError(
                    f"Modbus device {config.describe_endpoint()} does not accept a connection")
        finally:
            client.close()
        return f"Modbus device {config.describe_endpoint()} accepted a connection (nothing sent)"

    @classmethod
    def reopens(cls, config: DriverConfig) -> bool:
        """A device may come and go: the driver reconnects itself, and a driver that gave up
        (the register map refused) is opened again by the daemon with backoff."""
        return True

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        """``"Modbus device tcp 127.0.0.1:502 device 1"``."""
        assert isinstance(config, ModbusDriverConfig)
        return f"Modbus device {config.describe_endpoint()}"

    def __init__(self, config: ModbusDriverConfig, *, base_dir: Path | None = None) -> None:
        super().__init__()
        self.config = config
        self.channels = tuple(config.registers)
        self.sample_period = config.sample_period
        self.live = not config.lockstep
        self.stats.extra.update({k: 0 for k in _EXTRA_COUNTERS})  # fixed keys: thread-safe reads
        self.blocks = plan_blocks(
            [*config.registers.values(), *([config.counter] if config.counter else [])],
            first=config.counter,
        )
        self._where = [  # channel -> (block index, offset in block, map)
            (ch, self._block_of(m), m) for ch, m in config.registers.items()
        ]
        self._counter_where = (
            None if config.counter is None else self._block_of(config.counter)
        )
        self._counter = SampleCounter(None if config.counter is None
                                      else config.counter.modulus)
        self._init_queue(1 if config.lockstep else _LIVE_QUEUE)
        self.client = self._make_client(config)
        self._thread = threading.Thread(
            target=self._run, name=f"{_POLL_THREAD_NAME}-{config.describe_endpoint()}", daemon=True
        )
        self._thread.start()
        logger.info(
            "Modbus driver polling %s every %.4g s (%s): %d request(s) per poll, channels %s",
            config.describe_endpoint(),
            config.effective_poll_period,
            "lock-step" if config.lockstep else f"time source {config.time_source}",
            len(self.blocks),
            ", ".join(self.channels),
        )

    # -- construction -----------------------------------------------------------------------
    def _block_of(self, reg: ModbusRegister) -> tuple[int, int]:
        for i, block in enumerate(self.blocks):
            if block.covers(reg):
                return i, reg.address - block.address
        raise AssertionError(f"no block covers {reg.describe()}")  # pragma: no cover

    @staticmethod
    def _make_client(config: ModbusDriverConfig) -> ModbusTcpClient | ModbusSerialClient:
        common: dict[str, Any] = {"timeout": config.timeout, "retries": config.retries,
                                  "name": "twinwatch"}
        try:
            if config.transport == "tcp":
                return ModbusTcpClient(config.host, port=config.port, **common)
            assert config.serial_port is not None
            return ModbusSerialClient(
                config.serial_port,
                baudrate=config.baudrate,
                parity=config.parity,
                stopbits=config.stopbits,
                bytesize=config.bytesize,
                **common,
            )
        except (RuntimeError, TypeError, ValueError) as exc:
            raise DriverInitializationError(
                f"cannot create the Modbus {config.transport} client: {exc}"
            ) from exc

    # -- polling (the driver's thread) ------------------------------------------------------
    def _run(self) -> None:
        period = self.config.effective_poll_period
        next_due = time.monotonic()
        backoff = _BACKOFF_INITIAL
        while not self._stop.is_set():
            if not self.config.lockstep:
                wait = next_due - time.monotonic()
                if wait > 0 and self._stop.wait(wait):
                    break
            try:
                t, regs = self._poll()
            except _DeviceFailure as exc:
                self._on_failure(exc)
                delay = self._jittered(backoff)
                backoff = min(2 * backoff, self.config.backoff_max)
                if self._stop.wait(delay):
                    break
                next_due = time.monotonic()
                continue
            except _FatalConfigError as exc:
                self._fatal = str(exc)
                logger.error("Modbus driver stopped: %s", exc)
                break
            backoff = _BACKOFF_INITIAL
            self._on_success()
            now = time.monotonic()
            next_due += period
            if next_due < now - period:  # fell behind: skip the polls we missed
                missed = int((now - next_due) // period)
                if self.config.counter is None:
                    self.stats.gaps += missed
                next_due += missed * period
            sample = self._assemble(t, regs)
            if sample is None:
                if self.config.lockstep:  # a lock-step source that stopped: don't spin
                    self._stop.wait(period)
                continue
            self._deliver(sample)
        self._close_client()

    def _poll(self) -> tuple[float, list[list[int]]]:
        """Read every block once; returns (clock time of the first request, registers)."""
        client = self.client
        if not client.connected and not client.connect():
            raise _DeviceFailure(
                "connect_failures", f"cannot connect to {self.config.describe_endpoint()}"
            )
        self.stats.extra["polls"] += 1
        out: list[list[int]] = []
        t_clock = 0.0
        for i, block in enumerate(self.blocks):
            t0 = time.monotonic()
            read = (client.read_input_registers if block.table == "input"
                    else client.read_holding_registers)
            try:
                rr = read(block.address, count=block.count, device_id=self.config.device_id)
            except ModbusIOException as exc:
                self._close_client()
                raise _DeviceFailure("timeouts", f"no response: {exc}") from exc
            except (ConnectionException, OSError) as exc:
                self._close_client()
                raise _DeviceFailure("connect_failures", f"connection lost: {exc}") from exc
            except ModbusException as exc:
                self._close_client()
                raise _DeviceFailure("timeouts", f"request failed: {exc}") from exc
            if i == 0:
                t_clock = 0.5 * (t0 + time.monotonic())
            self.stats.frames += 1
            if isinstance(rr, ExceptionResponse) or rr.isError():
                code = int(getattr(rr, "exception_code", 0))
                what = (
                    f"{block.table} registers {block.address}-{block.address + block.count - 1}"
                    f" (device {self.config.device_id})"
                )
                if code in _FATAL_EXCEPTION_CODES:
                    raise _FatalConfigError(
                        f"{self.config.describe_endpoint()} answered {_FATAL_EXCEPTION_CODES[code]}"
                        f" to a read of {what}: the register map does not match the device"
                    )
                name = _TRANSIENT_EXCEPTION_CODES.get(code, "")
                hint = (" (while a PLC is reprogrammed; if it lasts, the register map does not "
                        "match the device)" if code == 2 else "")
                raise _DeviceFailure(
                    "exception_responses",
                    f"exception {code:02d}{f' {name}' if name else ''} reading {what}{hint}")
            regs = list(rr.registers)
            if len(regs) != block.count:
                self.stats.bad_frames += 1
                self.log_once(
                    "short",
                    "Modbus response with %d registers to a read of %d; counted in "
                    "stats.bad_frames",
                    len(regs),
                    block.count,
                )
                raise _DeviceFailure("exception_responses", "response of the wrong length")
            out.append(regs)
        return t_clock, out

    def _assemble(self, t_clock: float, regs: list[list[int]]) -> Sample | None:
        """Decode one poll; None for a duplicate poll (counter has not advanced)."""
        t = t_clock
        if self._counter_where is not None:
            assert self.config.counter is not None
            bi, off = self._counter_where
            counter = self.config.counter
            raw = int(counter.decode(regs[bi][off : off + counter.count]))
            if self._count(self._counter, raw, "Modbus sample counter", unit="answer",
                           repeats_expected=True):
                return None
            if self.config.time_source == "counter":
                assert self._counter.count is not None
                t = self._counter.count * self.sample_period
        values: dict[str, float] = {}
        for ch, (bi, off), m in self._where:
            value = m.decode(regs[bi][off : off + m.count]) * m.scale + m.offset
            if not math.isfinite(value):
                self.stats.bad_values += 1
                self.log_once(
                    f"nonfinite:{ch}",
                    "Modbus %s -> %s decoded to %s; counted in stats.bad_values",
                    m.describe(),
                    ch,
                    value,
                )
            values[ch] = value
        return Sample(t, values)

    def _deliver(self, sample: Sample) -> None:
        if self.config.lockstep:
            while not self._stop.is_set():
                try:
                    self._queue.put(sample, timeout=0.1)
                    return
                except queue.Full:
                    continue
            return
        self._put_dropping_oldest(sample)

    @property
    def waiting(self) -> str | None:
        """While the device does not answer (or answers with exceptions): since when and the
        last error; None while it delivers."""
        since = self._down_since
        if since is None:
            return None
        return (f"Modbus device {self.config.describe_endpoint()} not answering for "
                f"{time.monotonic() - since:.0f} s ({self._last_error}); retrying with backoff "
                f"up to {self.config.backoff_max:g} s")

    def _on_failure(self, exc: _DeviceFailure) -> None:
        self.stats.extra[exc.kind] += 1
        where = self.config.describe_endpoint()
        self._outage(str(exc), "Modbus device %s not available: %s; retrying with backoff up "
                     "to %.3g s (further failures at DEBUG)", where, exc,
                     self.config.backoff_max, again=f"Modbus device {where} still down: {exc}")

    def _on_success(self) -> None:
        down = self._recovered()
        if down is not None:
            logger.warning(
                "Modbus device %s is back after %.2f s down (%d errors so far)",
                self.config.describe_endpoint(),
                down,
                self.stats.errors,
            )

    def _close_client(self) -> None:
        try:
            self.client.close()
        except (OSError, ModbusException) as exc:  # pragma: no cover - closing a dead socket
            logger.debug("closing the Modbus client: %s", exc)

    # -- closing ----------------------------------------------------------------------------
    def _close_internal(self) -> None:
        self._stop.set()
        thread = getattr(self, "_thread", None)
        if thread is not None and thread.is_alive():
            thread.join(self.config.timeout * (self.config.retries + 1) + 2.0)
            if thread.is_alive():  # pragma: no cover - a request hung beyond its timeout
                logger.warning("Modbus polling thread did not stop in time")
        logger.debug("Modbus driver closed (%s)", self.stats.as_dict())
