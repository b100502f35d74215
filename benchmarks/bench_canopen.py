"""The CANopen input's cost (issue 38): CPU per 2 s window (200 samples at 100 Hz) of decoding a
CiA 402 drive's frames, and the same for the DBC path of the CAN driver, for comparison.

The simulated drive (:class:`~twinwatch.plant.canopen_drive.CiA402Drive`: SYNC, the master's
RPDO1, the drive's TPDO1-3, a heartbeat every 100 ms; about 4.1 frames per sample) is run for
``--seconds`` of plant time onto a virtual bus and its frames captured once. Then:

* decode: the captured frames handed to :class:`~twinwatch.drivers.canopen.CanopenDriver`'s
  frame handler (the PDO mapping from the EDS, scaling, the SYNC cycle, EMCY/heartbeat
  bookkeeping): the driver's own CPU, no bus;
* bus + decode: the frames sent again on a virtual bus and read through ``read()`` (python-can's
  receive queue as well): what a live bus costs the acquisition thread, less the kernel;
* live bus: the frames sent by a thread each at its own time and read through ``read(0.2)``
  as the acquisition loop reads, with the driver's batches (``BATCH_S``: a wake-up of the
  reading thread about twice a batch) and without (a wake-up a frame): the reading thread's
  CPU;
* DBC: the simulated DC motor's three DBC frames a sample decoded by the CAN driver's frame
  handler (cantools), the same way.

Usage::

    python benchmarks/bench_canopen.py [--seconds 60] [--live 10]
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WINDOW = 200  # samples per window (2 s at 100 Hz), the default [acquisition] window


def _capture(seconds: float) -> list:
    import can

    from twinwatch.plant.canopen_drive import CiA402Drive
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    tx = can.Bus(interface="virtual", channel="bench-canopen-capture", preserve_timestamps=True)
    rx = can.Bus(interface="virtual", channel="bench-canopen-capture")
    drive = CiA402Drive(DCMotorPlant(DCMotorPlantConfig(duration=seconds)), tx)
    frames = []
    for _ in range(int(round(seconds / 0.01))):
        drive.step()
        while (m := rx.recv(0)) is not None:
            frames.append(m)
    tx.shutdown()
    rx.shutdown()
    return frames


def _driver(bus=None):
    from twinwatch.drivers.canopen import CanopenDriver
    from twinwatch.drivers.simulated_canopen import drive_channels

    cfg = {"type": "canopen", "interface": "virtual", "channel": "bench-canopen", "node_id": 5,
           "eds": "twinwatch:plant/dcmotor-cia402.eds", "sample_period": 0.01,
           "channels": drive_channels()}
    return CanopenDriver.from_config(cfg, base_dir=ROOT, bus=bus)


def _live(frames: list) -> tuple[float, float, int]:
    """CPU [s] per window of the thread that reads the drive's ``frames`` through ``read()``
    as the acquisition loop does (``read(0.2)``) while a thread sends each on a virtual bus
    at its own time: with the driver's batches (:data:`~twinwatch.drivers.base.BATCH_S`)
    and without (0: a wake-up a frame); and the samples read."""
    import threading

    import can

    from twinwatch.drivers import base

    result = []
    saved = base.BATCH_S
    for batch in (saved, 0.0):
        base.BATCH_S = batch
        rx = can.Bus(interface="virtual", channel=f"bench-canopen-live-{batch}")
        tx = can.Bus(interface="virtual", channel=f"bench-canopen-live-{batch}")
        driver = _driver(bus=rx)

        def send(tx: can.BusABC = tx) -> None:
            t0, f0 = time.monotonic(), frames[0].timestamp
            for frame in frames:
                wait = t0 + (frame.timestamp - f0) - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                tx.send(frame)

        sender = threading.Thread(target=send)
        got, cpu = 0, time.thread_time()
        sender.start()
        while sender.is_alive() or not rx.queue.empty():
            got += driver.read(timeout=0.2) is not None
        result.append((time.thread_time() - cpu) / (got / WINDOW))
        sender.join()
        driver.close()
        tx.shutdown()
        rx.shutdown()
    base.BATCH_S = saved
    return result[0], result[1], got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="plant seconds")
    ap.add_argument("--live", type=float, default=10.0,
                    help="seconds of the frames sent in real time for the live-bus row")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    import can

    frames = _capture(args.seconds)
    n_samples = int(round(args.seconds / 0.01))
    windows = n_samples / WINDOW
    print(f"{len(frames)} frames for {n_samples} samples ({len(frames) / n_samples:.2f} a "
          f"sample), {windows:.0f} windows of {WINDOW}")

    # decode only
    driver = _driver(bus=can.Bus(interface="virtual", channel="bench-canopen-idle"))
    got = 0
    cpu = time.thread_time()
    for frame in frames:
        got += driver._on_frame(frame) is not None
    decode = time.thread_time() - cpu
    driver.close()
    print(f"decode:       {decode / windows * 1e3:7.2f} ms CPU per window "
          f"({decode / len(frames) * 1e6:.1f} us a frame), {got} samples")

    # through a virtual bus and read()
    rx = can.Bus(interface="virtual", channel="bench-canopen-bus")
    tx = can.Bus(interface="virtual", channel="bench-canopen-bus", preserve_timestamps=True)
    driver = _driver(bus=rx)
    got, cpu_bus = 0, 0.0
    for start in range(0, len(frames), 4000):  # the virtual bus's queue is unbounded
        for frame in frames[start:start + 4000]:
            tx.send(frame)
        cpu = time.thread_time()
        while True:
            sample = driver.read(timeout=0.0)
            if sample is None and rx.queue.empty():  # every frame sent has been read
                break
            got += sample is not None
        cpu_bus += time.thread_time() - cpu
    driver.close()
    tx.shutdown()
    rx.shutdown()
    print(f"bus + decode: {cpu_bus / windows * 1e3:7.2f} ms CPU per window, {got} samples")
    live = _live(frames[:int(len(frames) * min(args.live, args.seconds) / args.seconds)])
    print(f"live bus:     {live[0] * 1e3:7.2f} ms CPU per window; read sample by sample, "
          f"without waiting for a batch: {live[1] * 1e3:.2f} ms ({live[2]} samples, "
          f"{args.live:.0f} s each)")

    # the DBC path, for comparison
    import cantools

    from twinwatch.drivers.can import CanDriver, CanDriverConfig, CanSignalMap
    from twinwatch.drivers.simulated import _MESSAGES, plant_dbc_path
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    db = cantools.database.load_file(str(plant_dbc_path()))
    plant = DCMotorPlant(DCMotorPlantConfig(duration=args.seconds))
    dbc_frames = []
    for k in range(n_samples):
        s = plant.next_sample()
        for name, sigs in _MESSAGES:
            msg = db.get_message_by_name(name)
            data = {x: s.values[x] for x in sigs}
            if name == "TW_Motor_Sample":
                data["sample_counter"] = k
            dbc_frames.append(can.Message(arbitration_id=msg.frame_id, data=msg.encode(data),
                                          is_extended_id=False, timestamp=s.t))
    can_cfg = CanDriverConfig(type="can", dbc=plant_dbc_path(), sync_message="TW_Motor_Sample",
                              time_source="counter",
                              counter_signal="TW_Motor_Sample.sample_counter",
                              sample_period=0.01,
                              signals={ch: CanSignalMap(message=m, signal=ch)
                                       for m, sigs in _MESSAGES for ch in sigs})
    idle = can.Bus(interface="virtual", channel="bench-dbc-idle")
    dbc = CanDriver(can_cfg, bus=idle)
    got = 0
    cpu = time.thread_time()
    for frame in dbc_frames:
        got += dbc._on_frame(frame) is not None
    dbc_cpu = time.thread_time() - cpu
    dbc.close()
    idle.shutdown()
    print(f"DBC decode:   {dbc_cpu / windows * 1e3:7.2f} ms CPU per window "
          f"({len(dbc_frames) / n_samples:.0f} frames a sample), {got} samples")


if __name__ == "__main__":
    main()
