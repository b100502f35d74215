"""The fleet across boxes at size (issue 39): N machines' fleet summaries through a mesh of
three Zenoh routers to a fleet view at the far end.

Processes, all on 127.0.0.1 (free ports, scouting off):

* three routers (Python sessions in router mode, as the tests use; ``zenohd`` in production):
  R0, R1 connected to R0, R2 connected to R0 and R1 (a full mesh);
* ``--boxes`` box processes (gateways), half clients of R0 and half of R1, each holding its
  share of the N machines as the daemon's own Zenoh output (``HealthPublisher``: liveliness
  token, latest queryable, advanced publishers; one session per box, shared as in a gateway;
  ``--presence box``: one liveliness token per box instead of one per machine).
  Each machine replays a recorded message stream (``twinwatch run`` on the simulated DC motor
  with its resistance degrading, 300 windows of 2 s: the state database's health messages and
  their fleet summaries) under its own name, from its own offset in the recording, a window
  every 2 s of wall time: its summary goes out on change and at least every
  ``--summary-interval`` s, and a share of the machines (``--health-share``) also publish
  their full health every window;
* the far client on R2: ``SummaryWatcher`` (what ``twinwatch watch --fleet`` and ``twinwatch
  fleet report`` read) and ``watch --fleet``'s screen every second (the ranked view rendered,
  a screen's worth), plus a plain subscriber counting the full health messages;
* a late joiner on R2 started in the steady state;
* then ``twinwatch fleet report`` on R2 (its own process, as a user runs it: ``--expect N
  --horizon`` ``--report-horizon``, default 5min, ``--json``).

Printed: the time for the far client to hold every machine (from the boxes' start); in the
steady state the messages per second delivered to it, the summaries delivered of those
published (losses), the CPU of each router and of the client (share of one core), the
client's memory per machine; the late joiner's time to hold every machine's latest summary
and to render its first full screen; the machines the fleet report listed against those
due by the same rule (:func:`twinwatch.watch.ranking.service_report`) from the summaries the
boxes last published before the report's time (their age counted from when published), the
machines whose due-ness changed while it ran counted apart, its wall time and CPU; with R1
killed (SIGKILL) and restarted after ``--outage`` s: the machines lost from the view, the
summaries published meanwhile and delivered, and the time until the client holds every
machine's latest summary again.

Usage::

    python benchmarks/bench_fleet.py --machines 1000
    nice -n 5 python benchmarks/bench_fleet.py --machines 10000 --boxes 10

Not part of the test suite. ``--recording state.sqlite`` reuses a state database instead of
recording one (about 15 s).
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WINDOW_S = 2.0
TICK = os.sysconf("SC_CLK_TCK")
PLACEHOLDER = "@@MACHINE@@"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def zconf(mode: str, listen: list[str], connect: list[str], base: Path | None = None) -> Any:
    """A session's configuration on loopback, scouting off; ``base``: a zenohd configuration
    file to start from (its endpoints replaced), e.g. config/zenoh-site-router.json5."""
    import zenoh

    conf = zenoh.Config() if base is None else zenoh.Config.from_file(str(base))
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf


def rec_index(j: int, k: int, n_rec: int) -> int:
    """The recording's window that machine ``j`` replays as its window ``k`` (each machine
    from its own offset in the ``n_rec`` windows)."""
    return ((j * 37) % n_rec + k) % n_rec


def replayed(summaries: list[dict[str, Any]], box: str, j: int, k: int,
             wall: float) -> dict[str, Any]:
    """Machine ``j`` of ``box``'s summary of its window ``k``, published at ``wall`` [s since
    the epoch] (:func:`rec_index`; the boxes publish these, the parent rebuilds them to
    check the fleet report)."""
    s = dict(summaries[rec_index(j, k, len(summaries))])
    s.update(machine=f"{box}-m{j:05d}", box=box, run=f"{box}-run", window=k, wall=wall)
    return s


def say(**event: Any) -> None:
    sys.stdout.write(json.dumps(event) + "\n")
    sys.stdout.flush()


# -- the roles (each its own process) ----------------------------------------------------------
def role_router(listen: str, connect: list[str], base: Path | None = None) -> None:
    import zenoh

    deadline = time.monotonic() + 20
    while True:
        try:
            session = zenoh.open(zconf("router", [listen], connect, base))
            break
        except zenoh.ZError:  # the port of a router just killed may take a moment
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    say(event="ready")
    sys.stdin.read()  # until the parent closes it (or kills us)
    session.close()


def role_box(a: argparse.Namespace) -> None:
    from twinwatch.sinks.base import SharedResources
    from twinwatch.sinks.zenoh import HealthPublisher, ZenohConfig

    rec = json.loads(Path(a.recording).read_text())
    summaries, texts = rec["summaries"], rec["texts"]
    n_rec = len(summaries)
    shared = SharedResources()
    prefix = f"twinwatch/{a.box}" if a.layout == "box" else "twinwatch"
    cfg = ZenohConfig(mode="client", connect=[a.endpoint, *a.connect],
                      summary_interval=a.interval,
                      box=a.box, cache=a.cache, key_prefix=prefix, presence=a.presence)
    names = [f"{a.box}-m{j:05d}" for j in range(a.machines)]
    t0 = time.monotonic()
    pubs = [HealthPublisher(cfg, name, shared=shared) for name in names]
    declared = time.monotonic() - t0
    full = {j for j in range(a.machines) if (j * 7919) % 1000 < a.health_share * 1000}
    window = [0] * a.machines
    last: dict[str, int] = {}
    log: list[tuple[str, int, float]] = []
    lock = threading.Lock()
    stop = threading.Event()

    def commands() -> None:
        for line in sys.stdin:
            cmd = line.split()
            if not cmd:
                continue
            if cmd[0] == "dump":
                with lock:
                    Path(cmd[1]).write_text(json.dumps(last))
                say(event="dumped")
            elif cmd[0] == "since":  # each machine's summaries published from a wall time
                t = float(cmd[2])    # on, newest first, and the one standing then
                out: dict[str, list[tuple[int, float]]] = {}
                done: set[str] = set()
                with lock:
                    for name, k, w in reversed(log):
                        if name not in done:
                            out.setdefault(name, []).append((k, w))
                            if w < t:
                                done.add(name)
                        if len(done) == len(names):
                            break
                Path(cmd[1]).write_text(json.dumps(out))
                say(event="sent")
            elif cmd[0] == "quit":
                break
        stop.set()

    threading.Thread(target=commands, daemon=True).start()
    if a.trace_routers:
        threading.Thread(target=_trace_routers, args=(pubs[0], stop),
                         daemon=True).start()
    say(event="ready", declared_s=round(declared, 2), full=len(full))
    start = time.monotonic()
    # machine j's windows end at start + phase_j + k * WINDOW_S (staggered over the window)
    phase = [WINDOW_S * ((j * 0.6180339887) % 1.0) for j in range(a.machines)]
    due = sorted(range(a.machines), key=lambda j: phase[j])
    k_round = 0
    while not stop.is_set():
        base = start + k_round * WINDOW_S
        for j in due:
            t = base + phase[j]
            delay = t - time.monotonic()
            if delay > 0 and stop.wait(delay):
                break
            k = window[j]
            i = rec_index(j, k, n_rec)  # the full health of replayed()'s summary
            pub, name = pubs[j], names[j]
            if j in full:
                pub.publish(texts[i].replace(PLACEHOLDER, name))
            s = replayed(summaries, a.box, j, k, round(time.time(), 3))
            if pub.publish_summary(s):
                with lock:
                    last[name] = k
                    log.append((name, k, s["wall"]))
            window[j] = k + 1
        k_round += 1
    Path(a.log).write_text(json.dumps(log))
    for p in pubs:
        p.close()
    say(event="done")


def _trace_routers(pub: Any, stop: threading.Event) -> None:
    """``--trace-routers``: print (not as an event) each change of the routers the box's
    session is connected to, with the wall time: when a box lost R1 and reached R0."""
    session = pub._session  # the box's shared session (a benchmark may look inside)
    seen: list[str] | None = None
    while not stop.wait(0.05):
        try:
            now = sorted(str(z)[:8] for z in session.info.routers_zid())
        except Exception:  # noqa: BLE001 - the session closing
            return
        if now != seen:
            sys.stdout.write(f"routers {now} at {time.time():.3f}\n")
            sys.stdout.flush()
            seen = now


def _rss_kb(pid: int | str = "self") -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def role_client(a: argparse.Namespace) -> None:
    import io
    import logging

    import zenoh
    from rich.console import Console

    from twinwatch.watch.ranking import fleet_view
    from twinwatch.watch.render_fleet import render_fleet
    from twinwatch.watch.summaries import SummaryWatcher

    # the watcher's asks (how many machines answered, asked again) on stderr, timed (with
    # --trace-routers also at wall time [s], beside the kill's)
    wall = " at %(created).3f" if a.trace_routers else ""
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr,
                        format=f"  [{a.name}] %(relativeCreated).0f ms{wall} %(message)s")
    logging.getLogger("twinwatch.watch.summaries").setLevel(logging.DEBUG)
    rss0 = _rss_kb()
    t_open = time.monotonic()
    session = zenoh.open(zconf("client", [], [a.endpoint]))
    received: list[tuple[str, int, float]] = []  # machine, window, wall time received
    health = [0]

    def short(machine: str) -> str:  # <box>/<name> (--layout box) -> <name>, as the boxes log
        return machine.rsplit("/", 1)[-1]

    def on_summary(machine: str, s: dict[str, Any]) -> None:
        received.append((short(machine), s.get("window", -1), time.time()))

    def on_health(sample: Any) -> None:
        health[0] += 1

    boxed = a.layout == "box"  # keys twinwatch/<box>/<machine>/...: machines named <box>/<m>
    watcher = SummaryWatcher(session, prefix="twinwatch/*" if boxed else "twinwatch",
                             on_summary=on_summary,
                             exact=False if a.no_exact else None).start()
    sub = (session.declare_subscriber("twinwatch/*/*/health" if boxed else "twinwatch/*/health",
                                      on_health) if a.health else None)
    say(event="ready")
    stop = threading.Event()

    def commands() -> None:
        for line in sys.stdin:
            cmd = line.split()
            if not cmd:
                continue
            if cmd[0] == "dump":
                held = {short(m): r.summary.get("window") for m, r in watcher.received.items()}
                Path(cmd[1]).write_text(json.dumps(held))
                say(event="dumped", held=len(held), delivered=len(received), health=health[0],
                    rss_kb=_rss_kb(), rss0_kb=rss0)
            elif cmd[0] == "log":
                Path(cmd[1]).write_text(json.dumps(received))
                say(event="logged")
            elif cmd[0] == "quit":
                break
        stop.set()

    threading.Thread(target=commands, daemon=True).start()
    out = Console(file=io.StringIO(), width=160)
    full_at = None
    last_progress = time.monotonic()
    last_render = -1e9

    def render() -> float:
        """Rank and draw a screen's worth, as `watch --fleet` does; returns its time [ms]."""
        t = time.monotonic()
        view = fleet_view(watcher.received, time.time(), limit=20)
        out.file = io.StringIO()
        out.print(render_fleet(view, title="bench"))
        return 1e3 * (time.monotonic() - t)

    # the screen is rendered once a second, as `watch --fleet` refreshes it, and when every
    # machine is first held; the count is polled every 0.1 s (rendering 10 000 machines'
    # screen every 0.1 s took the GIL from the thread taking in the replies: 0.6-0.85 s a
    # render on the saturated box)
    while not stop.is_set():
        held = len(watcher)
        if full_at is None and held >= a.expect:
            full_at = time.monotonic()
            render_ms = render()
            last_render = time.monotonic()
            say(event="full", after_s=round(full_at - t_open, 2),
                render_ms=round(render_ms, 1), rss_kb=_rss_kb(), rss0_kb=rss0)
        elif time.monotonic() - last_render >= 1.0:
            render()
            last_render = time.monotonic()
        if full_at is None and time.monotonic() - last_progress >= 5.0:
            last_progress = time.monotonic()
            boxes: dict[str, int] = {}
            for m in watcher.received:
                b = short(m).split("-")[0]
                boxes[b] = boxes.get(b, 0) + 1
            say(event="progress", held=held, after_s=round(last_progress - t_open, 1),
                boxes=boxes)
        stop.wait(0.1)
    if sub is not None:
        sub.undeclare()
    watcher.close()
    session.close()


# -- the parent ----------------------------------------------------------------------------------
class Proc:
    """A child process speaking JSON lines on stdout."""

    def __init__(self, args: list[str], name: str, nice: int = 0) -> None:
        self.name = name
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        pre = ["nice", "-n", str(nice)] if nice else []
        self.p = subprocess.Popen([*pre, sys.executable, __file__, *args], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True, env=env)
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            try:
                self.events.put(json.loads(line))
            except ValueError:
                sys.stderr.write(f"[{self.name}] {line}")

    def expect(self, event: str, timeout: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            try:
                e = self.events.get(timeout=max(deadline - time.monotonic(), 0.01))
            except queue.Empty:
                raise TimeoutError(f"{self.name}: no {event} within {timeout} s") from None
            if e.get("event") == event:
                return e
            if e.get("event") == "progress":
                print(f"  [{self.name}] {e['held']} machines held after {e['after_s']} s "
                      f"{e.get('boxes')}", file=sys.stderr, flush=True)

    def send(self, line: str) -> None:
        assert self.p.stdin is not None
        if self.p.stdin.closed:
            return
        self.p.stdin.write(line + "\n")
        self.p.stdin.flush()

    def cpu_s(self) -> float:
        try:
            f = Path(f"/proc/{self.p.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return 0.0
        return (int(f[11]) + int(f[12])) / TICK  # utime + stime

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
        self.p.wait()

    def close(self, timeout: float = 30) -> None:
        if self.p.poll() is None:
            try:
                assert self.p.stdin is not None
                self.p.stdin.close()
                self.p.wait(timeout)
            except (subprocess.TimeoutExpired, BrokenPipeError, OSError):
                self.kill()


def record(path: Path | None, tmp: Path) -> Path:
    """The recorded stream: each window's health text (the machine's name a placeholder) and
    its fleet summary, as JSON."""
    from twinwatch.twin.health import read_health
    from twinwatch.twin.summary import fleet_summary

    if path is None:
        text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
        text = text.replace("duration = 1200.0", "duration = 600.0")
        text = text.replace("[zenoh]", "[zenoh]\nenabled = false", 1)
        text = text.replace("[recording]", "[recording]\nenabled = false", 1)
        text = text.replace('path = "state.sqlite"', f'path = "{tmp / "state.sqlite"}"')
        (tmp / "m.toml").write_text(text)
        env = dict(os.environ, PYTHONPATH=str(ROOT), CI="true")
        subprocess.run([sys.executable, "-m", "twinwatch", "run", str(tmp / "m.toml"),
                        "--no-progress", "--fresh"], cwd=tmp, env=env, check=True,
                       capture_output=True, timeout=1800)
        path = tmp / "state.sqlite"
    con = sqlite3.connect(path)
    docs = [r[0] for r in con.execute("SELECT doc FROM health ORDER BY id")]
    con.close()
    summaries, texts = [], []
    for d in docs:
        h = json.loads(d)
        name = h["machine"]
        summaries.append(fleet_summary(read_health(d), box="", wall=0.0))
        texts.append(d.replace(json.dumps(name), json.dumps(PLACEHOLDER)))
    out = tmp / "recording.json"
    out.write_text(json.dumps({"summaries": summaries, "texts": texts}))
    sizes = sorted(len(json.dumps(s, separators=(",", ":"))) for s in summaries)
    print(f"recording: {len(docs)} windows; a summary {sizes[0]}-{sizes[-1]} bytes (median "
          f"{sizes[len(sizes) // 2]}), a health message {len(docs[-1])} bytes")
    return out


def check_report(a: argparse.Namespace, n: int, endpoint: str, box_procs: list[Proc],
                 rec: Path, tmp: Path) -> None:
    """``twinwatch fleet report`` run as a user runs it (its own process, on the client's
    router), its list against what the boxes last published: the machines due by the
    report's own rule (:func:`~twinwatch.watch.ranking.service_report`, the age of a summary
    from when its box published it) at the report's time."""
    import resource

    from twinwatch.watch.ranking import Received, service_report

    summaries = json.loads(rec.read_text())["summaries"]
    out = tmp / "report.json"
    cmd = [sys.executable, "-m", "twinwatch", "fleet", "report", "--connect", endpoint,
           "--prefix", "twinwatch/*" if a.layout == "box" else "twinwatch",
           "--expect", str(n), "--wait", "60", "--horizon", a.report_horizon,
           "--json", str(out)]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    w_start, t_start = time.time(), time.monotonic()
    p = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, timeout=300)
    took = time.monotonic() - t_start
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = ru1.ru_utime - ru0.ru_utime + ru1.ru_stime - ru0.ru_stime
    if p.returncode != 0 or not out.exists():
        print(f"fleet report FAILED (exit {p.returncode}): {p.stderr.strip()[-2000:]}")
        return
    doc = json.loads(out.read_text())
    t_r, horizon = float(doc["t"]), float(doc["horizon_s"])
    listed = {str(r["machine"]).rsplit("/", 1)[-1] for r in doc["rows"]}  # <box>/<machine>
    # what each box published from the report's start on, newest first, and what stood then
    published: dict[str, list[tuple[int, float]]] = {}
    for b in box_procs:
        path = tmp / f"{b.name}.since.json"
        b.send(f"since {path} {w_start}")
        b.expect("sent", 60)
        published.update(json.loads(path.read_text()))

    def summary(m: str, k: int, wall: float) -> dict[str, Any]:
        box, j = m.rsplit("-m", 1)
        return replayed(summaries, box, int(j), k, wall)

    def is_due(s: dict[str, Any], at: float) -> bool:  # the report's rule, at its time
        return bool(service_report({"m": Received(s, at)}, t_r, horizon))

    truth: dict[str, Received] = {}
    changed: set[str] = set()   # its due-ness changed from the report's start to its time
    for m, entries in published.items():
        during = [(k, w) for k, w in entries if w <= t_r]  # newest first
        standing = [x for x in during if x[1] >= w_start] + [
            x for x in during if x[1] < w_start][:1]
        if not standing:
            continue
        k, w = standing[0]
        truth[m] = Received(summary(m, k, w), w)
        if len({is_due(summary(m, k2, w2), w2) for k2, w2 in standing}) > 1:
            changed.add(m)
    rows = service_report(truth, t_r, horizon)
    due = {str(r["machine"]) for r in rows}
    why: dict[str, int] = {}
    for r in rows:
        for reason in r["why"].split("+"):
            why[reason] = why.get(reason, 0) + 1
    missing = sorted(due - listed - changed)
    extra = sorted(listed - due - changed)
    # a machine missing only because the report counted a summary's age from its arrival
    # (the report started, asked, got it) rather than from when its box made it: so
    # fleet report did before 2026-11-26 (20 of 3378 at 10 000 machines)
    by_age = [m for m in missing if not is_due(truth[m].summary, max(truth[m].at, w_start))]
    print(f"fleet report (--horizon {a.report_horizon}): {len(due)} machines due of "
          f"{len(truth)} ({', '.join(f'{k} {v}' for k, v in sorted(why.items()))}); the "
          f"report listed {len(listed)} (of {doc['machines']} machines it held); missing: "
          f"{len(missing)} {missing[:5]}; extra: {len(extra)} {extra[:5]}")
    print(f"  {len(changed)} machines' due-ness changed while it ran (not compared: "
          f"{len(changed & listed)} of them listed); "
          f"{len(by_age)} of the missing due only by their summary's age since published "
          f"(counted from its arrival); the report took {took:.1f} s wall, "
          f"{cpu:.1f} s CPU ({cpu / took:.2f} of a core), its time "
          f"{t_r - w_start:.1f} s after its start")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--role", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--connect", nargs="*", default=[], help=argparse.SUPPRESS)
    ap.add_argument("--box", help=argparse.SUPPRESS)
    ap.add_argument("--name", default="client", help=argparse.SUPPRESS)
    ap.add_argument("--log", help=argparse.SUPPRESS)
    ap.add_argument("--expect", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--health", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--interval", type=float, default=10.0, help=argparse.SUPPRESS)
    ap.add_argument("--machines", type=int, default=1000, help="machines in all (default 1000)")
    ap.add_argument("--boxes", type=int, default=None,
                    help="box processes (default: one per 500 machines, at least 2)")
    ap.add_argument("--summary-interval", type=float, default=10.0,
                    help="[zenoh] summary_interval of every machine [s] (default 10; the "
                    "daemon's default is 60)")
    ap.add_argument("--health-share", type=float, default=0.02,
                    help="share of the machines publishing their full health every window "
                    "(default 0.02)")
    ap.add_argument("--cache", type=int, default=30, help="[zenoh] cache (default 30)")
    ap.add_argument("--no-exact", action="store_true",
                    help="the fleet client declares no subscriber per machine "
                         "(SummaryWatcher(exact=False); the default with --layout box)")
    ap.add_argument("--layout", choices=("flat", "box"), default="flat",
                    help="keys twinwatch/<machine>/... (flat, default) or "
                         "twinwatch/<box>/<machine>/... (box: [zenoh] key_prefix per box, the "
                         "client on twinwatch/*)")
    ap.add_argument("--failover", action="store_true",
                    help="each box lists the other router too ([zenoh] connect = [its router, "
                    "the other]): a box whose router is killed goes to the other, and the "
                    "catch-up is timed from the kill")
    ap.add_argument("--steady", type=float, default=30.0, help="steady-state measure [s]")
    ap.add_argument("--outage", type=float, default=5.0, help="router R1 down for [s]")
    ap.add_argument("--recording", type=Path, default=None,
                    help="a state database to replay (default: record one)")
    ap.add_argument("--nice", type=int, default=0, help="nice of the boxes' processes")
    ap.add_argument("--site-acl", type=Path, nargs="?", default=None,
                    const=ROOT / "config" / "zenoh-site-router.json5",
                    help="the routers start from this zenohd configuration (default "
                         "config/zenoh-site-router.json5: the boxes' advanced publishers' "
                         "declarations stay off the mesh, as behind a site's router)"),
    ap.add_argument("--presence", choices=("machine", "box"), default="machine",
                    help="the boxes' [zenoh] presence: a liveliness token per machine "
                         "(machine, the default) or one per box standing for its machines")
    ap.add_argument("--trace-routers", action="store_true",
                    help="each box prints when its session's router changes, the client's "
                         "log lines their wall time, and the kill's wall time is printed (why "
                         "a box's tokens come back late)")
    ap.add_argument("--report-horizon", default="5min",
                    help="`twinwatch fleet report --horizon` after the late joiner, checked "
                         "against the boxes' latest (default 5min: about a quarter of the "
                         "recording's summaries due; 'none': no report)")
    ap.add_argument("--full-timeout", type=float, default=600.0,
                    help="longest wait for the far client to hold every machine [s]")
    a = ap.parse_args()
    if a.role == "router":
        return role_router(a.endpoint, a.connect, a.site_acl)
    if a.role == "box":
        a.recording = str(a.recording)
        return role_box(a)
    if a.role == "client":
        return role_client(a)
    run(a)


def run(a: argparse.Namespace) -> None:
    n = a.machines
    boxes = a.boxes or max(2, n // 500)
    per = [n // boxes + (1 if i < n % boxes else 0) for i in range(boxes)]
    tmp = Path(tempfile.mkdtemp(prefix="bench_fleet_"))
    rec = record(a.recording, tmp)
    ports = [free_port() for _ in range(3)]
    eps = [f"tcp/127.0.0.1:{p}" for p in ports]
    router_connect = [[], [eps[0]], [eps[0], eps[1]]]
    procs: list[Proc] = []

    def router(i: int) -> Proc:
        p = Proc(["--role", "router", "--endpoint", eps[i], "--connect", *router_connect[i],
                  *(["--site-acl", str(a.site_acl)] if a.site_acl else [])], f"R{i}")
        p.expect("ready", 30)
        return p

    def client(name: str, health: bool) -> Proc:
        args = ["--role", "client", "--name", name, "--endpoint", eps[2], "--expect", str(n),
                "--layout", a.layout] + (["--no-exact"] if a.no_exact else []) + (
                    ["--trace-routers"] if a.trace_routers else [])
        return Proc(args + (["--health"] if health else []), name)

    print(f"{n} machines on {boxes} boxes ({per[0]} each), summary interval "
          f"{a.summary_interval:g} s, full health of {a.health_share:.0%} of the machines, "
          f"cache {a.cache}, keys {a.layout}, presence by {a.presence}, "
          f"{'no ' if a.no_exact or a.layout == 'box' else ''}subscriber per machine; "
          "routers R0, R1 -> R0, R2 -> R0 + R1; boxes on R0 and R1, the client on R2"
          + (f"; the routers' configuration {a.site_acl.name}" if a.site_acl else ""))
    try:
        routers = [router(i) for i in range(3)]
        procs += routers
        watch = client("client", True)
        procs.append(watch)
        watch.expect("ready", 60)
        t_boxes = time.monotonic()
        box_procs = []
        for i in range(boxes):
            name = f"b{i:02d}"
            p = Proc(["--role", "box", "--endpoint", eps[i % 2],
                      *(["--connect", eps[1 - i % 2]] if a.failover else []),
                      "--box", name, "--machines",
                      str(per[i]), "--interval", str(a.summary_interval), "--layout", a.layout,
                      "--health-share", str(a.health_share), "--cache", str(a.cache),
                      "--recording", str(rec),
                      "--log", str(tmp / f"{name}.log.json"), "--presence", a.presence,
                      *(["--trace-routers"] if a.trace_routers else [])], name, nice=a.nice)
            box_procs.append(p)
        procs += box_procs
        ready = [p.expect("ready", 900) for p in box_procs]
        print(f"boxes declared their machines in {max(r['declared_s'] for r in ready):.1f} s "
              f"(slowest box), all publishing {time.monotonic() - t_boxes:.1f} s after start; "
              f"{sum(r['full'] for r in ready)} machines publish their full health")
        try:
            full = watch.expect("full", a.full_timeout)
            print(f"far client holds all {n} machines {time.monotonic() - t_boxes:.1f} s "
                  "after the boxes started")
        except TimeoutError:  # measure the rest anyway: the limit is what this shows
            full = {"rss0_kb": 0, "render_ms": float("nan")}
            print(f"far client does NOT hold all {n} machines {a.full_timeout:g} s after the "
                  "boxes started (see its progress above); measuring on")

        def dump(p: Proc, path: Path) -> dict[str, Any]:
            p.send(f"dump {path}")
            e = p.expect("dumped", 60)
            e["data"] = json.loads(path.read_text())
            return e

        def box_latest() -> dict[str, int]:
            out: dict[str, int] = {}
            for p in box_procs:
                out.update(dump(p, tmp / f"{p.name}.last.json")["data"])
            return out

        # -- the steady state ----------------------------------------------------------------
        time.sleep(5.0)
        c0 = {p.name: p.cpu_s() for p in procs}
        d0 = dump(watch, tmp / "w0.json")
        t0, w0 = time.monotonic(), time.time()
        time.sleep(a.steady)
        c1 = {p.name: p.cpu_s() for p in procs}
        d1 = dump(watch, tmp / "w1.json")
        t1, w1 = time.monotonic(), time.time()
        dt = t1 - t0
        rate_s = (d1["delivered"] - d0["delivered"]) / dt
        rate_h = (d1["health"] - d0["health"]) / dt
        cpu = {k: (c1[k] - c0[k]) / dt for k in c1}
        mem = (d1["rss_kb"] - full["rss0_kb"]) / n
        print(f"steady state ({dt:.0f} s): {rate_s:.0f} summaries/s + {rate_h:.0f} full health "
              f"messages/s delivered to the far client")
        print("CPU (share of one core): " + ", ".join(
            f"{k} {cpu[k]:.2f}" for k in ("R0", "R1", "R2", "client"))
            + f"; boxes {sum(v for k, v in cpu.items() if k.startswith('b')):.2f} in all")
        print(f"client memory: {d1['rss_kb'] / 1024:.0f} MB RSS, {mem:.1f} kB per machine "
              f"(RSS less the {full['rss0_kb'] / 1024:.0f} MB before its session); a full "
              f"screen rendered in {full['render_ms']:.0f} ms")

        # -- a late joiner -------------------------------------------------------------------
        late = client("late", False)
        procs.append(late)
        late.expect("ready", 60)
        try:
            lf: dict[str, Any] | None = late.expect("full", 120)
        except TimeoutError:
            lf = None
        before = box_latest()
        time.sleep(1.0)
        held = dump(late, tmp / "late.json")["data"]
        behind = sum(1 for m, w in before.items() if (held.get(m) if held.get(m) is not None
                                                       else -1) < w)
        if lf is not None:
            print(f"late joiner: held every machine {lf['after_s']:.2f} s after opening its "
                  f"session (first full screen then, {lf['render_ms']:.0f} ms to render); "
                  f"{behind} machines behind their box's latest summary 1 s later")
        else:
            print(f"late joiner: NOT every machine within 120 s: {len(held)} held, {behind} "
                  "behind their box's latest summary")
        late.send("quit")
        late.close()

        # -- `twinwatch fleet report`, as a user runs it ---------------------------------------
        if a.report_horizon != "none":
            check_report(a, n, eps[2], box_procs, rec, tmp)
            time.sleep(2.0)

        # -- router R1 killed and restarted --------------------------------------------------
        on_r1 = {f"{p.name}-m" for i, p in enumerate(box_procs) if i % 2 == 1}
        held_before = dump(watch, tmp / "k0.json")["data"]
        ck0 = {p.name: p.cpu_s() for p in procs if p is not routers[1]}
        t_kill, w_kill = time.monotonic(), time.time()
        routers[1].kill()
        if a.trace_routers:
            print(f"  R1 killed at {w_kill:.3f}", file=sys.stderr)

        def is_behind(held: int | None, latest: int) -> bool:
            return (held if held is not None else -1) < latest

        def catch_up(since: float) -> tuple[float | None, list[str], dict[str, Any]]:
            """Until the client holds every box's latest summary (or 120 s): the time [s]
            from ``since``, the machines behind at the end, what the client held."""
            lag: list[str] = []
            held: dict[str, Any] = {}
            told = False
            while time.monotonic() - since < 120:
                latest = box_latest()
                time.sleep(0.3)
                held = dump(watch, tmp / "k1.json")["data"]
                lag = [m for m, w in latest.items() if is_behind(held.get(m), w)]
                if not lag:
                    return time.monotonic() - since, lag, held
                if not told and time.monotonic() - since >= 10.0:
                    told = True
                    print(f"  {time.monotonic() - since:.1f} s on: {len(lag)} machines behind "
                          f"(e.g. {', '.join(sorted(lag)[:3])})")
                time.sleep(0.5)
            return None, lag, held

        if a.failover:  # R1's boxes go to R0: caught up with R1 still down?
            caught, lag, held = catch_up(t_kill)
            lost = [m for m in held_before if m not in held]
            dk = time.monotonic() - t_kill
            ck1 = {p.name: p.cpu_s() for p in procs if p.name in ck0}
            share = {n: (ck1[n] - ck0[n]) / dk for n in ck0}
            print(f"  CPU (share of one core) from the kill on, {dk:.0f} s: " + ", ".join(
                f"{n} {v:.2f}" for n, v in share.items() if not n.startswith(("b", "late")))
                + f"; boxes {sum(v for n, v in share.items() if n.startswith('b')):.2f} in all")
            print(f"R1 killed, its boxes on R0 (--failover): {len(lost)} machines lost from "
                  "the view; the client held every machine's latest summary "
                  + (f"{caught:.1f} s after the kill" if caught is not None
                     else f"NOT within 120 s ({len(lag)} behind)"))
        time.sleep(max(a.outage - (time.monotonic() - t_kill), 0.0))
        procs.remove(routers[1])
        routers[1] = router(1)
        procs.append(routers[1])
        t_restart, w_restart = time.monotonic(), time.time()
        caught, lag, held = catch_up(t_restart)
        lost = [m for m in held_before if m not in held]
        print(f"R1 killed, restarted after {a.outage:g} s and routing again "
              f"{t_restart - t_kill:.1f} s after the kill ({sum(per[1::2])} machines behind it): "
              f"{len(lost)} machines lost from the view; the client held every machine's "
              "latest summary " + (f"{caught:.1f} s after the restart" if caught is not None
                                   else f"NOT within 120 s ({len(lag)} behind)"))
        time.sleep(2.0)
        # -- the logs ------------------------------------------------------------------------
        watch.send(f"log {tmp / 'received.json'}")
        watch.expect("logged", 60)
        for p in box_procs:
            p.send("quit")
        for p in box_procs:
            p.expect("done", 120)
        published: list[tuple[str, int, float]] = []
        for p in box_procs:
            published += json.loads((tmp / f"{p.name}.log.json").read_text())
        arrived: dict[tuple[str, int], float] = {}
        for m, w, t in json.loads((tmp / "received.json").read_text()):
            arrived.setdefault((m, w), t)
        got = set(arrived)
        steady = [(m, w) for m, w, t in published if w0 <= t <= w1]
        missing = [x for x in steady if x not in got]
        print(f"steady-state losses: {len(missing)} of {len(steady)} summaries published "
              f"between the two measures not delivered ({len(steady) / (w1 - w0):.0f} "
              "published/s)")
        outage = [(m, w) for m, w, t in published if w_kill <= t <= w_restart
                  and any(m.startswith(b) for b in on_r1)]
        print(f"from the kill to the restart R1's boxes published {len(outage)} summaries, "
              f"{sum(1 for x in outage if x in got)} of them reached the client")
        edges = (0.1, 0.5, 1, 2, 5, 10, 20, 60, 1e9)

        def histogram(xs: list[float]) -> str:
            counts = [sum(1 for x in xs if lo <= x < hi)
                      for lo, hi in zip((0.0, *edges[:-1]), edges, strict=True)]
            return ", ".join(f"<{hi:g}: {c}" for hi, c in zip(edges, counts, strict=True) if c)

        for who, odd in (("R0's boxes", False), ("R1's boxes", True)):
            print(f"  steady state, {who}: delivered after [s]: " + histogram(
                [arrived[(m, w)] - t for m, w, t in published if w0 <= t <= w1
                 and (m, w) in got and any(m.startswith(b) for b in on_r1) == odd]))
        for who, moved in (("R1's boxes (moved)", True), ("R0's boxes", False)):
            sent = [(m, w, t) for m, w, t in published
                    if w_kill <= t <= min(w_kill + 30, w_restart)
                    and any(m.startswith(b) for b in on_r1) == moved]
            lost = [t - w_kill for m, w, t in sent if (m, w) not in got]
            late = [arrived[(m, w)] - t for m, w, t in sent if (m, w) in got]
            print(f"  {who}, from the kill to the restart (30 s at most): {len(sent)} "
                  "summaries sent, "
                  f"{len(lost)} never delivered (sent this long after the kill [s]: "
                  f"{histogram(lost) or '-'}); delivered after [s]: {histogram(late) or '-'}")
        print(f"load average now: {os.getloadavg()[0]:.1f} (2 cores, shared)")
    finally:
        for p in procs:
            if p.name.startswith(("client", "late")):
                try:
                    p.send("quit")
                except (BrokenPipeError, OSError):
                    pass
            p.close(10)
        for p in procs:
            p.kill()


if __name__ == "__main__":
    main()
