"""The ``[zenoh]`` table: the session (mode, endpoints), TLS, authentication, access
control, the publishers' cache and the fleet summary (docs/configuration.md).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Self

from pydantic import Field, StrictFloat, StrictInt, field_validator, model_validator

from twinwatch._lazy import lazy_module
from twinwatch._table import StrictTable
from twinwatch.sinks.base import SinkConfig

if TYPE_CHECKING:
    import zenoh
    from zenoh import ext as zenoh_ext
else:  # imported when a session opens: loading a configuration does not load zenoh
    zenoh = lazy_module("zenoh")
    zenoh_ext = lazy_module("zenoh.ext")

_ENDPOINT_RE = re.compile(
    r"^(?P<proto>tcp|udp|tls|quic|ws)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*))"
    r":(?P<port>[0-9]{1,5})$"
)
# One key-expression chunk without wildcards or the characters zenoh reserves.
_CHUNK_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
# " at /root/.cargo/.../unicast.rs:338." suffixes of zenoh error messages.
RUST_LOCATION_RE = re.compile(r"\s+at \S+\.rs:\d+\.?")


class ZenohTlsConfig(StrictTable):
    """``[zenoh.tls]``: TLS for ``tls/`` endpoints, mutual TLS with ``enable_mtls`` (zenoh's
    ``transport/link/tls``). Paths are relative to the configuration file's directory.

    Private keys are secrets: a key file that others can read (mode ``o+r``) is refused at
    load, and a configuration holding a key inline (``*_private_key_base64``) must not be
    readable by others either (install it ``0640 root:twinwatch``).
    """

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

    def missing(self, *, listen: bool, connect: bool, client: bool) -> str | None:
        """What a ``tls/`` ``listen`` or ``connect`` endpoint, or mutual TLS on a ``client``
        connection, needs of this table and it lacks; None when nothing."""
        if listen and not (self.listen_certificate
                           and (self.listen_private_key or self.listen_private_key_base64)):
            return ("a tls/ listen endpoint needs [zenoh.tls] listen_certificate and "
                    "listen_private_key")
        if connect and not self.root_ca_certificate:
            return ("a tls/ connect endpoint needs [zenoh.tls] root_ca_certificate (the CA "
                    "that signed the router's certificate)")
        if self.enable_mtls and client and not (
                self.connect_certificate
                and (self.connect_private_key or self.connect_private_key_base64)):
            return ("enable_mtls with connect endpoints needs [zenoh.tls] connect_certificate "
                    "and connect_private_key")
        return None


class ZenohAuthConfig(StrictTable):
    """``[zenoh.auth]``: zenoh user/password authentication (``transport/auth/usrpwd``).

    ``password`` inline makes the configuration a secret (it must not be readable by others);
    ``dictionary_file`` (``user:password`` lines, the routers' side) is a secret file.
    """

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
                msg = RUST_LOCATION_RE.sub("", str(exc)).strip()
                raise ValueError(f"zenoh refuses this access_control table: {msg}") from None
        return value

    def input_files(self) -> dict[str, str]:
        """Key in the table -> path of every file the session reads (certificates, keys)."""
        out: dict[str, str] = {}
        if self.tls is not None:
            out.update({f"tls.{k}": v for k in ZenohTlsConfig.FILES if (v := getattr(self.tls, k))})
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

    def inline_secrets(self) -> list[str]:
        """Dotted keys (``zenoh.tls.*``) of secrets written in the configuration itself."""
        return [f"zenoh.{k}" for k in self.inline_secret_keys()]

    @field_validator("listen", "connect")
    @classmethod
    def _check_endpoints(cls, value: list[str]) -> list[str]:
        for endpoint in value:
            match = _ENDPOINT_RE.match(endpoint)
            if match is None:
                raise ValueError(f"endpoint {endpoint!r} is not of the form proto/host:port "
                                 "(proto one of tcp, udp, tls, quic, ws), e.g. "
                                 "'tcp/127.0.0.1:7447'")
            port = int(match["port"])
            if not 1 <= port <= 65535:
                raise ValueError(f"endpoint {endpoint!r}: port {port} is not in 1..65535")
        return value

    @field_validator("key_prefix")
    @classmethod
    def _check_prefix(cls, value: str) -> str:
        check_key(value, what="key_prefix")
        return value

    @model_validator(mode="after")
    def _check_mode(self) -> Self:
        if self.mode == "client":
            if not self.connect:
                raise ValueError("mode 'client' needs at least one [zenoh].connect endpoint")
            if "listen" in self.model_fields_set and self.listen:
                raise ValueError("mode 'client' does not listen: remove [zenoh].listen or use "
                                 "mode 'peer'")
        elif not self.listen and not self.connect:
            raise ValueError(f"mode {self.mode!r} needs a [zenoh].listen or a [zenoh].connect "
                             "endpoint")
        return self

    @model_validator(mode="after")
    def _check_tls(self) -> Self:
        listen = [] if self.mode == "client" else self.listen
        problem = (self.tls or ZenohTlsConfig()).missing(
            listen=any(e.startswith("tls/") for e in listen),
            connect=any(e.startswith("tls/") for e in self.connect), client=bool(self.connect))
        if problem is not None:
            raise ValueError(problem)
        return self


def check_key(key: str, *, what: str) -> None:
    """Raise :class:`ValueError` unless ``key`` is ``/``-separated plain chunks."""
    if not key or any(_CHUNK_RE.match(chunk) is None for chunk in key.split("/")):
        raise ValueError(f"{what} {key!r} must be non-empty chunks of letters, digits, '_', '-' "
                         "or '.' separated by '/' (no wildcards, no leading or trailing '/')")
