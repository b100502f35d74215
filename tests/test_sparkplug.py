"""The Sparkplug B output (issue 38, part 1) against a real Mosquitto broker, read by a host
decoder that subscribes ``spBv1.0/#`` and decodes every message with Eclipse Tahu's protobuf:
births before data, aliases only in DDATA, ``seq`` without gaps from each NBIRTH, ``bdSeq`` of
the NDEATH (clean stop and the will after ``kill -9``) equal to the NBIRTH's, a rebirth on
NCMD, the primary host's STATE waited for, replays from the outbox flagged historical, every
stored window delivered. No mock broker: ``mosquitto`` runs on 127.0.0.1 on a free port.
"""

from __future__ import annotations

import json
import re
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from harness.daemon import sim_config
from twinwatch.config.loader import load_config
from twinwatch.errors import ConfigError
from twinwatch.sinks.sparkplug import (
    DeviceSession,
    EdgeNodeSession,
    MetricSpec,
    SparkplugConfig,
    SparkplugPublisher,
    metric_specs,
    metric_values,
)
from twinwatch.sinks.sparkplug_pb import DATATYPE, FILE_DESCRIPTOR

from .helpers.mqtt import (
    Broker,
    Subscriber,
    finish,
    needs_mosquitto,
    running_broker,
    stored_window,
    twinwatch,
)
from .helpers.paths import ROOT
from .helpers.sparkplug import HostDecoder, Payload, stored

PROTO = ROOT / "twinwatch" / "sinks" / "sparkplug_pb" / "sparkplug_b.proto"


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    yield from running_broker(tmp_path / "broker")


# -- the host decoder ---------------------------------------------------------------------------
def table(port: int, extra: str = "") -> str:
    return (f'\n[outputs.sparkplug]\nport = {port}\ngroup_id = "plant1"\nkeepalive = 5\n'
            f"reconnect_max = 1.0\n{extra}")


# -- the schema ---------------------------------------------------------------------------------
def test_the_compiled_descriptor_is_the_shipped_proto() -> None:
    """Every field of every message in sparkplug_b.proto (name, number, label, type) is in the
    compiled descriptor the payloads are built from, and nothing else is."""
    from google.protobuf import descriptor_pb2

    fd = descriptor_pb2.FileDescriptorProto.FromString(FILE_DESCRIPTOR)
    assert fd.name == "sparkplug_b.proto" and fd.package == "org.eclipse.tahu.protobuf"
    compiled: set[tuple[str, str, int]] = set()

    def walk(msg: Any) -> None:
        for f in msg.field:
            compiled.add((msg.name, f.name, f.number))
        for nested in msg.nested_type:
            walk(nested)

    for msg in fd.message_type:
        walk(msg)
    text = re.sub(r"//[^\n]*", "", PROTO.read_text())
    written = set()
    stack: list[str] = []
    for line in text.splitlines():
        if m := re.match(r"\s*message\s+(\w+)\s*{", line):
            stack.append(m.group(1))
        elif re.match(r"\s*(oneof|enum)\s+\w+\s*{", line):
            stack.append("")  # a oneof's fields belong to the message around it
        elif re.match(r"\s*}", line):
            stack.pop()
        elif m := re.match(r"\s*(?:optional\s+|repeated\s+|required\s+)?[\w.]+\s+(\w+)\s*="
                           r"\s*(\d+)\s*;", line):
            owner = next(n for n in reversed(stack) if n)
            written.add((owner, m.group(1), int(m.group(2))))
    assert not stack and len(written) > 50
    assert written == compiled
    enum = {v.name: v.number for v in fd.enum_type[0].value}
    assert all(enum[k] == v for k, v in DATATYPE.items())


def test_seq_and_bdseq_wrap_aliases_are_unique_and_case_clashes_refused() -> None:
    node = EdgeNodeSession("g", "e")
    s = DeviceSession(node, "d")
    assert [node.new_connection() for _ in range(258)][-3:] == [255, 0, 1]
    assert EdgeNodeSession("g", "e", bd_seq=255).new_connection() == 0   # kept, then wraps
    assert s.declare([MetricSpec("A/x", "Double", "m"), MetricSpec("A/y", "Int32")])
    assert not s.declare([MetricSpec("A/x", "Double", "m")])
    nbirth = Payload.FromString(node.nbirth(1))
    assert nbirth.seq == 0
    seqs = [Payload.FromString(s.ddata({"A/x": 1.0}, 1, 1)).seq for _ in range(300)]
    assert seqs[:3] == [1, 2, 3] and seqs[254:257] == [255, 0, 1]
    d = Payload.FromString(s.ddata({"A/x": 2.5, "A/y": -3, "unknown": 1}, 5, 4,
                                   historical=True))
    assert [(m.alias, m.name, m.is_historical) for m in d.metrics] == [(1, "", True),
                                                                       (2, "", True)]
    assert d.metrics[0].double_value == 2.5
    assert d.metrics[1].int_value == (-3) & 0xFFFFFFFF   # two's complement (Sparkplug B)
    birth = Payload.FromString(s.dbirth({"A/x": float("nan")}, 7))
    assert [(m.name, m.alias, m.is_null) for m in birth.metrics] == [("A/x", 1, True),
                                                                     ("A/y", 2, True)]
    assert birth.metrics[0].properties.keys == ["engUnit"]
    assert birth.metrics[0].properties.values[0].string_value == "m"
    with pytest.raises(ValueError, match="differ only in case"):
        s.declare([MetricSpec("a/X", "Double")])


def test_metrics_read_the_typed_message() -> None:
    from twinwatch.twin.health import read_health

    doc = read_health({"machine": "m", "run": "r1", "window": 4, "t_start": 8.0, "t_end": 9.99,
                       "trusted": True, "nrmse": 0.01, "counters": {"gaps": 2},
                       "parameters": {"Ra": {"value": 6.6, "unit": "ohm", "nominal": 6.5,
                                             "deviation_pct": 1.5, "status": "estimated",
                                             "rel_std_pct": 0.5, "rul": None}},
                       "alarms": {"Ra": {"level": "warning", "deviation_pct": 1.5}},
                       "diagnosis": {"status": "fault", "probability": 0.9,
                                     "faults": [{"id": "winding", "action": "rewind",
                                                 "probability": 0.9}]}})
    names = [s.name for s in metric_specs({"Ra": "ohm"}, set(), doc)]
    values = metric_values(doc)
    assert set(values) == set(names)
    assert values["Parameters/Ra/Low"] == pytest.approx(6.6 - 2 * 0.033)
    assert values["Parameters/Ra/Alarm Level"] == 1 and values["Parameters/Ra/RUL"] is None
    assert values["Diagnosis/Fault"] == "winding" and values["Diagnosis/Probability"] == 90.0
    assert values["Counters/gaps"] == 2 and values["Window/Index"] == 4


@pytest.mark.parametrize("line, key", [
    ('group_id = "plant/1"', "group_id"),
    ('edge_node_id = "edge+1"', "edge_node_id"),
    ('device_id = "#"', "device_id"),
    ('primary_host_id = ""', "primary_host_id"),
    ("qos = 2", "qos"),
])
def test_check_config_refuses_ids_sparkplug_does_not_allow(tmp_path: Path, line: str,
                                                           key: str) -> None:
    with pytest.raises(ConfigError, match=rf"outputs\.sparkplug\.{key}") as exc:
        load_config(sim_config(tmp_path, extra=f"\n[outputs.sparkplug]\n{line}\n"))
    (named,) = [ln for ln in str(exc.value).splitlines() if "outputs.sparkplug" in ln]
    assert "topic level" in named or "qos" in named, named


def test_the_example_config_passes_check_config() -> None:
    from click.testing import CliRunner

    from twinwatch.cli import main

    result = CliRunner().invoke(main, ["check-config",
                                       str(ROOT / "config" / "dc-motor-sim-sparkplug.toml")])
    assert result.exit_code == 0, result.output


def test_check_config_on_a_gateway_directory_names_the_machines_edge_node_clashes(
        tmp_path: Path) -> None:
    """Machines of one gateway that are devices of one edge node must set its session keys
    alike and take device ids of their own: ``check-config`` on the directory says so, naming
    the file and the key (the gateway refuses the second at its start)."""
    from click.testing import CliRunner

    from twinwatch.cli import main

    from .helpers.cli import machine_config

    machines = tmp_path / "machines"
    machines.mkdir()
    node = '\n[outputs.sparkplug]\ngroup_id = "plant1"\nedge_node_id = "line1"\n'
    for name, extra in (("m1", ""), ("m2", "")):
        path = machine_config(machines, name, port=None, realtime=False)
        path.write_text(path.read_text() + node + extra)

    def check() -> Any:
        return CliRunner().invoke(main, ["check-config", str(machines)])

    r = check()
    assert r.exit_code == 0 and "2 of 2 machine configurations OK" in r.output, r.output
    m2 = machines / "m2.toml"
    m2.write_text(m2.read_text() + 'keepalive = 17\ndevice_id = "m1"\n')
    r = check()
    assert r.exit_code == 1, r.output
    lines = [ln for ln in r.output.splitlines() if "m2.toml: outputs.sparkplug" in ln]
    assert len(lines) == 2, r.output
    assert "outputs.sparkplug.keepalive: machine 'm2' is a device of edge node plant1/line1" \
        in lines[0] and f"({machines / 'm1.toml'})" in lines[0]
    assert "outputs.sparkplug.device_id: 'm1' is already a device" in lines[1]
    assert "1 of 2 machine configurations OK" in r.output


# -- against Mosquitto --------------------------------------------------------------------------
@needs_mosquitto
def test_a_run_births_data_by_alias_and_ndeath_on_a_clean_stop(tmp_path: Path,
                                                             broker: Broker) -> None:
    host = HostDecoder.start(broker.port)
    cfg = sim_config(tmp_path, duration=20.0, extra=table(broker.port))
    code, out, err = finish(twinwatch(cfg, cwd=tmp_path))
    assert code == 0, err
    windows = stored(tmp_path / "state.sqlite")
    assert len(windows) == 10
    host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 20, "the NDEATH")
    counts = host.check_session()
    assert counts == {"NBIRTH": 1, "DBIRTH": 1, "DDATA": 10, "DDEATH": 1, "NDEATH": 1}, counts
    kinds = host.kinds()
    assert kinds[:2] == ["NBIRTH", "DBIRTH"] and kinds[-2:] == ["DDEATH", "NDEATH"]
    assert [(r, w) for r, w, _ in host.windows()] == windows   # each once, in order
    assert not any(h for _, _, h in host.windows())
    topics = {d.kind: d.topic for d in host.messages()}
    assert topics["DDATA"] == "spBv1.0/plant1/DDATA/dc-motor-sim/dc-motor-sim"
    assert topics["NBIRTH"] == "spBv1.0/plant1/NBIRTH/dc-motor-sim"
    (dbirth,) = [d.payload for d in host.messages() if d.kind == "DBIRTH"]
    by_name = {m.name: m for m in dbirth.metrics}
    ra = by_name["Parameters/Ra/Value"]
    assert ra.datatype == DATATYPE["Double"] and list(ra.properties.keys) == ["engUnit"]
    assert ra.properties.values[0].string_value == "ohm"
    assert 5.0 < ra.double_value < 8.0
    assert by_name["Parameters/Ra/Alarm"].string_value == "normal"   # the config's rule
    assert by_name["Diagnosis/Status"].datatype == DATATYPE["String"]
    assert "10 windows delivered" in out, out
    host.close()


def _open(tmp_path: Path, port: int, **kw: Any) -> tuple[SparkplugPublisher, Any]:
    from twinwatch.sinks.base import SinkContext
    from twinwatch.sinks.store import StateStore

    store = StateStore(tmp_path / "s.sqlite", prune_every=0)
    cfg = SparkplugConfig(port=port, keepalive=5, reconnect_max=1.0, group_id="g", **kw)
    pub = SparkplugPublisher.open("sparkplug", cfg, SinkContext(
        machine="m1", model="dc_motor", parameters={"Ra": "ohm"}, cwd=tmp_path,
        outbox=lambda name: store.outbox(name, "m1")))
    return pub, store


@needs_mosquitto
def test_ncmd_rebirth_and_a_broker_restart_replays_historical(tmp_path: Path,
                                                              broker: Broker) -> None:
    import paho.mqtt.client as mqtt

    host = HostDecoder.start(broker.port)
    pub, store = _open(tmp_path, broker.port)
    try:
        for w in range(3):
            pub.write(stored_window(store, w))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 3, 20, "3 DDATA")
        # Node Control/Rebirth, as Ignition sends it
        cmd = Payload(timestamp=int(time.time() * 1000))
        cmd.metrics.add(name="Node Control/Rebirth", datatype=DATATYPE["Boolean"],
                        boolean_value=True)
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-scada")
        c.connect("127.0.0.1", broker.port)
        c.loop_start()
        c.publish("spBv1.0/g/NCMD/m1", cmd.SerializeToString(), qos=1).wait_for_publish(5)
        c.loop_stop()
        c.disconnect()
        host.wait(lambda ms: [d.kind for d in ms].count("NBIRTH") == 2, 20, "the rebirth")
        pub.write(stored_window(store, 3))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 4, 20, "4 DDATA")
        assert pub.counters()["rebirths"] == 1

        # the broker away while 4 windows are stored: sent after the new births, historical
        # but the newest
        host.close()
        broker.stop()
        for w in range(4, 8):
            pub.write(stored_window(store, w))
        time.sleep(1.0)
        broker.start()
        host = HostDecoder.start(broker.port)
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) >= 4, 30, "the backlog")
    finally:
        pub.close()
        store.close()
    host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 10, "the NDEATH")
    counts = host.check_session()
    assert counts["NBIRTH"] == 1 and counts["DBIRTH"] == 1 and counts["NDEATH"] == 1
    nbirth = next(d.payload for d in host.messages() if d.kind == "NBIRTH")
    # a new will on every connection attempt (the first connection's was 0)
    assert [m.long_value for m in nbirth.metrics if m.name == "bdSeq"][0] >= 1
    got = host.windows()
    assert [w for _, w, _ in got] == [4, 5, 6, 7]
    assert all(h for _, _, h in got)     # stored while the broker was away: replays
    assert pub.counters()["delivered"] == 8 and pub.counters()["pending"] == 0
    host.close()


@needs_mosquitto
def test_the_primary_host_state_is_waited_for(tmp_path: Path, broker: Broker) -> None:
    import paho.mqtt.client as mqtt

    host = HostDecoder.start(broker.port)
    scada = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-scada")
    scada.connect("127.0.0.1", broker.port)
    scada.loop_start()

    def state(online: bool) -> None:
        payload = json.dumps({"online": online, "timestamp": int(time.time() * 1000)})
        scada.publish("spBv1.0/STATE/scada", payload, qos=1, retain=True).wait_for_publish(5)

    state(False)
    pub, store = _open(tmp_path, broker.port, primary_host_id="scada")
    try:
        for w in range(2):
            pub.write(stored_window(store, w))
        time.sleep(2.0)
        assert [d.kind for d in host.messages()] == ["STATE"]   # nothing while it is offline
        state(True)
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 2, 20, "2 DDATA")
        state(False)   # the host leaves: NDEATH, the windows wait
        host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 20, "the NDEATH")
        pub.write(stored_window(store, 2))
        time.sleep(1.5)
        assert sum(d.kind == "DDATA" for d in host.messages()) == 2
        state(True)
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 3, 20, "the window kept")
    finally:
        pub.close()
        store.close()
        scada.loop_stop()
        scada.disconnect()
    counts = host.check_session()
    assert counts["NBIRTH"] == 2 and counts["NDEATH"] == 2
    bd = [next(m.long_value for m in d.payload.metrics if m.name == "bdSeq")
          for d in host.messages() if d.kind == "NBIRTH"]
    assert bd[1] == bd[0] + 1    # a new connection
    host.close()


@needs_mosquitto
@pytest.mark.slow
def test_kill_9_gives_the_will_and_the_restart_replays_the_rest(tmp_path: Path,
                                                               broker: Broker) -> None:
    host = HostDecoder.start(broker.port)
    long = sim_config(tmp_path, duration=600.0, extra=table(broker.port),
                      **{"realtime = false": "realtime = true"})
    proc = twinwatch(long, cwd=tmp_path)
    try:
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) >= 2, 120, "2 DDATA")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 20, "the will (NDEATH)")
    first = host.check_session()
    assert first["NDEATH"] == 1 and "DDEATH" not in first   # the broker's will, no DDEATH
    short = sim_config(tmp_path, duration=6.0, extra=table(broker.port))
    code, out, err = finish(twinwatch(short, "--fresh", cwd=tmp_path))
    assert code == 0, err
    host.wait(lambda ms: sum(d.kind == "NDEATH" for d in ms) == 2, 20, "the second NDEATH")
    host.check_session()
    got = host.windows()
    windows = stored(tmp_path / "state.sqlite")
    assert {(r, w) for r, w, _ in got} == set(windows), "every stored window delivered"
    assert len(got) - len(set(got)) <= 10     # at most the inflight limit sent twice
    host.close()


@needs_mosquitto
def test_a_broker_refusing_the_client_is_one_line(tmp_path: Path, caplog: Any) -> None:
    """Mosquitto with an ACL that lets the client connect only with a password: the refusal
    names outputs.sparkplug and what to allow, once."""
    d = tmp_path / "broker"
    b = Broker(d, anonymous=False)
    b.start()
    try:
        with caplog.at_level("ERROR", logger="twinwatch.sinks.sparkplug"):
            pub, store = _open(tmp_path, b.port)
            try:
                time.sleep(3.0)
            finally:
                pub.close()
                store.close()
    finally:
        b.stop()
    lines = [r.getMessage() for r in caplog.records if "outputs.sparkplug" in r.getMessage()]
    assert len(lines) == 1 and "refused" in lines[0] and "NDEATH" in lines[0], lines


@needs_mosquitto
@pytest.mark.slow
def test_a_reload_adding_and_removing_a_machine_gives_dbirth_and_ddeath(
        tmp_path: Path, broker: Broker) -> None:
    """``twinwatch run DIR`` (one process): SIGHUP after m2.toml is removed and m3.toml added:
    m2's DDEATH and NDEATH, m3's NBIRTH and DBIRTH; m1 untouched (no new birth)."""
    import subprocess
    import sys

    from .helpers.cli import machine_config

    machines = tmp_path / "machines"
    machines.mkdir()
    for name in ("m1", "m2"):
        path = machine_config(machines, name, port=None)
        path.write_text(path.read_text() + table(broker.port))
    host = HostDecoder.start(broker.port)
    proc = subprocess.Popen([sys.executable, "-m", "twinwatch", "run", "--no-progress",
                             "--workers", "1", str(machines)], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def ddata(node: str) -> int:
        return sum(d.kind == "DDATA" and d.topic.split("/")[3] == node
                   for d in host.messages())

    try:
        host.wait(lambda ms: ddata("m1") >= 1 and ddata("m2") >= 1, 120, "m1's and m2's data")
        (machines / "m2.toml").unlink()
        path = machine_config(machines, "m3", port=None)
        path.write_text(path.read_text() + table(broker.port))
        proc.send_signal(signal.SIGHUP)
        host.wait(lambda ms: ddata("m3") >= 1, 120, "m3's data after the SIGHUP")
        host.wait(lambda ms: any(d.topic == "spBv1.0/plant1/NDEATH/m2" for d in ms), 30,
                  "m2's NDEATH")
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    host.check_session()
    topics = [d.topic for d in host.messages()]
    m2 = [t.split("/")[2] for t in topics if t.split("/")[3] == "m2"]
    assert m2[:2] == ["NBIRTH", "DBIRTH"] and m2[-2:] == ["DDEATH", "NDEATH"], m2
    m3 = [t.split("/")[2] for t in topics if t.split("/")[3] == "m3"]
    assert m3[:2] == ["NBIRTH", "DBIRTH"] and m3[-2:] == ["DDEATH", "NDEATH"], m3
    m1 = [t.split("/")[2] for t in topics if t.split("/")[3] == "m1"]
    assert m1.count("NBIRTH") == 1, m1      # the reload kept m1's output open
    host.close()


@needs_mosquitto
@pytest.mark.slow
def test_300_windows_with_a_broker_restart_a_kill_9_and_a_rebirth(tmp_path: Path,
                                                                  broker: Broker) -> None:
    """Issue 38's done-when: a host decoder over a run of about 300 windows with the broker
    restarted in the middle and the daemon killed with SIGKILL later, then started again: every
    stored window delivered (a few sent twice at most: those in flight), the replays flagged
    historical, ``seq`` without gaps per birth, a DBIRTH before any DDATA, the will's NDEATH on
    the kill, a rebirth on NCMD."""
    import paho.mqtt.client as mqtt

    host = HostDecoder(Subscriber(broker.port, ["spBv1.0/#"], client_id="test-host-300",
                                  persistent=True))   # the broker queues for it while away
    # the plant as fast as it runs (11 windows a second on a quiet box, 3-4 on one loaded by
    # other work) and the output held to 2 windows a second: the outbox falls behind, the
    # kill leaves windows undelivered; the second start at a faster pace catches up. The
    # first run must outlive 60 DDATA at 2 a second and the broker's restart (about 45 s of
    # wall time): 1200 windows of plant, not 300 (which a quiet box ran in 27 s, and the
    # daemon then stopped, its close_timeout over, before the 60th DDATA)
    # the machine a device of the edge node line1-edge (the process), not an edge node of its own
    node = 'edge_node_id = "line1-edge"\n'
    first = sim_config(tmp_path, duration=2400.0, extra=table(broker.port, node + "rate = 2.0\n"),
                       **{'scenario = "resistance_degradation"':
                          'scenario = "resistance_degradation"\nfault_period = 1200.0'})

    def ddata() -> int:
        assert proc.poll() is None, "the daemon stopped before the test was done with it"
        return sum(d.kind == "DDATA" for d in host.messages())

    proc = twinwatch(first, cwd=tmp_path)
    try:
        host.wait(lambda ms: ddata() >= 30, 300, "30 DDATA")
        broker.stop()
        time.sleep(3.0)
        broker.start()
        host.wait(lambda ms: [d.kind for d in ms].count("NBIRTH") >= 2, 60, "the births again")
        host.wait(lambda ms: ddata() >= 60, 300, "60 DDATA")
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    except AssertionError as exc:   # what the daemon said, for the failure's report
        proc.kill()
        raise AssertionError(f"{exc}; the daemon's log: {proc.communicate()[1][-4000:]}") \
            from None
    finally:
        if proc.poll() is None:
            proc.kill()
    host.wait(lambda ms: ms[-1].kind == "NDEATH", 30, "the will (NDEATH) after the kill")
    # the backlog and new windows to make 300 at least (150 or more: a window is 2 s of
    # plant time): a faster pace and time at the stop to catch up
    before = len(stored(tmp_path / "state.sqlite"))
    second = sim_config(tmp_path, duration=max(300.0, 2.0 * (310 - before)), extra=table(
        broker.port, node + "rate = 100.0\nclose_timeout = 60.0\n"))
    proc = twinwatch(second, "--fresh", cwd=tmp_path)
    try:
        host.wait(lambda ms: [d.kind for d in ms].count("NBIRTH") >= 3, 120, "the restart")
        cmd = Payload(timestamp=int(time.time() * 1000))
        cmd.metrics.add(name="Node Control/Rebirth", datatype=DATATYPE["Boolean"],
                        boolean_value=True)
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-scada-300")
        c.connect("127.0.0.1", broker.port)
        c.loop_start()
        c.publish("spBv1.0/plant1/NCMD/line1-edge", cmd.SerializeToString(),
                  qos=1).wait_for_publish(5)
        c.loop_stop()
        c.disconnect()
        code, out, err = finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0, err
    host.wait(lambda ms: ms[-1].kind == "NDEATH", 30, "the NDEATH of the clean stop")
    counts = host.check_session()
    windows = stored(tmp_path / "state.sqlite")
    got = host.windows()
    assert len(windows) >= 300, len(windows)
    assert {(r, w) for r, w, _ in got} == set(windows), "every stored window delivered"
    repeats = len(got) - len({(r, w) for r, w, _ in got})
    assert repeats <= 20, repeats           # at most the windows in flight, per disruption
    # the births: the start, after the broker restart, the second start, the rebirth; the
    # deaths: the kill's will and the clean stop, and the broker restart's will when the
    # broker published it before the new connection's NBIRTH (Mosquitto does on SIGTERM)
    assert counts["NBIRTH"] == 4 and counts["DBIRTH"] == 4, counts
    assert counts["NDEATH"] in (2, 3), counts
    runs = sorted({r for r, _ in windows}, key=[r for r, _ in windows].index)
    assert len(runs) == 2
    assert {d.topic for d in host.messages() if d.kind == "DDATA"} == {
        "spBv1.0/plant1/DDATA/line1-edge/dc-motor-sim"}
    nbirths = [d.payload for d in host.messages() if d.kind == "NBIRTH"]
    bd = [next(m.long_value for m in p.metrics if m.name == "bdSeq") for p in nbirths]
    assert bd[2] > bd[1], bd   # kept across the kill: the restart's NBIRTH a bdSeq after
    # the first run's windows the kill left undelivered came with the second run: replays
    births, late = 0, []
    for d in host.messages():
        births += d.kind == "NBIRTH"
        if d.kind == "DDATA" and births >= 3:   # the second start's connection
            v = {host.aliases[m.alias]: m for m in d.payload.metrics}
            if v["Window/Run"].string_value == runs[0]:
                late.append((v["Window/Index"].long_value, v["Window/Index"].is_historical))
    assert late and all(h for _, h in late), late
    print(f"300-window run: {len(windows)} windows stored, {len(got)} DDATA received, "
          f"{repeats} repeats, {len(late)} replayed after the restart, counts {counts}")
    host.close()


@needs_mosquitto
@pytest.mark.slow
def test_a_broker_whose_acl_drops_the_births_and_the_will_is_one_line(tmp_path: Path,
                                                                      caplog: Any) -> None:
    """Mosquitto 2.0 accepts a connection whose will its ACL forbids and acknowledges the
    publishes it drops (MQTT 3.1.1 has no refusal for either): the NBIRTH not heard back is
    one error line naming outputs.sparkplug and the topics to allow, and a problem (STATUS)."""
    d = tmp_path / "broker"
    d.mkdir()
    (d / "acl").write_text("topic readwrite other/#\n")
    b = Broker(d, extra=f"acl_file {d / 'acl'}\n")
    b.start()
    try:
        with caplog.at_level("ERROR", logger="twinwatch.sinks.sparkplug"):
            pub, store = _open(tmp_path, b.port)
            try:
                pub.write(stored_window(store, 0))
                deadline = time.monotonic() + 15
                while pub.problem is None and time.monotonic() < deadline:
                    time.sleep(0.2)
                problem = pub.problem
            finally:
                pub.close()
                store.close()
    finally:
        b.stop()
    lines = [r.getMessage() for r in caplog.records if "outputs.sparkplug" in r.getMessage()]
    assert len(lines) == 1 and "spBv1.0/g/#" in lines[0] and "will" in lines[0], lines
    assert problem is not None and "NBIRTH" in problem


@needs_mosquitto
def test_qos_0_as_sparkplug_says_still_counts_every_window(tmp_path: Path,
                                                          broker: Broker) -> None:
    host = HostDecoder.start(broker.port)
    pub, store = _open(tmp_path, broker.port, qos=0)
    try:
        for w in range(5):
            pub.write(stored_window(store, w))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 5, 20, "5 DDATA")
    finally:
        pub.close()
        store.close()
    host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 10, "the NDEATH")
    host.check_session()
    assert [w for _, w, _ in host.windows()] == list(range(5))
    assert pub.counters()["delivered"] == 5 and pub.counters()["pending"] == 0
    host.close()


# -- issue 56: a restart's births, write attempts, seq past 255 ---------------------------------
def _run_window(store: Any, run: str, w: int, machine: str = "m1") -> Any:
    """Store window ``w`` of ``run`` as the gate does (its alarm: Ra in alarm in run r1) and
    return what write() gets."""
    from types import SimpleNamespace

    level = "alarm" if run == "r1" else "normal"
    doc = json.dumps({"machine": machine, "run": run, "window": w, "t_start": 2.0 * w,
                      "t_end": 2.0 * w + 1.99, "parameters": {"Ra": {
                          "value": 7.5 if run == "r1" else 6.5, "unit": "ohm",
                          "deviation_pct": 15.0 if run == "r1" else 0.0,
                          "status": "estimated"}},
                      "alarms": {"Ra": {"level": level, "since_t": 0.0, "since_window": 0,
                                        "deviation_pct": 15.0, "pending": None}}})
    assert store.save_window({"machine": machine, "window": w, "t_start": 2.0 * w,
                              "t_end": 2.0 * w + 1.99}, None, doc=doc)
    return SimpleNamespace(health=SimpleNamespace(window=w), health_json=doc, events=[])


def _open_run(tmp_path: Path, port: int, store: Any, run: str) -> SparkplugPublisher:
    from twinwatch.sinks.base import AlarmBands, SinkContext

    cfg = SparkplugConfig(port=port, keepalive=5, reconnect_max=1.0, group_id="g")
    return SparkplugPublisher.open("sparkplug", cfg, SinkContext(
        machine="m1", model="dc_motor", parameters={"Ra": "ohm"}, cwd=tmp_path, run=run,
        alarm_bands={"Ra": AlarmBands(alarm_high=10.0, alarm_low=-10.0)},
        outbox=lambda name: store.outbox(name, "m1")))


def _dbirth_runs(host: HostDecoder) -> list[tuple[int, str | None]]:
    """(the NBIRTH it follows, its Window/Run or None when null) of every DBIRTH."""
    out, births = [], 0
    for d in host.messages():
        births += d.kind == "NBIRTH"
        if d.kind == "DBIRTH":
            (run,) = [m for m in d.payload.metrics if m.name == "Window/Run"]
            out.append((births, None if run.is_null else run.string_value))
    return out


@needs_mosquitto
def test_a_new_run_never_births_with_the_previous_runs_window(tmp_path: Path,
                                                              broker: Broker) -> None:
    """Issue 56: run r1 ends with Ra in alarm and one window not delivered (a kill); the next
    start is a new run r2. Its births carry r2's first window, or nulls until it comes (the
    undelivered r1 window then replayed, historical); never r1's last window (before: the
    first DBIRTH of every restart carried the old run id, Ra in alarm, for 1.5 s)."""
    from twinwatch.sinks.store import StateStore

    host = HostDecoder.start(broker.port)
    store = StateStore(tmp_path / "s.sqlite", prune_every=0)
    try:
        pub = _open_run(tmp_path, broker.port, store, "r1")
        try:
            for w in range(3):
                pub.write(_run_window(store, "r1", w))
            host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 3, 20, "r1's 3 DDATA")
        finally:
            pub.close()
        _run_window(store, "r1", 3)   # stored, never delivered: the process was killed
        pub = _open_run(tmp_path, broker.port, store, "r2")
        try:
            host.wait(lambda ms: [d.kind for d in ms].count("NBIRTH") == 2, 20, "r2's NBIRTH")
            host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 4, 20, "r1's last")
            pub.write(_run_window(store, "r2", 0))
            host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 5, 20, "r2's first")
        finally:
            pub.close()
    finally:
        store.close()
    host.wait(lambda ms: [d.kind for d in ms].count("NDEATH") == 2, 20, "the NDEATH")
    host.check_session()
    births = _dbirth_runs(host)
    assert births[0] == (1, "r1")
    assert [r for n, r in births if n == 2] and all(r in (None, "r2") for n, r in births
                                                    if n == 2), births
    got = host.windows()
    assert [(r, w) for r, w, _ in got] == [("r1", 0), ("r1", 1), ("r1", 2), ("r1", 3),
                                           ("r2", 0)]
    assert got[3][2] and not got[4][2]   # r1's last a replay (historical), r2's live
    host.close()


@needs_mosquitto
def test_a_command_that_writes_is_refused_once_per_topic_naming_its_metrics(
        tmp_path: Path, broker: Broker, caplog: Any) -> None:
    """Issue 56: a DCMD setting a metric and an NCMD other than Rebirth: nothing written, no
    birth, one WARNING per topic naming the metrics (before: the DCMD at INFO, invisible at
    the default level; the NCMD without a line), counted in commands_refused."""
    import logging

    import paho.mqtt.client as mqtt

    caplog.set_level(logging.INFO)
    host = HostDecoder.start(broker.port)
    pub, store = _open(tmp_path, broker.port)
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="test-scada-write")
    c.connect("127.0.0.1", broker.port)
    c.loop_start()
    try:
        pub.write(stored_window(store, 0))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 1, 20, "a DDATA")

        def send(topic: str, **metrics: Any) -> None:
            cmd = Payload(timestamp=int(time.time() * 1000))
            for name, value in metrics.items():
                m = cmd.metrics.add(name=name.replace("__", "/"))
                if isinstance(value, bool):
                    m.datatype, m.boolean_value = DATATYPE["Boolean"], value
                else:
                    m.datatype, m.double_value = DATATYPE["Double"], value
            c.publish(topic, cmd.SerializeToString(), qos=1).wait_for_publish(5)

        for _ in range(2):
            send("spBv1.0/g/DCMD/m1/m1", Parameters__Ra__Nominal=7.0)
            send("spBv1.0/g/NCMD/m1", **{"Node Control__Reboot": True})
        host.wait(lambda ms: sum(d.kind in ("DCMD", "NCMD") for d in ms) == 4, 20,
                  "the 4 commands")
        pub.write(stored_window(store, 1))   # the node goes on: a window after the commands
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 2, 20, "the next DDATA")
        refused = pub.counters()["commands_refused"]
    finally:
        c.loop_stop()
        c.disconnect()
        pub.close()
        store.close()
    said = [r for r in caplog.records if "writes" in r.getMessage()
            and r.levelno == logging.WARNING]
    assert len(said) == 2, [r.getMessage() for r in said]
    assert "DCMD on spBv1.0/g/DCMD/m1/m1 writes Parameters/Ra/Nominal: refused" in \
        said[0].getMessage()
    assert "NCMD on spBv1.0/g/NCMD/m1 writes Node Control/Reboot: refused" in \
        said[1].getMessage()
    assert refused == 4
    counts = host.check_session()
    assert counts["NBIRTH"] == 1 and counts["DBIRTH"] == 1, counts   # no birth, nothing else
    host.close()


@needs_mosquitto
def test_seq_wraps_past_255_within_one_connection_without_a_gap(tmp_path: Path,
                                                                 broker: Broker) -> None:
    """Issue 56: 300 windows in one connection (seq 0 .. 255, 0 .. 45): every message handed
    to paho has the next seq (nothing built and not sent), and a host whose session the
    broker keeps (QoS 1, persistent: it misses nothing even across its own reconnection)
    sees the NBIRTH, the DBIRTH and 300 DDATA without a gap. Rules out the one seq gap seen
    once inside a connection (issue 56) on twinwatch's side."""
    host = HostDecoder(Subscriber(broker.port, ["spBv1.0/#"], client_id="test-host-wrap",
                                  persistent=True))
    pub, store = _open(tmp_path, broker.port)
    handed: list[tuple[str, int]] = []
    try:
        pub.write(stored_window(store, 0))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 1, 20, "the first DDATA")
        node = pub._node
        client = node.client
        publish = client.publish

        def recording(topic: str, payload: bytes, *a: Any, **kw: Any) -> Any:
            handed.append((topic.split("/")[2], Payload.FromString(payload).seq))
            return publish(topic, payload, *a, **kw)

        client.publish = recording  # type: ignore[method-assign]
        for w in range(1, 300):
            pub.write(stored_window(store, w))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 300, 120, "300 DDATA")
        assert node.client is client and node.connects == 1   # one connection throughout
    finally:
        pub.close()
        store.close()
    host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 20, "the NDEATH")
    counts = host.check_session()   # asserts each seq is the one after the last, mod 256
    assert counts == {"NBIRTH": 1, "DBIRTH": 1, "DDATA": 300, "DDEATH": 1, "NDEATH": 1}, counts
    seqs = [seq for kind, seq in handed if kind != "NDEATH"]
    assert seqs == [(seqs[0] + k) % 256 for k in range(len(seqs))]
    assert len(seqs) >= 300 and 255 in seqs and seqs.index(255) < len(seqs) - 1
    ddata = [d.payload.seq for d in host.messages() if d.kind == "DDATA"]
    assert ddata[:2] == [2, 3] and ddata[253:256] == [255, 0, 1], ddata[250:258]
    assert [w for _, w, _ in host.windows()] == list(range(300))
    host.close()
