"""The twin's health as an OPC UA information model a SCADA reads (issue 35, asyncua).

The built-in output ``opcua`` (table ``[outputs.opcua]``, a publisher: it gets only the windows
the state database stored) serves, on ``endpoint`` (``opc.tcp://127.0.0.1:4840`` by default),
one object per machine under ``Objects/TwinWatch`` (namespace ``namespace``), every variable
read-only (docs/opcua-output.md draws the whole model)::

    TwinWatch/<machine>
      DeviceHealth            DeviceHealthEnumeration (OPC UA Part 100 / NAMUR NE 107)
      DeviceHealthReason      why, for a person
      Model, Run, Window, WindowStart_s, WindowEnd_s, Trusted, NRMSE
      Parameters/<name>/      Value (AnalogItemType: EngineeringUnits, EURange), Low, High
                              (2-sigma interval), Status, Nominal, Deviation_pct, RelStd_pct,
                              AlarmLevel, Trend/..., RUL/...
      Diagnosis/              Status, TopFault, Part, Probability, Action, Urgency, NoFault,
                              Unknown, Alarms[], Faults/{Ids,Parts,Probabilities,Actions,
                              Urgencies}[] (ranked)
      Terms                   String[]: the discovered terms as equations
      Counters/<name>         Int64, one per health counter

Every value of a window is written with the window's source time stamp: a source on the wall
clock (a bus, a live recording: times after the year 2000) is used as it is; a source whose time
starts at 0 (a simulated plant, a replay) is placed on the wall clock once per run (its first
window at the moment it was written), so the stamps keep the plant's spacing exactly.

**DeviceHealth** (:func:`device_health`, the NE 107 mapping; the first that applies):
FAILURE when a parameter's deviation alarm is at ``alarm`` or a raised fault alarm's urgency is
``high``; CHECK_FUNCTION when the diagnosis says ``check_function`` (the twin does not describe
the machine), a bus message is silent, or no window came for ``stale_after`` seconds (the source
is lost: checked every second, it overrides the rest); OFF_SPEC when a deviation is at
``warning``; MAINTENANCE_REQUIRED when a RUL level is raised (warning or alarm) or a raised
fault alarm's urgency is ``low`` or ``medium``; else NORMAL.

**Alarms & Conditions.** Each alarm event of a window (a parameter's deviation or RUL level, a
fault of the diagnosis, the check function: ``out.events``) is an ``OffNormalAlarmType`` event,
emitted by the machine's object and by the Server object (a SCADA subscribes to either):
``ActiveState`` true while the level is not ``normal``, ``Severity`` 800 (alarm), 500
(warning), 200 (a clear), ``Message`` the operator's sentence the MQTT and Zenoh outputs carry,
``SourceName`` the machine, ``ConditionName`` ``<parameter> deviation`` / ``<parameter> rul`` /
the fault id. ``Retain`` while active: ``ConditionRefresh`` replays the active ones.

**Read-only.** Variables are ``CurrentRead`` only; a permission rule set refuses Write,
AddNodes, DeleteNodes, AddReferences, DeleteReferences and RegisterServer for every user
(``admin`` included); twinwatch defines no method. **History**: ``history = N`` keeps the last N
windows of each parameter's ``Value`` in memory for HistoryRead (asyncua's history); 0 (the
default): none (the state database's history is served by Zenoh's history query, not here).

**One server per endpoint and process.** The machines of a gateway that name the same endpoint
share one server (:class:`~twinwatch.sinks.base.SharedResources`, reference-counted: the first
opens it, the last closes it); a machine removed by a reload removes its object. The service
host places machines with one endpoint in one worker process
(:func:`twinwatch.daemon.workers.session_group`).

Threads: the server runs in its own thread, ``twinwatch-opcua``, on its own asyncio loop;
:meth:`OpcUaPublisher.write` (the outputs' thread) flattens the window into (node, value) pairs
and hands them to that loop, never waiting for a client.
"""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import math
import re
import threading
import time
from collections.abc import Hashable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Self

from pydantic import Field, StrictFloat, StrictInt, field_validator, model_validator

from twinwatch._lazy import lazy_module
from twinwatch.errors import PublisherError
from twinwatch.sinks.base import ProcessedWindow, Sink, SinkConfig, SinkContext

if TYPE_CHECKING:
    from twinwatch.twin.health import DiagnosisHealth, HealthMessage

# Imported when the output opens: loading a configuration does not load asyncua. Typed Any:
# asyncua annotates its protocol types as NewTypes (ua.Int16, ua.String, ...), which every
# literal would have to be wrapped in to satisfy mypy.
asyncua: Any = lazy_module("asyncua")
ua: Any = lazy_module("asyncua.ua")


class _QuietStart(logging.Filter):
    """asyncua's start logs a traceback when the port is taken (twinwatch says it in one line:
    :class:`OpcUaServer`) and two warnings about identity tokens on an endpoint without
    security (the default here: anonymous clients only, nothing to verify)."""

    DROPPED = ("%s error starting server", "No signing policy available",
               "No encrypting policy available")

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.DROPPED)


_QUIET = _QuietStart()


def _import() -> None:
    """Bind the real modules once a server opens: every ``ua.X`` through the lazy module
    costs an import-system lookup (a sixth of a window's writing, measured)."""
    global asyncua, ua
    import asyncua as real
    from asyncua import ua as real_ua

    asyncua, ua = real, real_ua
    quiet = logging.getLogger("asyncua.server.server")
    if _QUIET not in quiet.filters:
        quiet.addFilter(_QUIET)

logger = logging.getLogger(__name__)

__all__ = ["DEVICE_HEALTH", "OpcUaConfig", "OpcUaPublisher", "OpcUaServer", "device_health"]

#: The counters are written at most this often [s of plant time] (every window's other values
#: are written as they change).
COUNTERS_EVERY_S = 10.0

#: OPC UA Part 100 (Devices) DeviceHealthEnumeration: NAMUR NE 107's states, by value.
DEVICE_HEALTH: Mapping[str, int] = {"NORMAL": 0, "FAILURE": 1, "CHECK_FUNCTION": 2,
                                    "OFF_SPEC": 3, "MAINTENANCE_REQUIRED": 4}

SECURITY = Literal["None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt"]
_ENDPOINT_RE = re.compile(r"^opc\.tcp://(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*)"
                          r":(?P<port>[0-9]{1,5})(?P<path>/[^\s]*)?$")
_NAN = "NaN"  # a NaN's key among the values written last
_WALL_CLOCK_FROM = 946_684_800.0  # 2000-01-01: a source time after it is on the wall clock

#: Alarm event severity by the level an event moves to (OPC UA 1..1000).
SEVERITY: Mapping[str, int] = {"alarm": 800, "warning": 500, "normal": 200}

#: UN/CEFACT common codes of the SI units the twins use (EUInformation.UnitId); others -1.
_CEFACT: Mapping[str, str] = {"ohm": "OHM", "H": "81", "A": "AMP", "V": "VLT", "s": "SEC",
                              "rad/s": "2A", "rad": "C81", "kg m^2": "B32", "N m": "NU",
                              "Pa": "PAL", "m": "MTR", "m/s": "MTS", "N": "NEW", "kg": "KGM",
                              "m^3/s": "MQS", "W": "WTT", "1/s": "C97"}
_UNITS_URI = "http://www.opcfoundation.org/UA/units/un/cefact"


class OpcUaConfig(SinkConfig):
    """``[outputs.opcua]``: the OPC UA server output (see the module docstring).

    Example::

        [outputs.opcua]
        endpoint = "opc.tcp://127.0.0.1:4840"
        # security = ["Basic256Sha256_SignAndEncrypt"]
        # certificate = "/etc/twinwatch/opcua-server.der"
        # private_key = "/etc/twinwatch/opcua-server.pem"    # 0640 root:twinwatch
    """

    enabled: bool = Field(True, description="false: the output is not opened")
    endpoint: str = Field("opc.tcp://127.0.0.1:4840",
                          description="opc.tcp://host:port the server listens on")
    namespace: str = Field("urn:twinwatch:health", min_length=1,
                           description="the namespace URI of the machines' nodes")
    security: list[SECURITY] = Field(
        default_factory=lambda: list[SECURITY](["None"]), min_length=1,
        description="endpoints offered: None, Basic256Sha256_Sign, "
        "Basic256Sha256_SignAndEncrypt (the last two need certificate and private_key)")
    certificate: str | None = Field(None, description="the server's certificate (DER or PEM)")
    private_key: str | None = Field(None, description="its private key (PEM; a secret: 0640)")
    trusted_clients: list[str] = Field(
        default_factory=list, description="client certificates (DER or PEM) allowed on the "
        "signed endpoints; empty: any client certificate")
    history: StrictInt = Field(0, ge=0, le=100_000,
                               description="windows of each parameter's Value kept for "
                               "HistoryRead (in memory); 0: no history")
    stale_after: StrictFloat = Field(
        30.0, gt=0, allow_inf_nan=False,
        description="s without a window before DeviceHealth says CHECK_FUNCTION (source lost)")

    @field_validator("endpoint")
    @classmethod
    def _endpoint(cls, value: str) -> str:
        m = _ENDPOINT_RE.match(value)
        if m is None:
            raise ValueError(f"endpoint {value!r} is not of the form opc.tcp://host:port, "
                             f"e.g. 'opc.tcp://127.0.0.1:4840'")
        if not 1 <= int(m["port"]) <= 65535:
            raise ValueError(f"endpoint {value!r}: port {m['port']} is not in 1..65535")
        return value

    @model_validator(mode="after")
    def _check(self) -> Self:
        secure = [s for s in self.security if s != "None"]
        if secure and not (self.certificate and self.private_key):
            raise ValueError(f"security {secure[0]!r} needs certificate and private_key (the "
                             f"server's certificate and its key), or security = ['None']")
        if len(set(self.security)) != len(self.security):
            raise ValueError("security lists an endpoint twice")
        return self

    def host_port(self) -> tuple[str, int]:
        """The endpoint's host and port."""
        m = _ENDPOINT_RE.match(self.endpoint)
        assert m is not None
        return m["host"].strip("[]"), int(m["port"])

    def input_files(self) -> dict[str, str]:
        """The certificate, the private key and the trusted client certificates."""
        out = {k: v for k in ("certificate", "private_key") if (v := getattr(self, k))}
        out.update({f"trusted_clients.{i}": p for i, p in enumerate(self.trusted_clients)})
        return out

    def secret_input_files(self) -> dict[str, str]:
        """The private key: refused when others can read it."""
        return {"private_key": self.private_key} if self.private_key else {}

    def resolve_paths(self, base_dir: Path) -> None:
        """Make the file paths absolute against ``base_dir`` (``~`` expanded)."""
        def resolve(v: str) -> str:
            p = Path(v).expanduser()
            return str(p if p.is_absolute() else (base_dir / p).resolve())

        if self.certificate:
            self.certificate = resolve(self.certificate)
        if self.private_key:
            self.private_key = resolve(self.private_key)
        self.trusted_clients = [resolve(p) for p in self.trusted_clients]

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The port the server listens on."""
        host, port = self.host_port()
        return {f"opcua:{host}:{port}"}

    def server_key(self) -> str:
        """What one shared server is made of: everything but ``enabled`` and ``stale_after``
        (machines whose tables differ only in those share it)."""
        return "opcua:" + json.dumps(self.model_dump(exclude={"enabled", "stale_after"}),
                                     sort_keys=True)


# -- the NE 107 mapping ---------------------------------------------------------------------
def device_health(health: HealthMessage) -> tuple[int, str]:
    """The window's DeviceHealth (OPC UA Part 100, NAMUR NE 107) and why, for a person.

    Args:
        health: the window's typed health message (its ``alarms``, ``diagnosis``,
            ``source``).

    Returns:
        ``(value, reason)``: a :data:`DEVICE_HEALTH` value and one line. The source lost (no
        window for ``stale_after``) is the publisher's, not the message's.
    """
    alarms = health.alarms
    diag = health.diagnosis
    raised = _raised_faults(diag)
    dev_alarm = [n for n, a in alarms.items() if a.level == "alarm"]
    high = [f for f, u in raised if u == "high"]
    if dev_alarm or high:
        what = [f"{n} beyond its alarm threshold" for n in dev_alarm]
        what += [f"fault {f} (urgency high)" for f in high]
        return DEVICE_HEALTH["FAILURE"], "failure: " + "; ".join(what)
    if diag is not None and diag.status == "check_function":
        return (DEVICE_HEALTH["CHECK_FUNCTION"], "check function: the twin does not describe "
                "this machine" + (f" ({diag.check_failed})" if diag.check_failed else ""))
    if health.source.silent:
        return (DEVICE_HEALTH["CHECK_FUNCTION"],
                "check function: silent on the bus: " + ", ".join(health.source.silent))
    warn = [n for n, a in alarms.items() if a.level == "warning"]
    if warn:
        return (DEVICE_HEALTH["OFF_SPEC"],
                "off spec: " + "; ".join(f"{n} beyond its warning threshold" for n in warn))
    rul = [f"{n} RUL {a.rul.level}" for n, a in alarms.items()
           if a.rul is not None and a.rul.level != "normal"]
    rul += [f"fault {f} (urgency {u})" for f, u in raised if u != "high"]
    if rul:
        return DEVICE_HEALTH["MAINTENANCE_REQUIRED"], "maintenance required: " + "; ".join(rul)
    return DEVICE_HEALTH["NORMAL"], "normal"


def _raised_faults(diag: DiagnosisHealth | None) -> list[tuple[str, str]]:
    """(fault id, urgency) of the diagnosis' raised fault alarms (the check function aside)."""
    if diag is None:
        return []
    urgency = {f.id: f.urgency for f in diag.faults}
    return [(f, urgency.get(f, "medium")) for f in diag.alarms if f != "check_function"]


# -- the server ------------------------------------------------------------------------------
class _ReadOnly:
    """asyncua permission rule set: every user may read, browse, subscribe, read history and
    call the server's standard methods (ConditionRefresh); nobody may write or change the
    address space."""

    DENIED: ClassVar[tuple[str, ...]] = (
        "WriteRequest", "AddNodesRequest", "DeleteNodesRequest", "AddReferencesRequest",
        "DeleteReferencesRequest", "RegisterServerRequest", "RegisterServer2Request",
        "HistoryUpdateRequest")

    def __init__(self) -> None:
        self._denied = {ua.NodeId(getattr(ua.ObjectIds, f"{n}_Encoding_DefaultBinary"))
                        for n in self.DENIED}

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        return action_type_id not in self._denied


class _Machine:
    """One machine's nodes: its object, the variables by path, the run's clock anchor."""

    def __init__(self, name: str, obj: Any, stale_after: float) -> None:
        self.name = name
        self.obj = obj
        self.stale_after = stale_after                  # s without a window: CHECK_FUNCTION
        self.vars: dict[str, tuple[Any, Any]] = {}     # path -> (NodeId, VariantType)
        self.anchor: tuple[str, float] | None = None    # (run, wall - plant) for plant time
        self.last_window = time.monotonic()
        self.stale = False
        self.health: tuple[int, str] = (DEVICE_HEALTH["NORMAL"], "no window yet")
        self.events: list[Any] = []                     # event generators (machine, Server)
        self.last: dict[str, tuple[Any, int | None]] = {}  # path -> what was written last
        self.nodes: list[Any] = []                      # every node made for it
        self.active: dict[str, dict[str, Any]] = {}     # condition -> its raising event
        self.counters_t: float | None = None            # plant time the counters were written


class OpcUaServer:
    """One asyncua server in its own thread and event loop, serving the machines of this
    process that name its endpoint (shared through :class:`SharedResources`).

    Args:
        config: the table (its server settings).

    Raises:
        PublisherError: the port is taken, a certificate or key cannot be loaded, the server
            does not start within 30 s.
    """

    def __init__(self, config: OpcUaConfig) -> None:
        _import()
        self.config = config
        self.machines: dict[str, _Machine] = {}
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name="twinwatch-opcua", daemon=True)
        self._thread.start()
        self._closed = False
        self.writes = 0
        self.errors = 0
        self._tasks: set[asyncio.Task[None]] = set()
        try:
            self._call(self._start(), 30.0)
        except BaseException:
            self._stop_loop()
            raise

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.run_forever()

    def _call(self, coro: Any, timeout: float = 30.0) -> Any:
        """Run ``coro`` on the server's loop and wait for its result."""
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    async def _start(self) -> None:
        cfg = self.config
        host, port = cfg.host_port()
        server = asyncua.Server()
        await server.init()
        server.set_endpoint(cfg.endpoint)
        server.set_server_name("twinwatch")
        server.allow_remote_admin(False)
        policies = {"None": ua.SecurityPolicyType.NoSecurity,
                    "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
                    "Basic256Sha256_SignAndEncrypt":
                        ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt}
        server.set_security_policy([policies[s] for s in cfg.security],
                                   permission_ruleset=_ReadOnly())
        if cfg.certificate and cfg.private_key:
            for key, load in (("certificate", server.load_certificate),
                              ("private_key", server.load_private_key)):
                try:
                    await load(getattr(cfg, key))
                except Exception as exc:  # noqa: BLE001 - cryptography's and OSError's alike
                    raise PublisherError(
                        f"outputs.opcua.{key} = {getattr(cfg, key)}: cannot be loaded "
                        f"({type(exc).__name__}: {exc}); give a DER or PEM file") from None
        if cfg.trusted_clients:
            trusted = set()
            from asyncua.crypto import uacrypto
            for i, path in enumerate(cfg.trusted_clients):
                try:
                    cert = await uacrypto.load_certificate(path)
                except Exception as exc:  # noqa: BLE001
                    raise PublisherError(
                        f"outputs.opcua.trusted_clients.{i} = {path}: cannot be loaded "
                        f"({type(exc).__name__}: {exc}); give a DER or PEM file") from None
                trusted.add(uacrypto.der_from_x509(cert))

            async def validate(cert: Any, app: Any) -> None:
                if uacrypto.der_from_x509(cert) not in trusted:
                    logger.warning("OPC UA client %s refused: its certificate is not in "
                                   "outputs.opcua.trusted_clients", app.ApplicationUri)
                    raise ua.UaStatusCodeError(ua.StatusCodes.BadCertificateUntrusted)

            server.set_certificate_validator(validate)
        self.ns = await server.register_namespace(cfg.namespace)
        from asyncua.common.structures104 import new_enum

        self.health_type = (await new_enum(server, self.ns, "DeviceHealthEnumeration",
                                           list(DEVICE_HEALTH))).nodeid
        objects = server.get_objects_node()
        self.root = await objects.add_folder(ua.NodeId("TwinWatch", self.ns),
                                             ua.QualifiedName("TwinWatch", self.ns))
        try:
            await server.start()
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise PublisherError(
                    f"outputs.opcua.endpoint {cfg.endpoint}: port {port} on {host} is already "
                    f"taken by another server; give another port, or stop that "
                    f"server") from None
            raise PublisherError(f"outputs.opcua.endpoint {cfg.endpoint}: cannot listen "
                                 f"({exc.strerror or exc})") from None
        self.server = server
        self.isession = server.iserver.isession
        self.aspace = server.iserver.aspace
        self._watch = asyncio.ensure_future(self._watchdog())

    # -- machines ---------------------------------------------------------------------------
    def add_machine(self, context: SinkContext, stale_after: float) -> None:
        """Create ``context.machine``'s object (its parameters from the context: units,
        nominal values, alarm bands) and its alarm event generators.

        Raises:
            PublisherError: the machine is already served by this server (two outputs of one
                machine), or the nodes cannot be created.
        """
        self._call(self._add_machine(context, stale_after))

    def remove_machine(self, machine: str) -> None:
        """Delete the machine's object and every node under it (a machine stopped or removed
        by a reload)."""
        if self._closed:
            return
        try:
            self._call(self._remove_machine(machine))
        except Exception as exc:  # noqa: BLE001 - closing goes on
            logger.warning("OPC UA: removing %s's nodes failed: %s", machine, exc)

    def publish(self, machine: str, health: HealthMessage, events: list[dict[str, Any]]
                ) -> None:
        """Write one window's values (and raise its alarm events) on the server's loop; does
        not wait."""
        if self._closed:
            return
        self._loop.call_soon_threadsafe(self._schedule, machine, health, events)

    def flush(self, timeout: float = 30.0) -> None:
        """Wait until what :meth:`publish` handed over is written (tests, the benchmark)."""
        if not self._closed:
            self._call(self._drain(), timeout)

    async def _drain(self) -> None:
        await asyncio.sleep(0)  # the publish calls queued before this one are scheduled
        while self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)

    def _schedule(self, machine: str, health: HealthMessage, events: list[dict[str, Any]]
                  ) -> None:
        task = self._loop.create_task(self._publish(machine, health, events))
        self._tasks.add(task)
        task.add_done_callback(self._done)

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            self.errors += 1
            if self.errors == 1:
                logger.error("OPC UA: writing a window failed: %s", task.exception())

    async def _add_machine(self, ctx: SinkContext, stale_after: float) -> None:
        name = ctx.machine
        if name in self.machines:
            raise PublisherError(f"outputs.opcua: machine {name!r} is already served on "
                                 f"{self.config.endpoint}; give each machine one name")
        ns = self.ns
        b = _Builder(ns, name)
        obj = b.object(None, name, self.root.nodeid, folder_parent=True)
        m = _Machine(name, obj, stale_after)
        dt = ua.ObjectIds
        b.variable(m, obj, "DeviceHealth", ua.Variant(0, ua.VariantType.Int32), self.health_type)
        for path, vtype, dtype, first in (
                ("DeviceHealthReason", ua.VariantType.String, dt.String, "no window yet"),
                ("Model", ua.VariantType.String, dt.String, ctx.model),
                ("Run", ua.VariantType.String, dt.String, ctx.run),
                ("Window", ua.VariantType.Int64, dt.Int64, -1),
                ("WindowStart_s", ua.VariantType.Double, dt.Double, math.nan),
                ("WindowEnd_s", ua.VariantType.Double, dt.Double, math.nan),
                ("Trusted", ua.VariantType.Boolean, dt.Boolean, False),
                ("NRMSE", ua.VariantType.Double, dt.Double, math.nan),
                ("Terms", ua.VariantType.String, dt.String, [])):
            b.variable(m, obj, path, ua.Variant(first, vtype), ua.NodeId(dtype))
        params = b.object(m, "Parameters", obj)
        for p, unit in ctx.parameters.items():
            po = b.object(m, f"Parameters.{p}", params, browse=p)
            value = b.variable(m, po, f"Parameters.{p}.Value",
                               ua.Variant(math.nan, ua.VariantType.Double),
                               ua.NodeId(dt.Double), browse="Value",
                               vtype=ua.NodeId(dt.AnalogItemType))
            b.prop(value, f"Parameters.{p}.Value.EngineeringUnits", "EngineeringUnits",
                   ua.Variant(_eu(unit), ua.VariantType.ExtensionObject),
                   ua.NodeId(dt.EUInformation))
            b.prop(value, f"Parameters.{p}.Value.EURange", "EURange",
                   ua.Variant(_eu_range(p, ctx), ua.VariantType.ExtensionObject),
                   ua.NodeId(dt.Range))
            for leaf, vt, dtype in _PARAM_LEAVES:
                parent = po
                if "." in leaf:
                    sub, _ = leaf.split(".", 1)
                    key = f"Parameters.{p}.{sub}"
                    parent = b.nodes.get(key) or b.object(m, key, po, browse=sub)
                init: Any = "" if vt == "String" else (False if vt == "Boolean" else math.nan)
                b.variable(m, parent, f"Parameters.{p}.{leaf}",
                           ua.Variant(init, getattr(ua.VariantType, vt)),
                           ua.NodeId(getattr(dt, dtype)), browse=leaf.rsplit(".", 1)[-1])
        diag = b.object(m, "Diagnosis", obj)
        faults = b.object(m, "Diagnosis.Faults", diag, browse="Faults")
        for leaf, vt, dtype in _DIAG_LEAVES:
            parent = faults if leaf.startswith("Faults.") else diag
            array = leaf.startswith("Faults.") or leaf == "Alarms"
            init = [] if array else ("" if vt == "String" else math.nan)
            b.variable(m, parent, f"Diagnosis.{leaf}",
                       ua.Variant(init, getattr(ua.VariantType, vt)),
                       ua.NodeId(getattr(dt, dtype)), browse=leaf.rsplit(".", 1)[-1])
        b.object(m, "Counters", obj)
        results = await self.isession.add_nodes(b.items)
        for r in results:
            r.StatusCode.check()
        m.nodes += [item.RequestedNewNodeId for item in b.items]
        # the machine's object emits events; the Server object relays them (one subscription
        # on the Server object sees every machine's alarms)
        await self.isession.add_references(b.references)
        for emitter in (obj, ua.NodeId(ua.ObjectIds.Server)):
            gen = await self.server.get_event_generator(ua.ObjectIds.OffNormalAlarmType,
                                                        emitting_node=emitter)
            m.events.append(gen)
        if self.config.history:
            nodes = [self.server.get_node(nid) for path, (nid, _) in m.vars.items()
                     if path.endswith(".Value") and path.startswith("Parameters.")]
            await self.server.historize_node_data_change(nodes, period=None,
                                                         count=self.config.history)
        self.machines[name] = m

    async def _remove_machine(self, machine: str) -> None:
        m = self.machines.pop(machine, None)
        if m is None:
            return
        now = datetime.now(UTC)
        for what, e in list(m.active.items()):  # ConditionRefresh no longer replays them
            await self._alarm(m, {**e, "level": "normal", "message": (
                f"{machine}: {what}: no longer monitored (the machine was stopped or "
                f"removed)")}, now, when=now)
        if self.config.history:
            nodes = [self.server.get_node(nid) for path, (nid, _) in m.vars.items()
                     if path.endswith(".Value") and path.startswith("Parameters.")]
            try:
                await self.server.dehistorize_node_data_change(nodes)
            except Exception:  # noqa: BLE001
                logger.debug("dehistorizing %s failed", machine, exc_info=True)
        # every node of the machine, without asyncua's search of the whole address space for
        # references to each (DeleteTargetReferences: 2 s of CPU a machine, the loop blocked):
        # only the TwinWatch folder and the Server object refer to the machine from outside
        items = [ua.DeleteNodesItem(NodeId=nid, DeleteTargetReferences=False)
                 for nid in m.nodes]
        for r in await self.isession.delete_nodes(ua.DeleteNodesParameters(NodesToDelete=items)):
            r.check()
        for holder in (self.root.nodeid, ua.NodeId(ua.ObjectIds.Server)):
            data = self.aspace[holder]
            data.references[:] = [r for r in data.references if r.NodeId != m.obj]

    async def _publish(self, machine: str, h: HealthMessage, events: list[dict[str, Any]]
                       ) -> None:
        m = self.machines.get(machine)
        if m is None:
            return
        now = datetime.now(UTC)
        m.last_window = time.monotonic()
        m.stale = False
        ts = _source_time(m, h.run, h.t_end, now)
        m.health = device_health(h)
        values = flat_values(h, m.health)
        # the counters (some 40 a machine, most changing every window) at most every
        # COUNTERS_EVERY_S of plant time: half the writes of a window, and a SCADA trends them
        # at that pace anyway (measured: a 50-machine gateway's output cost 9 % of a core)
        counters_due = (m.counters_t is None or h.t_end < m.counters_t
                        or h.t_end - m.counters_t >= COUNTERS_EVERY_S)
        if counters_due:
            m.counters_t = h.t_end
        else:
            values = {k: v for k, v in values.items() if not k.startswith("Counters.")}
        write = self.aspace.write_attribute_value
        value_attr = ua.AttributeIds.Value
        good = ua.StatusCode()
        missing: list[tuple[str, Any]] = []
        last = m.last
        for path, (value, status) in values.items():
            # a value is written when it (or its status) changes: its SourceTimestamp is the
            # window it last changed in (OPC UA Part 4, 7.7.3); Window changes every window
            key = (value if value == value else _NAN, status)  # NaN equals NaN here
            if last.get(path) == key:
                continue
            node = m.vars.get(path)
            if node is None:
                if path.startswith("Counters."):
                    missing.append((path, value))
                continue
            last[path] = key
            nid, vt = node
            dv = ua.DataValue(ua.Variant(value, vt),
                              good if status is None else ua.StatusCode(status),
                              SourceTimestamp=ts, ServerTimestamp=now)
            await write(nid, value_attr, dv)
            self.writes += 1
        if missing:
            await self._add_counters(m, missing, ts, now)
        for e in events:
            await self._alarm(m, e, now)

    async def _add_counters(self, m: _Machine, missing: list[tuple[str, Any]],
                            ts: datetime, now: datetime) -> None:
        b = _Builder(self.ns, m.name)
        parent = ua.NodeId(f"{m.name}.Counters", self.ns)
        for path, value in missing:
            b.variable(m, parent, path, ua.Variant(int(value), ua.VariantType.Int64),
                       ua.NodeId(ua.ObjectIds.Int64), browse=path.split(".", 1)[1])
        for r in await self.isession.add_nodes(b.items):
            r.StatusCode.check()
        m.nodes += [item.RequestedNewNodeId for item in b.items]

    async def _alarm(self, m: _Machine, e: dict[str, Any], now: datetime,
                     when: datetime | None = None) -> None:
        level = str(e.get("level", "normal"))
        kind = str(e.get("kind", "deviation"))
        what = (str(e.get("fault")) if kind == "diagnosis"
                else f"{e.get('parameter')} {kind}")
        active = level != "normal"
        t = e.get("t")
        if when is None:
            when = _source_time(m, None, float(t), now) if isinstance(t, int | float) else now
        if active:
            m.active[what] = e
        else:
            m.active.pop(what, None)
        source = (ua.NodeId(f"{m.name}.Parameters.{e.get('parameter')}", self.ns)
                  if kind != "diagnosis" else ua.NodeId(f"{m.name}.Diagnosis", self.ns))
        if source not in self.aspace:
            source = m.obj
        for gen in m.events:
            ev = gen.event
            ev.Severity = SEVERITY.get(level, 500)
            ev.SourceName = m.name
            ev.SourceNode = source
            ev.ConditionName = what
            ev.NodeId = ua.NodeId(f"{m.name}.Conditions.{what}", self.ns)
            ev.Retain = active
            ev.ActiveState = ua.LocalizedText("Active" if active else "Inactive")
            setattr(ev, "ActiveState/Id", active)
            setattr(ev, "AckedState/Id", not active)
            setattr(ev, "EnabledState/Id", True)
            ev.EnabledState = ua.LocalizedText("Enabled")
            await gen.trigger(time_attr=when, message=str(e.get("message", what)))

    async def _watchdog(self) -> None:
        """Every second: a machine without a window for its ``stale_after`` is CHECK_FUNCTION
        (its source is lost, or its estimation stopped)."""
        while True:
            await asyncio.sleep(1.0)
            now = time.monotonic()
            for m in list(self.machines.values()):
                limit = m.stale_after
                if m.stale or now - m.last_window < limit:
                    continue
                m.stale = True
                nid, _ = m.vars["DeviceHealth"]
                rid, _ = m.vars["DeviceHealthReason"]
                stamp = datetime.now(UTC)
                reason = (f"check function: no window for {limit:g} s (the source is lost "
                          f"or the estimation stopped); last: {m.health[1]}")
                # remembered as written: the next window writes its own health again
                m.last["DeviceHealth"] = (DEVICE_HEALTH["CHECK_FUNCTION"], None)
                m.last["DeviceHealthReason"] = (reason, None)
                for node, var in ((nid, ua.Variant(DEVICE_HEALTH["CHECK_FUNCTION"],
                                                   ua.VariantType.Int32)),
                                  (rid, ua.Variant(reason, ua.VariantType.String))):
                    await self.aspace.write_attribute_value(
                        node, ua.AttributeIds.Value,
                        ua.DataValue(var, SourceTimestamp=stamp, ServerTimestamp=stamp))

    def close(self) -> None:
        """Stop the server and its thread. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._call(self._stop(), 15.0)
        except Exception as exc:  # noqa: BLE001
            logger.warning("OPC UA server on %s did not stop cleanly: %s",
                           self.config.endpoint, exc)
        self._stop_loop()

    async def _stop(self) -> None:
        self._watch.cancel()
        await self.server.stop()
        # the sessions of clients still connected (their timeout loops, their subscriptions'
        # publishing loops): cancelled, not left pending when the loop closes
        rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in rest:
            t.cancel()
        await asyncio.gather(*rest, return_exceptions=True)

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        if not self._thread.is_alive():
            self._loop.close()


# what every parameter object holds besides Value: (path, VariantType, DataType)
_PARAM_LEAVES: tuple[tuple[str, str, str], ...] = (
    ("Low", "Double", "Double"), ("High", "Double", "Double"),
    ("Status", "String", "String"), ("Nominal", "Double", "Double"),
    ("Deviation_pct", "Double", "Double"), ("RelStd_pct", "Double", "Double"),
    ("AlarmLevel", "String", "String"), ("RulAlarmLevel", "String", "String"),
    ("Trend.Model", "String", "String"), ("Trend.Rate", "Double", "Double"),
    ("Trend.RateLow", "Double", "Double"), ("Trend.RateHigh", "Double", "Double"),
    ("Trend.RatePctPerHour", "Double", "Double"), ("Trend.Degrading", "Boolean", "Boolean"),
    ("RUL.Status", "String", "String"), ("RUL.Alarm_s", "Double", "Double"),
    ("RUL.AlarmLow_s", "Double", "Double"), ("RUL.AlarmHigh_s", "Double", "Double"),
    ("RUL.Warning_s", "Double", "Double"), ("RUL.WarningLow_s", "Double", "Double"),
    ("RUL.WarningHigh_s", "Double", "Double"))

_DIAG_LEAVES: tuple[tuple[str, str, str], ...] = (
    ("Status", "String", "String"), ("TopFault", "String", "String"),
    ("Part", "String", "String"), ("Probability", "Double", "Double"),
    ("Action", "String", "String"), ("Urgency", "String", "String"),
    ("NoFault", "Double", "Double"), ("Unknown", "Double", "Double"),
    ("Alarms", "String", "String"), ("Faults.Ids", "String", "String"),
    ("Faults.Parts", "String", "String"), ("Faults.Probabilities", "Double", "Double"),
    ("Faults.Actions", "String", "String"), ("Faults.Urgencies", "String", "String"))


class _Builder:
    """The AddNodesItems of one machine, created in one AddNodes call."""

    def __init__(self, ns: int, machine: str) -> None:
        self.ns = ns
        self.machine = machine
        self.items: list[Any] = []
        self.references: list[Any] = []
        self.nodes: dict[str, Any] = {}

    def _nid(self, path: str | None) -> Any:
        return ua.NodeId(self.machine if path is None else f"{self.machine}.{path}", self.ns)

    def object(self, m: _Machine | None, path: str | None, parent: Any, *,
               browse: str | None = None, folder_parent: bool = False) -> Any:
        nid = self._nid(path)
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nid
        name = browse or (path or self.machine).rsplit(".", 1)[-1]
        item.BrowseName = ua.QualifiedName(name, self.ns)
        item.ParentNodeId = parent
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.Organizes if folder_parent
                                         else ua.ObjectIds.HasComponent)
        item.NodeClass = ua.NodeClass.Object
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.BaseObjectType)
        attrs = ua.ObjectAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(name)
        attrs.EventNotifier = 1 if path is None else 0   # the machine: SubscribeToEvents
        attrs.WriteMask = attrs.UserWriteMask = 0
        item.NodeAttributes = attrs
        self.items.append(item)
        if path is None:  # the Server object notifies of the machine's events
            ref = ua.AddReferencesItem()
            ref.SourceNodeId = ua.NodeId(ua.ObjectIds.Server)
            ref.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasNotifier)
            ref.IsForward = True
            ref.TargetNodeId = nid
            ref.TargetNodeClass = ua.NodeClass.Object
            self.references.append(ref)
        if path is not None:
            self.nodes[path] = nid
        return nid

    def variable(self, m: _Machine, parent: Any, path: str, value: Any, datatype: Any, *,
                 browse: str | None = None, vtype: Any = None) -> Any:
        nid = self._nid(path)
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nid
        name = browse or path.rsplit(".", 1)[-1]
        item.BrowseName = ua.QualifiedName(name, self.ns)
        item.ParentNodeId = parent
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.NodeClass = ua.NodeClass.Variable
        item.TypeDefinition = vtype or ua.NodeId(ua.ObjectIds.BaseDataVariableType)
        item.NodeAttributes = _var_attrs(name, value, datatype)
        self.items.append(item)
        m.vars[path] = (nid, value.VariantType)
        return nid

    def prop(self, parent: Any, path: str, browse: str, value: Any, datatype: Any) -> Any:
        nid = self._nid(path)
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nid
        item.BrowseName = ua.QualifiedName(browse, 0)
        item.ParentNodeId = parent
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasProperty)
        item.NodeClass = ua.NodeClass.Variable
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.PropertyType)
        item.NodeAttributes = _var_attrs(browse, value, datatype)
        self.items.append(item)
        return nid


def _var_attrs(name: str, value: Any, datatype: Any) -> Any:
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.Description = ua.LocalizedText(name)
    attrs.DataType = datatype
    attrs.Value = value
    if isinstance(value.Value, list):
        attrs.ValueRank = ua.ValueRank.OneDimension
        attrs.ArrayDimensions = [0]
    else:
        attrs.ValueRank = ua.ValueRank.Scalar
    attrs.WriteMask = attrs.UserWriteMask = 0
    attrs.AccessLevel = attrs.UserAccessLevel = (ua.AccessLevel.CurrentRead.mask
                                                  | ua.AccessLevel.HistoryRead.mask)
    attrs.Historizing = False
    return attrs


def _eu(unit: str) -> Any:
    """EUInformation of an SI unit (UN/CEFACT code where there is one, else UnitId -1)."""
    code = _CEFACT.get(unit)
    unit_id = -1
    if code is not None:
        unit_id = 0
        for c in code:
            unit_id = (unit_id << 8) | ord(c)
    return ua.EUInformation(NamespaceUri=_UNITS_URI, UnitId=unit_id,
                            DisplayName=ua.LocalizedText(unit),
                            Description=ua.LocalizedText(unit))


def _eu_range(p: str, ctx: SinkContext) -> Any:
    """EURange: the parameter's ``[alarms]`` alarm band around nominal when it has a rule
    (what a bar graph should span), else 0 .. 2 x nominal."""
    nom = float(ctx.nominal.get(p, math.nan))
    bands = ctx.alarm_bands.get(p)
    if not math.isfinite(nom):
        return ua.Range(Low=math.nan, High=math.nan)
    lo, hi = 0.0, 2.0 * nom
    if bands is not None:
        high = bands.alarm_high if bands.alarm_high is not None else bands.warning_high
        low = bands.alarm_low if bands.alarm_low is not None else bands.warning_low
        if high is not None:
            hi = nom * (1.0 + high / 100.0)
        if low is not None:
            lo = nom * (1.0 + low / 100.0)
    return ua.Range(Low=min(lo, hi), High=max(lo, hi))


def _source_time(m: _Machine, run: str | None, t: float, now: datetime) -> datetime:
    """The wall-clock time of plant time ``t``: ``t`` itself on a wall-clock source, else
    anchored once per run (the run's first window written at ``now``)."""
    if t >= _WALL_CLOCK_FROM:
        return datetime.fromtimestamp(t, UTC)
    if run is not None and (m.anchor is None or m.anchor[0] != run):
        m.anchor = (run, now.timestamp() - t)
    offset = m.anchor[1] if m.anchor is not None else now.timestamp() - t
    return datetime.fromtimestamp(offset + t, UTC)


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


_PARAM_STATUS: Mapping[str, int] = {"held": 0x40900000,     # UncertainLastUsableValue
                                    "suspect": 0x40000000}  # Uncertain


def flat_values(h: HealthMessage, health: tuple[int, str]) -> dict[str, tuple[Any, int | None]]:
    """The window's values by node path (``Parameters.Ra.Value``), each with its OPC UA status
    code (None: Good). A null of the message is NaN (numbers) or ``""`` (texts).

    Args:
        h: the typed health message.
        health: its :func:`device_health`.
    """
    out: dict[str, tuple[Any, int | None]] = {
        "DeviceHealth": (health[0], None), "DeviceHealthReason": (health[1], None),
        "Model": (h.model, None), "Run": (h.run, None), "Window": (h.window, None),
        "WindowStart_s": (h.t_start, None), "WindowEnd_s": (h.t_end, None),
        "Trusted": (h.trusted, None), "NRMSE": (_num(h.nrmse), None),
        "Terms": ([t.equation for t in h.terms], None)}
    for name, p in h.parameters.items():
        base = f"Parameters.{name}."
        value = _num(p.value)
        rel = _num(p.rel_std_pct) / 100.0
        half = 2.0 * abs(value) * rel
        a = h.alarms.get(name)
        rul = p.rul
        t = p.trend
        out[base + "Value"] = (value, _PARAM_STATUS.get(p.status))
        out[base + "Low"] = (value - half, None)
        out[base + "High"] = (value + half, None)
        out[base + "Status"] = (p.status, None)
        out[base + "Nominal"] = (_num(p.nominal), None)
        out[base + "Deviation_pct"] = (_num(p.deviation_pct), None)
        out[base + "RelStd_pct"] = (_num(p.rel_std_pct), None)
        out[base + "AlarmLevel"] = (a.level if a is not None else "", None)
        out[base + "RulAlarmLevel"] = (a.rul.level if a is not None and a.rul is not None
                                       else "", None)
        out[base + "Trend.Model"] = ((t.model or "") if t is not None else "", None)
        out[base + "Trend.Rate"] = (_num(t.rate) if t else math.nan, None)
        out[base + "Trend.RateLow"] = (_num(t.rate_low) if t else math.nan, None)
        out[base + "Trend.RateHigh"] = (_num(t.rate_high) if t else math.nan, None)
        out[base + "Trend.RatePctPerHour"] = (_num(t.rate_pct_per_h) if t else math.nan, None)
        out[base + "Trend.Degrading"] = (bool(t.degrading) if t else False, None)
        out[base + "RUL.Status"] = (rul.status if rul is not None else "", None)
        for level, c in (("Alarm", rul.alarm if rul else None),
                         ("Warning", rul.warning if rul else None)):
            out[base + f"RUL.{level}_s"] = (_num(c.rul_s) if c else math.nan, None)
            out[base + f"RUL.{level}Low_s"] = (_num(c.low_s) if c else math.nan, None)
            out[base + f"RUL.{level}High_s"] = (_num(c.high_s) if c else math.nan, None)
    d = h.diagnosis
    if d is not None:
        top = d.faults[0] if d.status == "fault" and d.faults else None
        out.update({
            "Diagnosis.Status": (d.status, None),
            "Diagnosis.TopFault": (top.id if top else "", None),
            "Diagnosis.Part": (top.component if top else "", None),
            "Diagnosis.Probability": (float(d.probability), None),
            "Diagnosis.Action": (top.action if top else "", None),
            "Diagnosis.Urgency": (top.urgency if top else "", None),
            "Diagnosis.NoFault": (float(d.no_fault), None),
            "Diagnosis.Unknown": (float(d.unknown), None),
            "Diagnosis.Alarms": (list(d.alarms), None),
            "Diagnosis.Faults.Ids": ([f.id for f in d.faults], None),
            "Diagnosis.Faults.Parts": ([f.component for f in d.faults], None),
            "Diagnosis.Faults.Probabilities": ([float(f.probability) for f in d.faults], None),
            "Diagnosis.Faults.Actions": ([f.action for f in d.faults], None),
            "Diagnosis.Faults.Urgencies": ([f.urgency for f in d.faults], None)})
    for name, v in h.counters.items():
        out[f"Counters.{name}"] = (int(v), None)
    return out


# -- the sink --------------------------------------------------------------------------------
class OpcUaPublisher(Sink):
    """The OPC UA output (the module docstring): the built-in ``opcua``, ``[outputs.opcua]``.

    Args:
        config: the validated table.
        context: the daemon's context (machine, model, parameters and their units, nominal
            values, alarm bands; ``shared``: the process's shared servers).

    Raises:
        PublisherError: the port is taken, a certificate or key cannot be loaded, the machine
            is already served, another machine serves the endpoint with other settings.
    """

    config_class: ClassVar[type[OpcUaConfig]] = OpcUaConfig
    counter_prefix: ClassVar[str | None] = "opcua"
    open_order: ClassVar[int] = 15   # a port: before the file locks (20, 30)

    def __init__(self, config: OpcUaConfig, context: SinkContext) -> None:
        self._closed = True  # until fully open
        self.config = config
        self.machine = context.machine
        self.windows = 0
        self.events = 0
        self._shared = context.shared
        self._key = config.server_key()
        if self._shared is not None:
            other = [k for k in self._shared.keys() if k.startswith("opcua:") and k != self._key
                     and json.loads(k[6:]).get("endpoint") == config.endpoint]
            if other:
                raise PublisherError(
                    f"outputs.opcua: {config.endpoint} is served by another machine of this "
                    f"process with other server settings; give the machines of one endpoint "
                    f"the same [outputs.opcua] table (stale_after aside)")
            self.server: OpcUaServer = self._shared.acquire(
                self._key, lambda: OpcUaServer(config), _close_server)
        else:
            self.server = OpcUaServer(config)
        try:
            self.server.add_machine(context, config.stale_after)
        except BaseException:
            self._release()
            raise
        self._closed = False

    @classmethod
    def from_config(cls, config: OpcUaConfig, context: SinkContext) -> Self:
        """Open the output: the server (or this process's shared one) and the machine's
        object."""
        return cls(config, context)

    @classmethod
    def reload_key(cls, config: OpcUaConfig, context: SinkContext) -> Hashable:
        """The table, and the machine's model, parameters, nominal values and alarm bands
        (what its nodes are made of): a reload that changes them makes the object anew."""
        bands = tuple(sorted((k, (b.warning_high, b.warning_low, b.alarm_high, b.alarm_low))
                             for k, b in context.alarm_bands.items()))
        return (super().reload_key(config, context), context.model,
                tuple(context.parameters.items()), tuple(sorted(context.nominal.items())), bands)

    def write(self, out: ProcessedWindow) -> None:
        """The window pipeline's call (a stored window): hand its values and alarm events to
        the server's loop; never waits for a client."""
        if self._closed:
            return
        self.server.publish(self.machine, out.health, list(out.events))
        self.windows += 1
        self.events += len(out.events)

    def counters(self) -> dict[str, int]:
        """``windows`` (written), ``events`` (alarm events raised), ``errors`` (writes that
        failed, the whole server's)."""
        return {"windows": int(self.windows), "events": int(self.events),
                "errors": int(self.server.errors)}

    @property
    def status(self) -> str:
        return f"OPC UA on {self.config.endpoint}"

    def summary(self) -> list[str]:
        return [f"health was served over OPC UA on {self.config.endpoint} "
                f"({self.windows} windows, {self.events} alarm events)"]

    def close(self) -> None:
        """Remove the machine's object; the last machine of the server stops it."""
        if self._closed:
            return
        self._closed = True
        self.server.remove_machine(self.machine)
        self._release()

    def _release(self) -> None:
        if self._shared is not None:
            self._shared.release(self._key)
        else:
            self.server.close()


def _close_server(server: OpcUaServer) -> None:
    server.close()

