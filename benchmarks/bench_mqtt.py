"""Does the MQTT output slow the estimation? (issue 18: "the estimation time per window is
unchanged within noise with the output on").

Runs ``twinwatch run`` on the simulated DC motor (resistance degradation, as fast as possible,
state database on, Zenoh and Rerun off) alternately without and with ``[outputs.mqtt]`` to a
Mosquitto this script starts on 127.0.0.1 (a free port), and prints, per variant, the
estimation time per window (the health message's ``elapsed_s``, read from the state
database): median, 90th percentile and mean over every window of its runs, and the MQTT
output's delivered count. Alternating the variants spreads the shared machine's noise over
both.

Usage::

    python benchmarks/bench_mqtt.py                    # 3 runs each of 60 windows
    python benchmarks/bench_mqtt.py --runs 5 --windows 100

Not part of the test suite; needs ``mosquitto`` (Debian: apt-get install mosquitto).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_broker(directory: Path) -> tuple[subprocess.Popen[bytes], int]:
    exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not os.path.exists(exe):
        sys.exit("mosquitto is not installed (Debian: apt-get install mosquitto)")
    port = free_port()
    conf = directory / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\n")
    proc = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    for _ in range(100):
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return proc, port
        except OSError:
            time.sleep(0.05)
    proc.kill()
    sys.exit("mosquitto did not start")


def config(directory: Path, windows: int, mqtt_port: int | None) -> Path:
    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    text = text.replace("duration = 1200.0", f"duration = {2.0 * windows}")
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false", 1)
    text = text.replace("[recording]", "[recording]\nenabled = false", 1)
    text = text.replace('path = "state.sqlite"', f'path = "{directory / "state.sqlite"}"')
    if mqtt_port is not None:
        text += f"\n[outputs.mqtt]\nport = {mqtt_port}\n"
    path = directory / "m.toml"
    path.write_text(text)
    return path


def run(windows: int, mqtt_port: int | None) -> tuple[list[float], int, list[str]]:
    """One run: the estimation times [s] of its windows, the windows delivered, the stored
    messages."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        env = dict(os.environ, PYTHONPATH=str(ROOT), CI="true")
        subprocess.run([sys.executable, "-m", "twinwatch", "run",
                        str(config(d, windows, mqtt_port)), "--no-progress", "--fresh"],
                       cwd=d, env=env, check=True, capture_output=True, timeout=1800)
        con = sqlite3.connect(d / "state.sqlite")
        texts = [r[0] for r in con.execute("SELECT doc FROM health ORDER BY id")]
        con.close()
    docs = [json.loads(t) for t in texts]
    times = [float(h["elapsed_s"]) for h in docs[1:]]  # the first window compiles
    delivered = int(docs[-1]["counters"].get("mqtt_delivered", 0)) if docs else 0
    return times, delivered, texts


def thread_cost(port: int, texts: list[str], repeat: int = 5) -> tuple[float, float]:
    """The MQTT output's own thread, in this process, on the real messages of a run: its CPU
    time per window [ms] (the thread's clock), and the wall time from the store's commit to
    the broker's acknowledgement [ms], median."""
    from types import SimpleNamespace

    sys.path.insert(0, str(ROOT))
    from twinwatch.sinks.base import SinkContext
    from twinwatch.sinks.mqtt import MqttConfig, MqttPublisher
    from twinwatch.sinks.store import StateStore

    with tempfile.TemporaryDirectory() as tmp:
        store = StateStore(Path(tmp) / "s.sqlite", prune_every=0)
        ctx = SinkContext(machine="dc-motor-sim", model="dc_motor",
                          outbox=lambda name: store.outbox(name, "dc-motor-sim"))
        pub = MqttPublisher.open("mqtt", MqttConfig(port=port), ctx)
        while not pub.connected:
            time.sleep(0.05)
        clock = time.pthread_getcpuclockid(pub._thread.ident or 0)
        cpu0 = time.clock_gettime(clock)
        latency = []
        n = 0
        for _ in range(repeat):
            for text in texts:
                h = json.loads(text)
                store.save_window({"machine": h["machine"], "window": h["window"],
                                   "t_start": h["t_start"], "t_end": h["t_end"]}, None,
                                  doc=text)
                t0 = time.perf_counter()
                pub.write(SimpleNamespace(health=SimpleNamespace(window=h["window"]),  # type: ignore[arg-type]
                                          health_json=text, events=[]))
                n += 1
                while pub.delivered < n:
                    time.sleep(0.0005)
                latency.append(time.perf_counter() - t0)
        cpu = time.clock_gettime(clock) - cpu0
        pub.close()
        store.close()
    return 1000 * cpu / n, 1000 * statistics.median(latency)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="runs of each variant")
    ap.add_argument("--windows", type=int, default=60, help="windows per run")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        broker, port = start_broker(Path(tmp))
        try:
            results: dict[str, list[float]] = {"without MQTT": [], "with MQTT": []}
            delivered = []
            texts: list[str] = []
            for i in range(args.runs):
                for name, p in (("without MQTT", None), ("with MQTT", port)):
                    times, n, texts = run(args.windows, p)
                    results[name] += times
                    if p is not None:
                        delivered.append(n)
                    print(f"run {i + 1} {name}: median {1000 * statistics.median(times):.1f} ms "
                          f"over {len(times)} windows", flush=True)
            cpu_ms, latency_ms = thread_cost(port, texts)
        finally:
            broker.terminate()
            broker.wait(timeout=10)
    print(f"\nestimation time per window (elapsed_s), {args.runs} runs x {args.windows} windows, "
          f"as fast as possible, 2 cores shared:")
    for name, times in results.items():
        q = statistics.quantiles(times, n=10)
        print(f"  {name:13s} median {1000 * statistics.median(times):6.1f} ms, p90 "
              f"{1000 * q[-1]:6.1f} ms, mean {1000 * statistics.fmean(times):6.1f} ms "
              f"({len(times)} windows)")
    a, b = (statistics.median(results[k]) for k in ("without MQTT", "with MQTT"))
    print(f"  with/without: {b / a:.3f} (median); windows delivered per run (last window's "
          f"counter, the window itself in flight): {delivered}")
    print(f"the MQTT output's own thread on these messages: {cpu_ms:.2f} ms of CPU per window; "
          f"stored -> acknowledged by the broker: median {latency_ms:.1f} ms")


if __name__ == "__main__":
    main()
