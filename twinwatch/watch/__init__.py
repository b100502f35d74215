"""See health without writing code: ``twinwatch watch`` (the fleet at a glance) and ``twinwatch
tail MACHINE`` (one line per health message as it arrives). The keys read are in docs/fleet.md.

A watcher opens one Zenoh session (explicit endpoints, scouting off: :func:`open_session`) to a
daemon or a router, finds the machines by liveliness (``<prefix>/*/alive``, or the box tokens
``<prefix>/@box/*/*`` of ``presence = "box"``), follows ``<prefix>/*/health`` and
``<prefix>/*/alarm`` with ``zenoh.ext`` advanced subscribers (the publisher's cache; what it no
longer holds is asked from the machine's ``history``: no window lost, none delivered twice:
:class:`FleetWatcher`), and asks a machine that gave nothing from a cache for its latest window.

:class:`Fleet` holds what the network showed (thread-safe), and :meth:`Fleet.snapshot` is the
one summary every view reads (``watch --once --json``, the rich table: :func:`render`). The
health message is read as JSON, not through the typed model, so a watcher shows daemons of
other versions: an unknown field is ignored, a missing one shown as absent.

Modules: ``session`` (the Zenoh session), ``fleet`` and ``view`` (the machines' state),
``subscription``, ``render``, ``tail``; for the fleet summaries (``watch --fleet``, ``fleet
report``): ``summaries``, ``ranking``, ``render_fleet``.

This room imports the ground floor only (zenoh through :mod:`twinwatch._lazy`, rich inside
:func:`render`) and the message's typed view (:mod:`twinwatch.twin.health`): never the
daemon, the sinks or the twin's estimation (``watch`` starts in well under a second).
"""

from __future__ import annotations

from twinwatch.errors import WatchError
from twinwatch.watch.fleet import Fleet
from twinwatch.watch.render import FILE_WIDTH, age, console, gap_line, render
from twinwatch.watch.session import DEFAULT_CONNECT, Mode, check_endpoints, open_session
from twinwatch.watch.subscription import (
    HISTORY_TIMEOUT_S,
    Delivery,
    FleetWatcher,
    Gap,
    watching,
)
from twinwatch.watch.tail import Tail, health_line
from twinwatch.watch.view import MachineState

__all__ = [
    "DEFAULT_CONNECT",
    "FILE_WIDTH",
    "HISTORY_TIMEOUT_S",
    "Delivery",
    "Fleet",
    "FleetWatcher",
    "Gap",
    "MachineState",
    "Mode",
    "WatchError",
    "Tail",
    "age",
    "check_endpoints",
    "console",
    "gap_line",
    "health_line",
    "open_session",
    "render",
    "watching",
]
