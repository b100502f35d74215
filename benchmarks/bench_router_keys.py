"""What a Zenoh router mesh pays to route a fleet's declarations, by the layout of the keys
(issue 39): ``twinwatch/<machine>/...`` (flat: every machine a child of one chunk) against
``twinwatch/<box>/<machine>/...`` (box: ``[zenoh] key_prefix = "twinwatch/<box>"``).

A Zenoh 1.x router registers each key it is told about by matching it against the keys it
holds, chunk by chunk: every child of a chunk is tried (``Resource::get_matches``; ``perf`` on
the fleet benchmark's routers at 10 000 machines: 78-82 % of their CPU, called from
``register_expr`` on every declaration). With N machines under one chunk, each declaration
costs O(N) and the fleet's O(N^2); under a box's chunk, O(N / boxes + boxes).

Processes, all on 127.0.0.1 (free ports, scouting off): three routers (R0; R1 -> R0; R2 -> R0
and R1), ``--boxes`` box processes (clients, half of R0 and half of R1) declaring, per machine,
what a gateway declares for it (the latest/history queryable on ``P/**``, or with
``--entities box-queryable`` one per box on ``twinwatch/<box>/**`` as a gateway now declares;
the summary's publisher; the liveliness token ``P/alive``; the health's advanced publisher with
its cache and publisher detection), and a client on R2 following the tokens. Printed: when
the far client saw every machine's token, when the routers went quiet (under 0.1 s of CPU in
2 s), and each router's CPU [s]. With ``--restart S``, R1 is then killed and restarted after
S seconds: when every token was back at the far client, and the routers' CPU meanwhile
(``--failover``: each box lists the other router too, and goes there when R1 dies).

    python benchmarks/bench_router_keys.py --machines 4000 --layout flat
    python benchmarks/bench_router_keys.py --machines 10000 --layout box --restart 5

Measured figures: docs/fleet.md. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from bench_fleet import (  # the fleet benchmark's loopback set-up
    TICK,
    free_port,
    role_router,
    zconf,
)


def cpu_s(pid: int) -> float:
    f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / TICK


def machine_key(layout: str, box: str, j: int) -> str:
    return f"twinwatch/{box}-m{j:05d}" if layout == "flat" else f"twinwatch/{box}/{box}-m{j:05d}"


def role_box(endpoint: str, machines: int, layout: str, box: str, entities: str,
             also: list[str]) -> None:
    import zenoh
    import zenoh.ext as zx

    session = zenoh.open(zconf("client", [], [endpoint, *also]))
    keep: list[object] = []
    if entities == "box-queryable" and layout == "box":
        keep.append(session.declare_queryable(f"twinwatch/{box}/**", lambda q: None))
    for j in range(machines):
        base = machine_key(layout, box, j)
        if entities == "machine":
            keep.append(session.declare_queryable(base + "/**", lambda q: None))
        keep.append(session.declare_publisher(base + "/summary"))
        keep.append(session.liveliness().declare_token(base + "/alive"))
        keep.append(zx.declare_advanced_publisher(
            session, base + "/health", cache=zx.CacheConfig(30),
            sample_miss_detection=zx.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=1.0),
            publisher_detection=True))
    print("ready", flush=True)
    sys.stdin.read()
    os._exit(0)  # closing thousands of entities one by one is not what is measured


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--role", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--connect", nargs="*", default=[], help=argparse.SUPPRESS)
    ap.add_argument("--box", help=argparse.SUPPRESS)
    ap.add_argument("--machines", type=int, default=4000, help="machines in all (default 4000)")
    ap.add_argument("--boxes", type=int, default=None, help="default: one per 500 machines")
    ap.add_argument("--layout", choices=("flat", "box"), default="flat")
    ap.add_argument("--timeout", type=float, default=600.0, help="give up after [s]")
    ap.add_argument("--entities", choices=("machine", "box-queryable"), default="machine",
                    help="per machine a latest/history queryable on P/** (machine, default) "
                    "or one queryable per box on twinwatch/<box>/** (box-queryable, "
                    "--layout box)")
    ap.add_argument("--failover", action="store_true",
                    help="each box lists the other router too ([zenoh] connect = [its "
                    "router, the other]): a box whose router is killed goes to the other")
    ap.add_argument("--restart", type=float, default=None,
                    help="then kill R1, restart it after this many seconds and time until "
                    "the far client sees every token again")
    a = ap.parse_args()
    if a.role == "router":
        role_router(a.endpoint, a.connect)
        return
    if a.role == "box":
        role_box(a.endpoint, a.machines, a.layout, a.box, a.entities, a.connect)
        return
    import zenoh

    boxes = a.boxes or max(2, a.machines // 500)
    per = a.machines // boxes
    n = per * boxes
    eps = [f"tcp/127.0.0.1:{free_port()}" for _ in range(3)]
    connect = [[], [eps[0]], [eps[0], eps[1]]]

    def spawn(*args: str) -> subprocess.Popen[str]:
        return subprocess.Popen([sys.executable, __file__, *args], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True)

    print(f"{n} machines on {boxes} boxes, keys {a.layout} "
          f"({machine_key(a.layout, 'b00', 0)}/...); routers R0, R1 -> R0, R2 -> R0 + R1")
    routers = [spawn("--role", "router", "--endpoint", eps[i], "--connect", *connect[i])
               for i in range(3)]
    procs = list(routers)
    try:
        for r in routers:
            r.stdout.readline()  # type: ignore[union-attr]
        client = zenoh.open(zconf("client", [], [eps[2]]))
        seen: set[str] = set()
        alive: set[str] = set()  # tokens present now (gone on DELETE: their router killed)
        pattern = "twinwatch/*/*/alive" if a.layout == "box" else "twinwatch/*/alive"

        def on_token(s: zenoh.Sample) -> None:
            key = str(s.key_expr)
            if s.kind == zenoh.SampleKind.PUT:
                seen.add(key)
                alive.add(key)
            else:
                alive.discard(key)

        sub = client.liveliness().declare_subscriber(pattern, on_token)
        c0 = [cpu_s(r.pid) for r in routers]
        t0 = time.monotonic()
        boxes_p = [spawn("--role", "box", "--endpoint", eps[i % 2],
                         *(["--connect", eps[1 - i % 2]] if a.failover else []),
                         "--machines", str(per),
                         "--layout", a.layout, "--box", f"b{i:02d}", "--entities", a.entities)
                   for i in range(boxes)]
        procs += boxes_p
        for b in boxes_p:
            b.stdout.readline()  # type: ignore[union-attr]
        declared = time.monotonic() - t0
        while len(seen) < n and time.monotonic() - t0 < a.timeout:
            time.sleep(0.5)
        all_seen = time.monotonic() - t0
        prev = [cpu_s(r.pid) for r in routers]
        while time.monotonic() - t0 < a.timeout:
            time.sleep(2.0)
            cur = [cpu_s(r.pid) for r in routers]
            if max(c - p for c, p in zip(cur, prev, strict=True)) < 0.1:
                break
            prev = cur
        quiet = time.monotonic() - t0
        used = [cpu_s(r.pid) - c for r, c in zip(routers, c0, strict=True)]
        print(f"boxes declared their machines in {declared:.1f} s; the far client saw "
              f"{len(seen)} of {n} tokens after {all_seen:.1f} s; routers quiet after "
              f"{quiet:.1f} s; router CPU R0 {used[0]:.1f} s, R1 {used[1]:.1f} s, "
              f"R2 {used[2]:.1f} s; load average {os.getloadavg()[0]:.1f} (2 cores)")
        if a.restart is not None:
            c0 = [cpu_s(r.pid) for r in routers]
            t_kill = time.monotonic()
            routers[1].kill()
            routers[1].wait()
            fewest, back_at = n, None  # the most tokens gone; when all were there again
            while time.monotonic() - t_kill < a.restart:
                fewest = min(fewest, len(alive))
                if fewest < n and back_at is None and len(alive) == n:
                    back_at = time.monotonic() - t_kill
                time.sleep(0.05)
            gone = n - fewest
            routers[1] = spawn("--role", "router", "--endpoint", eps[1], "--connect",
                               *connect[1])
            procs.append(routers[1])
            routers[1].stdout.readline()  # type: ignore[union-attr]
            c0[1] = 0.0  # a new process: its CPU from 0
            t_up = time.monotonic()
            while len(alive) < n and time.monotonic() - t_up < a.timeout:
                time.sleep(0.1)
            back = time.monotonic() - t_up
            used = [cpu_s(r.pid) - c for r, c in zip(routers, c0, strict=True)]
            if a.failover:
                print(f"R1 killed: at most {gone} tokens gone at the far client, every token "
                      "back " + (f"{back_at:.1f} s after the kill (the boxes on R0 now)"
                                 if back_at is not None else f"NOT within {a.restart:g} s"))
            print(f"R1 killed: {gone} tokens gone at the far client; restarted after "
                  f"{t_up - t_kill:.1f} s; every token back {back:.1f} s later "
                  f"({len(alive)} of {n}); router CPU meanwhile R0 {used[0]:.1f} s, "
                  f"R1 {used[1]:.1f} s, R2 {used[2]:.1f} s; load average "
                  f"{os.getloadavg()[0]:.1f}")
        sub.undeclare()
    finally:
        for p in procs:
            try:
                p.stdin.close()  # type: ignore[union-attr]
            except OSError:
                pass
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
    os._exit(0)  # the client session's close is not what is measured


if __name__ == "__main__":
    main()
