"""The service: the host and its worker processes, one machine's lifecycle, the daemon (runner)
and its parts (docs/architecture.md lists the modules). The daemon composes the other rooms;
nothing below it imports it.
"""
