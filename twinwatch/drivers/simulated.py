"""The built-in simulated plant, delivered over a python-can virtual bus.

The plant (:mod:`twinwatch.plant.dcmotor`) encodes each sample's measurements with the DBC
shipped in the package (``twinwatch/plant/dcmotor.dbc``: float32 signals ``Va``, ``ia``,
``omega``, ``Tload``, ``setpoint`` and a ``sample_counter``) and sends them on an in-process
python-can ``virtual`` bus; a :class:`~twinwatch.drivers.can.CanDriver` listening on the same
channel decodes them exactly as it would decode a real drive's frames. The sample clock is the
plant's (``sample_counter * sample_period``), so a run is the same as fast as possible or in
real time.

The plant is stepped lazily, one sample whenever the CAN driver has nothing left to decode: as
fast as possible, acquisition and simulation move in lock step and nothing queues up. With
``realtime = true`` each sample is sent when the wall clock reaches its plant time.

Monitoring only: the plant sends on a ``virtual`` bus and nothing else (enforced by the
config); twinwatch never transmits on a real bus.
"""

from __future__ import annotations

import itertools
import logging
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field

from twinwatch.drivers.base import DriverConfig, PlantDriver, Sample
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

if TYPE_CHECKING:  # imported when the driver opens: validating a config loads no CAN stack
    import can

    from twinwatch.drivers.can import CanDriver

logger = logging.getLogger(__name__)

_MESSAGES = (
    ("TW_Motor_Electrical", ("Va", "ia")),
    ("TW_Motor_Mechanical", ("omega", "Tload")),
    ("TW_Motor_Sample", ("setpoint",)),
)
_channel_ids = itertools.count()


def plant_dbc_path() -> Path:
    """Path of the DBC the simulated DC motor plant uses."""
    return Path(str(resources.files("twinwatch.plant").joinpath("dcmotor.dbc")))


class SimulatedDriverConfig(DriverConfig):
    """The ``[driver]`` table with ``type = "simulated"``.

    Attributes:
        machine: which simulated plant (only ``dc_motor`` so far).
        plant: the plant's scenario, duration, noise, set-points, ... (``[driver.plant]``).
        channel: name of the in-process virtual CAN channel ("auto": a unique name).
        realtime: pace the plant by the wall clock instead of running as fast as possible.
    """

    type: Literal["simulated"]
    machine: Literal["dc_motor"] = "dc_motor"
    plant: DCMotorPlantConfig = Field(default_factory=DCMotorPlantConfig)
    interface: Literal["virtual"] = Field(
        "virtual", description="only the in-process virtual bus: twinwatch never sends on a "
        "real bus")
    channel: str = "auto"
    realtime: bool = False

    def twin_channels(self) -> tuple[str, ...]:
        """The plant's channels, as its DBC carries them."""
        return tuple(ch for _, sigs in _MESSAGES for ch in sigs)


class SimulatedDriver(PlantDriver):
    """Simulated plant -> DBC-encoded frames -> virtual CAN bus -> :class:`CanDriver`.

    Raises:
        DriverInitializationError: the packaged DBC or the virtual bus cannot be opened.
        EndOfStream: from :meth:`read` once the plant reaches its duration.
    """

    config_class = SimulatedDriverConfig
    sample_machine = "dc-motor-sim"
    sample_title = "the simulated DC motor (paper Section 5.2) over a virtual CAN bus"

    def __init__(self, config: SimulatedDriverConfig) -> None:
        import can
        import cantools

        from twinwatch.drivers.can import CanDriver, CanDriverConfig, CanSignalMap

        super().__init__(config, live=config.realtime)
        self.plant = DCMotorPlant(config.plant)
        channel = config.channel
        if channel == "auto":
            channel = f"twinwatch-sim-{next(_channel_ids)}"
        dbc = plant_dbc_path()
        self._tx: can.BusABC | None = None

        def open_inner() -> CanDriver:
            db = cantools.database.load_file(str(dbc))
            assert isinstance(db, cantools.database.can.Database)
            self._messages = [(db.get_message_by_name(m), sigs) for m, sigs in _MESSAGES]
            self._message = can.Message
            rx, self._tx = self._virtual_pair(channel)
            can_cfg = CanDriverConfig(
                type="can",
                dbc=dbc,
                sync_message="TW_Motor_Sample",
                time_source="counter",
                counter_signal="TW_Motor_Sample.sample_counter",
                sample_period=config.plant.sample_period,
                signals={ch: CanSignalMap(message=m, signal=ch) for m, sigs in _MESSAGES
                         for ch in sigs},
            )
            return CanDriver(can_cfg, bus=rx)

        self._open_inner(open_inner, "simulated plant could not start: {exc}")
        logger.info("simulated %s plant, scenario %s, %.0f s, on virtual CAN channel %r",
                    config.machine, config.plant.scenario, config.plant.duration, channel)

    def _send_next(self) -> None:
        assert self._tx is not None
        sample = self.plant.next_sample()  # raises EndOfStream at the end
        if self.config.realtime:
            self._pace(sample.t)
        counter = int(round(sample.t / self.sample_period)) & 0xFFFFFFFF
        for msg, sigs in self._messages:
            data = {s: sample.values[s] for s in sigs}
            if msg.name == "TW_Motor_Sample":
                data["sample_counter"] = counter
            self._tx.send(self._message(arbitration_id=msg.frame_id, data=msg.encode(data),
                                        is_extended_id=False))

    def _read_internal(self, timeout: float | None) -> Sample | None:
        sample = self._take(0.0)
        if sample is not None:
            return sample
        self._send_next()
        return self._take(1.0 if timeout is None else max(timeout, 0.05))
