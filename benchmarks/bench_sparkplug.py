"""What does the Sparkplug B output cost per window? (issue 38: "benchmarks quote the CPU per
window").

Makes real health messages (``twinwatch run`` on the simulated DC motor, resistance
degradation, 10 windows, with ``[outputs.sparkplug]`` configured so the messages carry its
counters; no broker is needed: the windows wait in the outbox), then times, in this process,
the Sparkplug output's work for one window: the stored text read into the typed view
(``read_health``), the metric list checked against the birth (``metric_specs`` and
``SparkplugSession.declare``), the values read (``metric_values``) and the DDATA encoded
(protobuf); and, apart, a DBIRTH. Prints the CPU time (``time.process_time``) per window:
median of ``--repeats`` rounds of ``--n`` windows each, the payload sizes, and for comparison
the MQTT output's retained flat values of the same message (``flat_values``). Then (with
Mosquitto installed) ``--devices`` machines as devices of one edge node over one session on a
real broker: the process's CPU per machine-window delivered.

Usage::

    python benchmarks/bench_sparkplug.py             # 7 rounds of 2000 windows
    python benchmarks/bench_sparkplug.py --n 5000 --repeats 5
    python benchmarks/bench_sparkplug.py --devices 50 --windows 100   # one edge node, 50 machines

Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]


def health_docs(tmp: Path) -> list[str]:
    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    text = text.replace("duration = 1200.0", "duration = 20.0")
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false")
    text = text.replace("[recording]", "[recording]\nenabled = false")
    text = text.replace('path = "state.sqlite"', f'path = "{tmp / "state.sqlite"}"')
    text += '\n[outputs.sparkplug]\nport = 9\nclose_timeout = 0.0\nconnect_timeout = 0.2\n'
    cfg = tmp / "m.toml"
    cfg.write_text(text)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-m", "twinwatch", "run", str(cfg), "--no-progress"],
                   cwd=tmp, env=env, capture_output=True, check=False, timeout=600)
    con = sqlite3.connect(tmp / "state.sqlite")
    try:
        return [d for (d,) in con.execute("SELECT doc FROM health ORDER BY id")]
    finally:
        con.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="windows per round")
    ap.add_argument("--repeats", type=int, default=7, help="rounds")
    ap.add_argument("--devices", type=int, default=20,
                    help="machines as devices of one edge node on a real Mosquitto (0: skip)")
    ap.add_argument("--windows", type=int, default=100, help="windows per device")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from twinwatch.sinks.mqtt import flat_values
    from twinwatch.sinks.sparkplug import (
        DeviceSession,
        EdgeNodeSession,
        metric_specs,
        metric_values,
    )
    from twinwatch.twin.health import read_health

    with tempfile.TemporaryDirectory() as d:
        docs = health_docs(Path(d))
    if not docs:
        sys.exit("the simulated run stored no window")
    params = dict(read_health(docs[-1]).parameters or {})
    units = {k: str(p.unit or "") for k, p in params.items()}
    session = DeviceSession(EdgeNodeSession("plant1", "edge"), "motor")
    session.declare(metric_specs(units, {"Ra"}, read_health(docs[-1])))

    def one(doc: str) -> bytes:
        view = read_health(doc)
        session.declare(metric_specs(units, {"Ra"}, view))
        return session.ddata(metric_values(view), 0, 0)

    def rounds(fn: object) -> list[float]:
        out = []
        for _ in range(args.repeats):
            t0 = time.process_time()
            for i in range(args.n):
                fn(docs[i % len(docs)])  # type: ignore[operator]
            out.append((time.process_time() - t0) / args.n)
        return out

    ddata = rounds(one)
    parse = rounds(read_health)
    flat = rounds(lambda doc: flat_values(read_health(doc)))
    view = read_health(docs[-1])
    t0 = time.process_time()
    for _ in range(200):
        birth = session.dbirth(metric_values(view), 0)
    birth_s = (time.process_time() - t0) / 200
    size = len(one(docs[-1]))
    print(f"health messages: {len(docs)} windows of the simulated motor, "
          f"{statistics.mean(len(d) for d in docs):.0f} bytes of JSON each, "
          f"{len(session.specs)} device metrics")
    print(f"Sparkplug DDATA per window (parse + metrics + encode): median "
          f"{statistics.median(ddata) * 1e6:.0f} us CPU (min {min(ddata) * 1e6:.0f}, max "
          f"{max(ddata) * 1e6:.0f}), payload {size} bytes")
    print(f"  of which read_health (the typed view, shared with the MQTT output): median "
          f"{statistics.median(parse) * 1e6:.0f} us")
    print(f"MQTT output's flat values of the same message (read_health + flat_values): median "
          f"{statistics.median(flat) * 1e6:.0f} us")
    print(f"DBIRTH (all metrics with names, datatypes, engUnit): {birth_s * 1e6:.0f} us CPU, "
          f"{len(birth)} bytes")
    if args.devices:
        devices(docs, args.devices, args.windows)


def devices(docs: list[str], n: int, windows: int) -> None:
    """``n`` machines as devices of one edge node (one MQTT session, one thread) on a real
    Mosquitto (127.0.0.1, a free port): each given ``windows`` stored windows (in-memory
    outboxes), delivered with QoS 1; the process's CPU (every thread: the node's, paho's) from
    the first write to the last acknowledgement, per machine-window."""
    import shutil
    import socket
    import threading

    from twinwatch.sinks.base import SharedResources, SinkContext
    from twinwatch.sinks.sparkplug import SparkplugConfig, SparkplugPublisher

    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not Path(mosquitto).exists():
        print("devices: Mosquitto is not installed (apt-get install mosquitto): skipped")
        return
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as d:
        conf = Path(d) / "mosquitto.conf"
        conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\n"
                        f"max_queued_messages 100000\n" + ("user root\n" if os.geteuid() == 0
                                                           else ""))
        broker = subprocess.Popen([mosquitto, "-c", str(conf)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        try:
            time.sleep(0.5)
            shared = SharedResources(Path(d))
            cfg = SparkplugConfig(port=port, group_id="plant1", edge_node_id="bench",
                                  rate=1000.0, inflight=50)
            pubs = [SparkplugPublisher.open("sparkplug", cfg, SinkContext(
                machine=f"m{i:03d}", model="dc_motor", cwd=Path(d), shared=shared))
                for i in range(n)]
            deadline = time.monotonic() + 30
            while not pubs[0]._node.born and time.monotonic() < deadline:
                time.sleep(0.05)
            t0, w0 = time.process_time(), time.perf_counter()
            for k in range(windows):
                for p in pubs:
                    doc = docs[k % len(docs)]
                    p.write(SimpleNamespace(health=SimpleNamespace(window=k), health_json=doc,
                                            events=[]))  # type: ignore[arg-type]
            total = n * windows
            deadline = time.monotonic() + 300
            while (sum(p.delivered for p in pubs) < total and time.monotonic() < deadline):
                time.sleep(0.01)
            cpu, wall = time.process_time() - t0, time.perf_counter() - w0
            delivered = sum(p.delivered for p in pubs)
            threads = threading.active_count()
            for p in pubs:
                p.close()
        finally:
            broker.terminate()
            broker.wait()
    print(f"{n} machine(s) as devices of one edge node (one session, {threads} threads): "
          f"{delivered}/{total} windows delivered (QoS 1) in {wall:.2f} s; CPU "
          f"{cpu / max(delivered, 1) * 1e6:.0f} us per machine-window (every thread of the "
          f"process: the typed view, the metrics, the protobuf, paho, the outboxes)")


if __name__ == "__main__":
    main()
