"""Publishing machine health over zenoh.

One :class:`HealthPublisher` per monitored machine. It owns one zenoh session and declares,
with ``P = {key_prefix}/{machine}``:

* a publisher on ``P/health``: one JSON document per acquisition window
  (encoding ``application/json``), see :meth:`HealthPublisher.publish`;
* publishers on ``P/<suffix>`` created on first use by :meth:`HealthPublisher.publish_json`
  (``P/alarm``, ...);
* every publisher is a ``zenoh.ext`` *advanced* publisher (:func:`declare_publisher`) with a
  cache of its last ``[zenoh] cache`` samples (30 windows: a minute), sequence numbers and a
  heartbeat for sample-miss detection, and publisher detection: an ``AdvancedSubscriber`` that
  joins late gets each machine's recent windows from the cache (through a router too), one that
  lost samples (a router outage, a dropped link) gets them again from the cache or is told how
  many it missed (its sample-miss listener) and asks ``P/history`` for them (``twinwatch
  watch``/``tail`` do). Its cache and heartbeat live under ``P/health/@adv/...``, which the
  queryable below and ``P/**`` never match (``@`` chunks are verbatim in zenoh);
* the machine's fleet summary on ``P/summary`` (:mod:`twinwatch.twin.summary`: state, alarm
  levels, top fault, RUL, deviations in a few hundred bytes), when it changed and at least
  every ``[zenoh] summary_interval`` seconds (:meth:`HealthPublisher.publish_summary`), a plain
  publisher: late joiners get the latest from the queryable below. Its matching listener sends
  the latest summary again whenever a subscriber becomes reachable (the router's session
  failed over to another router, a restarted router is back, the first subscriber came): a
  watcher holds it without asking, as soon as routes exist again (``summaries_resent``);
* a liveliness token ``P/alive``, present while the publisher is open: a remote process sees the
  machine appear and disappear with ``session.liveliness().declare_subscriber(...)`` or polls it
  with ``session.liveliness().get(...)``. With ``[zenoh] presence = "box"`` the machines of a
  gateway's shared session declare none: one token per box, ``<key_prefix>/@box/<box>/<zid>``,
  stands for them all, and a get on that key answers their names (:class:`QueryDispatch`);
* one queryable on ``P/**`` (in a gateway, one on ``<key_prefix>/**`` for every machine sharing
  the session: :class:`QueryDispatch`) that answers a ``session.get(selector)`` with the
  *latest* payload of every topic above whose key intersects the selector:
  ``get("twinwatch/m1/health")`` returns the last health document, ``get("twinwatch/m1/**")``
  the last health and the last alarm. Topics not published yet are not answered (the get
  ends with no reply).

* handlers added with :meth:`HealthPublisher.add_query_handler` answer their own key under the
  same queryable; opened as the daemon's output (:meth:`HealthPublisher.from_config`) it serves
  ``P/history?t_from=..;t_to=..;by=wall;limit=..;run=..`` from the state database this way,
  asking the gate through its :class:`~twinwatch.sinks.base.SinkContext`
  (:func:`history_parameters`).

Every session is configured by :func:`to_zenoh_config`: explicit endpoints only, multicast and
gossip scouting off, so the daemon never talks to anything it was not told to. TLS/mTLS
(``[zenoh.tls]``), user/password authentication (``[zenoh.auth]``) and zenoh's access control
(``[zenoh.access_control]``, zenoh's own table, passed through verbatim and validated by zenoh
at load time) come from the configuration.

With ``retry_connect=True`` (the daemon) a session whose router cannot be reached at start is
opened in the background, with a delay that doubles up to ``[zenoh].retry_max`` seconds:
publishing is a counted no-op until then (the state database keeps every window, and the
history queryable serves them once the router is there). A connection lost later is restored
by zenoh itself.

An external process subscribes with (``pip install eclipse-zenoh``)::

    import json, zenoh
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    with zenoh.open(conf) as session:
        for reply in session.get("twinwatch/motor1/health", timeout=2.0):
            if reply.ok is not None:
                print("latest:", json.loads(reply.ok.payload.to_string()))
        with session.declare_subscriber("twinwatch/*/health") as sub:
            for sample in sub:
                print(sample.key_expr, json.loads(sample.payload.to_string()))
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import random
import re
import socket
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Self

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    field_validator,
    model_validator,
)

from twinwatch._lazy import lazy_module
from twinwatch.errors import PublisherError
from twinwatch.io.encoding import to_json
from twinwatch.io.keys import box_chunk, box_token_key
from twinwatch.sinks.base import (
    AlarmBands,
    ProcessedWindow,
    SharedResources,
    Sink,
    SinkConfig,
    SinkContext,
)
from twinwatch.twin.summary import fleet_summary, summary_changed

if TYPE_CHECKING:
    import zenoh
    from zenoh import ext as zenoh_ext
else:  # imported when a session opens: loading a configuration does not load zenoh
    zenoh = lazy_module("zenoh")
    zenoh_ext = lazy_module("zenoh.ext")

logger = logging.getLogger(__name__)

UNRULED_THRESHOLD_PCT = 5.0
"""A parameter without an alarm rule is measured against this deviation [% of nominal] for
the fleet summary's ``worst`` (:func:`worst_parameter`): the examples' warning threshold."""

__all__ = [
    "HISTORY_LIMIT",
    "UNRULED_THRESHOLD_PCT",
    "worst_parameter",
    "HealthPublisher",
    "PublisherError",
    "QueryDispatch",
    "ZenohAuthConfig",
    "ZenohConfig",
    "ZenohTlsConfig",
    "declare_publisher",
    "history_parameters",
    "open_session",
    "session_key",
    "to_json",
    "to_zenoh_config",
]

_ENDPOINT_RE = re.compile(
    r"^(?P<proto>tcp|udp|tls|quic|ws)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*))"
    r":(?P<port>[0-9]{1,5})$"
)
# One key-expression chunk without wildcards or the characters zenoh reserves.
_CHUNK_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
# " at /root/.cargo/.../unicast.rs:338." suffixes of zenoh error messages.
_RUST_LOCATION_RE = re.compile(r"\s+at \S+\.rs:\d+\.?")


class ZenohTlsConfig(BaseModel):
    """``[zenoh.tls]``: TLS for ``tls/`` endpoints, mutual TLS with ``enable_mtls`` (zenoh's
    ``transport/link/tls``). Paths are relative to the configuration file's directory.

    Private keys are secrets: a key file that others can read (mode ``o+r``) is refused at
    load, and a configuration holding a key inline (``*_private_key_base64``) must not be
    readable by others either (install it ``0640 root:twinwatch``).
    """

    model_config = ConfigDict(extra="forbid")

    root_ca_certificate: str | None = Field(
        None, description="CA certificate (PEM) that signs the peer's certificate")
    listen_certificate: str | None = Field(None, description="our certificate on listen/tls")
    listen_private_key: str | None = Field(None, description="its private key (PEM)")
    connect_certificate: str | None = Field(None, description="our client certificate (mTLS)")
    connect_private_key: str | None = Field(None, description="its private key (PEM, mTLS)")
    listen_private_key_base64: str | None = Field(None, description="listen key inline, base64")
    connect_private_key_base64: str | None = Field(None, description="connect key inline")
    enable_mtls: bool = Field(False, description="require and present client certificates")
    verify_name_on_connect: bool = Field(True, description="check the server name against "
                                         "its certificate")
    close_link_on_expiration: bool = Field(False, description="close a link when the peer's "
                                           "certificate expires")

    FILES: ClassVar[tuple[str, ...]] = ("root_ca_certificate", "listen_certificate",
                                        "listen_private_key", "connect_certificate",
                                        "connect_private_key")
    SECRET_FILES: ClassVar[tuple[str, ...]] = ("listen_private_key", "connect_private_key")
    INLINE_SECRETS: ClassVar[tuple[str, ...]] = ("listen_private_key_base64",
                                                 "connect_private_key_base64")


class ZenohAuthConfig(BaseModel):
    """``[zenoh.auth]``: zenoh user/password authentication (``transport/auth/usrpwd``).

    ``password`` inline makes the configuration a secret (it must not be readable by others);
    ``dictionary_file`` (``user:password`` lines, the routers' side) is a secret file.
    """

    model_config = ConfigDict(extra="forbid")

    user: str | None = None
    password: str | None = None
    dictionary_file: str | None = None


class ZenohConfig(SinkConfig):
    """The ``[zenoh]`` section of a machine configuration.

    Attributes:
        mode: zenoh node kind. ``"peer"`` (default) listens on :attr:`listen` and may also
            connect to :attr:`connect`; ``"client"`` only connects (``connect`` must be set,
            ``listen`` must not); ``"router"`` listens and routes for clients, standing in for a
            ``zenohd`` when there is none.
        listen: endpoints ``proto/host:port`` to listen on, e.g. ``"tcp/127.0.0.1:7447"``.
        connect: endpoints to connect to (a router or another peer).
        key_prefix: first chunk(s) of every key, ``"twinwatch"`` gives
            ``twinwatch/<machine>/health``. ``/``-separated chunks, no wildcards.
        enabled: when false, :class:`HealthPublisher` opens no session and publishing is a no-op.
        retry_max: longest delay [s] between attempts to reach an unreachable router at start.
        cache: samples each publisher keeps for late joiners and for subscribers recovering
            what they missed (zenoh.ext ``AdvancedPublisher`` cache): the last ``cache``
            windows on ``P/health``, alarm events on ``P/alarm``; 0: plain publishers (no
            cache, no miss detection: a subscriber catches up with the history query only).
        heartbeat: period [s] of the sporadic heartbeat that lets a subscriber notice a lost
            *last* sample (sent only when something was published since the last one); 0: a
            loss is noticed at the next sample only.
        summary_interval: longest time [s, wall] between two fleet summaries of a machine on
            ``P/summary`` (:mod:`twinwatch.twin.summary`): one goes out at once when it
            changed, else at least this often.
        box: what identifies this daemon's host in the fleet summaries (the fleet view groups
            machines by it); None: the host name.
        presence: how the network sees that a machine is there. ``"machine"`` (default): a
            liveliness token ``P/alive`` per machine. ``"box"``: in a gateway (machines sharing
            a session) one token per box, ``<key_prefix>/@box/<box>/<session id>``, stands for
            all its machines (:class:`QueryDispatch`; a get on it answers their names), and
            its machines declare none: a router's death moves one declaration per box, not one
            per machine. A daemon with a session of its own keeps its machine's token.
        tls: ``[zenoh.tls]`` (:class:`ZenohTlsConfig`), needed by ``tls/`` endpoints.
        auth: ``[zenoh.auth]`` (:class:`ZenohAuthConfig`).
        access_control: zenoh's ``access_control`` table verbatim (``enabled``,
            ``default_permission``, ``rules``, ``subjects``, ``policies``), validated by zenoh.

    Unknown keys are an error (``extra="forbid"``).
    """

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    key_prefix: str = "twinwatch"
    enabled: bool = True
    retry_max: StrictFloat = Field(30.0, gt=0)
    cache: StrictInt = Field(30, ge=0, le=100_000)
    heartbeat: StrictFloat = Field(1.0, ge=0)
    summary_interval: StrictFloat = Field(60.0, gt=0, le=86400)
    box: str | None = Field(None, min_length=1, max_length=128)
    presence: Literal["machine", "box"] = "machine"
    tls: ZenohTlsConfig | None = None
    auth: ZenohAuthConfig | None = None
    access_control: dict[str, Any] | None = None

    @field_validator("access_control")
    @classmethod
    def _check_access_control(cls, value: dict[str, Any] | None) -> dict[str, Any] | None:
        if value is not None:
            try:
                zenoh.Config().insert_json5("access_control", json.dumps(value))
            except zenoh.ZError as exc:
                msg = _RUST_LOCATION_RE.sub("", str(exc)).strip()
                raise ValueError(f"zenoh refuses this access_control table: {msg}") from None
        return value

    def input_files(self) -> dict[str, str]:
        """Key in the table -> path of every file the session reads (certificates, keys)."""
        out: dict[str, str] = {}
        if self.tls is not None:
            for k in ZenohTlsConfig.FILES:
                v = getattr(self.tls, k)
                if v:
                    out[f"tls.{k}"] = v
        if self.auth is not None and self.auth.dictionary_file:
            out["auth.dictionary_file"] = self.auth.dictionary_file
        return out

    def secret_input_files(self) -> dict[str, str]:
        """Key in the table -> path of the files holding secrets (private keys, passwords)."""
        secret = {f"tls.{k}" for k in ZenohTlsConfig.SECRET_FILES} | {"auth.dictionary_file"}
        return {k: v for k, v in self.input_files().items() if k in secret}

    def inline_secret_keys(self) -> list[str]:
        """Keys in the table of secrets written in the configuration itself."""
        keys = []
        if self.tls is not None:
            keys += [f"tls.{k}" for k in ZenohTlsConfig.INLINE_SECRETS if getattr(self.tls, k)]
        if self.auth is not None and self.auth.password:
            keys.append("auth.password")
        return keys

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The endpoints the session listens on."""
        return set() if self.mode == "client" else set(self.listen)

    def file_paths(self) -> dict[str, str]:
        """Dotted key (``zenoh.tls.*``) -> path of every file the session reads."""
        return {f"zenoh.{k}": v for k, v in self.input_files().items()}

    def secret_files(self) -> dict[str, str]:
        """Dotted key -> path of the files holding secrets (private keys, password lists)."""
        return {f"zenoh.{k}": v for k, v in self.secret_input_files().items()}

    def inline_secrets(self) -> list[str]:
        """Dotted keys (``zenoh.tls.*``) of secrets written in the configuration itself."""
        return [f"zenoh.{k}" for k in self.inline_secret_keys()]

    def resolve_paths(self, base_dir: Path) -> None:
        """Make relative certificate/key paths absolute against ``base_dir`` (the config
        file's directory); ``~`` is expanded."""
        for obj, keys in ((self.tls, ZenohTlsConfig.FILES), (self.auth, ("dictionary_file",))):
            if obj is None:
                continue
            for k in keys:
                v = getattr(obj, k)
                if v:
                    p = Path(v).expanduser()
                    setattr(obj, k, str(p if p.is_absolute() else (base_dir / p).resolve()))

    @field_validator("listen", "connect")
    @classmethod
    def _check_endpoints(cls, value: list[str]) -> list[str]:
        for endpoint in value:
            match = _ENDPOINT_RE.match(endpoint)
            if match is None:
                raise ValueError(
                    f"endpoint {endpoint!r} is not of the form proto/host:port "
                    "(proto one of tcp, udp, tls, quic, ws), e.g. 'tcp/127.0.0.1:7447'"
                )
            port = int(match["port"])
            if not 1 <= port <= 65535:
                raise ValueError(f"endpoint {endpoint!r}: port {port} is not in 1..65535")
        return value

    @field_validator("key_prefix")
    @classmethod
    def _check_prefix(cls, value: str) -> str:
        _check_key(value, what="key_prefix")
        return value

    @model_validator(mode="after")
    def _check_mode(self) -> Self:
        if self.mode == "client":
            if not self.connect:
                raise ValueError("mode 'client' needs at least one [zenoh].connect endpoint")
            if "listen" in self.model_fields_set and self.listen:
                raise ValueError(
                    "mode 'client' does not listen: remove [zenoh].listen or use mode 'peer'"
                )
        elif not self.listen and not self.connect:
            raise ValueError(
                f"mode {self.mode!r} needs a [zenoh].listen or a [zenoh].connect endpoint"
            )
        listen = [] if self.mode == "client" else self.listen
        tls = self.tls
        if any(e.startswith("tls/") for e in listen):
            if tls is None or not tls.listen_certificate or not (
                    tls.listen_private_key or tls.listen_private_key_base64):
                raise ValueError("a tls/ listen endpoint needs [zenoh.tls] listen_certificate "
                                 "and listen_private_key")
        if any(e.startswith("tls/") for e in self.connect):
            if tls is None or not tls.root_ca_certificate:
                raise ValueError("a tls/ connect endpoint needs [zenoh.tls] root_ca_certificate "
                                 "(the CA that signed the router's certificate)")
        if tls is not None and tls.enable_mtls and self.connect and not (
                tls.connect_certificate and (tls.connect_private_key
                                             or tls.connect_private_key_base64)):
            raise ValueError("enable_mtls with connect endpoints needs [zenoh.tls] "
                             "connect_certificate and connect_private_key")
        return self


def _check_key(key: str, *, what: str) -> None:
    """Raise :class:`ValueError` unless ``key`` is ``/``-separated plain chunks."""
    if not key or any(_CHUNK_RE.match(chunk) is None for chunk in key.split("/")):
        raise ValueError(
            f"{what} {key!r} must be non-empty chunks of letters, digits, '_', '-' or '.' "
            "separated by '/' (no wildcards, no leading or trailing '/')"
        )


def to_zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """Build the :class:`zenoh.Config` for ``cfg``.

    Multicast and gossip scouting are always off: the session only uses the endpoints given.
    In client mode no listen endpoint is set.

    Raises:
        PublisherError: zenoh rejected a value (should not happen for a validated ``cfg``).
    """
    conf = zenoh.Config()
    listen = [] if cfg.mode == "client" else list(cfg.listen)
    try:
        conf.insert_json5("mode", json.dumps(cfg.mode))
        conf.insert_json5("listen/endpoints", json.dumps(listen))
        conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
        if cfg.tls is not None:
            for key, value in cfg.tls.model_dump(exclude_none=True).items():
                conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
        if cfg.auth is not None:
            for key, value in cfg.auth.model_dump(exclude_none=True).items():
                conf.insert_json5(f"transport/auth/usrpwd/{key}", json.dumps(value))
        if cfg.access_control is not None:
            conf.insert_json5("access_control", json.dumps(cfg.access_control))
    except zenoh.ZError as exc:
        # never echo the config: it may hold secrets
        raise PublisherError(f"invalid zenoh configuration (mode={cfg.mode}): "
                             f"{_RUST_LOCATION_RE.sub('', str(exc)).strip()}") from exc
    return conf


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    """Open a zenoh session for ``cfg`` (see :func:`to_zenoh_config`).

    The caller owns the session and must ``close()`` it (or use it as a context manager).

    Raises:
        PublisherError: the session could not open; the message says which endpoint failed
            and what to change (port already in use, nothing listening, unknown host).
    """
    for key, path in cfg.file_paths().items():
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            raise PublisherError(f"cannot read {key} = {path}: {exc.strerror or exc}; fix the "
                                 f"path in [zenoh.tls]/[zenoh.auth] or the file's permissions "
                                 f"(the service user must read it)") from exc
    conf = to_zenoh_config(cfg)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        raise PublisherError(_explain_open_failure(cfg, str(exc))) from exc
    logger.debug(
        "zenoh session %s open (mode=%s, listen=%s, connect=%s)",
        session.zid(),
        cfg.mode,
        cfg.listen if cfg.mode != "client" else [],
        cfg.connect,
    )
    return session


SESSION_FIELDS_NOT_SHARED = frozenset({"key_prefix", "enabled", "retry_max", "cache",
                                       "heartbeat", "summary_interval", "box", "presence"})
"""``[zenoh]`` keys that do not make the session (each machine's publisher has its own), so
machines that differ only in them share one session in a gateway."""


def session_key(cfg: ZenohConfig) -> str:
    """What makes a session (mode, endpoints, TLS, authentication, access control), as one
    string: in a gateway, machines whose ``[zenoh]`` gives the same key share one session
    (:class:`~twinwatch.sinks.base.SharedResources`)."""
    data = cfg.model_dump(mode="json", exclude=set(SESSION_FIELDS_NOT_SHARED))
    return "zenoh:" + json.dumps(data, sort_keys=True, default=str)


def declare_publisher(session: zenoh.Session, key: str, cfg: ZenohConfig
                      ) -> zenoh.Publisher | zenoh_ext.AdvancedPublisher:
    """Declare the publisher of one topic (``P/health``, ``P/alarm``) on ``session``: with
    ``cfg.cache`` > 0 a ``zenoh.ext`` advanced publisher (a cache of the last ``cache`` samples
    for late joiners and recovery, sequence numbers and a sporadic heartbeat every
    ``cfg.heartbeat`` s for sample-miss detection, publisher detection so a subscriber that
    is there first asks a publisher that comes later for its cache); else a plain publisher.
    JSON encoding either way. The one place a topic's publisher is made (a session shared by
    several machines declares each machine's here too).

    Raises:
        zenoh.ZError: the declaration failed (the session closed).
    """
    encoding = zenoh.Encoding.APPLICATION_JSON
    if cfg.cache == 0:
        return session.declare_publisher(key, encoding=encoding)
    heartbeat = cfg.heartbeat if cfg.heartbeat > 0 else None
    return zenoh_ext.declare_advanced_publisher(
        session, key, encoding=encoding, cache=zenoh_ext.CacheConfig(cfg.cache),
        sample_miss_detection=zenoh_ext.MissDetectionConfig(heartbeat=None,
                                                            sporadic_heartbeat=heartbeat),
        publisher_detection=True)


def _explain_open_failure(cfg: ZenohConfig, message: str) -> str:
    message = _RUST_LOCATION_RE.sub("", message).strip()
    lowered = message.lower()
    if "address already in use" in lowered:
        endpoint = next((e for e in cfg.listen if e in message), None) or ", ".join(cfg.listen)
        host_port = endpoint.split("/", 1)[-1]
        host, _, port = host_port.rpartition(":")
        return (
            f"cannot listen on {endpoint}: port {port} already in use on {host}: another "
            "twinwatch or zenoh peer is listening; set [zenoh].listen to another port "
            f"(zenoh: {message})"
        )
    if "unable to connect" in lowered:
        return (
            f"cannot connect to {', '.join(cfg.connect)}: nothing answers there; start the zenoh "
            "router/peer first or fix [zenoh].connect "
            f"(zenoh: {message})"
        )
    if "lookup address" in lowered or "name or service not known" in lowered:
        return (
            f"cannot resolve a host in listen={cfg.listen} connect={cfg.connect}: "
            f"fix the endpoint host in [zenoh] (zenoh: {message})"
        )
    return (
        f"cannot open zenoh session (mode={cfg.mode}, listen={cfg.listen}, "
        f"connect={cfg.connect}): {message}"
    )


QUERY_LOG_INTERVAL = 60.0
"""Seconds between two log lines about one client's bad or failing queries [s]."""


class RateLimitedLog:
    """At most one log line per key every ``interval`` seconds; the next line says how many
    were suppressed (any peer on the network can send queries: it must not flood the journal).

    Args:
        log: the logger to write to.
        interval: seconds between two lines of one key.
        max_keys: keys remembered (the oldest is forgotten beyond it).
    """

    def __init__(self, log: logging.Logger, interval: float, max_keys: int = 1000) -> None:
        self._log = log
        self.interval = interval
        self.max_keys = max_keys
        self._last: dict[str, tuple[float, int]] = {}
        self._lock = threading.Lock()

    def log(self, key: str, level: int, msg: str, *args: object) -> bool:
        """Log ``msg % args`` at ``level`` unless ``key`` logged less than ``interval`` ago.

        Returns:
            True if the line was written.
        """
        now = time.monotonic()
        with self._lock:
            last, suppressed = self._last.get(key, (-math.inf, 0))
            if now - last < self.interval:
                self._last[key] = (last, suppressed + 1)
                return False
            self._last.pop(key, None)
            self._last[key] = (now, 0)
            while len(self._last) > self.max_keys:
                self._last.pop(next(iter(self._last)))
        if suppressed:
            msg += " (%d similar from %s suppressed in the last %.0f s)"
            args = (*args, suppressed, key, self.interval)
        self._log.log(level, msg, *args)
        return True


def _client(query: zenoh.Query) -> str:
    """Who sent ``query``: its source's zenoh id when the peer sent one, else "a peer"."""
    info = query.source_info
    source = getattr(info, "source_id", None) if info is not None else None
    zid = getattr(source, "zid", None)
    return f"peer {zid}" if zid is not None else "a peer"


@dataclasses.dataclass
class _BoxPresence:
    """A box's presence in :class:`QueryDispatch` (``[zenoh] presence = "box"``): its name, the
    key of its token and queryable (:func:`~twinwatch.io.keys.box_token_key`), the two
    entities, and the machines it stands for."""

    name: str
    key: str
    token: zenoh.LivelinessToken
    queryable: zenoh.Queryable[None]
    machines: set[str] = dataclasses.field(default_factory=set)


class QueryDispatch:
    """One queryable on ``<key_prefix>/**`` answering the gets of every machine that shares a
    session in a gateway (:class:`~twinwatch.sinks.base.SharedResources`), each asked only
    when the get's key expression reaches its ``<key_prefix>/<machine>/**``; and one matching
    listener telling them all when a subscriber of their summaries is reachable again.

    A queryable per machine on ``P/**`` made every router of a fleet match each machine's
    wildcard key against the keys it holds: at 10 000 machines behind a three-router mesh the
    far end saw every machine 40 s after their boxes started and 12.7 s after a router
    restart; one per box, 14 s and 7.3 s, with a third of the routers' CPU
    (benchmarks/bench_router_keys.py, docs/fleet.md). A get sees no difference: each machine
    replies on its own keys.

    The matching listener is the session's, not a machine's: a publisher that never puts,
    declared on the first machine's summary key (which a fleet watcher's subscription
    covers), whose matching status turning true again (the session failed over to another
    router, a restarted router is back) sends every machine's latest summary again
    (:meth:`HealthPublisher.resend_summary`). A listener per machine had every router of a
    10 000-machine mesh keep 10 000 interests, and a failover renew 5000 of them at once.

    With ``[zenoh] presence = "box"`` it also holds the box's presence: one liveliness token
    on :func:`~twinwatch.io.keys.box_token_key` (``<prefix>/@box/<box>/<session zid>``)
    for every machine of that box added with ``box``, and a queryable on the same key
    answering ``{"box": <name>, "machines": [<machine>, ...]}`` (what ``twinwatch watch``
    reads to show those machines alive, or gone when the token goes). The token is declared
    with the box's first machine and undeclared with its last. A router's death then moves
    one token per box through the mesh where it moved one per machine (docs/fleet.md, fifth
    round).

    Args:
        session: the shared session.
        prefix: the machines' ``[zenoh] key_prefix``.

    Raises:
        zenoh.ZError: the queryable could not be declared (the session closed).
    """

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.prefix = prefix
        self._session = session
        self._lock = threading.Lock()
        self._machines: dict[str, tuple[zenoh.KeyExpr, Callable[[zenoh.Query], None]]] = {}
        self._resend: dict[str, Callable[[], None]] = {}
        self._probe: zenoh.Publisher | None = None
        self._listener: zenoh.MatchingListener | None = None
        self._matching = False
        self._boxes: dict[str, _BoxPresence] = {}  # box chunk -> its token and machines
        self._queryable = session.declare_queryable(f"{prefix}/**", self._on_query)

    def add(self, machine: str, answer: Callable[[zenoh.Query], None],
            resend: Callable[[], None] | None = None, *, box: str | None = None) -> None:
        """Answer the gets reaching ``<prefix>/<machine>/**`` with ``answer(query)`` (which
        replies and does not drop the query); call ``resend()`` (which sends the machine's
        latest summary again) when a subscriber of the summaries is reachable again; with
        ``box`` (``[zenoh] presence = "box"``), the machine's presence is that box's token.

        Raises:
            zenoh.ZError: the first machine's probe, or its box's token, could not be declared.
        """
        with self._lock:
            self._machines[machine] = (zenoh.KeyExpr(f"{self.prefix}/{machine}/**"), answer)
            if resend is not None:
                self._resend[machine] = resend
            if box is not None:
                self._add_to_box(machine, box)
            probe = None
            if self._probe is None and resend is not None:
                probe = self._probe = self._session.declare_publisher(
                    f"{self.prefix}/{machine}/summary")
        if probe is not None:
            # outside the lock: the listener's first status may come in its declaration
            self._listener = probe.declare_matching_listener(self._on_matching)

    def _add_to_box(self, machine: str, box: str) -> None:
        """``machine`` is present through ``box``'s token, declared now if it is the box's
        first (under the lock: a query on the box's key waits for it)."""
        chunk = box_chunk(box)
        entry = self._boxes.get(chunk)
        if entry is None:
            key = box_token_key(self.prefix, box, str(self._session.zid()))
            queryable = self._session.declare_queryable(key, self._on_box_query)
            try:
                token = self._session.liveliness().declare_token(key)
            except zenoh.ZError:
                queryable.undeclare()
                raise
            entry = self._boxes[chunk] = _BoxPresence(box, key, token, queryable)
            logger.info("presence of the machines of box %s: the liveliness token %s", box, key)
        entry.machines.add(machine)

    @property
    def box_tokens(self) -> list[str]:
        """The key of every box token declared now."""
        with self._lock:
            return [e.key for e in self._boxes.values()]

    def _on_box_query(self, query: zenoh.Query) -> None:
        """A get on a box's token key: ``{"box", "machines"}`` of every box it reaches."""
        try:
            with self._lock:
                boxes = [(e.key, e.name, sorted(e.machines)) for e in self._boxes.values()]
            for key, name, machines in boxes:
                if query.key_expr.intersects(key):
                    query.reply(key, json.dumps({"box": name, "machines": machines}),
                                encoding=zenoh.Encoding.APPLICATION_JSON)
        except zenoh.ZError as exc:
            logger.debug("replying to query %s failed: %s", query.selector, exc)
        finally:
            query.drop()

    def remove(self, machine: str) -> None:
        """Stop answering for ``machine`` (a get running meanwhile may still reach it); the
        last machine of a box undeclares its token."""
        gone: list[_BoxPresence] = []
        with self._lock:
            self._machines.pop(machine, None)
            self._resend.pop(machine, None)
            for chunk, entry in list(self._boxes.items()):
                entry.machines.discard(machine)
                if not entry.machines:
                    gone.append(self._boxes.pop(chunk))
        for entry in gone:  # outside the lock: the queryable waits for a running callback
            self._undeclare_box(entry)

    def _undeclare_box(self, entry: _BoxPresence) -> None:
        for what, entity in (("liveliness token", entry.token), ("queryable", entry.queryable)):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.warning("closing the zenoh %s of box %s failed: %s", what, entry.name,
                               exc)

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        """The probe's matching listener (on a zenoh thread): a subscriber reachable again
        sends every machine's latest summary again."""
        matching = bool(status.matching)
        was, self._matching = self._matching, matching
        if not matching or was:
            return
        with self._lock:
            resend = list(self._resend.values())
        for send in resend:
            send()

    def _on_query(self, query: zenoh.Query) -> None:
        with self._lock:
            machines = list(self._machines.values())
        try:
            for key, answer in machines:
                if query.key_expr.intersects(key):
                    answer(query)
        finally:
            query.drop()

    def close(self) -> None:
        """Undeclare the queryable, the matching listener and its probe (each waits for a
        running callback), and the boxes' tokens left."""
        with self._lock:
            boxes, self._boxes = list(self._boxes.values()), {}
        for entry in boxes:
            self._undeclare_box(entry)
        entities = (("queryable", self._queryable), ("matching listener", self._listener),
                    ("summary probe", self._probe))
        for what, entity in entities:
            if entity is None:
                continue
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                logger.warning("closing the zenoh %s on %s/** failed: %s", what, self.prefix,
                               exc)


class HealthPublisher(Sink):
    """Publishes one machine's health (and other JSON topics) on zenoh: the built-in output
    ``zenoh`` (table ``[zenoh]``, a publisher: it gets only the windows the state store stored).

    Keys, with ``P = {config.key_prefix}/{machine}``: ``P/health`` (publisher and queryable
    answering the latest document), ``P/<suffix>`` for :meth:`publish_json`, liveliness token
    ``P/alive``. See the module docstring for how a remote process reads them.

    :meth:`publish` and :meth:`publish_json` may be called from a worker thread while
    :meth:`close` is called from another; a failing put is logged once (then at DEBUG until a
    put succeeds again), counted in :attr:`errors`, and never raised. After :meth:`close`,
    publishing is a silent no-op. With ``config.enabled`` false nothing is opened and
    publishing is a no-op.

    Args:
        config: the ``[zenoh]`` configuration.
        machine: machine name, one key chunk (letters, digits, ``_``, ``-``, ``.``).

    Raises:
        ValueError: ``machine`` is not a valid key chunk.
        PublisherError: the session or a declaration could not be created.
    """

    config_class: ClassVar[type[ZenohConfig]] = ZenohConfig
    counter_prefix: ClassVar[str | None] = "zenoh"
    open_order: ClassVar[int] = 10  # the port first: a second daemon fails before any file

    def __init__(self, config: ZenohConfig, machine: str, *,
                 retry_connect: bool = False, shared: SharedResources | None = None) -> None:
        self._closed = True  # until fully open, so __del__ and close() are safe
        if "/" in machine:
            raise ValueError(f"machine {machine!r} must be a single key chunk (no '/')")
        _check_key(machine, what="machine")
        self.config = config
        self.machine = machine
        self.base_key = f"{config.key_prefix}/{machine}"
        self.health_key = f"{self.base_key}/health"
        self.summary_key = f"{self.base_key}/summary"
        self.alive_key = f"{self.base_key}/alive"
        self.box = config.box or socket.gethostname() or "localhost"
        self.summaries = 0
        self.summaries_resent = 0
        self._matching: zenoh.MatchingListener | None = None
        self._summary_matching = False  # a subscriber of P/summary was reachable last
        self._summary: dict[str, Any] | None = None  # the last summary published
        self._summary_at = -math.inf  # monotonic time it was published [s]
        self.published = 0
        self.errors = 0
        self.not_connected = 0
        self._lock = threading.Lock()
        self._failing = False
        self._latest: dict[str, str] = {}
        self._handlers: dict[str, Callable[[zenoh.Query], Any]] = {}
        self._publishers: dict[str, zenoh.Publisher | zenoh_ext.AdvancedPublisher] = {}
        self._session: zenoh.Session | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._queryable: zenoh.Queryable[None] | None = None
        self._give_up = threading.Event()
        self._connector: threading.Thread | None = None
        self._query_log = RateLimitedLog(logger, QUERY_LOG_INTERVAL)
        self._detached = False
        self._shared = shared
        self._shared_key: str | None = None
        # in a gateway, the queryable every machine of the shared session answers through
        self._dispatch: QueryDispatch | None = None
        self._dispatch_key: str | None = None
        if not config.enabled:
            logger.info("zenoh publishing disabled for %s", machine)
            return
        try:
            session = self._open_session()
        except PublisherError as exc:
            unreachable = "nothing answers there" in str(exc)
            if not (retry_connect and unreachable):
                raise
            logger.warning("%s; twinwatch runs on (estimation, state database) and keeps "
                           "trying every %g s at most; subscribers catch up on the missed "
                           "windows with the history query", exc, config.retry_max)
            self._closed = False
            self._connector = threading.Thread(target=self._connect_loop,
                                               name="twinwatch-zenoh-connect", daemon=True)
            self._connector.start()
            return
        self._attach(session)
        self._closed = False

    def _open_session(self) -> zenoh.Session:
        """This publisher's session: its own (:func:`open_session`), or in a gateway the one
        every machine with the same session settings shares (:attr:`SinkContext.shared`,
        keyed by :func:`session_key`).

        Raises:
            PublisherError: as :func:`open_session`.
        """
        if self._shared is None:
            return open_session(self.config)
        key = session_key(self.config)
        session = self._shared.acquire(key, lambda: open_session(self.config),
                                       lambda s: s.close())
        self._shared_key = key
        return session

    def _close_session(self, session: zenoh.Session) -> None:
        """Close this publisher's own session, or release its share of a shared one (the
        last machine to release it closes it)."""
        key, self._shared_key = self._shared_key, None
        if self._shared is not None and key is not None:
            self._shared.release(key)
        else:
            session.close()

    def _attach(self, session: zenoh.Session) -> None:
        """Declare the health publisher, queryable and token on ``session`` and use it."""
        queryable: zenoh.Queryable[None] | None = None
        try:
            publisher = declare_publisher(session, self.health_key, self.config)
            if self._shared is not None and self._shared_key is not None:
                key = f"{self._shared_key}|queryable|{self.config.key_prefix}"
                dispatch: QueryDispatch = self._shared.acquire(
                    key, lambda: QueryDispatch(session, self.config.key_prefix),
                    QueryDispatch.close)
                self._dispatch, self._dispatch_key = dispatch, key  # released on failure
                by_box = self.config.presence == "box"
                dispatch.add(self.machine, self._answer, self.resend_summary,
                             box=self.box if by_box else None)
            else:
                by_box = False  # a session of its own: the machine's token is the box's
                queryable = session.declare_queryable(f"{self.base_key}/**", self._on_query)
            token = None if by_box else session.liveliness().declare_token(self.alive_key)
        except zenoh.ZError as exc:
            self._leave_dispatch()
            self._close_session(session)
            raise PublisherError(
                f"cannot declare zenoh entities under {self.base_key}: {exc}"
            ) from exc
        with self._lock:
            self._publishers[self.health_key] = publisher
            self._queryable, self._token, self._session = queryable, token, session
        cfg = self.config
        logger.info(
            "publishing health of %s on %s (mode=%s, listen=%s, connect=%s)",
            self.machine,
            self.health_key,
            cfg.mode,
            cfg.listen if cfg.mode != "client" else [],
            cfg.connect,
        )

    def _connect_loop(self) -> None:
        """Open the session in the background until it works or :meth:`close` is called;
        the delay doubles from 0.5 s up to ``retry_max``, with +-20 % jitter."""
        delay = 0.5
        while not self._give_up.wait(delay * random.uniform(0.8, 1.2)):
            try:
                session = self._open_session()
            except PublisherError as exc:
                logger.debug("zenoh still unreachable: %s", exc)
                delay = min(2 * delay, self.config.retry_max)
                continue
            if self._give_up.is_set():
                self._close_session(session)
                return
            try:
                self._attach(session)
            except PublisherError as exc:
                logger.error("%s", exc)
                return
            logger.warning("zenoh reached (%s) after %d windows were not published: "
                           "publishing resumes", ", ".join(self.config.connect),
                           self.not_connected)
            return

    # -- the sink contract ---------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: ZenohConfig, context: SinkContext) -> Self:
        """The daemon's publisher: a router unreachable at start is retried in the background;
        with a state store (``context.history``) the history query is served.

        Raises:
            PublisherError: the session or a declaration could not be created.
            ValueError: the machine name is not a key chunk.
        """
        publisher = cls(config, context.machine, retry_connect=True, shared=context.shared)
        publisher.attach(context)
        return publisher

    def attach(self, context: SinkContext) -> None:
        """Serve the history of ``context`` (a new daemon after a reload adopts the session)."""
        super().attach(context)
        self._detached = False
        if context.history is not None and f"{self.base_key}/history" not in self._handlers:
            self.add_query_handler("history", self._on_history_query)

    def detach(self) -> None:
        """A reload hands the session over: history queries are answered "reloading"."""
        super().detach()
        self._detached = True

    def _on_history_query(self, query: Any) -> dict[str, Any]:
        """``get("P/history?t_from=..;t_to=..;by=plant|wall;limit=..;run=..")`` (zenoh
        thread): one reply ``{"count", "more", "windows": [health, ...]}``, oldest first (one
        run's with ``run``: a run id, or ``current``, the running daemon's).

        Raises:
            ValueError: a bad parameter (replied as an error naming it), or no history to
                serve (reloading; no state database).
        """
        history = self.context.history if self.context is not None else None
        if self._detached:
            raise ValueError("the daemon is reloading: ask again in a moment")
        if history is None:
            raise ValueError("this daemon keeps no history (no state database: [state])")
        t_from, t_to, limit, by, run, after = history_parameters(query.parameters)
        if run == "current":
            run = self.context.run if self.context is not None and self.context.run else None
            if run is None:
                raise ValueError("run='current': this daemon has no run id")
        # ``after`` only when asked: a HistoryQuery written before it existed still serves
        windows = (history(t_from, t_to, limit, by, run) if after is None
                   else history(t_from, t_to, limit, by, run, after))
        more = len(windows) == limit
        # the cursor of the next page in the time asked: the gate's (by wall time the stamp it
        # saved the window with: the messages carry plant time only), else by plant time the
        # last window's end
        nxt = getattr(windows, "next_after", None) if more and windows else None
        if nxt is None and more and windows and by == "plant":
            nxt = windows[-1].t_end
        return {"machine": self.machine, "by": by, "t_from": t_from, "t_to": t_to, "run": run,
                "after": after, "count": len(windows), "more": more, "next_after": nxt,
                # each stored message as it was stored (the fields it carries, no others)
                "windows": [w.model_dump(by_alias=True, exclude_unset=True) for w in windows]}

    def counters(self) -> dict[str, int]:
        """``published`` (the windows' and events' puts), ``summaries`` (the fleet summaries
        sent, :meth:`publish_summary`), ``summaries_resent`` (the latest summary sent again
        when a subscriber became reachable again), ``errors`` (failed puts), ``not_connected``
        (windows before the router was reached)."""
        return {"published": int(self.published), "summaries": int(self.summaries),
                "summaries_resent": int(self.summaries_resent),
                "errors": int(self.errors), "not_connected": int(self.not_connected)}

    @property
    def status(self) -> str:
        return f"health on {self.health_key}"

    def summary(self) -> list[str]:
        if self.config.mode == "client":
            where = f"a client of {', '.join(self.config.connect)}"
        else:
            where = f"listening on {', '.join(self.config.listen) or 'nothing'}"
        return [f"health was published on {self.health_key} (zenoh, {where})"]

    @property
    def connected(self) -> bool:
        """A session is open (False while the router is still being reached at start)."""
        return self._session is not None

    def add_query_handler(self, key_suffix: str, handler: Callable[[zenoh.Query], Any]) -> None:
        """Answer gets on ``P/{key_suffix}`` with ``handler(query)`` (called on a zenoh thread):
        a mapping is replied as JSON on that key; a :class:`ValueError` is replied as an error
        with its message.

        Raises:
            ValueError: ``key_suffix`` is not a plain key.
        """
        _check_key(key_suffix, what="key_suffix")
        self._handlers[f"{self.base_key}/{key_suffix}"] = handler

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run (or when publishing is disabled)."""
        return self._closed

    @property
    def session(self) -> zenoh.Session | None:
        """The underlying zenoh session (``None`` when disabled)."""
        return self._session

    def publish(self, health: Mapping[str, Any]) -> None:
        """Publish one health document on ``P/health`` and keep it as the latest.

        Args:
            health: JSON-serialisable mapping (see :func:`to_json`).
        """
        self._put(self.health_key, health)

    def publish_json(self, key_suffix: str, payload: Mapping[str, Any]) -> None:
        """Publish ``payload`` as JSON on ``P/{key_suffix}`` and keep it as the latest.

        Args:
            key_suffix: one or more ``/``-separated key chunks, e.g. ``"alarm"``; not
                ``"alive"`` (reserved for liveliness).
            payload: JSON-serialisable mapping (see :func:`to_json`).

        Raises:
            ValueError: ``key_suffix`` is not a plain key or is ``"alive"``.
        """
        _check_key(key_suffix, what="key_suffix")
        if key_suffix == "alive":
            raise ValueError("key_suffix 'alive' is reserved for the liveliness token")
        self._put(f"{self.base_key}/{key_suffix}", payload)

    def write(self, out: ProcessedWindow) -> None:
        """The window pipeline's sink call: the window's health on ``P/health`` (its one
        encoding, :attr:`~twinwatch.sinks.base.ProcessedWindow.health_json`), then its alarm
        events on ``P/alarm``, then its fleet summary on ``P/summary`` when it changed or
        ``[zenoh] summary_interval`` passed (:meth:`publish_summary`), with the machine's
        worst parameter by its own threshold (:func:`worst_parameter`) as ``worst``."""
        self._put(self.health_key, out.health_json)
        for event in out.events:
            self.publish_json("alarm", event)
        summary = fleet_summary(out.health, box=self.box, wall=time.time())
        bands = self.context.alarm_bands if self.context is not None else {}
        summary["worst"] = worst_parameter(out.health, bands)
        self.publish_summary(summary)

    def publish_summary(self, summary: Mapping[str, Any], *, now: float | None = None
                        ) -> bool:
        """Publish a fleet summary (:func:`~twinwatch.twin.summary.fleet_summary`) on
        ``P/summary`` if it changed since the last one published
        (:func:`~twinwatch.twin.summary.summary_changed`) or ``[zenoh] summary_interval``
        seconds passed since; it is kept as the latest: a get on ``P/summary`` (or
        ``<prefix>/*/summary`` for the fleet) returns it, which is how a late joiner or a
        watcher back from a router outage gets it (the summary's publisher is a plain one).

        Args:
            summary: the summary (plain JSON types).
            now: monotonic time [s] (default: :func:`time.monotonic`).

        Returns:
            True if it was published.
        """
        now = time.monotonic() if now is None else now
        doc = dict(summary)
        if not summary_changed(self._summary, doc) and not _worst_changed(
                self._summary, doc) and now - self._summary_at < self.config.summary_interval:
            return False
        self._summary, self._summary_at = doc, now
        self._put(self.summary_key, doc)
        self.summaries += 1
        return True

    def _put(self, key: str, payload: Mapping[str, Any] | str) -> None:
        with self._lock:
            if self._closed:
                logger.debug("publisher closed, dropping %s", key)
                return
            if self._session is None:  # router not reached yet (retry_connect)
                if key != self.summary_key:  # windows and events, not their summaries
                    self.not_connected += 1
                self._latest[key] = payload if isinstance(payload, str) else to_json(payload)
                return
            try:
                text = payload if isinstance(payload, str) else to_json(payload)
                publisher = self._publishers.get(key)
                if publisher is None:
                    # the summary's publisher is a plain one: its latest is this queryable's
                    # (a fleet of 5000 machines' advanced publishers through three routers
                    # left a far advanced subscriber without a quarter of them for minutes:
                    # benchmarks/bench_fleet.py, docs/fleet.md)
                    cfg = (self.config if key != self.summary_key else self.config.model_copy(
                        update={"cache": 0}))
                    publisher = declare_publisher(self._session, key, cfg)
                    self._publishers[key] = publisher
                    if (key == self.summary_key and self._dispatch is None
                            and isinstance(publisher, zenoh.Publisher)):
                        # its own session's listener (a gateway's: QueryDispatch's)
                        self._matching = publisher.declare_matching_listener(
                            self._on_summary_matching)
                publisher.put(text)
            except (zenoh.ZError, TypeError, ValueError) as exc:
                self.errors += 1
                if not self._failing:
                    logger.error("publishing on %s failed: %s", key, exc)
                    self._failing = True
                else:
                    logger.debug("publishing on %s failed again: %s", key, exc)
                return
            self._latest[key] = text
            if key != self.summary_key:  # the summaries are counted in summaries
                self.published += 1
            if self._failing:
                logger.info("publishing on %s works again", key)
                self._failing = False

    def _on_summary_matching(self, status: zenoh.MatchingStatus) -> None:
        """The summary publisher's matching listener, a machine of its own session (on a
        zenoh thread, never under the lock: it may run inside the declaration): when a
        subscriber becomes reachable again, the latest summary is sent again
        (:meth:`resend_summary`). Measured (a box on two routers, the first killed): the
        box's session failed over at once, matching went false and true in the same 10 ms,
        and the latest summary reached the watcher on the other router then, where a get to
        that box went unanswered while the mesh settled."""
        matching = bool(status.matching)
        was, self._summary_matching = self._summary_matching, matching
        if matching and not was:
            self.resend_summary()

    def resend_summary(self) -> None:
        """Send the latest summary again (none yet, or closed: nothing); counted in
        ``summaries_resent``. Called on a zenoh thread, without the lock."""
        if self._closed:
            return
        text = self._latest.get(self.summary_key)
        publisher = self._publishers.get(self.summary_key)
        if text is None or publisher is None:
            return
        try:
            publisher.put(text)
        except zenoh.ZError as exc:
            logger.debug("sending %s again failed: %s", self.summary_key, exc)
            return
        self.summaries_resent += 1
        logger.debug("%s sent again: a subscriber is reachable again", self.summary_key)

    def _leave_dispatch(self) -> None:
        """Stop answering through the gateway's queryable; the last machine undeclares it."""
        dispatch, key = self._dispatch, self._dispatch_key
        self._dispatch = self._dispatch_key = None
        if dispatch is not None:
            dispatch.remove(self.machine)
        if self._shared is not None and key is not None:
            self._shared.release(key)

    def _on_query(self, query: zenoh.Query) -> None:
        """Answer a get on this machine's own queryable (:meth:`_answer`), then drop it."""
        try:
            self._answer(query)
        finally:
            query.drop()

    def _answer(self, query: zenoh.Query) -> None:
        """Answer a get with the latest payload of every topic its key expression intersects
        and the handlers' answers (the query is not dropped: the caller does)."""
        with self._lock:
            latest = list(self._latest.items())
        try:
            for key, text in latest:
                if query.key_expr.intersects(key):
                    query.reply(key, text, encoding=zenoh.Encoding.APPLICATION_JSON)
            for key, handler in self._handlers.items():
                if not query.key_expr.intersects(key):
                    continue
                try:
                    answer = handler(query)
                except ValueError as exc:
                    query.reply_err(str(exc))
                    self._query_log.log(_client(query), logging.WARNING,
                                        "query %s refused: %s", query.selector, exc)
                    continue
                except Exception as exc:  # noqa: BLE001 - a query must not kill zenoh's thread
                    query.reply_err(f"internal error: {exc}")
                    self._query_log.log(_client(query), logging.ERROR,
                                        "answering %s failed: %s: %s", query.selector,
                                        type(exc).__name__, exc)
                    logger.debug("answering %s failed", query.selector, exc_info=True)
                    continue
                query.reply(key, to_json(answer), encoding=zenoh.Encoding.APPLICATION_JSON)
        except zenoh.ZError as exc:
            logger.debug("replying to query %s failed: %s", query.selector, exc)

    def close(self) -> None:
        """Undeclare the token, queryable and publishers, then close the session. Idempotent."""
        self._give_up.set()
        connector, self._connector = self._connector, None
        if connector is not None:
            connector.join(timeout=30)
        with self._lock:
            if self._closed:
                return
            self._closed = True
            token, queryable, session = self._token, self._queryable, self._session
            publishers = list(self._publishers.values())
            matching, self._matching = self._matching, None
            self._token = self._queryable = None
            self._publishers.clear()
        # Outside the lock: undeclaring the queryable waits for a running _on_query callback.
        steps: list[tuple[str, Callable[[], Any]]] = []
        if token is not None:
            steps.append(("liveliness token", token.undeclare))
        if queryable is not None:
            steps.append(("queryable", queryable.undeclare))
        steps.append(("gateway's queryable", self._leave_dispatch))
        if matching is not None:
            steps.append(("summary's matching listener", matching.undeclare))
        steps += [("publisher", p.undeclare) for p in publishers]
        if session is not None:
            steps.append(("session", lambda: self._close_session(session)))
        for what, step in steps:
            try:
                step()
            except zenoh.ZError as exc:
                logger.warning("closing zenoh %s of %s failed: %s", what, self.machine, exc)
        logger.info(
            "zenoh publisher of %s closed (%d published, %d errors)",
            self.machine,
            self.published,
            self.errors,
        )

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"HealthPublisher({self.health_key!r}, {state}, published={self.published})"


HISTORY_LIMIT = 1000
"""Most windows one history query returns (page on with ``after`` = the reply's
``next_after``)."""

HISTORY_PARAMETERS = ("t_from", "t_to", "by", "limit", "run", "after")

_RUN_RE = re.compile(r"^[A-Za-z0-9_.:-]{1,64}$")


def history_parameters(params: Any) -> tuple[float | None, float | None, int,
                                              Literal["plant", "wall"], str | None,
                                              float | None]:
    """The history query's parameters, checked: ``t_from`` and ``t_to`` finite seconds (either
    may be absent), ``t_from <= t_to``, ``by`` ``plant`` or ``wall``, ``limit`` a whole number
    from 1 (at most :data:`HISTORY_LIMIT` are returned), ``run`` a run id (the health
    message's ``run``: letters, digits, ``_.:-``) or ``current`` (absent: every run),
    ``after`` finite seconds (only windows ending strictly after it: the paging cursor, the
    previous reply's ``next_after``; ``t_from`` is inclusive and would repeat the last window).

    Args:
        params: the selector's parameters (a mapping with ``get``, zenoh's ``Parameters``).

    Returns:
        ``(t_from, t_to, limit, by, run, after)``.

    Raises:
        ValueError: naming the bad parameter.
    """
    unknown = [k for k, _ in _items(params) if k not in HISTORY_PARAMETERS]
    if unknown:
        raise ValueError(f"unknown parameter {unknown[0]!r}: use "
                         f"{', '.join(HISTORY_PARAMETERS)}")

    def num(key: str) -> float | None:
        raw = params.get(key)
        if raw in (None, ""):
            return None
        try:
            value = float(raw)
        except ValueError:
            raise ValueError(f"{key}={raw!r} is not a number [s]") from None
        if not math.isfinite(value):
            raise ValueError(f"{key}={raw!r}: give a finite time [s], or leave it out for "
                             f"an open end")
        return value

    raw_by = params.get("by") or "plant"
    if raw_by not in ("plant", "wall"):
        raise ValueError(f"by={raw_by!r}: use by=plant (source time) or by=wall (epoch s)")
    by: Literal["plant", "wall"] = "wall" if raw_by == "wall" else "plant"
    t_from, t_to = num("t_from"), num("t_to")
    if t_from is not None and t_to is not None and t_from > t_to:
        raise ValueError(f"t_from={t_from:g} is after t_to={t_to:g}")
    lim = num("limit")
    if lim is not None and (lim < 1 or not lim.is_integer()):
        raise ValueError(f"limit={params.get('limit')!r}: give a whole number from 1 "
                         f"(at most {HISTORY_LIMIT} are returned)")
    limit = HISTORY_LIMIT if lim is None else min(int(lim), HISTORY_LIMIT)
    run = params.get("run")
    if run in (None, ""):
        run = None
    elif _RUN_RE.match(str(run)) is None:
        raise ValueError(f"run={run!r}: give a run id as the health messages carry it "
                         f"(e.g. run=20261122T101530Z-3f9a2c), or run=current")
    return t_from, t_to, limit, by, (None if run is None else str(run)), num("after")


def _items(params: Any) -> list[tuple[str, str]]:
    """(key, value) pairs of zenoh ``Parameters`` or a plain mapping."""
    if isinstance(params, dict):
        return list(params.items())
    return [(str(k), str(v)) for k, v in params]


def worst_parameter(health: Any, bands: Mapping[str, AlarmBands]) -> dict[str, Any] | None:
    """The parameter furthest off nominal by its own threshold, for the fleet summary's
    ``worst`` (the fleet view's deviation column leads with it; issue 56: with only Ra's
    deviation shown, a machine with D +20 % looked healthy).

    Each parameter with a finite deviation (not ``tied`` nor ``fixed``: those are not
    estimated) is measured as ``|deviation| / threshold``: its alarm rule's warning threshold
    on the side it deviates to (the alarm threshold when the rule has no warning there; 0 when
    the rule has no threshold on that side: a side the rule does not watch), or
    :data:`UNRULED_THRESHOLD_PCT` without a rule.

    Args:
        health: the window's typed message (its ``parameters``).
        bands: the ``[alarms]`` thresholds by parameter [% of nominal]
            (:attr:`~twinwatch.sinks.base.SinkContext.alarm_bands`).

    Returns:
        ``{"parameter", "deviation_pct", "threshold_pct" (null without a rule), "share"
        (|deviation| / threshold)}``, or None when no parameter has a deviation.
    """
    best: tuple[float, dict[str, Any]] | None = None
    for name, p in (health.parameters or {}).items():
        if p is None or p.status in ("tied", "fixed"):
            continue
        dev = p.deviation_pct
        if not isinstance(dev, int | float) or not math.isfinite(dev):
            continue
        b = bands.get(name)
        if b is None:
            threshold: float | None = None
            share = abs(dev) / UNRULED_THRESHOLD_PCT
        else:
            if dev >= 0:
                th = b.warning_high if b.warning_high is not None else b.alarm_high
            else:
                th = b.warning_low if b.warning_low is not None else b.alarm_low
            threshold = None if th is None else abs(float(th))
            share = abs(dev) / threshold if threshold else 0.0
        if best is None or share > best[0]:
            best = (share, {"parameter": name, "deviation_pct": float(f"{dev:.4g}"),
                            "threshold_pct": threshold, "share": round(share, 3)})
    return best[1] if best is not None else None


def _worst_changed(old: Mapping[str, Any] | None, new: Mapping[str, Any]) -> bool:
    """The worst parameter (:func:`worst_parameter`) is another one than in the summary
    published last: a change, published at once."""
    def name(doc: Mapping[str, Any] | None) -> Any:
        worst = doc.get("worst") if doc is not None else None
        return worst.get("parameter") if isinstance(worst, Mapping) else None

    return old is not None and name(old) != name(new)
