"""The simulated plants: the "real machine" of the paper's virtual environment.

A plant steps the paper's equations with time-varying fault parameters (its scenarios) and
never shares state with the twin that observes it. May import :mod:`twinwatch.io` (samples, the
Modbus register map, the drive description) and this room only: never the twin, the drivers or
the daemon.
"""
