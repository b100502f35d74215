"""Sparkplug B with the process as the edge node and each machine a device (issue 38, item 1):
one MQTT session for every machine of a process naming the same broker, group and edge node;
``seq`` one count across the devices' messages; DBIRTH, DDEATH per device; NDEATH after the
last device; NCMD answered with NBIRTH and every DBIRTH, DCMD ``Device Control/Rebirth`` with
that device's; ``bdSeq`` kept across restarts; a gateway's worker processes never split an
edge node. Against a real Mosquitto, read by the host decoder of ``test_sparkplug``.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from twinwatch.errors import PublisherError
from twinwatch.sinks.base import SharedResources, SinkContext
from twinwatch.sinks.sparkplug import SparkplugConfig, SparkplugPublisher
from twinwatch.sinks.sparkplug_pb import DATATYPE

from .helpers.mqtt import Broker, Subscriber, needs_mosquitto, running_broker, stored_window
from .helpers.sparkplug import HostDecoder, Payload, stored


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    yield from running_broker(tmp_path / "broker")


def _device(tmp_path: Path, shared: SharedResources, machine: str, port: int,
            **kw: Any) -> tuple[SparkplugPublisher, Any]:
    from twinwatch.sinks.store import StateStore

    store = StateStore(tmp_path / f"{machine}.sqlite", prune_every=0)
    cfg = SparkplugConfig(**{"port": port, "keepalive": 5, "reconnect_max": 1.0,
                             "group_id": "g", "edge_node_id": "edge", **kw})
    try:
        pub = SparkplugPublisher.open("sparkplug", cfg, SinkContext(
            machine=machine, model="dc_motor", parameters={"Ra": "ohm"}, cwd=tmp_path,
            outbox=lambda name: store.outbox(name, machine), shared=shared))
    except BaseException:
        store.close()
        raise
    return pub, store


def _command(port: int, topic: str, metric: str) -> None:
    import paho.mqtt.client as mqtt

    cmd = Payload(timestamp=int(time.time() * 1000))
    cmd.metrics.add(name=metric, datatype=DATATYPE["Boolean"], boolean_value=True)
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"test-scada-{time.time_ns()}")
    c.connect("127.0.0.1", port)
    c.loop_start()
    c.publish(topic, cmd.SerializeToString(), qos=1).wait_for_publish(5)
    c.loop_stop()
    c.disconnect()


def _kinds(host: HostDecoder) -> list[tuple[str, str]]:
    """(kind, device or "") of every message the edge node published."""
    return [(d.kind, (d.topic.split("/") + [""])[4]) for d in host.messages()
            if d.kind not in ("STATE", "NCMD", "DCMD")]


def _bd_seq(payload: Any) -> int:
    return int(next(m.long_value for m in payload.metrics if m.name == "bdSeq"))


@needs_mosquitto
def test_two_machines_are_devices_of_one_edge_node_on_one_session(tmp_path: Path,
                                                                  broker: Broker) -> None:
    host = HostDecoder.start(broker.port)
    shared = SharedResources(tmp_path)
    m1, s1 = _device(tmp_path, shared, "m1", broker.port)
    m2, s2 = _device(tmp_path, shared, "m2", broker.port)
    stores = [s1, s2]
    try:
        assert m1._node is m2._node and shared.references(m1._key) == 2   # one session
        for w in range(3):
            m1.write(stored_window(s1, w, "m1"))
            m2.write(stored_window(s2, w, "m2"))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 6, 20, "6 DDATA")
        # NCMD: NBIRTH and both DBIRTHs again
        _command(broker.port, "spBv1.0/g/NCMD/edge", "Node Control/Rebirth")
        host.wait(lambda ms: sum(d.kind == "DBIRTH" for d in ms) == 4, 20, "the rebirth")
        # DCMD Device Control/Rebirth to m2: m2's DBIRTH only
        _command(broker.port, "spBv1.0/g/DCMD/edge/m2", "Device Control/Rebirth")
        host.wait(lambda ms: sum(d.kind == "DBIRTH" for d in ms) == 5, 20, "m2's rebirth")
        assert _kinds(host)[-1] == ("DBIRTH", "m2")
        m1.write(stored_window(s1, 3, "m1"))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 7, 20, "7 DDATA")
        m2.close()   # a machine leaves: its DDEATH, the node stays
        host.wait(lambda ms: any(d.kind == "DDEATH" for d in ms), 20, "m2's DDEATH")
        time.sleep(0.5)
        assert "NDEATH" not in [k for k, _ in _kinds(host)]
        # a machine joins the live node: its DBIRTH with its first window, no NBIRTH
        m3, s3 = _device(tmp_path, shared, "m3", broker.port)
        stores.append(s3)
        m3.write(stored_window(s3, 0, "m3"))
        host.wait(lambda ms: sum(d.kind == "DDATA" for d in ms) == 8, 20, "m3's DDATA")
        m3.close()
        m1.close()
    finally:
        for p in (m1, m2):
            p.close()
        for s in stores:
            s.close()
    host.wait(lambda ms: any(d.kind == "NDEATH" for d in ms), 20, "the NDEATH")
    counts = host.check_session()   # seq one count across the devices, births before data
    assert counts == {"NBIRTH": 2, "DBIRTH": 6, "DDATA": 8, "DDEATH": 3, "NDEATH": 1,
                      "NCMD": 1, "DCMD": 1}, counts
    kinds = _kinds(host)
    assert kinds[0] == ("NBIRTH", "")   # one session: one NBIRTH for both machines
    for m in ("m1", "m2", "m3"):        # each device's first message is its DBIRTH
        assert next(k for k, dev in kinds if dev == m) == "DBIRTH", (m, kinds)
    assert kinds[-3:] == [("DDEATH", "m3"), ("DDEATH", "m1"), ("NDEATH", "")], kinds[-3:]
    assert [w for _, w, _ in host.windows("m1")] == [0, 1, 2, 3]
    assert [w for _, w, _ in host.windows("m2")] == [0, 1, 2]
    assert [w for _, w, _ in host.windows("m3")] == [0]
    seqs = [d.payload.seq for d in host.messages()
            if d.kind not in ("NDEATH", "STATE", "NCMD", "DCMD")]
    assert len(seqs) == 19 and seqs[:3] == [0, 1, 2]
    # bdSeq kept across restarts: the next start's NBIRTH carries the one after
    bd = _bd_seq(next(d.payload for d in host.messages() if d.kind == "NBIRTH"))
    assert (tmp_path / "sparkplug-g-edge.bdseq").read_text().strip() == str(bd)
    again, s4 = _device(tmp_path, SharedResources(tmp_path), "m1", broker.port)
    try:
        host.wait(lambda ms: sum(d.kind == "NBIRTH" for d in ms) == 3, 20, "a new NBIRTH")
    finally:
        again.close()
        s4.close()
    nbirths = [d.payload for d in host.messages() if d.kind == "NBIRTH"]
    assert _bd_seq(nbirths[-1]) == (bd + 1) % 256
    host.close()


@needs_mosquitto
def test_devices_of_one_edge_node_must_share_its_session_settings(tmp_path: Path,
                                                                  broker: Broker) -> None:
    shared = SharedResources(tmp_path)
    m1, s1 = _device(tmp_path, shared, "m1", broker.port)
    try:
        with pytest.raises(PublisherError) as exc:
            _device(tmp_path, shared, "m2", broker.port, keepalive=7)
        line = str(exc.value)
        assert "\n" not in line and line.startswith("outputs.sparkplug.keepalive:"), line
        assert "'m1'" in line and "edge_node_id" in line
        with pytest.raises(PublisherError, match=r"^outputs\.sparkplug\.device_id: 'm1' is "
                           r"already machine 'm1'"):
            _device(tmp_path, shared, "m9", broker.port, device_id="m1")
        assert shared.references(m1._key) == 1     # the refused ones released their share
        # another edge node on the same broker: a session of its own
        other, s2 = _device(tmp_path, shared, "m2", broker.port, edge_node_id="edge2",
                            keepalive=7)
        assert other._node is not m1._node
        other.close()
        s2.close()
    finally:
        m1.close()
        s1.close()
    assert shared.keys() == []


def test_a_gateway_never_splits_an_edge_node_over_worker_processes(tmp_path: Path) -> None:
    """Placement (``--workers 2``): the machines naming one edge node go to one worker (its one
    MQTT session), those naming another or none are spread."""
    from twinwatch.daemon.workers import place, worker_processes

    from .helpers.cli import machine_config

    d = tmp_path / "machines"
    d.mkdir()
    spb = '\n[outputs.sparkplug]\ngroup_id = "plant1"\n'
    files = {}
    for name, edge in (("a1", "line1"), ("a2", "line1"), ("a3", "line1"), ("b1", "line2"),
                       ("b2", "line2"), ("c1", None)):
        path = machine_config(d, name, port=None)
        extra = spb + (f'edge_node_id = "{edge}"\n' if edge else "")
        path.write_text(path.read_text() + extra)
        files[name] = path
    workers = place(sorted(files.values()), [], 2)
    where = {p.stem: k for k, ps in enumerate(workers) for p in ps}
    assert where["a1"] == where["a2"] == where["a3"]
    assert where["b1"] == where["b2"] != where["a1"]
    assert worker_processes(d, 2) == 2
    for name in ("b1", "b2", "c1"):   # every machine on line1: one worker whatever --workers
        files[name].write_text(files[name].read_text().replace('"line2"', '"line1"')
                               + ('edge_node_id = "line1"\n' if name == "c1" else ""))
    assert worker_processes(d, 2) == 1


@needs_mosquitto
@pytest.mark.slow
def test_a_gateway_is_one_edge_node_across_a_reload_a_kill_9_and_a_restart(
        tmp_path: Path, broker: Broker) -> None:
    """``twinwatch run DIR`` (``--workers 1``), three machines naming edge node ``line1``: one
    NBIRTH and each machine's DBIRTH; a SIGHUP after m2.toml is removed and m4.toml added gives
    m2's DDEATH and m4's DBIRTH on the same session (no new NBIRTH); ``kill -9``: the will's
    NDEATH; the restart: NBIRTH with bdSeq + 1, every stored window of every machine delivered
    (the first run's undelivered ones flagged historical); SIGTERM: every DDEATH, then NDEATH."""
    from .helpers.cli import machine_config

    machines = tmp_path / "machines"
    machines.mkdir()
    # the first run's output held to a window every 4 s per machine (the plant makes one
    # every 2 s): the kill leaves windows undelivered, the restart's replays
    table = (f'\n[outputs.sparkplug]\nport = {broker.port}\ngroup_id = "plant1"\n'
             f'edge_node_id = "line1"\nreconnect_max = 1.0\n'
             f"close_timeout = 20.0\ninflight = 1\n")
    # keepalive: the default 30 s (a box loaded by other work stalled the output's thread 7.5
    # s during the reload once, past a 5 s keepalive's 1.5x: a new connection, a new NBIRTH,
    # correct, but not the one session this test follows; the will on the kill does not wait
    # for the keepalive: the socket closes)

    def add(name: str, rate: float = 0.25) -> None:
        path = machine_config(machines, name, port=None)
        path.write_text(path.read_text() + table + f"rate = {rate}\n")

    for name in ("m1", "m2", "m3"):
        add(name)
    host = HostDecoder(Subscriber(broker.port, ["spBv1.0/#"], client_id="test-host-gw",
                                  persistent=True))

    def run(*args: str) -> subprocess.Popen[str]:
        import os

        from .helpers.paths import ROOT
        env = dict(os.environ, CI="true", PYTHONPATH=str(ROOT))
        return subprocess.Popen([sys.executable, "-m", "twinwatch", "run", "--no-progress",
                                 "--workers", "1", *args, str(machines)], cwd=tmp_path,
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)

    def ddata(device: str) -> int:
        return sum(d.kind == "DDATA" and d.topic.endswith(f"/{device}")
                   for d in host.messages())

    proc = run()
    try:
        host.wait(lambda ms: all(ddata(m) >= 2 for m in ("m1", "m2", "m3")), 180,
                  "every machine's data")
        (machines / "m2.toml").unlink()
        add("m4")
        proc.send_signal(signal.SIGHUP)
        host.wait(lambda ms: ddata("m4") >= 1, 180, "m4's data after the SIGHUP")
        host.wait(lambda ms: any(d.kind == "DDEATH" for d in ms), 30, "m2's DDEATH")
        first = _kinds(host)
        assert [k for k, _ in first].count("NBIRTH") == 1, first   # one session throughout
        assert ("DDEATH", "m2") in first and "NDEATH" not in [k for k, _ in first]
        time.sleep(4.0)   # a few windows more, some left undelivered by the kill
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    host.wait(lambda ms: ms[-1].kind == "NDEATH", 30, "the will (NDEATH) after the kill")
    for name in ("m1", "m3", "m4"):
        add(name, rate=50.0)
    proc = run("--resume", "--duration", "8")
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    host.wait(lambda ms: ms[-1].kind == "NDEATH", 30, "the NDEATH of the clean stop")
    counts = host.check_session()
    kinds = _kinds(host)
    assert counts["NBIRTH"] == 2 and counts["NDEATH"] == 2, (counts, kinds, err[-6000:])
    nbirths = [d.payload for d in host.messages() if d.kind == "NBIRTH"]
    assert _bd_seq(nbirths[1]) == (_bd_seq(nbirths[0]) + 1) % 256   # kept across the kill
    second = kinds[kinds.index(("NBIRTH", ""), 1):]
    deaths = [dev for k, dev in second if k == "DDEATH"]
    assert sorted(deaths) == ["m1", "m3", "m4"] and second[-1] == ("NDEATH", ""), second[-6:]
    for m in ("m1", "m3", "m4"):
        windows = stored(tmp_path / m / "state.sqlite")
        got = host.windows(m)
        assert {(r, w) for r, w, _ in got} == set(windows), f"{m}: every window delivered"
        assert len(got) - len(set(got)) <= 10, m   # at most the inflight sent twice
    # the first run's windows the kill left undelivered came after the restart's NBIRTH:
    # flagged historical (stored before that connection's births)
    runs = {r for r, _ in stored(tmp_path / "m1" / "state.sqlite")}
    assert len(runs) == 2
    births, late = 0, []
    for d in host.messages():
        births += d.kind == "NBIRTH"
        parts = d.topic.split("/")
        if d.kind == "DDATA" and births == 2:
            names = host.device_aliases[(parts[3], parts[4])]
            v = {names[m.alias]: m for m in d.payload.metrics}
            late.append((v["Window/Run"].string_value, v["Window/Index"].is_historical))
    first_run = stored(tmp_path / "m1" / "state.sqlite")[0][0]
    replayed = [h for r, h in late if r == first_run]
    assert replayed and all(replayed), late
    print(f"gateway edge node: counts {counts}, bdSeq {[_bd_seq(p) for p in nbirths]}")
    host.close()
