"""The OPC UA server of one endpoint (:class:`OpcUaServer`): asyncua's server in its own
thread on its own asyncio loop, where the machines' objects are created and deleted, each
window's values written and its alarm events raised.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import math
import threading
import time
from collections.abc import Callable, Coroutine
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, ClassVar

from twinwatch.errors import PublisherError
from twinwatch.sinks.opcua import _ua
from twinwatch.sinks.opcua.config import OpcUaConfig
from twinwatch.sinks.opcua.model import (
    _DIAG_LEAVES,
    _NAN,
    _PARAM_LEAVES,
    COUNTERS_EVERY_S,
    DEVICE_HEALTH,
    SEVERITY,
    _Builder,
    _eu,
    _eu_range,
    _Machine,
    _source_time,
    device_health,
    flat_values,
)

# the real modules once a server opens (:func:`~twinwatch.sinks.opcua._ua.rebinds`)
asyncua: Any = _ua.asyncua
ua: Any = _ua.ua
_ua.rebinds(globals())

if TYPE_CHECKING:
    from twinwatch.sinks.base import SinkContext
    from twinwatch.twin.health import HealthMessage

logger = logging.getLogger(__package__)  # the log lines name the package

__all__ = ["OpcUaServer"]


# -- the server ------------------------------------------------------------------------------
class _ReadOnly:
    """asyncua permission rule set: every user may read, browse, subscribe, read history and
    call the server's standard methods (ConditionRefresh); nobody may write or change the
    address space (RegisterServer: :func:`_refuse_register`)."""

    DENIED: ClassVar[tuple[str, ...]] = (
        "WriteRequest", "AddNodesRequest", "DeleteNodesRequest", "AddReferencesRequest",
        "DeleteReferencesRequest", "RegisterServerRequest", "RegisterServer2Request",
        "HistoryUpdateRequest")

    def __init__(self) -> None:
        self._denied = {ua.NodeId(getattr(ua.ObjectIds, f"{n}_Encoding_DefaultBinary"))
                        for n in self.DENIED}

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        return action_type_id not in self._denied


def _refuse_register(iserver: Any) -> None:
    """Refuse RegisterServer and RegisterServer2 to every client (``Bad_UserAccessDenied``):
    asyncua hands them to the internal server before any session exists and without the
    permission rule set (asyncua 2.1, ``server/uaprocessor.py``), so any client could point
    ``FindServers`` at an address of its choosing. Logged once per server."""
    said = False

    def refuse(*_args: Any) -> None:
        nonlocal said
        if not said:
            said = True
            logger.warning("OPC UA: a client tried to register a server (RegisterServer): "
                           "refused, Bad_UserAccessDenied (twinwatch is no discovery server; "
                           "logged once)")
        raise ua.uaerrors.BadUserAccessDenied()

    iserver.register_server = refuse
    iserver.register_server2 = refuse


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
        _ua.bind()
        self.config = config
        self.machines: dict[str, _Machine] = {}
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name="twinwatch-opcua", daemon=True)
        self._thread.start()
        self._closed = False
        self.writes = 0
        self.errors = 0
        self._tasks: set[asyncio.Task[None]] = set()
        self._names: set[str] = set()        # machines added (their nodes made or to be)
        self._names_lock = threading.Lock()
        self._building: dict[str, asyncio.Task[None]] = {}  # machine -> its nodes' making
        try:
            self._call(self._start(), 30.0)
        except BaseException:
            self._stop_loop()
            raise

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.run_forever()

    def _call(self, coro: Any, timeout: float = 30.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    async def _start(self) -> None:
        cfg = self.config
        host, port = cfg.host_port()
        server = asyncua.Server()
        await server.init()
        _refuse_register(server.iserver)
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

        health_type = await new_enum(server, self.ns, "DeviceHealthEnumeration",
                                     list(DEVICE_HEALTH))
        # the state names for clients before OPC UA 1.04, which read EnumStrings rather than
        # the DataTypeDefinition (the values are 0..4 in order, as EnumStrings requires)
        await health_type.add_property(
            ua.NodeId("DeviceHealthEnumeration.EnumStrings", self.ns),
            ua.QualifiedName("EnumStrings", 0),
            ua.Variant([ua.LocalizedText(n) for n in DEVICE_HEALTH],
                       ua.VariantType.LocalizedText),
            datatype=ua.NodeId(ua.ObjectIds.LocalizedText))
        self.health_type = health_type.nodeid
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
        """Create ``context.machine``'s object and its alarm event generators on the server's
        loop, without waiting for it (a gateway's machines start at once); whatever is handed
        to the loop after this call comes after its nodes. Nodes that cannot be made are
        logged and counted in :attr:`errors`.

        Raises:
            PublisherError: the machine is already served by this server (two outputs of one
                machine).
        """
        name = context.machine
        with self._names_lock:
            if name in self._names:
                raise PublisherError(f"outputs.opcua: machine {name!r} is already served on "
                                     f"{self.config.endpoint}; give each machine one name")
            self._names.add(name)
        self._loop.call_soon_threadsafe(self._schedule_add, context, stale_after)

    def _schedule_add(self, context: SinkContext, stale_after: float) -> None:
        self._building[context.machine] = self._schedule(self._add_machine, context, stale_after)

    async def _built(self, machine: str) -> None:
        task = self._building.get(machine)
        if task is not None and not task.done():
            await asyncio.gather(task, return_exceptions=True)

    def remove_machine(self, machine: str) -> None:
        """Delete the machine's object and every node under it (a machine stopped or removed
        by a reload)."""
        with self._names_lock:
            self._names.discard(machine)
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
        self._loop.call_soon_threadsafe(self._schedule, self._publish, machine, health, events)

    def flush(self, timeout: float = 30.0) -> None:
        """Wait until what :meth:`publish` handed over is written."""
        if not self._closed:
            self._call(self._drain(), timeout)

    async def _drain(self) -> None:
        await asyncio.sleep(0)  # the publish calls queued before this one are scheduled
        while self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)

    def _schedule(self, work: Callable[..., Coroutine[Any, Any, None]], *args: Any
                  ) -> asyncio.Task[None]:
        """``work(*args)`` as a task of the server's loop (called there), tracked until done."""
        task = self._loop.create_task(work(*args))
        self._tasks.add(task)
        task.add_done_callback(self._done)
        return task

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            self.errors += 1
            building = [m for m, t in self._building.items() if t is task]
            if building:
                logger.error("OPC UA: %s's nodes could not be made: %s", building[0],
                             task.exception())
            elif self.errors == 1:
                logger.error("OPC UA: writing a window failed: %s", task.exception())

    async def _add_machine(self, ctx: SinkContext, stale_after: float) -> None:
        name = ctx.machine
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
                               vtype=ua.NodeId(dt.AnalogItemType),
                               history=self.config.history > 0)
            b.prop(value, f"Parameters.{p}.Value.EngineeringUnits", "EngineeringUnits",
                   ua.Variant(_eu(unit), ua.VariantType.ExtensionObject),
                   ua.NodeId(dt.EUInformation))
            b.prop(value, f"Parameters.{p}.Value.EURange", "EURange",
                   ua.Variant(_eu_range(p, ctx), ua.VariantType.ExtensionObject),
                   ua.NodeId(dt.Range))
            for leaf, vt in _PARAM_LEAVES:  # a VariantType, its DataType alike
                parent = po
                if "." in leaf:
                    sub, _ = leaf.split(".", 1)
                    key = f"Parameters.{p}.{sub}"
                    parent = b.nodes.get(key) or b.object(m, key, po, browse=sub)
                init: Any = "" if vt == "String" else (False if vt == "Boolean" else math.nan)
                b.variable(m, parent, f"Parameters.{p}.{leaf}",
                           ua.Variant(init, getattr(ua.VariantType, vt)),
                           ua.NodeId(getattr(dt, vt)), browse=leaf.rsplit(".", 1)[-1])
        diag = b.object(m, "Diagnosis", obj)
        faults = b.object(m, "Diagnosis.Faults", diag, browse="Faults")
        for leaf, vt in _DIAG_LEAVES:
            parent = faults if leaf.startswith("Faults.") else diag
            array = leaf.startswith("Faults.") or leaf == "Alarms"
            init = [] if array else ("" if vt == "String" else math.nan)
            b.variable(m, parent, f"Diagnosis.{leaf}",
                       ua.Variant(init, getattr(ua.VariantType, vt)),
                       ua.NodeId(getattr(dt, vt)), browse=leaf.rsplit(".", 1)[-1])
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
            await self.server.historize_node_data_change(self._value_nodes(m), period=None,
                                                         count=self.config.history)
        self.machines[name] = m

    def _value_nodes(self, m: _Machine) -> list[Any]:
        """The parameters' ``Value`` nodes (those ``[outputs.opcua] history`` keeps)."""
        return [self.server.get_node(nid) for path, (nid, _) in m.vars.items()
                if path.endswith(".Value") and path.startswith("Parameters.")]

    async def _remove_machine(self, machine: str) -> None:
        await self._built(machine)
        self._building.pop(machine, None)
        m = self.machines.pop(machine, None)
        if m is None:
            return
        now = datetime.now(UTC)
        for what, e in list(m.active.items()):  # ConditionRefresh no longer replays them
            await self._alarm(m, {**e, "level": "normal", "message": (
                f"{machine}: {what}: no longer monitored (the machine was stopped or "
                f"removed)")}, now, when=now)
        if self.config.history:
            try:
                await self.server.dehistorize_node_data_change(self._value_nodes(m))
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
        await self._built(machine)
        m = self.machines.get(machine)
        if m is None:
            return
        now = datetime.now(UTC)
        m.last_window = time.monotonic()
        m.stale = False
        ts = _source_time(m, h.run, h.t_end, now)
        m.health = device_health(h)
        # the counters at most every COUNTERS_EVERY_S of plant time: half the writes of a
        # window, and a SCADA trends them at that pace anyway
        counters_due = (m.counters_t is None or h.t_end < m.counters_t
                        or h.t_end - m.counters_t >= COUNTERS_EVERY_S)
        if counters_due:
            m.counters_t = h.t_end
        values = flat_values(h, m.health, counters=counters_due)
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
