"""The simulated DC motor as a CiA 402 drive on a CANopen bus (a python-can bus, e.g. virtual).

A ``canopen`` :class:`~canopen.LocalNode` holds the drive's object dictionary, read from the
EDS shipped beside this module (``dcmotor-cia402.eds``: see its ``[Comments]``), and its PDO
mappings. Each :meth:`CiA402Drive.step` advances the plant
(:class:`~twinwatch.plant.dcmotor.DCMotorPlant`) one sample and puts on the bus what a real cell
would: the master's SYNC and RPDO1, the drive's TPDO1-3 and its heartbeat every producer time
(0x1017); the frames and units: docs/canopen.md.

Every frame is stamped with plant time (the bus must keep the stamps it is given: a
``virtual`` bus with ``preserve_timestamps=True``). For tests,
:meth:`CiA402Drive.inject_fault` sends an EMCY and sets the statusword's fault bit,
:meth:`CiA402Drive.reset_fault` clears both, and :attr:`CiA402Drive.heartbeat` off stops the
heartbeat.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import canopen
import canopen.network

from twinwatch.io.sample import Sample
from twinwatch.plant.dcmotor import DCMotorPlant

if TYPE_CHECKING:
    import can

__all__ = ["EDS_NAME", "CiA402Drive", "drive_eds_path"]

#: The drive's EDS, shipped in this package.
EDS_NAME = "dcmotor-cia402.eds"
_MRPM = 60.0 / (2.0 * math.pi) * 1000.0  # rad/s -> 0.001 rev/min
#: statusword: ready to switch on, switched on, operation enabled, voltage enabled, quick stop
#: off, remote (CiA 402 "operation enabled" = 0x0237)
_OPERATION_ENABLED = 0x0237
_FAULT_BIT = 0x0008


def drive_eds_path() -> Path:
    """Path of the simulated drive's EDS."""
    return Path(str(resources.files("twinwatch.plant").joinpath(EDS_NAME)))


class _PlantClockNetwork(canopen.Network):
    """A canopen network whose frames carry plant time (``send_message`` is canopen's hook for
    another backend): the stamp :attr:`now` [s] is set before each step."""

    now = 0.0

    def send_message(self, can_id: int, data: Any, remote: bool = False) -> None:
        import can

        msg = can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False,
                          is_remote_frame=remote, timestamp=self.now)
        assert self.bus is not None
        with self.send_lock:
            self.bus.send(msg)


class CiA402Drive:
    """The DC motor plant behind a CiA 402 drive's object dictionary, on a CAN bus.

    Args:
        plant: the simulated DC motor.
        bus: the bus to send on (it must keep the given time stamps: a ``virtual`` bus with
            ``preserve_timestamps=True``); the caller owns it.
        node_id: the drive's node id (1-127).
        eds: the drive's EDS (default: the shipped one).

    Attributes:
        node: the ``canopen`` local node (its OD, PDO maps, EMCY producer).
        heartbeat: the heartbeat is sent (set False to stop it: a stuck firmware).
    """

    def __init__(self, plant: DCMotorPlant, bus: can.BusABC, *, node_id: int = 5,
                 eds: Path | None = None) -> None:
        self.plant = plant
        self.network = _PlantClockNetwork(bus)  # never connect(): it listens to nothing
        self.node = canopen.LocalNode(node_id, canopen.import_od(str(eds or drive_eds_path()),
                                                                 node_id))
        self.network.add_node(self.node)
        self.node.tpdo.read(from_od=True)
        self.node.rpdo.read(from_od=True)
        od = self.node.object_dictionary

        def default(index: int) -> float:
            var = od.get_variable(index)
            if var is None or not isinstance(var.default, int | float):
                raise ValueError(f"the drive's EDS gives no value of 0x{index:04X}")
            return float(var.default)

        self.node_id = node_id
        self.heartbeat_period = default(0x1017) / 1000.0
        self._rated_ma = default(0x6075)
        self._sync_overflow = int(default(0x1019))
        maps = self.node.tpdo.map
        assert maps is not None
        self._every = {m.cob_id: (m.trans_type or 1) for m in maps.values() if m.enabled}
        self._tpdos = [m for m in maps.values() if m.enabled and m.map]
        self._rpdo = self.node.rpdo[1]
        self._status = _OPERATION_ENABLED
        self.heartbeat = True
        self._k = 0
        self._next_heartbeat = 0.0
        self.node.nmt.state = "OPERATIONAL"
        self.dc_link = 30.0  # V

    def step(self) -> Sample:
        """Advance the plant one sample and send this sample period's frames.

        Returns:
            The plant's sample (its exact values: what the frames encode before rounding).

        Raises:
            EndOfStream: the plant reached its duration.
        """
        sample = self.plant.next_sample()
        v = sample.values
        t = sample.t
        net = self.network
        net.now = t
        self.network.sync.transmit(self._k % self._sync_overflow + 1)
        net.now = t + 20e-6  # the frames follow the SYNC on the bus
        self._rpdo["Controlword"].raw = 0x000F
        self._rpdo["Target velocity"].raw = round(v["setpoint"] * _MRPM)
        self._rpdo.transmit()
        raw = {
            0x6041: self._status,
            0x606C: round(v["omega"] * _MRPM),
            0x6078: max(-32768, min(32767, round(v["ia"] / (self._rated_ma * 1e-6)))),
            0x2100: round(v["Va"] * 1000.0),
            0x6079: round(self.dc_link * 1000.0),
        }
        for pdo in self._tpdos:
            if self._k % self._every.get(pdo.cob_id, 1):
                continue
            for var in pdo.map:
                var.raw = raw[var.index]
            net.now += 40e-6
            pdo.transmit()
        if self.heartbeat and t + 1e-9 >= self._next_heartbeat:
            net.now += 40e-6
            net.send_message(0x700 + self.node_id, bytes([0x05]))
            self._next_heartbeat = t + self.heartbeat_period
        self._k += 1
        return sample

    def inject_fault(self, code: int = 0x2310, register: int = 0x03) -> None:
        """The drive faults: an EMCY (default 0x2310, continuous over-current; error register
        generic + current) and the statusword's fault bit, from the next step on."""
        self.network.now = self.plant.t
        self.node.emcy.send(code, register)
        self._status = (self._status & ~0x0007) | _FAULT_BIT

    def reset_fault(self) -> None:
        """The fault is reset: an EMCY with code 0x0000 and the statusword operational."""
        self.network.now = self.plant.t
        self.node.emcy.reset()
        self._status = _OPERATION_ENABLED
