"""What sources and their consumers share, with no dependency on either.

:mod:`twinwatch.io.sample` holds the sample type, the end-of-stream signal and the channel
scaling every driver and simulated plant use; :mod:`twinwatch.io.modbus_registers` holds the
Modbus register map and codec that the Modbus driver reads with and the simulated Modbus plant
serves with; :mod:`twinwatch.io.drive` describes how a drive's controller runs (loops, periods,
limits), which the closed-loop twins and the simulated plants both implement;
:mod:`twinwatch.io.counter` unwraps a source's sample counter (the CAN and Modbus drivers share
it); :mod:`twinwatch.io.encoding` is the one JSON encoder; :mod:`twinwatch.io.keys` the Zenoh key
layout the publisher and the watchers share (the boxes' tokens). ``twinwatch.plant``,
``twinwatch.drivers`` and the twin's machines import from here, never from each other's
internals. Imports nothing of twinwatch but this room.
"""
