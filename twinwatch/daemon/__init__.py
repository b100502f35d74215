"""The service: the host and its worker processes, one machine's lifecycle, the daemon (runner)
and its parts (docs/architecture.md lists the modules). The daemon composes the other rooms: it
is handed a validated configuration (:mod:`twinwatch.config`), opens a driver
(:mod:`twinwatch.drivers`) and the sinks (:mod:`twinwatch.sinks`) through their registries, and
runs the twin's top (:mod:`twinwatch.twin.adaptation`, :mod:`twinwatch.twin.health`) on every
window. Nothing below it imports it.
"""
