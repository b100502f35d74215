"""See health without writing code: ``twinwatch watch`` (the fleet at a glance) and ``twinwatch
tail MACHINE`` (one line per health message as it arrives).

Every daemon's Zenoh output (:mod:`twinwatch.sinks.zenoh`) declares, with ``P =
<key_prefix>/<machine>``, the liveliness token ``P/alive`` while it runs, publishes each window's
health on ``P/health`` and alarm changes on ``P/alarm``, and answers ``get(P/health)`` with the
latest window. A watcher opens one Zenoh session (explicit endpoints, multicast and gossip
scouting off: :func:`open_session`), connected to a daemon directly (it is a peer listening on
``tcp/127.0.0.1:7447`` by default) or to a router the daemons connect to, and

* finds the machines by liveliness (a subscriber on ``<prefix>/*/alive`` with the tokens that
  exist already): a machine appears when its daemon starts and is marked gone when its token
  goes (a stop, a crash, a lost link: the router drops a dead session's tokens); with
  ``[zenoh] presence = "box"`` by its gateway's box token (``<prefix>/@box/*/*``), asked for
  the machines it stands for;
* follows ``<prefix>/*/health`` and ``<prefix>/*/alarm`` with ``zenoh.ext`` advanced
  subscribers: each machine's last windows come at once from its publisher's cache (also for a
  daemon that starts later), a loss on the way (a router restarting) is recovered from that
  cache, and what the cache no longer holds is reported by the sample-miss listener and asked
  from the machine's history (its state database, ``<prefix>/<machine>/history``): no window is
  lost for the watcher, and none is delivered twice (:class:`FleetWatcher`);
* asks a machine that gave nothing from a cache (plain publishers) for its latest window
  (``get(<prefix>/<machine>/health)``).

:class:`Fleet` holds what the network showed (thread-safe: Zenoh's threads update it), and
:meth:`Fleet.snapshot` is the one summary every view reads: the JSON of ``watch --once
--json`` (README, "Watching the fleet"), the rich table of ``watch`` (:func:`render`). The
health message is read as the JSON it is published as, not through the typed model, so that a
watcher shows daemons of other twinwatch versions: a field it does not know is ignored, one that
is missing is shown as absent (the prognostics' ``rul``, when the message carries it).

The room's modules, by job: ``session`` (the Zenoh session, the payloads decoded), the data
(``fleet``: the machines' state; ``subscription``: :class:`FleetWatcher`, what feeds it), what
each machine shows (``view``: its state and summary in the snapshot) and the rendering
(``render``: the rich table; ``tail``: one line per health message).

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
