"""The service: lifecycle (supervisor, gateway, runner, systemd, log filter), acquisition (ring
buffer, source keeper), window pipeline, alarms.

The daemon composes the other rooms: it is handed a validated configuration
(:mod:`twinwatch.config`), opens a driver (:mod:`twinwatch.drivers`) and the sinks
(:mod:`twinwatch.sinks`) through their registries, and runs the twin's top
(:mod:`twinwatch.twin.adaptation`, :mod:`twinwatch.twin.health`) on every window. Nothing below
it imports it.
"""
