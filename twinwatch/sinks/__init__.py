"""Outputs: where every processed window goes (state database, Zenoh, Rerun, plug-ins).

May import :mod:`twinwatch.io`, the twin's top (:mod:`twinwatch.twin.model`,
:mod:`twinwatch.twin.health`, :mod:`twinwatch.twin.adaptation`: the message and the window) and
this room; never the twin's internals, the drivers, the configuration or the daemon.
"""
