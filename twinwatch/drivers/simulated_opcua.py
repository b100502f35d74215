"""The simulated DC motor (or hydraulic actuator), served by an OPC UA server on loopback and
read back through a subscription (docs/opcua-input.md, "The simulated motor over OPC UA").

The plant (:mod:`twinwatch.plant.dcmotor`, paper Section 5.2; or :mod:`twinwatch.plant.hydraulic`,
Section 5.3, with ``machine = "hydraulic_actuator"``) is served by a
:class:`~twinwatch.plant.opcua_server.PlantOpcUaServer` on ``127.0.0.1:<port>`` (object
``Motor``: ``Va`` [V], ``ia`` [A], ``omega`` [rad/s], ``Tload`` [N m], ``setpoint`` [rad/s];
or ``Actuator``: ``x`` [m], ``p`` [Pa], ``A_valve`` [m^2], ``F_load`` [N], ``x_ref`` [m]) and
read by an :class:`~twinwatch.drivers.opcua.OpcUaDriver` through a real subscription.
``pacing``: ``"lockstep"`` (default, not ``live``: in-process flow control, nothing lost) or
``"realtime"`` (``live``; stopping :attr:`SimulatedOpcUaDriver.server` costs a counted gap).
The source timestamps are plant time on a wall-clock base, which the driver subtracts: ``t`` is
plant time. Monitoring only: the variables are read-only, the server listens on loopback.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Literal

from pydantic import Field, StrictFloat, StrictInt, model_validator

from twinwatch.drivers.base import (
    DriverConfig,
    EndOfStream,
    PlantDriver,
    Sample,
)
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
from twinwatch.plant.hydraulic import CHANNEL_UNITS as HYDRAULIC_UNITS
from twinwatch.plant.hydraulic import HydraulicPlant, HydraulicPlantConfig

if TYPE_CHECKING:  # imported when the driver opens: validating a config loads no asyncua
    from twinwatch.drivers.opcua import OpcUaDriver, OpcUaDriverConfig
    from twinwatch.plant.opcua_server import PlantOpcUaServer

logger = logging.getLogger(__name__)

__all__ = ["LOOPBACK", "SERVED", "UNITS", "SimulatedOpcUaDriver", "SimulatedOpcUaDriverConfig"]

LOOPBACK: Literal["127.0.0.1"] = "127.0.0.1"
_END_WAIT = 10.0  # [s] without a sample after the plant's end: its last samples were lost
_END_WAIT_RECONNECTING = 60.0  # [s] the same while the driver reconnects
#: The served channels and their units (the variables' EngineeringUnits).
UNITS: Mapping[str, str] = {"Va": "V", "ia": "A", "omega": "rad/s", "Tload": "N m",
                            "setpoint": "rad/s"}
#: machine -> (the object holding its variables, channel -> unit)
SERVED: Mapping[str, tuple[str, Mapping[str, str]]] = {
    "dc_motor": ("Motor", UNITS),
    "hydraulic_actuator": ("Actuator", HYDRAULIC_UNITS),
}


class SimulatedOpcUaDriverConfig(DriverConfig):
    """The ``[driver]`` table with ``type = "simulated_opcua"``.

    Attributes:
        machine: ``"dc_motor"`` (object ``Motor``) or ``"hydraulic_actuator"`` (object
            ``Actuator``: ``x`` [m], ``p`` [Pa], ``A_valve`` [m^2], ``F_load`` [N], ``x_ref``
            [m]).
        plant: the plant's scenario, duration, noise, ... (``[driver.plant]``: the DC
            motor's or the hydraulic actuator's keys, by ``machine``).
        pacing: ``"lockstep"`` (as fast as the consumer, nothing lost) or ``"realtime"``.
        publishing_interval: the subscription's publishing interval [s].
        timeout, backoff_max: the driver's request timeout and reconnect cap [s].
    """

    type: Literal["simulated_opcua"]
    machine: Literal["dc_motor", "hydraulic_actuator"] = "dc_motor"
    plant: DCMotorPlantConfig | HydraulicPlantConfig = Field(
        default_factory=DCMotorPlantConfig, union_mode="left_to_right",
        description="the plant of machine: the DC motor's keys below; the hydraulic "
        "actuator's are those of [driver] type = \"simulated_modbus\"")
    host: Literal["127.0.0.1"] = Field(
        LOOPBACK, description="loopback only: the simulated server is never exposed")
    port: StrictInt = Field(4841, ge=0, le=65535,
                            description="TCP port on 127.0.0.1 (0: any free)")
    pacing: Literal["lockstep", "realtime"] = "lockstep"
    publishing_interval: StrictFloat = Field(0.05, gt=0, allow_inf_nan=False)
    queue_size: StrictInt = Field(400, ge=4, le=100000,
                                  description="per monitored item; lock-step bursts: a quarter")
    timeout: StrictFloat = Field(5.0, gt=0, allow_inf_nan=False)
    backoff_max: StrictFloat = Field(1.0, ge=0.1, allow_inf_nan=False)

    @model_validator(mode="after")
    def _plant_of_the_machine(self) -> SimulatedOpcUaDriverConfig:
        if self.machine == "hydraulic_actuator" and isinstance(self.plant, DCMotorPlantConfig):
            # keys both plants have (duration, seed, ...): the hydraulic actuator's
            self.plant = HydraulicPlantConfig.model_validate(
                self.plant.model_dump(exclude_unset=True))
        elif self.machine == "dc_motor" and isinstance(self.plant, HydraulicPlantConfig):
            raise ValueError("plant: the hydraulic actuator's keys; set machine = "
                             "'hydraulic_actuator' or give the DC motor's")
        return self

    def twin_channels(self) -> tuple[str, ...]:
        """The plant channels served."""
        return tuple(SERVED[self.machine][1])

    @property
    def sample_period(self) -> float:
        """The plant's sample period [s]."""
        return self.plant.sample_period

    def opcua_config(self, server: PlantOpcUaServer) -> OpcUaDriverConfig:
        """The :class:`OpcUaDriverConfig` that subscribes to the simulated server."""
        from twinwatch.drivers.opcua import OpcUaChannelMap, OpcUaDriverConfig

        return OpcUaDriverConfig(
            type="opcua", endpoint=server.endpoint, sample_period=self.plant.sample_period,
            publishing_interval=max(self.publishing_interval, self.plant.sample_period),
            queue_size=self.queue_size, timeout=self.timeout, backoff_max=self.backoff_max,
            channels={ch: OpcUaChannelMap(node=server.node_id(ch), unit=unit)
                      for ch, unit in SERVED[self.machine][1].items()})


class SimulatedOpcUaDriver(PlantDriver):
    """Plant -> :class:`PlantOpcUaServer` (loopback) -> :class:`OpcUaDriver`.

    Attributes:
        plant: the simulated plant (:meth:`~DCMotorPlant.truth` gives the true parameters).
        server: the OPC UA server serving it (tests stop and restart it).
        opcua: the driver subscribing to it; its counters are this driver's :attr:`stats`.

    Raises:
        DriverInitializationError: the server cannot listen (the port is taken: the message
            names it) or the driver cannot subscribe.
        EndOfStream: from :meth:`read` once the plant has reached its duration and every
            sample served has been delivered.
    """

    config_class = SimulatedOpcUaDriverConfig
    sample_machine = "dc-motor-opcua-sim"
    sample_title = "the simulated DC motor (paper Section 5.2) over OPC UA"
    driver_name = "simulated OPC UA"

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        assert isinstance(config, SimulatedOpcUaDriverConfig)
        return f"the simulated {config.machine} over OPC UA on {LOOPBACK}:{config.port}"

    def __init__(self, config: SimulatedOpcUaDriverConfig) -> None:
        from twinwatch.drivers.opcua import OpcUaDriver
        from twinwatch.plant.opcua_server import PlantOpcUaServer

        super().__init__(config, live=config.pacing == "realtime")
        self.plant: DCMotorPlant | HydraulicPlant = (
            DCMotorPlant(config.plant) if isinstance(config.plant, DCMotorPlantConfig)
            else HydraulicPlant(config.plant))
        object_name, units = SERVED[config.machine]
        self._taken = 0
        self._last_t = -math.inf
        self._last_arrival = time.monotonic()
        # in flight or unread at most: two 200-sample windows plus a burst
        self._high_water = 400 + config.queue_size // 4
        self.server = PlantOpcUaServer(
            self.plant, units, object_name=object_name, pacing=config.pacing, host=LOOPBACK,
            port=config.port, publishing_interval=config.publishing_interval,
            burst=max(1, config.queue_size // 4), may_advance=self._may_advance)
        self.opcua: OpcUaDriver | None = None

        def open_inner() -> OpcUaDriver:
            self.server.start()
            return OpcUaDriver(config.opcua_config(self.server),
                               time_origin=self.server.base, on_take=self._on_take)

        self.opcua = self._open_inner(
            open_inner, "driver.port: the simulated OPC UA server could not start: {exc}; "
            "choose another port (0: any free one)")
        logger.info("simulated %s, scenario %s, %.0f s, served over OPC UA on %s "
                    "(%s pacing)", config.machine, config.plant.scenario, config.plant.duration,
                    self.server.endpoint, config.pacing)

    def _may_advance(self) -> bool:
        if self.opcua is None:  # not subscribed yet: every sample must reach the subscription
            return False
        return self.server.samples_served - self._taken - self.stats.gaps < self._high_water

    def _on_take(self, n: int) -> None:
        self._taken += n

    def _read_internal(self, timeout: float | None) -> Sample | None:
        sample = self._take(1.0 if timeout is None else timeout)
        if sample is not None:
            self._last_t = sample.t
            self._last_arrival = time.monotonic()
            return sample
        if self.server.finished:
            # the last samples may still be on their way through the subscription (or a
            # reconnect): the stream ends with the plant's last sample, or after 10 s without
            # any (it was lost: counted in stats.gaps)
            last = self.server.last_sample
            done = last is not None and self._last_t >= last.t - 0.5 * self.sample_period
            quiet = time.monotonic() - self._last_arrival
            if not done and (quiet > _END_WAIT_RECONNECTING
                             or (quiet > _END_WAIT and self.waiting is None)):
                assert last is not None
                missing = round((last.t - max(self._last_t, -self.sample_period))
                                / self.sample_period)
                self.stats.gaps += missing
                logger.warning("the simulated plant's last %d samples did not arrive; counted in "
                               "stats.gaps", missing)
                done = True
            if done:
                raise EndOfStream(
                    f"simulated plant reached its duration ({self.config.plant.duration} s)")
        return None
