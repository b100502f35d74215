"""The watcher's Zenoh session: the endpoints and the key prefix checked, a session that talks
only to the endpoints given (:func:`open_session`), and the payloads decoded (a health
message as its typed view, an alarm event or a history page as JSON).
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, contextmanager
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from twinwatch._lazy import lazy_module
from twinwatch.errors import WatchError

if TYPE_CHECKING:
    import zenoh

    from twinwatch.twin.health import HealthView
else:  # imported when a session opens
    zenoh = lazy_module("zenoh")


DEFAULT_CONNECT = ("tcp/127.0.0.1:7447",)
"""Where a watcher connects by default: a daemon (a peer listening there by default) or a
router on this host."""


Mode = Literal["client", "peer"]


_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*)"
                          r":[0-9]{1,5}$")


CHUNKS_RE = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")


# -- the session -------------------------------------------------------------------------------
def check_endpoints(connect: Sequence[str]) -> list[str]:
    """The endpoints, checked (``proto/host:port``).

    Raises:
        WatchError: none given, or one is malformed (named).
    """
    if not connect:
        raise WatchError("give at least one endpoint to connect to, e.g. --connect "
                         "tcp/127.0.0.1:7447")
    for e in connect:
        if _ENDPOINT_RE.match(e) is None:
            raise WatchError(f"endpoint {e!r} is not of the form proto/host:port (proto one of "
                             "tcp, udp, tls, quic, ws), e.g. tcp/127.0.0.1:7447")
    return list(connect)


def check_prefix(prefix: str) -> str:
    """The key prefix, checked: ``/``-separated plain chunks (as ``[zenoh] key_prefix``).

    Raises:
        WatchError: it is empty or has wildcards or reserved characters.
    """
    if CHUNKS_RE.match(prefix) is None:
        hint = (": a * in the prefix goes with watch --fleet and fleet report (the summaries); "
                "for the full health give one box's prefix" if "*" in prefix.split("/") else "")
        raise WatchError(f"key prefix {prefix!r} must be chunks of letters, digits, '_', '-' or "
                         f"'.' separated by '/' (the daemons' [zenoh] key_prefix){hint}")
    return prefix


FLEET_PREFIX_RE = re.compile(r"^[A-Za-z0-9_.\-]+(/([A-Za-z0-9_.\-]+|\*))*$")


def check_fleet_prefix(prefix: str) -> str:
    """The key prefix of a fleet's summaries, checked: as :func:`check_prefix`, and chunks
    after the first may be ``*`` (one chunk, any name), so that one watcher follows the
    gateways whose ``[zenoh] key_prefix`` put a chunk of their own before their machines
    (``twinwatch/*`` follows ``twinwatch/gw-line1/<machine>``, ``twinwatch/gw-line2/...``).

    Raises:
        WatchError: the first chunk is a wildcard, or a chunk has other wildcards or reserved
            characters.
    """
    if FLEET_PREFIX_RE.match(prefix) is None:
        raise WatchError(f"key prefix {prefix!r} must be chunks of letters, digits, '_', '-' "
                         "or '.' separated by '/'; a chunk after the first may be a whole * "
                         "(twinwatch/* follows gateways whose key_prefix is twinwatch/<box>)")
    return prefix


def prefix_base(prefix: str) -> str:
    """The plain chunks a fleet prefix (:func:`check_fleet_prefix`) starts with: what the keys
    of its machines share (``twinwatch/*`` -> ``twinwatch``). A machine is then named by the
    rest of its key before the topic (``gw-line1/m17``)."""
    chunks = prefix.split("/")
    n = chunks.index("*") if "*" in chunks else len(chunks)
    return "/".join(chunks[:n])


class Unreachable(WatchError):
    """Nothing answers at the endpoints (no daemon nor router up there yet): a watcher that
    follows may wait for one (``watch --fleet``)."""


def open_session(connect: Sequence[str] = DEFAULT_CONNECT, mode: Mode = "client"
                 ) -> zenoh.Session:
    """A Zenoh session that talks only to ``connect``: no listening, multicast and gossip
    scouting off (a watcher never discovers or is discovered by anything it was not told).

    Args:
        connect: endpoints of a daemon (a peer) or a router, ``tcp/127.0.0.1:7447``.
        mode: ``client`` (default: through the router or peer it connects to) or ``peer``.

    Raises:
        WatchError: an endpoint is malformed, or nothing answers there (client mode).
    """
    endpoints = check_endpoints(connect)
    conf = zenoh.Config()
    try:
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
    except zenoh.ZError as exc:
        raise WatchError(f"invalid zenoh settings (mode={mode}, connect={endpoints}): "
                         f"{exc}") from exc
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        msg = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()
        if "unable to connect" in msg.lower():
            raise Unreachable(f"cannot connect to {', '.join(endpoints)}: nothing answers there; "
                             "start a daemon (twinwatch run) or a zenoh router there, or give "
                             f"--connect (zenoh: {msg})") from exc
        raise WatchError(f"cannot open a zenoh session (mode={mode}, connect={endpoints}): "
                         f"{msg}") from exc


W = TypeVar("W")


@contextmanager
def sessions_watched(connect: Sequence[str], mode: Mode,
                     watcher: Callable[[zenoh.Session], AbstractContextManager[W]], *,
                     optional: Collection[str] = (),
                     on_skip: Callable[[str, str], None] | None = None,
                     unreachable: type[WatchError] = WatchError) -> Iterator[list[W]]:
    """Sessions on ``connect`` and a watcher entered on each (``watcher(session)``), all
    closed on exit: in client mode one session per endpoint (a client session talks to one of
    its endpoints only), else one session connecting to every endpoint.

    Args:
        optional: endpoints that may have nothing answering there: each such one is skipped
            and, once another answered, ``on_skip`` called with it and why.
        unreachable: the error raised when every endpoint was skipped.

    Yields:
        The watchers, one per session that opened (at least one).

    Raises:
        WatchError: a malformed endpoint (optional or not), an endpoint not ``optional`` that
            does not answer (see :func:`open_session`), or ``unreachable`` when none answers.
    """
    check_endpoints(connect)  # a malformed endpoint is refused, optional or not
    skippable = set(optional)
    groups = ([[e] for e in connect] if mode == "client" and (len(connect) > 1 or skippable)
              else [list(connect)])
    with contextlib.ExitStack() as stack:
        watchers: list[W] = []
        skipped: list[tuple[str, str]] = []
        for group in groups:
            try:
                session = open_session(group, mode)
            except WatchError as exc:
                if not set(group) <= skippable:
                    raise
                skipped.append((group[0], str(exc)))
                continue
            stack.callback(session.close)
            watchers.append(stack.enter_context(watcher(session)))
        if not watchers:
            raise unreachable(f"nothing answers at {', '.join(connect)}: start a daemon "
                              "(twinwatch run) or a zenoh router there")
        for endpoint, why in skipped:
            if on_skip is not None:
                on_skip(endpoint, why)
        yield watchers


def machine_of(key: str, prefix: str, suffix: str) -> str | None:
    """``<prefix>/<machine>/<suffix>`` -> machine (None for another key)."""
    head, tail = f"{prefix}/", f"/{suffix}"
    if key.startswith(head) and key.endswith(tail):
        machine = key[len(head):-len(tail)]
        return machine if machine and "/" not in machine else None
    return None


def decode_json(payload: Any) -> dict[str, Any] | None:
    """A JSON object from a Zenoh payload (an alarm event, a history page), or None (a
    non-object or bad JSON is ignored)."""
    try:
        doc = json.loads(payload.to_string())
    except (ValueError, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


def health_view(doc: HealthView | Mapping[str, Any]) -> HealthView:
    """A health message as its typed view (:func:`~twinwatch.twin.health.read_health`)."""
    from twinwatch.twin.health import HealthView, read_health

    return doc if isinstance(doc, HealthView) else read_health(doc)


def decode_health(payload: Any) -> tuple[HealthView, str] | None:
    """A health message from a Zenoh payload: its typed view and its text, or None (bad JSON
    or not an object is ignored)."""
    from twinwatch.twin.health import read_health

    try:
        text = payload.to_string()
        return read_health(text), text
    except (ValueError, UnicodeDecodeError):
        return None
