"""What sources and their consumers share, with no dependency on either.

:mod:`twinwatch.io.sample` holds the sample type, the end-of-stream signal and the channel
scaling every driver and simulated plant use; :mod:`twinwatch.io.modbus_registers` holds the
Modbus register map and codec that the Modbus driver reads with and the simulated Modbus plant
serves with. ``twinwatch.plant`` and ``twinwatch.drivers`` both import from here, never from
each other's internals (the plant does not import the drivers).
"""
