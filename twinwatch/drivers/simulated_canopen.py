"""The simulated DC motor as a CiA 402 drive on a virtual CANopen bus, read back passively
(docs/canopen.md, "The simulated drive").

The plant sits behind a ``canopen`` local node with the EDS shipped in the package
(:mod:`twinwatch.plant.canopen_drive`) on an in-process python-can ``virtual`` bus; a
:class:`~twinwatch.drivers.canopen.CanopenDriver` on the same channel decodes its frames from the
same EDS as it would a real drive's. The samples' time is the SYNC frames' stamps (plant time).
The plant is stepped lazily, one sample whenever the driver has nothing left to decode;
``realtime = true`` sends each sample's frames when the wall clock reaches its plant time.
Monitoring only: the simulated drive sends on a ``virtual`` bus; the driver sends nothing.
"""

from __future__ import annotations

import itertools
import logging
import time
from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field, StrictFloat, StrictInt

from twinwatch.drivers.base import (
    DriverConfig,
    PlantDriver,
    Sample,
)
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

if TYPE_CHECKING:  # imported when the driver opens: validating a config loads no CAN stack
    import can

    from twinwatch.drivers.canopen import CanopenDriver
    from twinwatch.plant.canopen_drive import CiA402Drive

logger = logging.getLogger(__name__)

__all__ = ["SimulatedCanopenDriver", "SimulatedCanopenDriverConfig", "drive_channels"]

_channel_ids = itertools.count()


def drive_channels() -> dict[str, dict[str, Any]]:
    """The twin channels of the shipped EDS: channel -> ``[driver.channels]`` entry."""
    return {
        "Va": {"object": "0x2100", "factor": "mV", "unit": "V"},
        "ia": {"object": "0x6078", "factor": "per_mille_rated_current", "unit": "A"},
        "omega": {"object": "0x606C", "factor": "0.001rpm", "unit": "rad/s"},
        "setpoint": {"object": "0x60FF", "factor": "0.001rpm", "unit": "rad/s"},
    }


class SimulatedCanopenDriverConfig(DriverConfig):
    """The ``[driver]`` table with ``type = "simulated_canopen"``.

    Attributes:
        machine: the simulated plant (only ``dc_motor``).
        plant: the plant's scenario, duration, noise, set-points (``[driver.plant]``).
        node_id: the simulated drive's node id.
        channel: the in-process virtual CAN channel ("auto": a unique name).
        realtime: pace the plant by the wall clock instead of running as fast as possible.

    The drive's own faults and the frames lost (for tests and demonstrations): the fields'
    descriptions.
    """

    type: Literal["simulated_canopen"]
    machine: Literal["dc_motor"] = "dc_motor"
    plant: DCMotorPlantConfig = Field(default_factory=DCMotorPlantConfig)
    node_id: StrictInt = Field(5, ge=1, le=127)
    interface: Literal["virtual"] = Field(
        "virtual", description="only the in-process virtual bus: twinwatch never sends on a "
        "real bus")
    channel: str = "auto"
    realtime: bool = False
    fault_at: StrictFloat | None = Field(
        None, ge=0, allow_inf_nan=False, description="plant time [s] the drive faults: an "
        "EMCY with fault_code and the statusword's fault bit (None: never)")
    fault_code: StrictInt = Field(0x2310, ge=0x1000, le=0xFFFF, description="the EMCY's "
                                  "error code (0x2310: continuous over-current)")
    fault_reset_at: StrictFloat | None = Field(
        None, ge=0, allow_inf_nan=False, description="plant time [s] the fault is reset (an "
        "EMCY error reset, the statusword operational again)")
    heartbeat_stop_at: StrictFloat | None = Field(
        None, ge=0, allow_inf_nan=False, description="plant time [s] the drive stops sending "
        "its heartbeat (a stuck firmware)")
    frame_loss: StrictFloat = Field(
        0.0, ge=0, le=0.5, allow_inf_nan=False, description="fraction of the frames on the "
        "bus lost at random, seeded by plant.seed (a loaded bus; 0: none)")

    def twin_channels(self) -> tuple[str, ...]:
        """The channels the drive's TPDOs and the master's RPDO carry."""
        return tuple(drive_channels())


class _LossyBus:
    """A bus that loses a fraction of the frames sent on it, at random (seeded): what the
    listener of a loaded bus misses. Only :meth:`send` (all the simulated drive uses)."""

    def __init__(self, bus: can.BusABC, loss: float, seed: int) -> None:
        import random

        self.bus = bus
        self.loss = loss
        self.lost = 0
        self._rng = random.Random(f"frame_loss:{seed}")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._rng.random() < self.loss:
            self.lost += 1
            return
        self.bus.send(msg, timeout)


class SimulatedCanopenDriver(PlantDriver):
    """Simulated plant -> CiA 402 drive (canopen local node) -> virtual bus ->
    :class:`CanopenDriver`.

    Attributes:
        drive: the simulated drive (tests inject an EMCY fault and stop its heartbeat).
        canopen: the CANopen driver reading it; its counters are this driver's :attr:`stats`.

    Raises:
        DriverInitializationError: the EDS or the virtual bus cannot be opened.
        EndOfStream: from :meth:`read` once the plant reaches its duration.
    """

    config_class = SimulatedCanopenDriverConfig
    sample_machine = "dc-motor-canopen-sim"
    sample_title = "the simulated DC motor as a CiA 402 drive on a virtual CANopen bus"
    driver_name = "simulated CANopen"

    def __init__(self, config: SimulatedCanopenDriverConfig) -> None:
        from twinwatch.drivers.canopen import CanopenDriver, CanopenDriverConfig
        from twinwatch.plant.canopen_drive import CiA402Drive, drive_eds_path

        super().__init__(config, live=config.realtime)
        channel = config.channel
        if channel == "auto":
            channel = f"twinwatch-canopen-sim-{next(_channel_ids)}"
        self.canopen: CanopenDriver | None = None
        self.drive: CiA402Drive | None = None

        def open_inner() -> CanopenDriver:
            rx, tx = self._virtual_pair(channel, preserve_timestamps=True)
            if config.frame_loss > 0:
                tx = _LossyBus(tx, config.frame_loss, config.plant.seed)
            self.drive = CiA402Drive(DCMotorPlant(config.plant), tx, node_id=config.node_id)
            co_cfg = CanopenDriverConfig.model_validate({
                "type": "canopen", "node_id": config.node_id, "eds": drive_eds_path(),
                "sample_period": config.plant.sample_period, "channels": drive_channels()})
            return CanopenDriver(co_cfg, bus=rx)

        self.canopen = self._open_inner(open_inner,
                                        "simulated CANopen drive could not start: {exc}")
        self._done: set[str] = set()
        logger.info("simulated %s plant as CiA 402 node %d, scenario %s, %.0f s, on virtual CAN "
                    "channel %r", config.machine, config.node_id, config.plant.scenario,
                    config.plant.duration, channel)

    def _send_next(self) -> None:
        assert self.drive is not None
        if self.config.realtime:
            self._pace(self.drive.plant.t)
        t = self.drive.step().t  # raises EndOfStream at the end
        c = self.config
        if c.fault_at is not None and t >= c.fault_at and "fault" not in self._done:
            self._done.add("fault")
            self.drive.inject_fault(c.fault_code)
        if (c.fault_reset_at is not None and t >= c.fault_reset_at
                and "reset" not in self._done):
            self._done.add("reset")
            self.drive.reset_fault()
        if c.heartbeat_stop_at is not None and t >= c.heartbeat_stop_at:
            self.drive.heartbeat = False

    def _read_internal(self, timeout: float | None) -> Sample | None:
        # the virtual bus delivers a frame as it is sent: a step whose frames give no sample
        # (a frame lost, the first cycles) is followed by the next one at once, up to the
        # read's timeout, instead of waiting for the timeout on each
        sample = self._take(0.0)
        if sample is not None:
            return sample
        deadline = time.monotonic() + (1.0 if timeout is None else max(timeout, 0.05))
        while True:
            self._send_next()
            sample = self._take(0.0)
            if sample is not None or time.monotonic() >= deadline:
                return sample
