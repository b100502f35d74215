"""The simulated hydraulic actuator, served as a Modbus TCP device on loopback and read back.

The plant (:mod:`twinwatch.plant.hydraulic`, paper Section 4.2 and 5.3) is served by a
:class:`~twinwatch.plant.modbus_server.PlantModbusServer` on ``127.0.0.1:<port>``; a
:class:`~twinwatch.drivers.modbus.ModbusDriver` polls it over TCP exactly as it would poll a
real hydraulic controller, so every sample travels the real Modbus data path (register
encoding, float32 word order, scaled integers, the sample counter, timeouts, reconnects).


The default register map (input registers, function code 4; 0-based PDU addresses; 32-bit
values high word first, i.e. ``word_order = "big"``; ``twin value = raw * scale + offset``):

=======  ========  =======  ======  =====  =======================================
address  channel   type     scale   unit   why this encoding
=======  ========  =======  ======  =====  =======================================
0-1      counter   uint32   --      --     sample index, round(t / sample_period)
2-3      x         float32  1       m      0.05-0.95 m; float32 resolves 6e-8 m
4-5      p         float32  1       Pa     ~50 kPa; D*v is only ~7 Pa of it, and
                                           float32 resolves 0.004 Pa (int16/32 with a
                                           usable range would not)
6-7      A_valve   uint32   1e-12   m^2    0-7.2e-5 m^2 -> 0-7.2e7 counts, 1.4e-8
                                           relative at full opening (float32: 6e-8)
8-9      F_load    int32    1e-3    N      9810 N -> 9 810 000 counts (+-2.1 MN)
10-11    x_ref     float32  1       m      the position reference (not a twin input)
=======  ========  =======  ======  =====  =======================================

With this map the D published over Modbus equals the one from the plant's exact values to well
within the paper's 3 % (tests/test_hydraulic_e2e.py).

Monitoring only: the driver sends read requests and nothing else; the server it starts
listens on the loopback interface only and answers writes with an exception.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Literal

from pydantic import Field, StrictFloat, StrictInt, model_validator

from twinwatch.drivers.base import (
    DriverConfig,
    EndOfStream,
    PlantDriver,
    Sample,
)
from twinwatch.io.modbus_registers import ModbusChannelMap, ModbusCounterMap, check_overlaps
from twinwatch.plant.hydraulic import CHANNELS, HydraulicPlant, HydraulicPlantConfig

if TYPE_CHECKING:  # imported when the driver opens: validating a config loads no pymodbus
    from twinwatch.drivers.modbus import ModbusDriver, ModbusDriverConfig

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_COUNTER",
    "DEFAULT_REGISTERS",
    "LOOPBACK",
    "SimulatedModbusDriver",
    "SimulatedModbusDriverConfig",
]

#: The only address the simulated device listens on and the driver connects to.
LOOPBACK: Literal["127.0.0.1"] = "127.0.0.1"

#: The default sample-counter register (see the module docstring).
DEFAULT_COUNTER = ModbusCounterMap(address=0, table="input", type="uint32", word_order="big")

#: The default register map, channel -> register (see the module docstring).
DEFAULT_REGISTERS: Mapping[str, ModbusChannelMap] = {
    "x": ModbusChannelMap(address=2, table="input", type="float32", unit="m"),
    "p": ModbusChannelMap(address=4, table="input", type="float32", unit="Pa"),
    "A_valve": ModbusChannelMap(address=6, table="input", type="uint32", scale=1e-12,
                                unit="m^2"),
    "F_load": ModbusChannelMap(address=8, table="input", type="int32", scale=1e-3, unit="N"),
    "x_ref": ModbusChannelMap(address=10, table="input", type="float32", unit="m"),
}


class SimulatedModbusDriverConfig(DriverConfig):
    """The ``[driver]`` table with ``type = "simulated_modbus"``.

    Attributes:
        plant: the hydraulic plant's scenario, duration, noise, ... (``[driver.plant]``).
        pacing: ``"lockstep"`` (as fast as possible, nothing lost) or ``"realtime"``.
        timeout: the driver's per-request timeout [s].
        backoff_max: cap of the driver's reconnect delay [s].
        registers: plant channel -> register (default :data:`DEFAULT_REGISTERS`); the twin
            needs ``x``, ``p``, ``A_valve`` and ``F_load``.
        counter: the sample-counter register (default :data:`DEFAULT_COUNTER`).
    """

    type: Literal["simulated_modbus"]
    machine: Literal["hydraulic_actuator"] = "hydraulic_actuator"
    plant: HydraulicPlantConfig = Field(default_factory=HydraulicPlantConfig)
    host: Literal["127.0.0.1"] = Field(
        LOOPBACK, description="loopback only: the simulated device is never exposed")
    port: StrictInt = Field(5020, ge=0, le=65535, description="TCP port on 127.0.0.1 (0: any free)")
    pacing: Literal["lockstep", "realtime"] = "lockstep"
    timeout: StrictFloat = Field(0.5, gt=0, allow_inf_nan=False)
    backoff_max: StrictFloat = Field(1.0, ge=0.1, allow_inf_nan=False)
    registers: dict[str, ModbusChannelMap] = Field(
        default_factory=lambda: dict(DEFAULT_REGISTERS), min_length=1)
    counter: ModbusCounterMap = Field(default_factory=lambda: DEFAULT_COUNTER)

    @model_validator(mode="after")
    def _check(self) -> SimulatedModbusDriverConfig:
        unknown = [ch for ch in self.registers if ch not in CHANNELS]
        if unknown:
            raise ValueError(f"registers: {', '.join(unknown)} not channels of the hydraulic "
                             f"plant ({', '.join(CHANNELS)})")
        check_overlaps({**{f"registers.{k}": v for k, v in self.registers.items()},
                        "counter": self.counter})
        return self

    def twin_channels(self) -> tuple[str, ...]:
        """The plant channels served (``registers``)."""
        return tuple(self.registers)

    @property
    def sample_period(self) -> float:
        """The plant's sample period [s] (cross-checked against acquisition.sample_period)."""
        return self.plant.sample_period

    def modbus_config(self, port: int) -> ModbusDriverConfig:
        """The :class:`ModbusDriverConfig` that reads the simulated device on ``port``."""
        from twinwatch.drivers.modbus import ModbusDriverConfig

        return ModbusDriverConfig(
            type="modbus",
            transport="tcp",
            host=LOOPBACK,
            port=port,
            timeout=self.timeout,
            backoff_max=self.backoff_max,
            sample_period=self.plant.sample_period,
            # real time: poll twice per sample, so scheduling jitter never skips a sample (the
            # extra polls are duplicates, skipped); lock-step polls as fast as it is read
            poll_period=self.plant.sample_period / 2 if self.pacing == "realtime" else None,
            time_source="counter",
            counter=self.counter,
            lockstep=self.pacing == "lockstep",
            registers=dict(self.registers),
        )


class SimulatedModbusDriver(PlantDriver):
    """Hydraulic plant -> :class:`PlantModbusServer` (TCP, loopback) -> :class:`ModbusDriver`.

    Attributes:
        plant: the simulated plant (its :meth:`~HydraulicPlant.truth` gives the true D and C).
        server: the Modbus device serving it (tests stop and restart it).
        modbus: the Modbus driver reading it; its counters are this driver's :attr:`stats`.

    Raises:
        DriverInitializationError: the server cannot listen (port in use) or the client
            cannot be created.
        EndOfStream: from :meth:`read` once the plant has reached its duration and every
            sample served has been delivered.
    """

    config_class = SimulatedModbusDriverConfig
    sample_model = "hydraulic_actuator"
    sample_machine = "hydraulic-sim"
    sample_title = "the simulated hydraulic actuator (paper Section 5.3) over Modbus TCP"
    driver_name = "simulated Modbus"

    def __init__(self, config: SimulatedModbusDriverConfig) -> None:
        from twinwatch.drivers.modbus import ModbusDriver
        from twinwatch.plant.modbus_server import PlantModbusServer

        super().__init__(config, live=config.pacing == "realtime")
        self.plant = HydraulicPlant(config.plant)
        self.server = PlantModbusServer(self.plant, config.registers, counter=config.counter,
                                        pacing=config.pacing, host=LOOPBACK, port=config.port)
        self.modbus: ModbusDriver | None = None

        def open_inner() -> ModbusDriver:
            self.server.start()
            return ModbusDriver(config.modbus_config(self.server.port))

        self.modbus = self._open_inner(open_inner,
                                       "simulated Modbus device could not start: {exc}")
        logger.info("simulated hydraulic plant, scenario %s, %.0f s, served over Modbus TCP "
                    "on %s:%d (%s pacing)", config.plant.scenario, config.plant.duration,
                    LOOPBACK, self.server.port, config.pacing)

    def _read_internal(self, timeout: float | None) -> Sample | None:
        sample = self._take(1.0 if timeout is None else timeout)
        if sample is None and self.server.finished:
            # The plant's last sample is put in the driver's queue before the server notices
            # the end (on the next counter read): look once more before ending the stream.
            sample = self._take(0.0)
            if sample is None:
                raise EndOfStream(
                    f"simulated plant reached its duration ({self.config.plant.duration} s)")
        return sample
