"""A simulated ODrive-like drive on CAN: the recording ``config/dc-motor-odrive.toml`` replays.

The shipped log ``twinwatch/plant/odrive-axis0.log.gz`` (candump format, gzip) holds 60 s of
axis 0 of an ODrive-like drive speaking CANSimple 0.6.10, recorded from the built-in DC motor
plant with the motor, the PI speed loop (every 10 ms, its output held in between: the applied
voltage is constant between two messages, as the example's open-loop twin assumes) and the
set-points of :data:`PLANT`. Every 10 ms, as the drive's cyclic messages with
``*_msg_rate_ms = 10``:

* ``Axis0_Get_Iq`` (0x014): ``Iq_Measured`` the armature current (an FOC drive's q-axis
  current plays the DC motor's), ``Iq_Setpoint`` the same;
* ``Axis0_Get_Bus_Voltage_Current`` (0x017): ``Bus_Voltage`` the armature voltage (this drive
  runs at full modulation; a real ODrive's bus voltage is only an upper bound of it:
  ``config/dc-motor-odrive.toml`` says what that costs), ``Bus_Current`` the current;
* ``Axis0_Get_Encoder_Estimates`` (0x009, the sync message, last): ``Vel_Estimate`` [rev/s],
  ``Pos_Estimate`` [rev];

and ``Axis0_Heartbeat`` (0x001) every 100 ms, which the example does not map. Frames carry no
sample counter (as ODrive's): each is stamped with a bus adapter's receive clock, the sample's
time plus a uniform jitter of +-50 us (``time_source = "frame"``). Signals are encoded with
ODrive's own DBC (PyPI odrive-can 2.1.0, MIT licence; not shipped: the example reads it from
``../shared/data/dbc``). docs/sources.md.

Record it again (deterministic: the same bytes once decompressed)::

    python -m twinwatch.plant.odrive ../shared/data/dbc/odrive-cansimple-0.6.10.dbc \\
        twinwatch/plant/odrive-axis0.log.gz
"""

from __future__ import annotations

import gzip
import math
import random
import sys
from collections.abc import Iterator
from pathlib import Path

from twinwatch.io.drive import DriveConfig, LoopConfig
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig, SetpointSchedule

__all__ = ["EPOCH", "PLANT", "SECONDS", "odrive_frames", "write_log"]

SECONDS = 60.0
"""Length of the shipped recording [s]."""
EPOCH = 1763800000.0
"""Wall-clock time [s since 1970] of the recording's first sample (its stamps are absolute, as
candump writes them)."""
JITTER = 50e-6
"""Receive-stamp jitter [s], uniform +-."""

PLANT = DCMotorPlantConfig(
    scenario="nominal", duration=SECONDS, sample_period=0.01, step=1e-5,
    Ra=0.05, La=2e-5, J=1e-3, Ke=0.0306, Kt=0.0306, D=1e-4, load_coefficient=0.0,
    drive=DriveConfig(period=0.01, speed=LoopConfig(kp=0.01, ki=0.1, output_min=-24.0,
                                                    output_max=24.0)),
    setpoint=SetpointSchedule(initial=50.0, levels=[50.0, 100.0, 150.0, 200.0],
                              dwell_min=2.0, dwell_max=6.0, seed=15),
    noise={"ia": 1.0, "omega": 0.5}, seed=15)
"""The drive and motor that recorded the shipped log (see the module docstring)."""


def odrive_frames(dbc: Path | str, *, plant: DCMotorPlantConfig = PLANT,
                  seed: int = 15) -> Iterator[tuple[float, int, bytes]]:
    """The drive's frames in the order a bus adapter receives them: ``(stamp [s], id, data)``.

    Args:
        dbc: ODrive's CANSimple DBC (``odrive-cansimple-0.6.10.dbc``).
        plant: the drive and motor.
        seed: the receive jitter's random seed.

    Raises:
        ValueError: ``dbc`` is not a CAN database (cantools also loads diagnostics databases).
    """
    import cantools

    db = cantools.database.load_file(str(dbc))
    if not isinstance(db, cantools.database.can.Database):
        raise ValueError(f"{dbc} is not a CAN database (cantools loaded a {type(db).__name__})")
    enc = db.get_message_by_name("Axis0_Get_Encoder_Estimates")
    iq = db.get_message_by_name("Axis0_Get_Iq")
    bus = db.get_message_by_name("Axis0_Get_Bus_Voltage_Current")
    beat = db.get_message_by_name("Axis0_Heartbeat")
    rng = random.Random(seed)
    motor = DCMotorPlant(plant)
    position = 0.0
    last = 0.0
    n = int(round(plant.duration / plant.sample_period))
    for k in range(n):
        s = motor.next_sample()
        v = s.values
        position += v["omega"] * plant.sample_period / (2.0 * math.pi)
        frames = [(-4e-4, iq, {"Iq_Setpoint": v["ia"], "Iq_Measured": v["ia"]}),
                  (-2e-4, bus, {"Bus_Voltage": v["Va"], "Bus_Current": v["ia"]}),
                  (0.0, enc, {"Pos_Estimate": position,
                              "Vel_Estimate": v["omega"] / (2.0 * math.pi)})]
        if k % 10 == 0:
            frames.insert(0, (-6e-4, beat, {"Axis_Error": 0, "Axis_State": 8,
                                            "Procedure_Result": 0, "Trajectory_Done_Flag": 0}))
        for offset, msg, data in frames:
            stamp = max(last, EPOCH + s.t + offset + rng.uniform(-JITTER, JITTER))
            last = stamp
            yield stamp, msg.frame_id, msg.encode(data)


def write_log(dbc: Path | str, out: Path | str, *, plant: DCMotorPlantConfig = PLANT) -> Path:
    """Record the drive's frames as a candump log (gzip when ``out`` ends in ``.gz``)."""
    text = "".join(f"({stamp:.6f}) can0 {fid:03X}#{data.hex().upper()}\n"
                   for stamp, fid, data in odrive_frames(dbc, plant=plant))
    out = Path(out)
    if out.suffix == ".gz":
        with out.open("wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0,
                                                  filename="") as gz:
            gz.write(text.encode("ascii"))
    else:
        out.write_text(text)
    return out


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m twinwatch.plant.odrive ODRIVE_DBC OUT.log[.gz]")
    print(write_log(sys.argv[1], sys.argv[2]))
