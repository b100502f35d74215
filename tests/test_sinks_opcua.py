"""The OPC UA output (issue 35, ``[outputs.opcua]``): a separate asyncua client browses the
server a gateway's machines share, reads each parameter with its units, DeviceHealth, the RUL
and the diagnosis, receives the Alarms & Conditions events when Ra's alarm is raised and when
it clears, cannot write, and sees a machine removed disappear. The fast tests drive the sink
with real health messages (one window of the simulated motor, estimated, then varied); the
slow one runs ``twinwatch run`` on a 20-machine gateway and reads it from another process."""

from __future__ import annotations

import asyncio
import math
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from twinwatch.config.loader import default_config, load_config
from twinwatch.errors import ConfigError, PublisherError
from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.sinks.base import AlarmBands, ProcessedWindow, SharedResources, SinkContext
from twinwatch.sinks.opcua import DEVICE_HEALTH, OpcUaConfig, OpcUaPublisher, device_health
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.health import (
    AlarmStatus,
    DiagnosisHealth,
    FaultHealth,
    HealthMessage,
    RulAlarmStatus,
    build_health,
)
from twinwatch.twin.models import create_model

from .helpers.plant import plant_windows

asyncua = pytest.importorskip("asyncua")
ua = asyncua.ua

NS = "urn:twinwatch:health"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def processed() -> tuple[Any, Any, Any]:
    cfg = default_config()
    model = create_model(cfg.machine.model, cfg.machine.options)
    adapter = TwinAdapter(model, cfg.estimation, cfg.discovery)
    _, (w,) = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=10), 1, skip=1)
    return model, w, adapter.process(w)


def message(processed: tuple[Any, Any, Any], machine: str, **over: Any) -> HealthMessage:
    model, w, result = processed
    h = build_health(machine=machine, model_name="dc_motor", run="r1", model=model, window=w,
                     adaptation=result, nominal={}, counters={"overruns": 0, "windows": 1})
    return h.model_copy(update=over) if over else h


def out(h: HealthMessage, processed: tuple[Any, Any, Any],
        events: list[dict[str, Any]] | None = None) -> ProcessedWindow:
    return ProcessedWindow(window=processed[1], result=processed[2], health=h,
                           health_json=h.to_json(), events=events or [], twin_state=None)


def context(machine: str, shared: SharedResources | None,
            model: Any) -> SinkContext:
    return SinkContext(machine=machine, model="dc_motor",
                       parameters={p.name: p.unit for p in model.parameters},
                       nominal={p.name: p.nominal for p in model.parameters},
                       alarm_bands={"Ra": AlarmBands(warning_high=5.0, warning_low=-5.0,
                                                     alarm_high=10.0, alarm_low=-10.0)},
                       run="r1", shared=shared)


def ra_event(machine: str, level: str, previous: str, t: float) -> dict[str, Any]:
    word = f"{level.upper()}" if level != "normal" else f"{previous.upper()} CLEARED to normal"
    return {"machine": machine, "kind": "deviation", "parameter": "Ra", "level": level,
            "previous": previous, "deviation_pct": 12.0, "threshold_pct": 10.0,
            "value": 7.28, "unit": "ohm", "nominal": 6.5, "t": t, "window": 3,
            "since_t": t - 6, "message": f"{machine}: {word}: Ra (armature resistance)"}


class Client:
    """A real asyncua client on its own loop (the test's thread)."""

    def __init__(self, url: str) -> None:
        self.loop = asyncio.new_event_loop()
        self.client = asyncua.Client(url, timeout=10)
        self.run(self.client.connect())
        self.ns = self.run(self.client.get_namespace_index(NS))
        self.events: list[Any] = []

    def run(self, coro: Any) -> Any:
        return self.loop.run_until_complete(coro)

    def node(self, path: str) -> Any:
        return self.client.get_node(ua.NodeId(path, self.ns))

    def read(self, path: str) -> Any:
        return self.run(self.node(path).read_data_value(raise_on_bad_status=False))

    def machines(self) -> list[str]:
        async def names() -> list[str]:
            root = await self.client.nodes.objects.get_child(f"{self.ns}:TwinWatch")
            return sorted([(await c.read_browse_name()).Name for c in await root.get_children()])
        return self.run(names())

    def subscribe_events(self, on: Any) -> None:
        client = self

        class Handler:
            def event_notification(self, event: Any) -> None:
                client.events.append(event)

        async def sub() -> None:
            s = await self.client.create_subscription(50, Handler())
            await s.subscribe_events(on, ua.ObjectIds.OffNormalAlarmType)
        self.run(sub())

    def pump(self, seconds: float, until: Any = None) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.run(asyncio.sleep(0.05))
            if until is not None and until():
                return

    def close(self) -> None:
        try:
            self.run(self.client.disconnect())
        finally:
            self.loop.close()


@pytest.fixture
def served(processed: tuple[Any, Any, Any]
           ) -> Iterator[tuple[str, SharedResources, dict[str, Any]]]:
    """Three machines of one process sharing one server."""
    port = free_port()
    cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}", stale_after=2.0)
    shared = SharedResources()
    sinks = {m: OpcUaPublisher.open("opcua", cfg, context(m, shared, processed[0]))
             for m in ("m1", "m2", "m3")}
    try:
        yield f"opc.tcp://127.0.0.1:{port}", shared, sinks
    finally:
        for s in sinks.values():
            s.close()
    assert shared.keys() == []  # the last machine closed the server


def test_a_client_browses_every_machine_and_reads_what_the_twin_says(
        served: tuple[str, SharedResources, dict[str, Any]], processed: Any) -> None:
    url, shared, sinks = served
    assert len(shared.keys()) == 1  # one server for the three machines
    for m, sink in sinks.items():
        sink.write(out(message(processed, m), processed))
    sinks["m1"].server.flush()
    c = Client(url)
    try:
        assert c.machines() == ["m1", "m2", "m3"]
        h = message(processed, "m2")
        for name, p in h.parameters.items():
            dv = c.read(f"m2.Parameters.{name}.Value")
            assert dv.Value.Value == pytest.approx(p.value, rel=1e-12)
            eu = c.run(c.client.get_node(ua.NodeId(f"m2.Parameters.{name}.Value.EngineeringUnits",
                                                   c.ns)).read_value())
            assert eu.DisplayName.Text == p.unit
            status = c.read(f"m2.Parameters.{name}.Status").Value.Value
            assert status == p.status
        ra = h.parameters["Ra"]
        eu = c.run(c.node("m2.Parameters.Ra.Value.EngineeringUnits").read_value())
        assert eu.UnitId == (ord("O") << 16) | (ord("H") << 8) | ord("M")   # UN/CEFACT OHM
        rng = c.run(c.node("m2.Parameters.Ra.Value.EURange").read_value())
        assert (rng.Low, rng.High) == pytest.approx((6.5 * 0.9, 6.5 * 1.1))  # the alarm band
        low, high = c.read("m2.Parameters.Ra.Low").Value.Value, c.read(
            "m2.Parameters.Ra.High").Value.Value
        half = 2 * ra.value * ra.rel_std_pct / 100
        assert (low, high) == pytest.approx((ra.value - half, ra.value + half))
        assert c.read("m2.Parameters.Ra.Deviation_pct").Value.Value == pytest.approx(
            ra.deviation_pct)
        assert c.read("m2.DeviceHealth").Value.Value == DEVICE_HEALTH["NORMAL"]
        assert c.read("m2.Window").Value.Value == h.window
        assert c.read("m2.Counters.windows").Value.Value == 1
        # the values carry the window's source time: the run's first window at its writing
        dv = c.read("m2.Parameters.Ra.Value")
        # POSIX time, not the plant's seconds from 0 (an hour either way: no bound on how
        # late a loaded box reads it)
        assert abs(dv.SourceTimestamp.timestamp() - time.time()) < 3600
        # read-only: a write is refused, the value stays
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            c.run(c.node("m2.Parameters.Ra.Value").write_value(
                ua.DataValue(ua.Variant(1.0, ua.VariantType.Double))))
        assert c.read("m2.Parameters.Ra.Value").Value.Value == pytest.approx(ra.value)
        with pytest.raises(ua.uaerrors.BadUserAccessDenied):
            c.run(c.node("m2").add_variable(ua.NodeId("x", c.ns), "x", 1.0))
    finally:
        c.close()


def test_rul_diagnosis_and_device_health_follow_the_message(
        served: tuple[str, SharedResources, dict[str, Any]], processed: Any) -> None:
    url, _, sinks = served
    base = message(processed, "m1")
    ra = base.parameters["Ra"]
    from twinwatch.twin.health import CrossingHealth, RulHealth
    crossing = CrossingHealth(threshold=7.15, status="predicted", t=500.0, t_low=400.0,
                              t_high=700.0, rul_s=480.0, low_s=380.0, high_s=680.0, wall=None,
                              wall_low=None, wall_high=None, probability=0.9)
    rul = RulHealth(status="degrading", warning=None, alarm=crossing, method="monte_carlo",
                    draws=200, interval=0.9)
    params = dict(base.parameters)
    params["Ra"] = ra.model_copy(update={"rul": rul})
    fault = FaultHealth(id="winding_short", component="armature winding", probability=0.93,
                        action="measure the armature resistance", urgency="high",
                        source="test", evidence_for=[], evidence_against=[])
    diag = DiagnosisHealth(status="fault", top="winding_short", probability=0.93,
                           no_fault=0.05, unknown=0.02, unknown_terms=[], faults=[fault],
                           shaft_speed=None, library="dc_motor", evidence=3,
                           alarms=["winding_short"])
    alarms = {"Ra": AlarmStatus(level="normal", since_t=0.0, since_window=0, deviation_pct=0.1,
                                pending=None,
                                rul=RulAlarmStatus(level="warning", since_t=0.0, since_window=0,
                                                   rul_s=480.0, pending=None))}
    h = message(processed, "m1", parameters=params, diagnosis=diag, alarms=alarms)
    sinks["m1"].write(out(h, processed))
    sinks["m1"].server.flush()
    c = Client(url)
    try:
        assert c.read("m1.Parameters.Ra.RUL.Status").Value.Value == "degrading"
        assert c.read("m1.Parameters.Ra.RUL.Alarm_s").Value.Value == 480.0
        assert c.read("m1.Parameters.Ra.RUL.AlarmLow_s").Value.Value == 380.0
        assert c.read("m1.Parameters.Ra.RUL.AlarmHigh_s").Value.Value == 680.0
        assert math.isnan(c.read("m1.Parameters.Ra.RUL.Warning_s").Value.Value)
        assert c.read("m1.Diagnosis.TopFault").Value.Value == "winding_short"
        assert c.read("m1.Diagnosis.Part").Value.Value == "armature winding"
        assert c.read("m1.Diagnosis.Probability").Value.Value == pytest.approx(0.93)
        assert c.read("m1.Diagnosis.Urgency").Value.Value == "high"
        assert c.read("m1.Diagnosis.Faults.Ids").Value.Value == ["winding_short"]
        # a raised fault of urgency high whose action is for the next stop: maintenance, not
        # FAILURE (issue 56: before, red in every SCADA on Ra -1.8 %)
        assert c.read("m1.DeviceHealth").Value.Value == DEVICE_HEALTH["MAINTENANCE_REQUIRED"]
        assert "winding_short (urgency high)" in c.read("m1.DeviceHealthReason").Value.Value
        # the same with the fault's urgency medium: the RUL warning and the fault ask for
        # maintenance
        medium = diag.model_copy(update={"faults": [fault.model_copy(update={"urgency":
                                                                             "medium"})]})
        sinks["m1"].write(out(h.model_copy(update={"diagnosis": medium}), processed))
        sinks["m1"].server.flush()
        assert c.read("m1.DeviceHealth").Value.Value == DEVICE_HEALTH["MAINTENANCE_REQUIRED"]
        # no window for stale_after (2 s): the source is lost, CHECK_FUNCTION
        c.pump(4.0, until=lambda: c.read("m1.DeviceHealth").Value.Value == 2)
        assert c.read("m1.DeviceHealth").Value.Value == DEVICE_HEALTH["CHECK_FUNCTION"]
        assert "no window" in c.read("m1.DeviceHealthReason").Value.Value
        # the next window sets it from the message again
        sinks["m1"].write(out(h.model_copy(update={"diagnosis": medium}), processed))
        sinks["m1"].server.flush()
        assert c.read("m1.DeviceHealth").Value.Value == DEVICE_HEALTH["MAINTENANCE_REQUIRED"]
        assert "no window" not in c.read("m1.DeviceHealthReason").Value.Value
    finally:
        c.close()


def _fault(urgency: str = "high") -> DiagnosisHealth:
    """The diagnosis with winding_short raised (its action: at the next stop)."""
    fault = FaultHealth(id="winding_short", component="armature winding", probability=0.93,
                        action="measure the armature resistance at the next stop",
                        urgency=urgency, source="test", evidence_for=[], evidence_against=[])
    return DiagnosisHealth(status="fault", top="winding_short", probability=0.93,
                           no_fault=0.05, unknown=0.02, unknown_terms=[], faults=[fault],
                           shaft_speed=None, library="dc_motor", evidence=3,
                           alarms=["winding_short"])


def _level(level: str, rul: str | None = None) -> AlarmStatus:
    return AlarmStatus(level=level, since_t=0.0, since_window=0, deviation_pct=6.0,
                       pending=None, rul=None if rul is None else RulAlarmStatus(
                           level=rul, since_t=0.0, since_window=0, rul_s=120.0, pending=None))


_CHECK = DiagnosisHealth(status="check_function", top=None, probability=1.0, no_fault=0.0,
                         unknown=0.0, unknown_terms=[], faults=[], shaft_speed=None,
                         library="dc_motor", evidence=0, check_failed="30 of 30")

#: docs/opcua-output.md's DeviceHealth table, row by row (its first column, in order): the
#: message that meets the row (and none above it), the state, a word of the reason
NE107_ROWS: list[tuple[str, str, dict[str, Any], str]] = [
    ("stale", "CHECK_FUNCTION", {}, "no window for"),
    ("deviation alarm", "FAILURE", {"alarms": {"Ra": _level("alarm", "alarm")},
                                    "diagnosis": _CHECK}, "inspect the machine now"),
    ("check function", "CHECK_FUNCTION", {"diagnosis": _CHECK,
                                          "alarms": {"Ra": _level("warning")}},
     "does not describe"),
    ("silent", "CHECK_FUNCTION", {"source": {"silent": ["TPDO1 (omega) for 1.2 s"]}},
     "silent on the bus"),
    ("deviation warning", "OFF_SPEC", {"alarms": {"Ra": _level("warning", "alarm")},
                                       "diagnosis": _fault()}, "beyond its warning threshold"),
    ("rul", "MAINTENANCE_REQUIRED", {"alarms": {"Ra": _level("normal", "alarm")}},
     "Ra RUL alarm"),
    ("fault", "MAINTENANCE_REQUIRED", {"diagnosis": _fault("high")},
     "winding_short (urgency high): measure the armature resistance at the next stop"),
    ("normal", "NORMAL", {"alarms": {"Ra": _level("normal", "normal")}}, "normal"),
]


@pytest.mark.parametrize(("row", "state", "update", "says"), NE107_ROWS,
                         ids=[r[0] for r in NE107_ROWS])
def test_the_ne107_mapping_row_by_row(processed: Any, row: str, state: str,
                                      update: dict[str, Any], says: str) -> None:
    """Each row of docs/opcua-output.md's table: the state a message meeting it gets, what
    must be done named in the reason; a row meets none above it, and the conditions of the
    rows below it (given too) do not change it: the first row that applies wins."""
    h = message(processed, "m1")
    if "source" in update:
        update = {**update, "source": h.source.model_copy(update=update["source"])}
    if row == "stale":  # the server's: no window for stale_after, whatever the last said
        port = free_port()
        cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}", stale_after=1.0)
        sink = OpcUaPublisher.open("opcua", cfg, context("m1", None, processed[0]))
        try:
            sink.write(out(message(processed, "m1", alarms={"Ra": _level("alarm")}), processed))
            sink.server.flush()
            c = Client(f"opc.tcp://127.0.0.1:{port}")
            try:
                c.pump(10.0, until=lambda: c.read("m1.DeviceHealth").Value.Value
                       == DEVICE_HEALTH[state])
                value = c.read("m1.DeviceHealth").Value.Value
                reason = c.read("m1.DeviceHealthReason").Value.Value
            finally:
                c.close()
        finally:
            sink.close()
    else:
        value, reason = device_health(h.model_copy(update=update))
    assert value == DEVICE_HEALTH[state], (row, reason)
    assert says in reason, reason


def test_the_docs_table_is_the_tested_rows() -> None:
    """docs/opcua-output.md's DeviceHealth table has the tested rows, in their order."""
    import re

    page = (Path(__file__).resolve().parents[1] / "docs" / "opcua-output.md").read_text()
    table = page.split("## DeviceHealth: the NE 107 mapping", 1)[1].split("\n## ", 1)[0]
    states = re.findall(r"^\| `([A-Z_]+)` \(\d\) \|", table, re.MULTILINE)
    assert states == [r[1] for r in NE107_ROWS], states


def test_a_client_that_registers_a_server_is_refused_and_find_servers_lists_twinwatch(
        served: tuple[str, SharedResources, dict[str, Any]], caplog: Any) -> None:
    """Issue 56: an anonymous client, without a session, sends RegisterServer and
    RegisterServer2 pointing at an address of its choosing: Bad_UserAccessDenied (before:
    accepted, and FindServers listed it); FindServers lists twinwatch only."""
    url = served[0]
    rogue = ua.RegisteredServer(ServerUri="urn:rogue", ProductUri="urn:rogue",
                                ServerNames=[ua.LocalizedText("rogue")],
                                ServerType=ua.ApplicationType.Server,
                                DiscoveryUrls=["opc.tcp://127.0.0.1:1"], IsOnline=True)

    async def attempt() -> tuple[list[str], list[Any]]:
        client = asyncua.Client(url, timeout=10)
        await client.connect_socket()
        refused = []
        try:
            await client.send_hello()
            await client.open_secure_channel()
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await client.uaclient.register_server(rogue)
            refused.append("RegisterServer")
            params = ua.RegisterServer2Parameters(
                Server=rogue, DiscoveryConfiguration=[ua.MdnsDiscoveryConfiguration(
                    MdnsServerName="rogue", ServerCapabilities=["NA"])])
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await client.uaclient.register_server2(params)
            refused.append("RegisterServer2")
            found = await client.find_servers()
            await client.close_secure_channel()
        finally:
            client.disconnect_socket()
        return refused, found

    refused, found = asyncio.run(attempt())
    assert refused == ["RegisterServer", "RegisterServer2"]
    assert [f.ApplicationUri for f in found] == ["urn:freeopcua:python:server"], found
    assert sum("tried to register a server" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("history", [0, 10])
def test_history_read_is_advertised_only_where_history_is_kept(processed: Any,
                                                                history: int) -> None:
    """Issue 56: AccessLevel (and Historizing) from [outputs.opcua] history: a parameter's
    Value is CurrentRead | HistoryRead only with history > 0; every other variable is
    CurrentRead only (before: HistoryRead everywhere, with history = 0)."""
    port = free_port()
    cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}", history=history)
    sink = OpcUaPublisher.open("opcua", cfg, context("m1", None, processed[0]))
    try:
        sink.server.flush()
        c = Client(f"opc.tcp://127.0.0.1:{port}")
        try:
            def attrs(path: str) -> tuple[int, int, bool]:
                node = c.node(path)
                got = c.run(node.read_attributes([ua.AttributeIds.AccessLevel,
                                                  ua.AttributeIds.UserAccessLevel,
                                                  ua.AttributeIds.Historizing]))
                return tuple(d.Value.Value for d in got)  # type: ignore[return-value]

            read = ua.AccessLevel.CurrentRead.mask
            hist = ua.AccessLevel.HistoryRead.mask
            kept = history > 0
            for p in ("Ra", "D", "J"):
                assert attrs(f"m1.Parameters.{p}.Value") == (
                    read | (hist if kept else 0), read | (hist if kept else 0), kept)
            for path in ("m1.DeviceHealth", "m1.Window", "m1.Parameters.Ra.Low",
                         "m1.Parameters.Ra.RUL.Alarm_s", "m1.Diagnosis.Status"):
                assert attrs(path) == (read, read, False), path
        finally:
            c.close()
    finally:
        sink.close()


def test_older_clients_read_the_device_health_state_names(
        served: tuple[str, SharedResources, dict[str, Any]]) -> None:
    """The DeviceHealthEnumeration data type carries EnumStrings (what clients before OPC UA
    1.04 read) besides its DataTypeDefinition: NORMAL, FAILURE, CHECK_FUNCTION, OFF_SPEC,
    MAINTENANCE_REQUIRED, value = index."""
    served[2]["m1"].server.flush()  # m1's nodes made
    c = Client(served[0])
    try:
        dtype = c.run(c.node("m1.DeviceHealth").read_data_type())
        node = c.client.get_node(dtype)
        prop = c.run(node.get_child("0:EnumStrings"))
        names = [t.Text for t in c.run(prop.read_value())]
        assert names == ["NORMAL", "FAILURE", "CHECK_FUNCTION", "OFF_SPEC",
                         "MAINTENANCE_REQUIRED"]
        assert [DEVICE_HEALTH[n] for n in names] == list(range(5))
        definition = c.run(node.read_data_type_definition())
        assert [(f.Name, f.Value) for f in definition.Fields] == list(DEVICE_HEALTH.items())
    finally:
        c.close()


def test_alarm_events_when_ra_is_raised_and_cleared_and_a_machine_removed_disappears(
        served: tuple[str, SharedResources, dict[str, Any]], processed: Any) -> None:
    url, shared, sinks = served
    for s in sinks.values():
        s.write(out(message(processed, s.machine), processed))
    sinks["m1"].server.flush()
    c = Client(url)
    try:
        c.subscribe_events(c.client.nodes.server)   # what a SCADA does: every machine's
        c.pump(0.3)
        sinks["m2"].write(out(message(processed, "m2"), processed,
                              [ra_event("m2", "alarm", "normal", 8.0)]))
        c.pump(5.0, until=lambda: len(c.events) >= 1)
        sinks["m2"].write(out(message(processed, "m2"), processed,
                              [ra_event("m2", "normal", "alarm", 20.0)]))
        c.pump(5.0, until=lambda: len(c.events) >= 2)
        assert len(c.events) == 2
        raised, cleared = c.events
        assert raised.SourceName == "m2" and raised.Severity == 800
        assert "ALARM: Ra" in raised.Message.Text
        assert raised.EventType == ua.NodeId(ua.ObjectIds.OffNormalAlarmType)
        assert cleared.Severity == 200 and "CLEARED" in cleared.Message.Text
        # the event's time is the window's source time: 12 s of plant time apart
        assert (cleared.Time - raised.Time).total_seconds() == pytest.approx(12.0, abs=0.01)
        # a machine removed (its daemon stopped by a reload) disappears; the others stay
        sinks.pop("m3").close()
        assert c.machines() == ["m1", "m2"]
        dv = c.read("m3.Parameters.Ra.Value")
        assert dv.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown
        assert shared.references(shared.keys()[0]) == 2
    finally:
        c.close()


@pytest.mark.slow
def test_bad_tables_refused_naming_the_key_and_a_taken_port(tmp_path: Path,
                                                          processed: Any) -> None:
    from harness.daemon import sim_config

    with pytest.raises(ConfigError, match=r"outputs\.opcua\.endpoint"):
        load_config(sim_config(tmp_path, extra='\n[outputs.opcua]\nendpoint = "tcp://x:1"\n'))
    with pytest.raises(ConfigError, match=r"needs certificate and private_key"):
        load_config(sim_config(tmp_path, extra='\n[outputs.opcua]\nsecurity = '
                                               '["Basic256Sha256_Sign"]\n'))
    with pytest.raises(ConfigError, match=r"outputs\.opcua\.security"):
        load_config(sim_config(tmp_path, extra='\n[outputs.opcua]\nsecurity = ["Basic128"]\n'))
    # the files: missing (check-config's preflight), a key others can read (at load), a file
    # that is no certificate (at open), each naming its key
    from twinwatch.config.preflight import check_runnable

    key = tmp_path / "k.pem"
    key.write_text("not a key")
    key.chmod(0o600)
    table = ('\n[outputs.opcua]\nsecurity = ["Basic256Sha256_Sign"]\ncertificate = '
             '"missing.der"\nprivate_key = "k.pem"\n')
    path = sim_config(tmp_path, extra=table)
    with pytest.raises(ConfigError, match=r"outputs\.opcua\.certificate: file .* not found"):
        check_runnable(load_config(path), str(path), base_dir=tmp_path, cwd=tmp_path)
    key.chmod(0o644)
    with pytest.raises(ConfigError, match=r"outputs\.opcua\.private_key = .* readable by other"):
        load_config(path)
    (tmp_path / "bad.der").write_text("not a certificate")
    cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{free_port()}",
                      security=["Basic256Sha256_Sign"], certificate=str(tmp_path / "bad.der"),
                      private_key=str(key))
    with pytest.raises(PublisherError, match=r"outputs\.opcua\.certificate = .*cannot be "
                                             r"loaded"):
        OpcUaPublisher.open("opcua", cfg, context("m1", None, processed[0]))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}")
        with pytest.raises(PublisherError, match=rf"port {port} on 127.0.0.1 is already taken"):
            OpcUaPublisher.open("opcua", cfg, context("m1", None, processed[0]))
        # `twinwatch run`: one line naming it, no traceback (asyncua's own is filtered)
        from .helpers.cli import cli

        path = sim_config(tmp_path, extra=f'\n[outputs.opcua]\nendpoint = '
                                          f'"opc.tcp://127.0.0.1:{port}"\n')
        r = cli("run", "--no-progress", str(path))
        assert r.exit_code == 1, r.output
        assert (f"outputs.opcua.endpoint opc.tcp://127.0.0.1:{port}: port {port} on "
                f"127.0.0.1 is already taken" in r.output)
        assert "Traceback" not in r.output


def test_history_of_the_parameters_when_asked(processed: Any) -> None:
    port = free_port()
    cfg = OpcUaConfig(endpoint=f"opc.tcp://127.0.0.1:{port}", history=10)
    sink = OpcUaPublisher.open("opcua", cfg, context("m1", None, processed[0]))
    try:
        model, w, result = processed
        base = message(processed, "m1")
        values = [6.5, 6.6, 6.7]
        for k, v in enumerate(values):
            params = dict(base.parameters)
            params["Ra"] = params["Ra"].model_copy(update={"value": v})
            h = base.model_copy(update={"window": k, "t_end": 2.0 * k + 2.0,
                                        "parameters": params})
            sink.write(out(h, processed))
        sink.server.flush()
        c = Client(f"opc.tcp://127.0.0.1:{port}")
        try:
            def history() -> list[Any]:
                got = c.run(c.node("m1.Parameters.Ra.Value").read_raw_history())
                return sorted((d for d in got if not math.isnan(d.Value.Value)),  # the NaN
                              key=lambda d: d.SourceTimestamp)   # before the first window

            # asyncua stores the history from an internal subscription: it lags the write
            deadline = time.monotonic() + 10
            while len(got := history()) < 3 and time.monotonic() < deadline:
                c.pump(0.2)
            assert [d.Value.Value for d in got] == values
            stamps = [d.SourceTimestamp.timestamp() for d in got]
            steps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
            assert steps == pytest.approx([2.0, 2.0])
        finally:
            c.close()
    finally:
        sink.close()


CLIENT = textwrap.dedent("""
    import asyncio, json, sys
    from asyncua import Client, ua

    async def main(url, n):
        events = []
        class H:
            def event_notification(self, e):
                events.append({"source": e.SourceName, "severity": e.Severity,
                               "message": e.Message.Text})
        async with Client(url, timeout=10) as c:
            ns = await c.get_namespace_index("urn:twinwatch:health")
            sub = await c.create_subscription(100, H())
            await sub.subscribe_events(c.nodes.server, ua.ObjectIds.OffNormalAlarmType)
            root = await c.nodes.objects.get_child(f"{ns}:TwinWatch")
            out = {}
            while True:
                try:
                    names = [(await m.read_browse_name()).Name
                             for m in await root.get_children()]
                except ua.UaStatusCodeError:  # a machine removed while we browse
                    continue
                done = {}
                for m in names:
                    node = lambda p: c.get_node(ua.NodeId(f"{m}.{p}", ns))
                    try:
                        window = await node("Window").read_value()
                        if window < 0:
                            continue
                        eu = await node("Parameters.Ra.Value.EngineeringUnits").read_value()
                        done[m] = {"Ra": await node("Parameters.Ra.Value").read_value(),
                                   "unit": eu.DisplayName.Text,
                                   "health": await node("DeviceHealth").read_value(),
                                   "rul": await node("Parameters.Ra.RUL.Status").read_value(),
                                   "diagnosis": await node("Diagnosis.Status").read_value(),
                                   "window": window}
                    except ua.UaStatusCodeError:  # removed while we read it
                        continue
                out = done
                print(json.dumps({"machines": names, "read": out, "events": events}),
                      flush=True)
                await asyncio.sleep(2.0)

    asyncio.run(main(sys.argv[1], int(sys.argv[2])))
""")


@pytest.mark.slow
def test_a_separate_client_process_reads_a_20_machine_gateway(tmp_path: Path) -> None:
    """``twinwatch run DIR`` on 20 simulated motors with one ``[outputs.opcua]`` endpoint (the
    service host puts them in one worker process): another process browses every machine,
    reads Ra with its unit, DeviceHealth, the RUL and the diagnosis, receives the ALARM event
    when a degrading Ra crosses its alarm threshold (m00: Ra falling 15 % linearly from 30 s
    to 230 s) and, on m01 (Ra 15 % up from 60 s, repaired at 140 s), when an alarm is raised
    and when it clears, and sees m19 disappear when its file is removed and the gateway
    reloaded (SIGHUP). Every machine runs in real time: the test takes about 4 minutes
    whatever the box (m00 and m01 once ran as fast as they estimated, sharing the one worker
    process and its GIL with 18 machines in real time: on a loaded box they got 0.15 to 0.6
    of real time, and the test waited up to 37 minutes)."""
    import json
    import signal

    from .helpers.cli import machine_config

    port = free_port()
    machines = tmp_path / "machines"
    machines.mkdir()
    table = f'\n[outputs.opcua]\nendpoint = "opc.tcp://127.0.0.1:{port}"\n'
    for i in range(20):
        faulted = i <= 1  # 900 s: still running at the reload
        path = machine_config(machines, f"m{i:02d}", port=None,
                              duration=900.0 if faulted else 3600.0, realtime=True)
        text = path.read_text() + table
        if not faulted:  # an hour of the default degradation: the part is replaced every 20 min
            text = text.replace('scenario = "resistance_degradation"',
                                'scenario = "resistance_degradation"\nfault_period = 1200.0')
        if i == 0:  # a degradation: Ra crosses its alarm threshold (-10 %) at about 163 s
            # (the default run's exponential fall crosses it at about 1080 s: on 2026-11-25's
            # CI box m00, sharing its process with 19 machines in real time, had reached 526 s
            # of plant time when a 600 s wait ran out). With 0.5 % noise: on the noise-free
            # plant this ramp (0.15 % of Ra a window, 37 times the default law's first rate)
            # leaves the ia residual coloured and the twin reads check function from 30 s
            assert 'scenario = "resistance_degradation"' in text and "noise = {}" in text
            text = text.replace('scenario = "resistance_degradation"', (
                'scenario = "nominal"\nparameter_faults = [{ parameter = "Ra", change = -15.0, '
                'start = 30.0, ramp = 200.0 }]'))
            text = text.replace("noise = {}", "noise = { ia = 0.5, omega = 0.5 }")
        if i == 1:  # a fault that is repaired: the Ra alarm raised, then cleared
            assert 'scenario = "resistance_degradation"' in text
            text = text.replace('scenario = "resistance_degradation"', (
                'scenario = "nominal"\nparameter_faults = [{ parameter = "Ra", change = 15.0, '
                'start = 60.0, ramp = 0.0, end = 140.0 }]'))
        path.write_text(text)
    # the machines in real time run for an hour: the test stops them (with 600 s, on a box
    # loaded by other work, they had ended before the reload, which then started them all
    # again and the client lost its server)
    # the gateway's output to files: 20 machines' log lines fill a pipe nobody reads while
    # the test waits (64 KiB by about a minute), and every machine then blocks on its next
    # log line (the address space stopped at window 30, no event came)
    log_out = (tmp_path / "gateway.out").open("w")
    log_err = (tmp_path / "gateway.err").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "twinwatch", "run", str(machines)],
                            cwd=tmp_path, stdout=log_out, stderr=log_err, text=True)
    script = tmp_path / "client.py"
    script.write_text(CLIENT)
    client = None
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                    break
            except OSError:
                assert proc.poll() is None, (tmp_path / "gateway.err").read_text()[-3000:]
                time.sleep(0.5)
        client = subprocess.Popen([sys.executable, str(script), f"opc.tcp://127.0.0.1:{port}",
                                   "20"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True)
        assert client.stdout is not None

        def until(what: Any, timeout: float) -> dict[str, Any]:
            assert client is not None and client.stdout is not None
            deadline = time.monotonic() + timeout
            last: dict[str, Any] = {}
            while time.monotonic() < deadline:
                line = client.stdout.readline()
                if not line:
                    break
                last = json.loads(line)
                if what(last):
                    return last
            if client.poll() is not None:
                last["client stderr"] = client.communicate()[1][-3000:]
            log_err.flush()
            raise AssertionError(f"not seen within {timeout} s: {str(last)[:6000]}; the "
                                 f"gateway's log: {(tmp_path / 'gateway.err').read_text()[-3000:]}")

        last = until(lambda d: len(d["read"]) == 20, 600)   # 20 starts on a loaded CI box
        assert sorted(last["machines"]) == [f"m{i:02d}" for i in range(20)]
        for m, got in last["read"].items():
            assert got["unit"] == "ohm" and 5.0 < got["Ra"] < 8.0, (m, got)  # m01: +15 %
            assert got["health"] in DEVICE_HEALTH.values()
            assert got["diagnosis"] in ("no_fault", "fault", "unknown", "check_function")
            assert got["rul"] in ("", "insufficient", "not_degrading", "degrading")
        def level_alarm(event: dict[str, Any]) -> bool:
            """Ra's level alarm, not its RUL alarm ("RUL ALARM: Ra reaches ..."): on a loaded box
            m00's trend reached its horizon before Ra crossed the threshold, and the health waited
            for was not yet FAILURE."""
            return "ALARM: Ra" in event["message"] and "RUL ALARM" not in event["message"]

        # m01's repaired fault: the Ra alarm raised, then cleared (OPC UA A&C, severity 200)
        back = "CLEARED to normal: Ra"
        last = until(lambda d: any(e["source"] == "m01" and back in e["message"]
                                   for e in d["events"]), 900)  # a loaded CI box: slow
        m01 = [e for e in last["events"] if e["source"] == "m01"]
        raised = [k for k, e in enumerate(m01) if level_alarm(e)]
        cleared = [k for k, e in enumerate(m01) if back in e["message"]]
        assert raised and cleared and raised[0] < cleared[-1], m01
        assert m01[raised[0]]["severity"] == 800 and m01[cleared[-1]]["severity"] == 200
        # m00's degradation crosses the Ra alarm threshold at 163 s of plant time (m01 cleared
        # at about 170 s: m00's alarm is out by now; a liveness bound, not a speed goal)
        last = until(lambda d: any(e["source"] == "m00" and level_alarm(e)
                                   for e in d["events"]), 600)
        alarm = next(e for e in last["events"] if e["source"] == "m00" and level_alarm(e))
        assert alarm["severity"] == 800
        last = until(lambda d: d["read"].get("m00", {}).get("health")
                     == DEVICE_HEALTH["FAILURE"], 30)   # NE 107: an alarm level is FAILURE
        assert last["read"]["m00"]["rul"] == "degrading"
        # a machine removed by a reload disappears from the address space
        (machines / "m19.toml").unlink()
        proc.send_signal(signal.SIGHUP)
        last = until(lambda d: "m19" not in d["machines"], 120)
        assert len(last["machines"]) == 19
    finally:
        if client is not None:
            client.kill()
            client.communicate()
        proc.terminate()
        proc.wait(timeout=120)
        log_out.close()
        log_err.close()


def _certificate(directory: Path, name: str, uri: str, server: bool) -> tuple[Path, Path]:
    """A self-signed application certificate (DER) and its key (PEM, 0600) by asyncua's own
    generator."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = directory / f"{name}.pem", directory / f"{name}.der"
    use = [ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH]
    asyncio.run(setup_self_signed_certificate(key, cert, uri, "localhost", use,
                                              {"commonName": name}))
    key.chmod(0o600)
    return cert, key


def test_signed_and_encrypted_endpoint_with_a_trusted_client_only(tmp_path: Path,
                                                                  processed: Any) -> None:
    """Basic256Sha256 SignAndEncrypt with the server's certificate and key from files: a client
    with a trusted certificate reads; one without security, or with a certificate the table
    does not trust, is refused."""
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    server_cert, server_key = _certificate(tmp_path, "server", "urn:freeopcua:python:server",
                                           True)
    good_cert, good_key = _certificate(tmp_path, "scada", "urn:test:scada", False)
    bad_cert, bad_key = _certificate(tmp_path, "stranger", "urn:test:stranger", False)
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    cfg = OpcUaConfig(endpoint=url, security=["Basic256Sha256_SignAndEncrypt"],
                      certificate=str(server_cert), private_key=str(server_key),
                      trusted_clients=[str(good_cert)])
    sink = OpcUaPublisher.open("opcua", cfg, context("m1", None, processed[0]))
    loop = asyncio.new_event_loop()
    try:
        sink.write(out(message(processed, "m1"), processed))
        sink.server.flush()

        async def read(cert: Path | None, key: Path | None) -> float:
            client = asyncua.Client(url, timeout=10)
            client.application_uri = "urn:test:scada" if cert == good_cert else \
                "urn:test:stranger"
            if cert is not None:
                await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                                          server_certificate=str(server_cert),
                                          mode=ua.MessageSecurityMode.SignAndEncrypt)
            async with client:
                ns = await client.get_namespace_index(NS)
                return float(await client.get_node(
                    ua.NodeId("m1.Parameters.Ra.Value", ns)).read_value())

        ra = message(processed, "m1").parameters["Ra"].value
        assert loop.run_until_complete(read(good_cert, good_key)) == pytest.approx(ra)
        with pytest.raises(ua.UaError, match="No matching endpoints"):
            loop.run_until_complete(read(None, None))   # no None endpoint offered
        with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
            loop.run_until_complete(read(bad_cert, bad_key))   # not in trusted_clients
    finally:
        loop.close()
        sink.close()
