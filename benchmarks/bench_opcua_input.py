"""The OPC UA input's cost (issue 35): CPU per 2 s window of the DC motor's five channels at
100 Hz, the client side (the driver) and, separately, the simulated plant's server.

The simulated DC motor is served by :class:`~twinwatch.plant.opcua_server.PlantOpcUaServer`
on a free loopback port and read by :class:`~twinwatch.drivers.opcua.OpcUaDriver` through one
subscription (sampling 10 ms, publishing 50 ms, DiscardOldest queues), both in this process,
each in its own thread: their CPU is each thread's own (``time.thread_time``), not wall time.

* client: the driver's thread from subscription on (asyncua's publish loop and binary
  decoding, the joining of values into samples) plus the caller's reads;
* server: the server's thread while serving (the plant's steps, the writes, the monitored
  items and the publish responses); the plant's own stepping, timed apart, is given too so
  the OPC UA part can be told from it; the address space's set-up at start (asyncua loads the
  standard nodes) separately, once per start.

``realtime`` (default): 100 Hz by the wall clock for ``--seconds`` (the cost of a live source);
``lockstep``: as fast as the client takes the samples (the throughput and its cost).

Usage::

    python benchmarks/bench_opcua_input.py [--seconds 30] [--pacing realtime|lockstep]
        [--restart S]
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="plant seconds served")
    ap.add_argument("--pacing", choices=["realtime", "lockstep"], default="realtime")
    ap.add_argument("--restart", type=float, default=0.0, metavar="S",
                    help="stop the plant's server for S wall seconds at half the run, then "
                    "start it again: the gap the driver counts")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)

    from twinwatch.drivers.base import EndOfStream
    from twinwatch.drivers.simulated_opcua import SimulatedOpcUaDriver, SimulatedOpcUaDriverConfig
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig

    cfg = SimulatedOpcUaDriverConfig(type="simulated_opcua", port=0, pacing=args.pacing,
                                     plant=DCMotorPlantConfig(duration=args.seconds))
    driver = SimulatedOpcUaDriver(cfg)
    if args.restart > 0:
        import threading

        def restart() -> None:
            while driver.plant.t < args.seconds / 2 and not driver.closed:
                time.sleep(0.01)
            driver.server.stop()
            time.sleep(args.restart)
            driver.server.start()

        threading.Thread(target=restart, daemon=True).start()
    n = 0
    reader_cpu0 = time.thread_time()
    wall1 = time.perf_counter()
    try:
        while True:
            if driver.read(1.0) is not None:
                n += 1
    except EndOfStream:
        pass
    wall = time.perf_counter() - wall1
    reader_cpu = time.thread_time() - reader_cpu0
    assert driver.opcua is not None
    client_cpu = driver.opcua.cpu_seconds + reader_cpu
    waited = driver.opcua.stats.extra["outages"]
    serving_cpu = driver.server.serving_cpu_seconds
    stats = driver.stats.as_dict()
    served = driver.server.samples_served
    driver.close()
    setup_cpu = driver.server.cpu_seconds - serving_cpu  # the thread's total, once stopped

    plant = DCMotorPlant(DCMotorPlantConfig(duration=args.seconds))
    c0 = time.thread_time()
    try:
        while True:
            plant.next_sample()
    except EndOfStream:
        pass
    plant_cpu = time.thread_time() - c0

    windows = n / WINDOW
    ms = 1000.0 / windows
    print(f"OPC UA input, simulated DC motor, 5 channels at 100 Hz, {args.pacing} pacing, "
          f"{args.seconds:g} s of plant time in {wall:.1f} s of wall time")
    print(f"  samples served {served}, delivered {n} ({windows:.1f} windows of {WINDOW}); "
          f"gaps {stats['gaps']}, overflows {stats['overflows']}, dropped {stats['dropped']}")
    if args.restart > 0:
        print(f"  server stopped {args.restart:g} s at plant time {args.seconds / 2:g} s: "
              f"{waited} outage, {stats['reconnects']} reconnect, {stats['gaps']} samples "
              f"counted missing ({stats['gaps'] * 0.01:.2f} s), served {served} = delivered "
              f"{n} + missing {stats['gaps']}: {served == n + stats['gaps']}")
    print(f"  client (driver thread + reads): {client_cpu:.3f} s CPU = "
          f"{client_cpu * ms:.1f} ms per window, {100 * client_cpu / (n * 0.01):.2f} % of a "
          f"core at 100 Hz")
    print(f"  server (serving thread):        {serving_cpu:.3f} s CPU = "
          f"{serving_cpu * ms:.1f} ms per window, {100 * serving_cpu / (n * 0.01):.2f} % of a "
          f"core at 100 Hz")
    print(f"    of which the plant's steps:   {plant_cpu:.3f} s CPU = "
          f"{plant_cpu * ms:.1f} ms per window")
    print(f"  server set-up (once per start): {setup_cpu:.2f} s CPU")


if __name__ == "__main__":
    main()
