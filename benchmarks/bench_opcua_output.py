"""What the OPC UA output costs (issue 35: "the output's CPU per machine-window in a 200-machine
gateway").

One process, as one worker of a gateway: ``--machines`` OPC UA outputs (``[outputs.opcua]``)
share one server on 127.0.0.1 (a free port), each machine's object made from the simulated DC
motor's parameters; every machine then writes ``--windows`` windows, a real health message (one
window of the simulated motor, estimated, with a diagnosis of five ranked faults, an alarm
state and a RUL on Ra; the value of Ra changing every window, the window's index and time too).
Printed: the CPU time (``time.process_time``: every thread of the process, the server's loop
included; not wall time) per machine-window, of which the caller's ``write`` (the outputs'
thread: flattening the message is done on the server's loop, so this is only the hand-over),
the values written per window, and the CPU and wall time to create the machines' objects.

``--subscribe`` starts a client in another process that monitors every parameter's ``Value``
of every machine (a SCADA's subscription, 500 ms publishing interval): the server then also
encodes and sends each change; the client's own CPU is not counted. ``--history N`` keeps N
windows of each ``Value`` for HistoryRead.

Usage::

    python benchmarks/bench_opcua_output.py                     # 200 machines, 20 windows
    python benchmarks/bench_opcua_output.py --machines 200 --windows 20 --subscribe
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CLIENT = textwrap.dedent("""
    import asyncio, sys
    from asyncua import Client, ua

    async def main(url, n):
        got = [0]
        class H:
            def datachange_notification(self, node, val, data):
                got[0] += 1
        async with Client(url, timeout=30) as c:
            ns = await c.get_namespace_index("urn:twinwatch:health")
            params = ("Ra", "La", "J", "Ke", "Kt", "D")
            nodes = [c.get_node(ua.NodeId(f"m{i:03d}.Parameters.{p}.Value", ns))
                     for i in range(n) for p in params]
            sub = await c.create_subscription(500, H())
            for k in range(0, len(nodes), 500):
                await sub.subscribe_data_change(nodes[k:k + 500])
            print("subscribed", len(nodes), flush=True)
            while True:
                await asyncio.sleep(1.0)
                print("notifications", got[0], flush=True)

    asyncio.run(main(sys.argv[1], int(sys.argv[2])))
""")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def base_message() -> Any:
    """One estimated window of the simulated motor with a diagnosis, alarms and a RUL."""
    import numpy as np

    from twinwatch.config.loader import default_config
    from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
    from twinwatch.twin.adaptation import TwinAdapter
    from twinwatch.twin.health import (
        AlarmStatus,
        CrossingHealth,
        DiagnosisHealth,
        FaultHealth,
        RulAlarmStatus,
        RulHealth,
        build_health,
    )
    from twinwatch.twin.model import WindowData
    from twinwatch.twin.models import create_model

    cfg = default_config()
    model = create_model(cfg.machine.model, cfg.machine.options)
    plant = DCMotorPlant(DCMotorPlantConfig(scenario="nominal", duration=10))
    samples = [plant.next_sample() for _ in range(400)][200:]
    w = WindowData(t=np.array([s.t for s in samples]),
                   channels={c: np.array([s.values[c] for s in samples])
                             for c in samples[0].values}, index=1)
    result = TwinAdapter(model, cfg.estimation, cfg.discovery).process(w)
    h = build_health(machine="m", model_name="dc_motor", run="bench", model=model, window=w,
                     adaptation=result, nominal={},
                     counters={f"c{i}": i for i in range(30)})
    crossing = CrossingHealth(threshold=5.85, status="predicted", t=900.0, t_low=800.0,
                              t_high=1000.0, rul_s=700.0, low_s=600.0, high_s=800.0,
                              wall=None, wall_low=None, wall_high=None, probability=0.9)
    params = dict(h.parameters)
    params["Ra"] = params["Ra"].model_copy(update={"rul": RulHealth(
        status="degrading", warning=crossing, alarm=crossing, method="monte_carlo",
        draws=200, interval=0.9)})
    faults = [FaultHealth(id=f"fault{i}", component=f"part {i}", probability=0.9 / (i + 1),
                          action="inspect", urgency="medium", source="bench",
                          evidence_for=[], evidence_against=[]) for i in range(5)]
    diag = DiagnosisHealth(status="fault", top="fault0", probability=0.9, no_fault=0.05,
                           unknown=0.05, unknown_terms=[], faults=faults, shaft_speed=None,
                           library="dc_motor", evidence=3)
    alarms = {"Ra": AlarmStatus(level="normal", since_t=0.0, since_window=0, deviation_pct=0.0,
                                pending=None, rul=RulAlarmStatus(
                                    level="normal", since_t=0.0, since_window=0,
                                    rul_s=700.0, pending=None))}
    return model, w, result, h.model_copy(update={"parameters": params, "diagnosis": diag,
                                                  "alarms": alarms})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=200)
    ap.add_argument("--windows", type=int, default=20, help="windows per machine")
    ap.add_argument("--subscribe", action="store_true",
                    help="a client process monitors every parameter's Value")
    ap.add_argument("--history", type=int, default=0, help="windows kept for HistoryRead")
    args = ap.parse_args()

    from twinwatch.sinks.base import ProcessedWindow, SharedResources, SinkContext
    from twinwatch.sinks.opcua import OpcUaConfig, OpcUaPublisher, flat_values

    model, w, result, base = base_message()
    port = free_port()
    url = f"opc.tcp://127.0.0.1:{port}"
    cfg = OpcUaConfig(endpoint=url, history=args.history, stale_after=3600.0)
    shared = SharedResources()
    parameters = {p.name: p.unit for p in model.parameters}
    nominal = {p.name: p.nominal for p in model.parameters}
    c0, t0 = time.process_time(), time.perf_counter()
    sinks = [OpcUaPublisher.open("opcua", cfg, SinkContext(
        machine=f"m{i:03d}", model="dc_motor", parameters=parameters, nominal=nominal,
        run="bench", shared=shared)) for i in range(args.machines)]
    sinks[0].server.flush(600.0)  # the objects are made on the server's loop
    c1, t1 = time.process_time(), time.perf_counter()
    print(f"{args.machines} machines' objects created: {c1 - c0:.2f} s CPU, {t1 - t0:.2f} s "
          f"wall ({(c1 - c0) / args.machines * 1e3:.1f} ms CPU per machine)")
    client = None
    if args.subscribe:
        script = Path(tempfile.mkdtemp()) / "client.py"
        script.write_text(CLIENT)
        client = subprocess.Popen([sys.executable, str(script), url, str(args.machines)],
                                  stdout=subprocess.PIPE, text=True)
        assert client.stdout is not None
        line = client.stdout.readline()
        print(f"client: {line.strip()}")
    try:
        outs = []
        for k in range(args.windows + 1):
            # every estimated value, its interval, deviation and trend move every window, as
            # the estimates of a real machine do (the nameplate and the texts do not)
            params = {}
            for name, p in base.parameters.items():
                f = 1 + 1e-4 * ((k * 7 + len(name)) % 11 - 5)
                upd: dict[str, Any] = {}
                if p.value is not None:
                    upd["value"] = p.value * f
                    upd["deviation_pct"] = (f - 1) * 100
                if p.rel_std_pct is not None:
                    upd["rel_std_pct"] = p.rel_std_pct * f
                if p.trend is not None:
                    upd["trend"] = p.trend.model_copy(update={
                        "rate": 1e-6 * f, "rate_low": 0.9e-6 * f, "rate_high": 1.1e-6 * f,
                        "rate_pct_per_h": 0.01 * f})
                params[name] = p.model_copy(update=upd)
            ra_rul = params["Ra"].rul
            if ra_rul is not None and ra_rul.alarm is not None:
                c = ra_rul.alarm.model_copy(update={"rul_s": 700.0 - 2 * k,
                                                    "low_s": 600.0 - 2 * k,
                                                    "high_s": 800.0 - 2 * k})
                params["Ra"] = params["Ra"].model_copy(update={"rul": ra_rul.model_copy(
                    update={"alarm": c, "warning": c})})
            diag = base.diagnosis
            if diag is not None:
                diag = diag.model_copy(update={"probability": 0.9 - 1e-3 * k, "faults": [
                    f.model_copy(update={"probability": f.probability - 1e-3 * k})
                    for f in diag.faults]})
            h = base.model_copy(update={"window": k + 1, "t_start": 2.0 * k,
                                        "t_end": 2.0 * k + 1.99, "parameters": params,
                                        "nrmse": 1e-3 * (1 + 1e-3 * k), "diagnosis": diag,
                                        "counters": dict(base.counters, windows=k)})
            outs.append(ProcessedWindow(window=w, result=result, health=h,
                                        health_json=h.to_json(), events=[], twin_state=None))
        values = len(flat_values(outs[0].health, (0, "")))
        server = sinks[0].server
        for s in sinks:  # the first window creates the counters' nodes: not measured
            s.write(outs[0])
        server.flush(120.0)
        outs = outs[1:]
        writes0 = server.writes
        caller = 0.0
        c0, t0 = time.process_time(), time.perf_counter()
        for out in outs:
            a = time.thread_time()
            for s in sinks:
                s.write(out)
            caller += time.thread_time() - a
            server.flush(120.0)
        c1, t1 = time.process_time(), time.perf_counter()
        n = args.machines * len(outs)
        print(f"{n} machine-windows, {values} values each ({server.writes - writes0} written: "
              f"those that changed), "
              f"errors {server.errors}")
        print(f"CPU per machine-window: {(c1 - c0) / n * 1e3:.2f} ms (process, every thread), "
              f"of which the caller's write {caller / n * 1e3:.3f} ms; wall {(t1 - t0):.1f} s")
        per_s = (c1 - c0) / n * args.machines / 2.0
        print(f"at one window per 2 s per machine: {per_s * 100:.1f} % of one core for "
              f"{args.machines} machines")
        if client is not None:
            time.sleep(1.5)
    finally:
        for s in sinks:
            s.close()
        if client is not None:
            client.kill()
            out_text = client.communicate()[0]
            last = [ln for ln in out_text.splitlines() if ln.startswith("notifications")]
            if last:
                print(f"client: {last[-1]}")


if __name__ == "__main__":
    main()
