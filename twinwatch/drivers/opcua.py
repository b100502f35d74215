"""OPC UA driver: one subscription on a server's variables into twin samples; never writes.

A background thread (``twinwatch-opcua-in``) runs asyncua's client in an asyncio loop of its own
and hands complete samples to :meth:`~twinwatch.drivers.base.Driver.read` through a queue.
Nodes (NodeId or browse path, unit checked against EngineeringUnits), the subscription, how
values are joined into samples by source-time slot ``k = round(t / sample_period)``, status
codes, reconnects, security and the one-line refusals (:class:`DriverConfigError`, ``run``
exits 78): docs/opcua-input.md.

A commented ``[driver]`` table: ``twinwatch/config/samples/driver_opcua.toml``
(``twinwatch sample-config --driver opcua``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from pydantic import Field, StrictFloat, StrictInt, model_validator

from twinwatch._table import StrictTable
from twinwatch.drivers.base import (
    DriverConfig,
    DriverConfigError,
    DriverInitializationError,
    QueuedDriver,
    Sample,
)
from twinwatch.io.threadlog import demote_thread_records

if TYPE_CHECKING:  # asyncua is imported when the driver opens: validating loads nothing
    from asyncua import Client, Node

logger = logging.getLogger(__name__)

__all__ = ["OpcUaChannelMap", "OpcUaDriver", "OpcUaDriverConfig", "UNECE_CODES", "unit_matches"]

_THREAD_NAME = "twinwatch-opcua-in"  # the output's server thread is "twinwatch-opcua"
_BACKOFF_INITIAL = 0.1  # [s]
_LIVE_QUEUE = 4096  # samples kept for a caller that does not read (older ones dropped)
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
#: OPC UA StatusCode bits: InfoType DataValue (0x400) with the Overflow bit (0x80)
_OVERFLOW_BITS = 0x480
_WAITING_FOR_INITIAL_DATA = 0x80320000  # BadWaitingForInitialData

#: UNECE Recommendation 20 common codes (the ``UnitId`` of an ``EUInformation`` is the code's
#: letters packed into an Int32, OPC UA Part 8 5.6.3) of the units the twins use.
UNECE_CODES: Mapping[str, str] = {
    "V": "VLT", "A": "AMP", "rad/s": "2A", "N m": "NU", "N m s/rad": "", "m": "MTR",
    "Pa": "PAL", "N": "NEW", "m^2": "MTK", "s": "SEC", "ohm": "OHM", "rpm": "RPM",
    "kg": "KGM", "m/s": "MTS", "m^3/s": "MQS", "W": "WTT", "degC": "CEL", "K": "KEL",
}


def _norm_unit(unit: str) -> str:
    return "".join(unit.replace("·", " ").replace("*", " ").replace("Ω", "ohm").split()).lower()


def unece_unit_id(code: str) -> int:
    """The ``EUInformation.UnitId`` of a UNECE common code (``"VLT"`` -> 5655636)."""
    value = 0
    for ch in code.upper():
        value = (value << 8) | ord(ch)
    return value


def unit_matches(declared: str, display_name: str | None, unit_id: int | None) -> bool:
    """Whether a node's EngineeringUnits (its display name and UNECE ``UnitId``) name the
    channel's declared unit (spaces, ``*`` and ``·`` ignored; ``"N m"`` = ``"N·m"``)."""
    if display_name and _norm_unit(display_name) == _norm_unit(declared):
        return True
    code = next((c for u, c in UNECE_CODES.items() if _norm_unit(u) == _norm_unit(declared)), "")
    return bool(code) and unit_id is not None and unit_id == unece_unit_id(code)


# asyncua's records from the driver's thread (the revised subscription values, each failed
# reconnect) at DEBUG, from the loggers the client's records come from
demote_thread_records(_THREAD_NAME, (
    "asyncua", "asyncua.client.client", "asyncua.client.ua_client",
    "asyncua.client.ua_client.UaClient", "asyncua.client.ua_client.UASocketProtocol",
    "asyncua.common.subscription", "asyncua.client.ua_session",
    "asyncua.client.ua_session.UaSession", "asyncua.common.node", "asyncua.crypto.uacrypto",
    "asyncua.crypto.security_policies", "asyncua.client.ua_file_transfer"))


# -- configuration ----------------------------------------------------------------------------


class OpcUaChannelMap(StrictTable):
    """One twin channel's variable (``[driver.channels] <channel> = {...}``).

    ``node``, ``browse_path`` and ``unit`` are documented in their fields.

    Attributes:
        scale, offset: ``twin value = value * scale + offset``.
    """

    node: str | None = Field(None, min_length=1, description='NodeId string, "ns=2;s=Motor.ia"')
    browse_path: str | None = Field(
        None, min_length=1, description='or browse path from Root, "0:Objects/2:Motor/2:ia"')
    scale: StrictFloat = Field(1.0, allow_inf_nan=False)
    offset: StrictFloat = Field(0.0, allow_inf_nan=False)
    unit: str | None = Field(None, min_length=1,
                             description="checked against the node's EngineeringUnits")

    @model_validator(mode="after")
    def _one_address(self) -> OpcUaChannelMap:
        if (self.node is None) == (self.browse_path is None):
            raise ValueError("give node (a NodeId string) or browse_path, exactly one")
        return self

    def describe(self) -> str:
        return self.node if self.node is not None else f"browse path {self.browse_path}"


class OpcUaDriverConfig(DriverConfig):
    """Configuration of :class:`OpcUaDriver` (the ``[driver]`` table with ``type = "opcua"``).

    The keys with a description in their field are documented there.

    Attributes:
        sample_period: the variables' sample period [s]: the monitored items' sampling
            interval and the slot width samples are joined on.
        timeout: per request and connect [s].
        backoff_max: cap of the reconnect delay [s] (starts at 0.1 s, doubles, jittered).
        security_policy: ``"None"`` or ``"Basic256Sha256"``.
        username, password_file, password: user identity (password: first line of the file).
        channels: twin channel -> :class:`OpcUaChannelMap`, at least one.
    """

    file_keys: ClassVar[tuple[str, ...]] = ("certificate", "private_key", "server_certificate",
                                            "password_file")

    type: Literal["opcua"]
    endpoint: str = Field(pattern=r"^opc\.tcp://[^/\s]+(/\S*)?$",
                          description="opc.tcp://host:port[/path]")
    sample_period: StrictFloat = Field(gt=0, allow_inf_nan=False)
    publishing_interval: StrictFloat = Field(0.05, gt=0, allow_inf_nan=False,
                                             description="s, notifications batch this much")
    queue_size: StrictInt | None = Field(None, ge=1, le=100000,
                                         description="per monitored item (default: 4 "
                                         "publishing intervals of samples, >= 10)")
    timeout: StrictFloat = Field(5.0, gt=0, allow_inf_nan=False)
    backoff_max: StrictFloat = Field(5.0, ge=_BACKOFF_INITIAL, allow_inf_nan=False)
    security_policy: Literal["None", "Basic256Sha256"] = "None"
    security_mode: Literal["Sign", "SignAndEncrypt"] | None = Field(
        None, description="Basic256Sha256 only")
    certificate: Path | None = Field(None, description="the client's certificate (file)")
    private_key: Path | None = Field(None, description="the client's private key (file, a secret)")
    server_certificate: Path | None = Field(None, description="the trusted server certificate")
    username: str | None = Field(None, min_length=1)
    password_file: Path | None = Field(None, description="the password's file (first line)")
    password: str | None = Field(None, description="the password inline (a file is safer)")
    channels: dict[str, OpcUaChannelMap] = Field(min_length=1)

    @model_validator(mode="after")
    def _consistent(self) -> OpcUaDriverConfig:
        keys = ("security_mode", "certificate", "private_key", "server_certificate")
        if self.security_policy == "None":
            given = [k for k in keys if getattr(self, k) is not None]
            if given:
                raise ValueError(f"{', '.join(given)} need security_policy = 'Basic256Sha256'")
        else:
            missing = [k for k in keys if getattr(self, k) is None]
            if missing:
                raise ValueError(f"security_policy = {self.security_policy!r} needs "
                                 f"{', '.join(missing)}")
        if self.password is not None and self.password_file is not None:
            raise ValueError("give password_file or password, not both")
        if (self.password is not None or self.password_file is not None) and not self.username:
            raise ValueError("a password needs a username")
        if any(not name for name in self.channels):
            raise ValueError("channels: empty channel name")
        if self.publishing_interval < self.sample_period:
            raise ValueError("publishing_interval must be at least sample_period")
        return self

    def twin_channels(self) -> tuple[str, ...]:
        """The twin channels this driver delivers (``channels``)."""
        return tuple(self.channels)

    @property
    def effective_queue_size(self) -> int:
        """``queue_size``, or 4 publishing intervals of samples (at least 10)."""
        if self.queue_size is not None:
            return self.queue_size
        return max(10, 4 * math.ceil(self.publishing_interval / self.sample_period - 1e-9))

    def secret_input_files(self, base_dir: Path) -> dict[str, Path]:
        """The private key and the password file (``check-config`` and ``run`` refuse them
        when other users can read them, as the outputs' secrets)."""
        cfg = self.resolved(base_dir)
        return {k: v for k in ("private_key", "password_file")
                if (v := getattr(cfg, k)) is not None}

    def inline_secret_keys(self) -> list[str]:
        """``password`` written in the configuration itself (the file is then a secret)."""
        return ["password"] if self.password is not None else []


# -- the driver -------------------------------------------------------------------------------

_EXTRA_COUNTERS = ("duplicates", "overflows", "server_stamps", "time_jumps", "outages",
                   "reconnects", "dropped", "notifications")
#: a source time further than this from the last sample's is a jump of its clock [s], not a
#: gap (ahead) or a repeated value (back)
_TIME_JUMP = 3600.0


class _Slot:
    __slots__ = ("values", "n", "bad", "t_sum")

    def __init__(self, n_channels: int) -> None:
        self.values: list[float] = [math.nan] * n_channels
        self.n = 0  # channels that delivered
        self.bad = False  # a channel's value was not Good or not a number
        self.t_sum = 0.0


class OpcUaDriver(QueuedDriver):
    """Twin samples from an OPC UA server's variables through one subscription; never writes.

    Args:
        time_origin: POSIX seconds subtracted from every sample time (0: ``t`` is POSIX
            seconds; the simulated plant gives its start, so that ``t`` is plant time).
        on_take: called (in the caller's thread) with the number of samples each read took
            from the queue (the simulated plant paces itself on it).

    Attributes:
        cpu_seconds: CPU time [s] the client's thread has used since it subscribed (asyncua's
            decoding and the joining; updated after each batch of notifications).

    Raises:
        DriverConfigError: a node does not exist or a browse path matches nothing, a unit
            mismatch, the server rejects the user or the certificate, a file cannot be read.
        DriverInitializationError: the server cannot be reached within ``timeout`` (the daemon
            waits for it and opens the driver again).
    """

    config_class = OpcUaDriverConfig
    live = True
    sample_machine = "dc-motor-opcua"
    sample_title = "a DC motor drive's OPC UA server, through one subscription"
    driver_name = "OPC UA"

    @classmethod
    def reopens(cls, config: DriverConfig) -> bool:
        """A server comes and goes: the daemon waits for it and opens it again."""
        return True

    @classmethod
    def describe(cls, config: DriverConfig) -> str:
        assert isinstance(config, OpcUaDriverConfig)
        return f"the OPC UA server {config.endpoint}"

    @classmethod
    def probe(cls, config: DriverConfig, *, base_dir: Path | None = None) -> str | None:
        """``check-config``: connect (with the configured security and user), find every
        channel's node, check its unit, subscribe, and close (nothing is written).

        Raises:
            DriverConfigError: a node, a browse path, a unit, the user or the certificate
                (the message names the key).
            DriverInitializationError: the server cannot be reached.
        """
        assert isinstance(config, OpcUaDriverConfig)
        cls(config, base_dir=base_dir).close()
        return (f"OPC UA server {config.endpoint}: {len(config.channels)} node(s) found, units "
                "checked, subscription accepted (nothing written)")

    def __init__(self, config: OpcUaDriverConfig, *, base_dir: Path | None = None,
                 time_origin: float = 0.0,
                 on_take: Callable[[int], None] | None = None) -> None:
        super().__init__()
        self.config = config.resolved(base_dir)
        self.channels = tuple(config.channels)
        self.sample_period = config.sample_period
        self.time_origin = time_origin
        self._on_take = on_take
        self.stats.extra.update({name: 0 for name in _EXTRA_COUNTERS})
        self.stats.extra.update({f"status_{ch}": 0 for ch in self.channels})
        self.cpu_seconds = 0.0
        self._cpu_base: float | None = None
        self._init_queue(_LIVE_QUEUE)
        self._opened = threading.Event()
        self._open_error: Exception | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        # slot bookkeeping (the loop thread only)
        self._pending: dict[int, _Slot] = {}
        self._last_k: int | None = None
        self._arrival = [0.0] * len(self.channels)  # monotonic time of each channel's last value
        self._jump_slots = int(_TIME_JUMP / self.sample_period)
        self._password = self._read_password()
        self._thread = threading.Thread(target=self._thread_main, name=_THREAD_NAME, daemon=True)
        self._thread.start()
        if not self._opened.wait(self.config.timeout * 3 + 10.0):
            self.close()
            raise DriverInitializationError(
                f"OPC UA server {self.config.endpoint} did not answer in time")
        if self._open_error is not None:
            err = self._open_error
            self.close()
            raise err
        logger.info("OPC UA driver subscribed to %s: channels %s, sampling %.4g s, publishing "
                    "%.4g s, queue %d", self.config.endpoint, ", ".join(self.channels),
                    self.sample_period, self.config.publishing_interval,
                    self.config.effective_queue_size)

    def _read_password(self) -> str | None:
        cfg = self.config
        if cfg.password_file is None:
            return cfg.password
        try:
            with open(cfg.password_file, encoding="utf-8") as f:
                return f.readline().rstrip("\r\n")
        except OSError as exc:
            raise DriverConfigError(f"driver.password_file: cannot read {cfg.password_file}: "
                                    f"{exc.strerror or exc}") from exc

    # -- reading (caller's thread) ----------------------------------------------------------
    def _read_internal(self, timeout: float | None) -> Sample | None:
        sample = super()._read_internal(timeout)
        if sample is not None and self._on_take is not None:
            self._on_take(1)
        return sample

    @property
    def waiting(self) -> str | None:
        """While the server is away: since when and the last error; None while it delivers."""
        since = self._down_since
        if since is None:
            return None
        return (f"OPC UA server {self.config.endpoint} away for "
                f"{time.monotonic() - since:.0f} s ({self._last_error}); reconnecting with "
                f"backoff up to {self.config.backoff_max:g} s")

    @property
    def silent(self) -> tuple[str, ...]:
        """The channels whose values stopped (for a second, or four publishing intervals) while
        the others' arrive, with how long: ``("ia for 3.1 s",)``."""
        if self._down_since is not None or not any(self._arrival):
            return ()
        now = time.monotonic()
        quiet = max(1.0, 4 * self.config.publishing_interval)
        newest = max(self._arrival)
        if now - newest > quiet:  # nothing arrives at all: not a silent channel
            return ()
        return tuple(f"{ch} for {now - t:.1f} s" for ch, t in zip(self.channels, self._arrival,
                                                                  strict=True)
                     if now - t > quiet)

    # -- the client thread ------------------------------------------------------------------
    def _thread_main(self) -> None:
        try:
            with asyncio.Runner() as runner:
                runner.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to the reader
            if not self._opened.is_set():
                self._open_error = DriverInitializationError(
                    f"OPC UA client for {self.config.endpoint} failed: {exc}")
            else:
                self._fatal = f"OPC UA client for {self.config.endpoint} failed: {exc}"
                logger.debug("%s", self._fatal)  # raised to the reader, who says it
        finally:
            self._opened.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        backoff = _BACKOFF_INITIAL
        first = True
        while not self._stop.is_set():
            client = self._make_client()
            lost = asyncio.Event()

            async def on_lost(exc: Exception, lost: asyncio.Event = lost) -> None:
                self._last_error = str(exc) or type(exc).__name__
                lost.set()

            client.connection_lost_callback = on_lost
            try:
                nodes = await self._connect(client)
                sub = await self._subscribe(client, nodes)
            except DriverConfigError as exc:
                await self._disconnect(client)
                if first:
                    self._open_error = exc
                    return
                self._fatal = str(exc)
                # said once, at ERROR, by whoever reads it (the source keeper, the acquisition)
                logger.debug("OPC UA driver stopped: %s", exc)
                return
            except Exception as exc:  # noqa: BLE001 - any failure to connect is retried
                await self._disconnect(client)
                if first:
                    self._open_error = DriverInitializationError(
                        f"OPC UA server {self.config.endpoint} not available: "
                        f"{_describe(exc)}")
                    return
                self._on_failure(_describe(exc))
                delay = self._jittered(backoff)
                backoff = min(2 * backoff, self.config.backoff_max)
                await self._sleep(delay)
                continue
            backoff = _BACKOFF_INITIAL
            if self._cpu_base is None:
                self._cpu_base = time.thread_time()
            if first:
                first = False
                self._opened.set()
            else:
                self._on_success()
            reason = await self._consume(sub, lost)
            await self._disconnect(client)
            if reason is not None:
                self._on_failure(reason)
                await self._sleep(self._jittered(backoff))

    async def _sleep(self, delay: float) -> None:
        assert self._wake is not None
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._wake.wait(), delay)

    def _make_client(self) -> Client:
        from asyncua import Client

        client = Client(self.config.endpoint, timeout=self.config.timeout,
                        watchdog_intervall=self.config.timeout)  # its probe's timeout too
        client.name = "twinwatch"
        client.description = "twinwatch (monitoring only)"
        if self.config.username:
            client.set_user(self.config.username)
            if self._password is not None:
                client.set_password(self._password)
        return client

    async def _connect(self, client: Client) -> list[Node]:
        """Connect (with security), find each channel's node and check its unit."""
        from asyncua import ua
        from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

        cfg = self.config
        if cfg.security_policy == "Basic256Sha256":
            assert cfg.certificate and cfg.private_key and cfg.server_certificate
            mode = (ua.MessageSecurityMode.Sign if cfg.security_mode == "Sign"
                    else ua.MessageSecurityMode.SignAndEncrypt)
            for key in ("certificate", "private_key", "server_certificate"):
                path = getattr(cfg, key)
                if not Path(path).is_file():
                    raise DriverConfigError(f"driver.{key}: file {path} not found")
            try:
                client.application_uri = await _application_uri(cfg.certificate,
                                                                client.application_uri)
                await client.set_security(SecurityPolicyBasic256Sha256, str(cfg.certificate),
                                          str(cfg.private_key),
                                          server_certificate=str(cfg.server_certificate),
                                          mode=mode)
            except (ValueError, TypeError, OSError) as exc:
                raise DriverConfigError(
                    f"driver.certificate: cannot load the certificate {cfg.certificate} / key "
                    f"{cfg.private_key} / server certificate {cfg.server_certificate}: {exc}; "
                    "give PEM or DER files") from exc
        try:
            await asyncio.wait_for(client.connect(), cfg.timeout * 2)
        except ua.UaStatusCodeError as exc:
            raise self._refusal(exc) from exc
        except ua.UaError as exc:
            if "No matching endpoints" not in str(exc):
                raise
            raise DriverConfigError(await self._no_endpoint()) from exc
        nodes: list[Node] = []
        for ch, m in cfg.channels.items():
            nodes.append(await self._find(client, ch, m))
        for (ch, m), node in zip(cfg.channels.items(), nodes, strict=True):
            if m.unit is not None:
                await self._check_unit(node, ch, m)
        return nodes

    async def _no_endpoint(self) -> str:
        """The line for a server that offers no endpoint with the configured security: what
        it offers (asked again: asyncua's connect does not say), naming the key."""
        from asyncua import Client

        cfg = self.config
        asked = (cfg.security_policy if cfg.security_policy == "None"
                 else f"{cfg.security_policy} {cfg.security_mode}")
        try:
            probe = Client(cfg.endpoint, timeout=cfg.timeout)
            endpoints = await asyncio.wait_for(probe.connect_and_get_server_endpoints(),
                                               cfg.timeout * 2)
            offers = sorted({f"{ep.SecurityPolicyUri.rsplit('#', 1)[-1]} "
                             f"{ep.SecurityMode.name}".replace(" None_", "").strip()
                             for ep in endpoints})
            offered = f"it offers {', '.join(offers) or 'no endpoint'}"
        except Exception as exc:  # noqa: BLE001 - the line is said without the list
            offered = f"its endpoints could not be listed ({_describe(exc)})"
        return (f"driver.security_policy: the OPC UA server {cfg.endpoint} has no endpoint for "
                f"security {asked!r}; {offered}: set security_policy and security_mode to one "
                "of those (Basic256Sha256 needs certificate, private_key and "
                "server_certificate)")

    def _refusal(self, exc: Exception) -> Exception:
        """A connect the server refused: the user or the certificate (config) or else."""
        name = type(exc).__name__
        where = self.config.endpoint
        if name in ("BadUserAccessDenied", "BadIdentityTokenRejected",
                    "BadIdentityTokenInvalid"):
            who = self.config.username or "anonymous"
            return DriverConfigError(
                f"driver.username: the OPC UA server {where} rejected user {who!r} ({name}): "
                "give a user and password_file it accepts")
        if name in ("BadCertificateUntrusted", "BadSecurityChecksFailed",
                    "BadCertificateInvalid", "BadCertificateUriInvalid",
                    "BadSecurityPolicyRejected", "BadCertificateRevoked"):
            return DriverConfigError(
                f"driver.certificate: the OPC UA server {where} refused the client certificate "
                f"{self.config.certificate} ({name}): have the server trust it (copy it into the "
                "server's trusted certificates) or set security_policy and security_mode to "
                "ones the server offers")
        return exc

    async def _find(self, client: Client, ch: str, m: OpcUaChannelMap) -> Node:
        from asyncua import ua

        key = f"driver.channels.{ch}"
        if m.node is not None:
            try:
                node = client.get_node(m.node)
            except (ValueError, ua.UaError) as exc:
                raise DriverConfigError(f"{key}.node: {m.node!r} is not a NodeId string: give "
                                        "e.g. \"ns=2;s=Motor.ia\" or \"ns=3;i=1001\"") from exc
            try:
                cls = await node.read_node_class()
            except ua.UaStatusCodeError as exc:
                raise DriverConfigError(
                    f"{key}.node: no node {m.node} on {self.config.endpoint} "
                    f"({type(exc).__name__}): give the NodeId of an existing variable (browse "
                    "the server) or use browse_path") from exc
        else:
            assert m.browse_path is not None
            path = [p for p in m.browse_path.split("/") if p]
            try:
                node = await client.nodes.root.get_child(path)
                cls = await node.read_node_class()
            except ua.UaStatusCodeError as exc:
                raise DriverConfigError(
                    f"{key}.browse_path: {m.browse_path!r} matches nothing on "
                    f"{self.config.endpoint} ({type(exc).__name__}): give the qualified names "
                    "from the Root folder, e.g. \"0:Objects/2:Motor/2:ia\"") from exc
        if cls != ua.NodeClass.Variable:
            raise DriverConfigError(f"{key}: {m.describe()} is a {cls.name}, not a Variable: "
                                    "map the variable holding the value")
        return node

    async def _check_unit(self, node: Node, ch: str, m: OpcUaChannelMap) -> None:
        from asyncua import ua

        assert m.unit is not None
        try:
            prop = await node.get_child("0:EngineeringUnits")
            eu = await prop.read_value()
        except ua.UaStatusCodeError:
            self.log_once(f"nounit:{ch}", "OPC UA %s (%s) has no EngineeringUnits: its unit "
                          "cannot be checked against %r", m.describe(), ch, m.unit)
            return
        if not isinstance(eu, ua.EUInformation):
            return
        name = eu.DisplayName.Text if eu.DisplayName is not None else None
        if not unit_matches(m.unit, name, eu.UnitId):
            raise DriverConfigError(
                f"driver.channels.{ch}.unit: node {m.describe()} is in {name!r} (EngineeringUnits"
                f", UnitId {eu.UnitId}), the channel is declared in {m.unit!r}: map a node in "
                f"{m.unit!r} or convert with scale/offset and declare the twin's unit")

    async def _subscribe(self, client: Client, nodes: list[Node]) -> Any:
        from asyncua import ua
        from asyncua.common.subscription import OverflowPolicy

        cfg = self.config
        params = ua.CreateSubscriptionParameters()
        params.RequestedPublishingInterval = cfg.publishing_interval * 1000.0
        params.RequestedLifetimeCount = 10000
        params.RequestedMaxKeepAliveCount = client.get_keepalive_count(
            params.RequestedPublishingInterval)
        params.MaxNotificationsPerPublish = 0
        params.Priority = 0
        qsize = cfg.effective_queue_size
        sub = await client.create_subscription(
            params, queue_maxsize=max(100000, 4 * qsize * len(nodes)),
            overflow=OverflowPolicy.DROP_OLDEST)
        requests = []
        for i, node in enumerate(nodes):
            rv = ua.ReadValueId()
            rv.NodeId = node.nodeid
            rv.AttributeId = ua.AttributeIds.Value
            mp = ua.MonitoringParameters()
            mp.ClientHandle = i + 1
            mp.SamplingInterval = cfg.sample_period * 1000.0
            mp.QueueSize = qsize
            mp.DiscardOldest = True
            flt = ua.DataChangeFilter()
            flt.Trigger = ua.DataChangeTrigger.StatusValueTimestamp
            mp.Filter = flt
            mir = ua.MonitoredItemCreateRequest()
            mir.ItemToMonitor = rv
            mir.MonitoringMode = ua.MonitoringMode.Reporting
            mir.RequestedParameters = mp
            requests.append(mir)
        results = await sub.create_monitored_items(requests)
        for ch, r in zip(self.channels, results, strict=True):
            if isinstance(r, ua.StatusCode):
                raise DriverConfigError(
                    f"driver.channels.{ch}: the server refused to monitor "
                    f"{cfg.channels[ch].describe()} ({r.name}): map a readable variable")
        # asyncua keeps the server's revised publishing interval as the subscription's
        revised_pub = float(sub.parameters.RequestedPublishingInterval) / 1000.0
        if abs(revised_pub - cfg.publishing_interval) > 1e-9:
            self.log_once("revised", "OPC UA server %s revised the publishing interval from "
                          "%.4g s to %.4g s", cfg.endpoint, cfg.publishing_interval, revised_pub,
                          level=logging.INFO)
        if revised_pub / cfg.sample_period > qsize:
            self.log_once("queue", "OPC UA publishing interval %.4g s holds %d samples, more "
                          "than the monitored items' queue (%d): values will be discarded "
                          "(counted as overflows and gaps); raise driver.queue_size",
                          revised_pub, round(revised_pub / cfg.sample_period), qsize)
        return sub

    async def _consume(self, sub: Any, lost: asyncio.Event) -> str | None:
        """Join the subscription's values into samples until the connection is lost (the
        reason) or the driver closes (None)."""
        from asyncua.common.subscription import DataChangeEvent

        lost_wait = asyncio.ensure_future(lost.wait())
        assert self._wake is not None
        wake_wait = asyncio.ensure_future(self._wake.wait())
        try:
            while True:
                get = asyncio.ensure_future(sub.next_event())
                done, _ = await asyncio.wait({get, lost_wait, wake_wait},
                                             return_when=asyncio.FIRST_COMPLETED)
                if get in done:
                    try:
                        ev = get.result()
                    except StopAsyncIteration:
                        return "subscription closed"
                    while ev is not None:  # this one, then what is queued, without waiting
                        if isinstance(ev, DataChangeEvent):
                            self._on_value(ev.data.monitored_item)
                        ev = self._nowait(sub)
                    self.cpu_seconds = time.thread_time() - (self._cpu_base or 0.0)
                    continue
                get.cancel()
                if self._stop.is_set():
                    return None
                return f"connection lost: {self._last_error}"
        finally:
            lost_wait.cancel()
            wake_wait.cancel()

    @staticmethod
    def _nowait(sub: Any) -> Any:
        q = sub._event_queue  # asyncua's iterator queue: drained without a task per event
        if q is None:
            return None
        try:
            return q.get_nowait()
        except asyncio.QueueEmpty:
            return None

    # -- joining values into samples (loop thread) ------------------------------------------
    def _on_value(self, item: Any) -> None:
        self.stats.frames += 1
        self.stats.extra["notifications"] += 1
        i = int(item.ClientHandle) - 1
        if not 0 <= i < len(self.channels):
            return
        ch = self.channels[i]
        self._arrival[i] = time.monotonic()
        dv = item.Value
        if dv.StatusCode is not None and dv.StatusCode.value == _WAITING_FOR_INITIAL_DATA:
            return  # the server has no value yet: no sample, nothing missing
        stamp = dv.SourceTimestamp
        if stamp is None:
            stamp = dv.ServerTimestamp
            self.stats.extra["server_stamps"] += 1
            self.log_once("server_stamps", "OPC UA server %s sends no source timestamps: its "
                          "server timestamps are the sample times (counted in "
                          "stats.extra.server_stamps)", self.config.endpoint)
            if stamp is None:
                self.stats.bad_frames += 1
                self.log_once("nostamp", "OPC UA value of %s without any timestamp: skipped "
                              "(stats.bad_frames)", ch)
                return
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=UTC)
        t = (stamp - _EPOCH).total_seconds() - self.time_origin
        k = round(t / self.sample_period)
        if self._last_k is not None and k <= self._last_k:
            if self._last_k - k <= self._jump_slots:
                self.stats.extra["duplicates"] += 1
                return
            self._time_jump(f"went back {(self._last_k - k) * self.sample_period:.3f} s")
        slot = self._pending.get(k)
        if slot is None:
            slot = self._pending[k] = _Slot(len(self.channels))
        status = dv.StatusCode
        code = 0 if status is None else int(status.value)
        if code & _OVERFLOW_BITS == _OVERFLOW_BITS:
            self.stats.extra["overflows"] += 1
            self.log_once("overflow", "OPC UA server %s discarded values of %s (Overflow bit): "
                          "raise queue_size or lower publishing_interval (counted in "
                          "stats.extra.overflows)", self.config.endpoint, ch)
        if code >> 30:  # Uncertain (01) or Bad (10, 11)
            self.stats.extra[f"status_{ch}"] += 1
            self.log_once(f"status:{ch}", "OPC UA %s (%s) reported %s: the sample is missing "
                          "(counted in stats.extra.status_%s)", self.config.channels[ch]
                          .describe(), ch, status.name if status is not None else code, ch)
            slot.bad = True
        else:
            variant = dv.Value
            raw: Any = None if variant is None else variant.Value
            try:
                value = float(raw) * self.config.channels[ch].scale \
                    + self.config.channels[ch].offset
            except (TypeError, ValueError):
                value = math.nan
            if not math.isfinite(value):
                self.stats.bad_values += 1
                self.log_once(f"nonfinite:{ch}", "OPC UA %s (%s) gave %r: the sample is missing "
                              "(counted in stats.bad_values)", self.config.channels[ch]
                              .describe(), ch, raw)
                slot.bad = True
            slot.values[i] = value
        slot.n += 1
        slot.t_sum += t
        if slot.n >= len(self.channels):
            self._complete(k)
        elif len(self._pending) > 4 * self.config.effective_queue_size + 100:
            self._complete(min(self._pending))  # a channel went silent: give up its slots

    def _complete(self, k: int) -> None:
        """Slot ``k`` is complete: the earlier ones never will be (gaps); deliver ``k``."""
        slot = self._pending.pop(k)
        for j in [j for j in self._pending if j < k]:
            del self._pending[j]
        if self._last_k is not None and k - self._last_k - 1 > self._jump_slots:
            self._time_jump(f"jumped {(k - self._last_k) * self.sample_period:.3f} s ahead")
        if self._last_k is not None and k - self._last_k > 1:
            missed = k - self._last_k - 1
            self.stats.gaps += missed
            self.log_once("gap", "OPC UA samples missing between %.3f s and %.3f s (%d); "
                          "counted in stats.gaps", self._last_k * self.sample_period,
                          k * self.sample_period, missed)
        self._last_k = k
        if slot.bad or slot.n < len(self.channels):
            self.stats.gaps += 1
            return
        self._put_dropping_oldest(Sample(slot.t_sum / slot.n, dict(zip(self.channels, slot.values,
                                                              strict=True))))

    def _time_jump(self, what: str) -> None:
        """The source clock jumped (set, a device restarted, a stale value from another clock):
        counted in ``stats.extra["time_jumps"]``, not as missing samples; the samples go on
        from the new time (the ring buffer abandons the window across it)."""
        self.stats.extra["time_jumps"] += 1
        self.log_once("time_jump", "OPC UA source timestamps of %s %s: counted in "
                      "stats.extra.time_jumps, not as missing samples", self.config.endpoint,
                      what)
        self._last_k = None
        self._pending.clear()

    # -- outages ----------------------------------------------------------------------------
    def _on_failure(self, reason: str) -> None:
        where = self.config.endpoint
        self._outage(reason, "OPC UA server %s not available: %s; reconnecting with backoff up "
                     "to %.3g s (further failures at DEBUG)", where, reason,
                     self.config.backoff_max, again=f"OPC UA server {where} still away: {reason}")

    def _on_success(self) -> None:
        down = self._recovered()
        if down is not None:
            logger.warning("OPC UA server %s is back after %.2f s; subscription recreated",
                           self.config.endpoint, down)

    async def _disconnect(self, client: Client) -> None:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(client.disconnect(), self.config.timeout)

    # -- closing ----------------------------------------------------------------------------
    def _close_internal(self) -> None:
        self._stop.set()
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None:
            with contextlib.suppress(RuntimeError):  # the loop has ended
                loop.call_soon_threadsafe(wake.set)
        thread = getattr(self, "_thread", None)
        if thread is not None and thread.is_alive() and thread is not threading.current_thread():
            thread.join(self.config.timeout * 2 + 2.0)
            if thread.is_alive():  # pragma: no cover
                logger.warning("OPC UA client thread did not stop in time")
        logger.debug("OPC UA driver closed (%s)", self.stats.as_dict())


async def _application_uri(certificate: Path, default: str) -> str:
    """The application URI in the client certificate's subjectAltName (the one the session
    must announce, OPC UA Part 4 6.1.3), or ``default`` when it has none."""
    from asyncua.crypto import uacrypto
    from cryptography import x509

    cert = await uacrypto.load_certificate(str(certificate))
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return default
    uris = san.get_values_for_type(x509.UniformResourceIdentifier)
    return uris[0] if uris else default


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
