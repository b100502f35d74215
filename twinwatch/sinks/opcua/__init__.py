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
(:func:`twinwatch.daemon.workers.session_keys`).

Threads: the server runs in its own thread, ``twinwatch-opcua``, on its own asyncio loop;
:meth:`OpcUaPublisher.write` (the outputs' thread) flattens the window into (node, value) pairs
and hands them to that loop, never waiting for a client.

The package's parts: :mod:`~twinwatch.sinks.opcua.config` (the table),
:mod:`~twinwatch.sinks.opcua.model` (the information model and the window's encoding into it),
:mod:`~twinwatch.sinks.opcua.server` (the server in its thread and loop),
:mod:`~twinwatch.sinks.opcua.publisher` (the sink), ``_ua`` (asyncua, imported when a server
opens).
"""

from __future__ import annotations

from twinwatch.sinks.opcua.config import OpcUaConfig
from twinwatch.sinks.opcua.model import DEVICE_HEALTH, device_health, flat_values
from twinwatch.sinks.opcua.publisher import OpcUaPublisher
from twinwatch.sinks.opcua.server import OpcUaServer

__all__ = ["DEVICE_HEALTH", "OpcUaConfig", "OpcUaPublisher", "OpcUaServer", "device_health",
           "flat_values"]
