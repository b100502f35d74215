"""``twinwatch watch`` and ``twinwatch tail`` (issue 16, item 5).

Unit level: the :class:`~twinwatch.watch.Fleet` on messages made here (a fake clock: a machine
appears, goes stale, goes, is forgotten; an older window is not taken for the latest; the RUL is
shown when the message carries the prognostics' fields), the tail line and the rich table.

End to end, as an operator runs them: a Zenoh router (a Python zenoh session in router mode
listening on 127.0.0.1), three daemons (``twinwatch run`` in subprocesses, simulated motors in
real time, each a Zenoh client of the router), one of them a motor whose Ra is 13 % below its
nameplate (an alarm on Ra within its first windows); ``twinwatch watch --once --json --wait 2``
lists all three with the alarm, the table shows them, ``twinwatch tail`` follows one, and the
live JSON stream marks a daemon killed with SIGKILL gone (about 30 s: in the slow lane; the fast
lane follows one daemon directly, in process). Every socket is on 127.0.0.1, every port picked
free at run time, scouting off.
"""

from __future__ import annotations

import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from twinwatch.watch import Fleet, FleetWatcher, health_line, render

from .helpers.cli import watch_daemon_config, watch_env
from .helpers.net import Collector, endpoint, free_port, wait_for, zsession
from .helpers.paths import ROOT

SIM = (ROOT / "config" / "dc-motor-sim.toml").read_text()


# -- the fleet, on messages made here ---------------------------------------------------------
def _msg(machine: str, window: int, *, run: str = "r1", ra_dev: float = 0.0,
         level: str = "normal", **extra: Any) -> dict[str, Any]:
    """A health message as a daemon publishes it (the fields the watcher reads)."""
    ra = 6.5 * (1 + ra_dev / 100)
    return {"schema": 8, "machine": machine, "model": "dc_motor", "run": run, "window": window,
            "t_start": 2.0 * window, "t_end": 2.0 * window + 1.99, "samples": 200,
            "parameters": {
                "Ra": {"value": ra, "unit": "ohm", "nominal": 6.5, "deviation_pct": ra_dev,
                       "status": "estimated", "held": False, "reason": None,
                       "rel_std_pct": 0.01, **extra},
                "Kt": {"value": 0.038, "unit": "N m/A", "nominal": 0.038, "deviation_pct": 0.0,
                       "status": "tied", "held": True, "reason": "tied to Ke",
                       "rel_std_pct": None}},
            "nrmse": 1.6e-5, "trusted": True, "elapsed_s": 0.05,
            "model_check": {"passed": True, "reasons": [], "widen": 1.0, "outputs": {}},
            "terms": [], "counters": {"windows_estimated": window + 1, "overruns": 0,
                                      "windows_abandoned": 2, "driver_frames": 400,
                                      "driver_gaps": 1},
            "alarms": {"Ra": {"level": level, "since_t": 10.0 if level != "normal" else None,
                              "since_window": None, "deviation_pct": ra_dev,
                              "pending": None}}}


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_a_machine_appears_goes_stale_goes_and_is_forgotten() -> None:
    clock = Clock()
    fleet = Fleet(stale_after=10.0, forget_after=60.0, clock=clock)
    fleet.token("m1", True)  # there before the watcher: since unknown
    assert fleet.health("m1", _msg("m1", 3))
    clock.t += 5
    fleet.token("m2", True)  # appeared while watching
    snap = fleet.snapshot()["machines"]
    assert [(m["machine"], m["state"], m["state_since_s"], m["window"]) for m in snap] == [
        ("m1", "alive", None, 3), ("m2", "alive", 0.0, None)]
    assert snap[0]["last_window_age_s"] == 5.0
    assert fleet.health("m1", _msg("m1", 5)) and not fleet.health("m1", _msg("m1", 4))
    assert fleet.health("m1", _msg("m1", 0, run="r2"))  # a new run starts from window 0
    clock.t += 11  # no window for 11 s (> 10 s and > 3 window lengths)
    assert fleet.snapshot()["machines"][0]["state"] == "stale"
    fleet.token("m1", False)
    clock.t += 30
    m1 = fleet.snapshot()["machines"][0]
    assert (m1["state"], m1["state_since_s"], m1["run"]) == ("gone", 30.0, "r2")
    clock.t += 31
    assert fleet.machines() == ["m2"]  # forgotten a minute after it went


def test_the_snapshot_reads_what_the_message_carries() -> None:
    fleet = Fleet(clock=Clock())
    fleet.token("m1", True)
    rul = {"status": "degrading", "method": "monte_carlo", "draws": 200, "interval": 0.9,
           "warning": None, "alarm": {"status": "predicted", "rul_s": 5400.0}}
    fleet.health("m1", _msg("m1", 7, ra_dev=-11.0, level="alarm", rul=rul, trend={"x": 1}))
    fleet.alarm("m1", {"parameter": "Ra", "previous": "warning", "level": "alarm", "t": 15.99})
    (m,) = fleet.snapshot()["machines"]
    json.dumps(m, allow_nan=False)
    assert list(m["parameters"]) == ["Ra"]  # tied and fixed ones are not estimated
    ra = m["parameters"]["Ra"]
    assert (ra["alarm"], ra["rul_s"], ra["rul_status"]) == ("alarm", 5400.0, "predicted")
    assert ra["deviation_pct"] == -11.0 and m["alarms"]["Ra"]["level"] == "alarm"
    assert m["quality"]["problems"] == {"windows_abandoned": 2, "driver_gaps": 1}
    assert m["quality"]["model_check"] is True and m["last_event"]["level"] == "alarm"
    line = health_line(_msg("m1", 7, ra_dev=-11.0, level="alarm"), wall=0.0)
    assert re.fullmatch(r"\d\d:\d\d:\d\d m1 #7 \[14\.00-15\.99 s\] Ra 5\.785 -11\.00 % "
                        r"nRMSE 1\.6e-05 check ok  ALARM Ra losses windows_abandoned 2, "
                        r"driver_gaps 1 \(run r1\)", line), line
    from rich.console import Console

    console = Console(record=True, width=200, color_system=None)
    console.print(render(fleet.snapshot(), title="fleet"))
    text = console.export_text()
    assert "fleet: 1 machine" in text and "-11.00 %" in text and "Ra ALARM since t=10 s" in text
    assert "RUL 90.0 min" in text and "driver_gaps 1" in text
    assert m["diagnosis"] is None and "n/a" in text  # a message without a diagnosis


def test_the_diagnosis_column_shows_the_most_probable_fault() -> None:
    fleet = Fleet(clock=Clock())
    fleet.token("m1", True)
    diag = {"status": "fault", "top": "winding_short", "probability": 0.934, "faults": [
        {"id": "winding_short", "probability": 0.934, "action": "measure Ra"}]}
    fleet.health("m1", _msg("m1", 7, ra_dev=-4.6) | {"diagnosis": diag})
    (m,) = fleet.snapshot()["machines"]
    assert m["diagnosis"] == {"fault": "winding_short", "probability": 0.934,
                              "action": "measure Ra"}
    from rich.console import Console

    console = Console(record=True, width=200, color_system=None)
    console.print(render(fleet.snapshot(), title="fleet"))
    text = console.export_text()
    assert "winding short" in text and "0.93" in text


def test_each_cell_of_the_table_and_the_tail_line_say_what_the_message_does() -> None:
    """The table's cells (render's named parts) and ``tail``'s line on what the other tests'
    machine does not carry: a machine gone, one without a window, a held parameter past its
    crossing, a fused one, a failed model check, an untrusted fit, no losses, terms."""
    from twinwatch.watch.render import (
        _alarms_cell,
        _last_cell,
        _parameters_cell,
        _quality_cell,
        _state_cell,
    )

    clock = Clock()
    fleet = Fleet(clock=clock)
    crossed = {"status": "degrading", "alarm": {"status": "crossed", "rul_s": None}}
    msg = _msg("m1", 3, ra_dev=5.5, level="warning", rul=crossed)
    msg["parameters"]["Ra"]["status"] = "held"
    msg["model_check"]["passed"] = False
    msg["trusted"] = False
    msg["counters"] = {"windows_estimated": 4}
    msg["terms"] = [{"equation": "a", "meaning": "x"}, {"equation": "b", "meaning": "y"}]
    fleet.token("m1", True)
    fleet.health("m1", msg)
    fleet.token("m2", True)
    clock.t += 30
    fleet.token("m1", False)
    clock.t += 12
    m1, m2 = fleet.snapshot()["machines"]
    assert _state_cell(m1).plain == "✕ gone\n12 s ago"
    assert _state_cell(m2).plain == "● alive"  # there before the watcher: since unknown
    assert _last_cell(m2).plain == "no window yet"
    assert _last_cell(m1).plain == "42 s ago\n#3 [6-8 s]\nrun r1"
    params = _parameters_cell(m1)
    assert params.plain == "Ra    +5.50 % held RUL: crossed"
    assert [str(span.style) for span in params.spans] == ["yellow", "dim", "cyan"]
    assert _alarms_cell(m1).plain == "Ra WARNING since t=10 s"
    assert _alarms_cell(m2).plain == "no rules"
    assert _quality_cell(m1).plain == ("nRMSE 1.6e-05, check FAILED, untrusted\n50 ms/window"
                                       "\nno losses")
    assert _quality_cell(m2).plain == ""
    line = health_line(msg, wall=0.0)
    assert line.endswith(" m1 #3 [6.00-7.99 s] Ra=6.8575 +5.50 % nRMSE 1.6e-05 check FAILED "
                         "untrusted  WARNING Ra +2 terms (run r1)"), line
    msg["parameters"]["Ra"]["status"] = "fused"
    msg["model_check"] = None
    assert " Ra~6.8575 +5.50 % nRMSE 1.6e-05 untrusted " in health_line(msg, wall=0.0)


# -- end to end: a router, three daemons ------------------------------------------------------
def _twinwatch(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "twinwatch", *args], capture_output=True,
                          text=True, timeout=timeout, env=watch_env())


class Fleet3:
    def __init__(self, ep: str, procs: dict[str, subprocess.Popen[str]],
                 health: Collector) -> None:
        self.ep = ep
        self.procs = procs
        self.health = health


@pytest.fixture(scope="module")
def fleet3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet3]:
    tmp = tmp_path_factory.mktemp("fleet")
    ep = endpoint(free_port())
    procs: dict[str, subprocess.Popen[str]] = {}
    with zsession("router", listen=[ep]) as router:
        health = Collector(router, "twinwatch/*/health")
        try:
            for name in ("m1", "m2", "m3"):
                d = tmp / name
                d.mkdir()
                (d / "m.toml").write_text(watch_daemon_config(name, ep, degraded=name == "m2"))
                procs[name] = subprocess.Popen(
                    [sys.executable, "-m", "twinwatch", "run", "m.toml", "--no-progress"],
                    cwd=d, env=watch_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                    text=True)
            wait_for(lambda: {h["machine"] for h in health.snapshot()} == {"m1", "m2", "m3"}
                     and any(h["machine"] == "m2" and h["alarms"]["Ra"]["level"] == "alarm"
                             for h in health.snapshot()), 180, "three daemons and m2's alarm")
            yield Fleet3(ep, procs, health)
        finally:
            health.sub.undeclare()
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in procs.values():
                try:
                    p.communicate(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.communicate()


@pytest.mark.slow  # three daemons in real time: about 30 s
def test_watch_once_json_lists_the_three_with_the_alarm(fleet3: Fleet3) -> None:
    t0 = time.monotonic()
    r = _twinwatch("watch", "--connect", fleet3.ep, "--once", "--json", "--wait", "2")
    elapsed = time.monotonic() - t0
    assert r.returncode == 0, r.stderr
    snap = json.loads(r.stdout)
    machines = {m["machine"]: m for m in snap["machines"]}
    assert sorted(machines) == ["m1", "m2", "m3"]
    for m in machines.values():
        assert m["state"] == "alive" and m["token"] is True
        assert m["window"] is not None and m["run"] and m["model"] == "dc_motor"
        assert m["last_window_age_s"] is not None and m["quality"]["model_check"] is not None
    m2 = machines["m2"]
    assert m2["alarms"]["Ra"]["level"] == "alarm"
    assert m2["parameters"]["Ra"]["alarm"] == "alarm"
    assert m2["parameters"]["Ra"]["deviation_pct"] == pytest.approx(-13.33, abs=0.1)
    assert machines["m1"]["alarms"]["Ra"]["level"] == "normal"
    assert len({m["run"] for m in machines.values()}) == 3
    print(f"watch --once --json listed 3 machines in {elapsed:.2f} s (process start to exit)")


@pytest.mark.slow  # three daemons in real time: about 30 s
def test_watch_table_shows_the_fleet(fleet3: Fleet3) -> None:
    r = _twinwatch("watch", "--connect", fleet3.ep, "--once")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert f"twinwatch fleet on {fleet3.ep} (client): 3 machines" in out
    rows = {name: [ln for ln in out.splitlines() if f"│ {name} " in ln] for name in
            ("m1", "m2", "m3")}
    assert all(len(v) == 1 for v in rows.values()), out
    assert "alive" in rows["m1"][0] and "-13.33 %" in rows["m2"][0] and "ALARM" in out


@pytest.mark.slow  # three daemons in real time: about 30 s
def test_tail_prints_one_line_per_health_message(fleet3: Fleet3) -> None:
    r = _twinwatch("tail", "m2", "--connect", fleet3.ep, "--count", "3")
    assert r.returncode == 0, r.stderr
    # the alarm event comes too (the publisher's cache gives a late tail the event that
    # raised it): a line of its own, not counted among the health messages
    out = r.stdout.splitlines()
    lines = [ln for ln in out if re.match(r"\d\d:\d\d:\d\d m2 #", ln)]
    assert len(lines) == 3, r.stdout
    # ... and the diagnosis's fault alarm (Ra 13 % low: the armature winding), its own line
    events = [ln for ln in out if ln not in lines and ln.strip()]
    assert all("m2: ALARM: Ra is 13.33 % below nominal" in ln
               or "m2: FAULT: winding_short (probability" in ln for ln in events), r.stdout
    windows = []
    for line in lines:
        m = re.match(r"\d\d:\d\d:\d\d m2 #(\d+) \[[\d.]+-[\d.]+ s\] Ra 6\.5\d* -13\.33 % .*"
                     r"ALARM Ra \(run \S+\)$", line)
        assert m, line
        windows.append(int(m.group(1)))
    assert windows == list(range(windows[0], windows[0] + 3))  # the latest, then as they come
    assert "m2: on the network" in r.stderr
    r = _twinwatch("tail", "m1", "--connect", fleet3.ep, "--count", "2", "--json")
    assert r.returncode == 0, r.stderr
    docs = [json.loads(line) for line in r.stdout.splitlines()]
    assert [d["machine"] for d in docs] == ["m1", "m1"] and docs[0]["run"] == docs[1]["run"]
    assert docs[1]["window"] == docs[0]["window"] + 1 and docs[0]["schema"] >= 6


@pytest.mark.slow  # three daemons in real time: about 30 s
def test_live_watch_marks_a_killed_daemon_gone(fleet3: Fleet3) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "twinwatch", "watch", "--connect",
                             fleet3.ep, "--json", "--interval", "0.3"], env=watch_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout or []],
                              daemon=True)
    reader.start()

    def states() -> dict[str, str]:
        snap = json.loads(lines.get(timeout=30))
        return {m["machine"]: m["state"] for m in snap["machines"]}

    try:
        while states() != {"m1": "alive", "m2": "alive", "m3": "alive"}:
            pass
        fleet3.procs["m3"].send_signal(signal.SIGKILL)
        deadline = time.monotonic() + 60
        seen = states()
        while seen.get("m3") != "gone" and time.monotonic() < deadline:
            seen = states()
        assert seen == {"m1": "alive", "m2": "alive", "m3": "gone"}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(timeout=5)
    assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""


def test_an_unreachable_network_is_one_line_and_exit_1() -> None:
    r = _twinwatch("watch", "--connect", endpoint(free_port()), "--once")
    assert r.returncode == 1
    assert r.stderr.startswith("Error: cannot connect to tcp/127.0.0.1:") and (
        "nothing answers there" in r.stderr) and "Traceback" not in r.stderr
    r = _twinwatch("tail", "m1", "--connect", "tcp/localhost")
    assert r.returncode == 1 and "is not of the form proto/host:port" in r.stderr


def test_a_watcher_in_process_follows_a_daemon_directly() -> None:
    """No router: the watcher connects to a daemon's own listening endpoint (a peer)."""
    from twinwatch.config.loader import default_config
    from twinwatch.daemon.runner import Daemon

    port = free_port()
    cfg = default_config()
    cfg.driver.plant.duration = 6.0  # type: ignore[union-attr]
    cfg.recording.enabled = False
    cfg.zenoh.listen = [endpoint(port)]
    fleet = Fleet()
    got: list[int] = []
    with Daemon(cfg, record=False) as daemon, zsession("client", connect=[endpoint(port)]) as s:
        with FleetWatcher(s, fleet, on_health=lambda m, d, t, how: got.append(d.window)):
            wait_for(lambda: fleet.machines() == ["dc-motor-sim"], 10, "the token")
            daemon.run()
            wait_for(lambda: len(got) == 3, 10, "three windows")
    assert got == [0, 1, 2]
    assert fleet.snapshot()["machines"][0]["window"] == 2


def test_the_table_into_a_file_keeps_every_column_unfolded() -> None:
    """Issue 24: `watch --once > file` squeezed the table to rich's 80 columns for a
    non-terminal (the columns' least widths add up to about 110: every header and cell folded).
    Into a file or a pipe the console is :data:`FILE_WIDTH` wide: every header on one line."""
    import io

    from twinwatch.watch import FILE_WIDTH, console

    fleet = Fleet(clock=Clock())
    fleet.token("m1", True)
    fleet.health("m1", _msg("m1", 7, ra_dev=-11.0, level="alarm"))
    buf = io.StringIO()
    out = console(buf)
    assert out.width == FILE_WIDTH
    out.print(render(fleet.snapshot(), title="fleet"))
    text = buf.getvalue()
    header = next(ln for ln in text.splitlines() if "machine" in ln and "state" in ln)
    for h in ("machine", "state", "last window", "parameters (vs nominal)", "alarms",
              "terms (DT'')", "diagnosis", "data quality"):
        assert h in header, (h, header)
    from rich.console import Console

    narrow = io.StringIO()
    Console(file=narrow).print(render(fleet.snapshot(), title="fleet"))  # what it was
    assert not any("parameters (vs nominal)" in ln for ln in narrow.getvalue().splitlines())


@pytest.mark.slow  # three daemons in real time (the module's fleet)
def test_watch_into_a_file_writes_every_refresh_and_flushes_on_sigterm(
        fleet3: Fleet3, tmp_path: Any) -> None:
    """Issue 26 item 6: `watch` into a file wrote nothing while it ran (a Live display) and
    nothing at all when stopped by SIGTERM. Not on a terminal it prints each refresh, full
    width, and flushes; SIGTERM ends it with what it wrote kept."""
    out = tmp_path / "watch.txt"
    with out.open("w") as f:
        proc = subprocess.Popen([sys.executable, "-m", "twinwatch", "watch", "--connect",
                                 fleet3.ep, "--interval", "0.5"], stdout=f,
                                stderr=subprocess.PIPE, text=True, env=watch_env())
        try:
            wait_for(lambda: out.read_text().count("machines") >= 2, 60,
                     "two refreshes written while it runs")
            assert proc.poll() is None
        finally:
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    text = out.read_text()
    running = [n for n, p in fleet3.procs.items() if p.poll() is None]  # m3 may be killed
    assert {"m1", "m2"} <= set(running) and all(n in text for n in running), (running, text)
    assert any("parameters (vs nominal)" in ln for ln in text.splitlines())


@pytest.mark.slow  # two daemons in real time behind two routers
def test_watch_once_json_over_two_endpoints_lists_every_machine(tmp_path: Any) -> None:
    """Issue 24: `--connect A --connect B` in client mode showed only the machines behind A
    (a client session talks to one endpoint). Two routers on two ports, one daemon behind
    each: `watch --once --json` over both lists both."""
    eps = [endpoint(free_port()), endpoint(free_port())]
    procs: list[subprocess.Popen[str]] = []
    with zsession("router", listen=[eps[0]]) as ra, zsession("router", listen=[eps[1]]) as rb:
        cols = [Collector(ra, "twinwatch/*/health"), Collector(rb, "twinwatch/*/health")]
        try:
            for name, ep in (("ma", eps[0]), ("mb", eps[1])):
                d = tmp_path / name
                d.mkdir()
                (d / "m.toml").write_text(watch_daemon_config(name, ep))
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "twinwatch", "run", "m.toml", "--no-progress"],
                    cwd=d, env=watch_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                    text=True))
            wait_for(lambda: all(c.snapshot() for c in cols), 120, "a window behind each")
            r = _twinwatch("watch", "--connect", eps[0], "--connect", eps[1], "--once",
                           "--json", "--wait", "3")
            assert r.returncode == 0, r.stderr
            names = sorted(m["machine"] for m in json.loads(r.stdout)["machines"])
            assert names == ["ma", "mb"], names
        finally:
            for c in cols:
                c.sub.undeclare()
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in procs:
                try:
                    p.communicate(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.communicate()


def test_rul_and_deviation_alarms_apart_and_losses_only() -> None:
    """Issue 24: "alarms: none" stood beside "last: Ra normal -> warning" (a RUL warning), and
    the loss column listed the driver's activity (``driver_polls``, ``driver_duplicates``).
    Now the RUL's level is its own line ("Ra RUL WARNING"), the last event says its kind, and
    only losses are listed."""
    import io

    msg = _msg("m1", 7, ra_dev=-3.0)
    msg["alarms"]["Ra"]["rul"] = {"level": "warning", "since_t": 488.0, "since_window": 5,
                                  "rul_s": 500.0, "pending": None}
    msg["counters"].update({"driver_polls": 10265, "driver_duplicates": 9})
    fleet = Fleet(clock=Clock())
    fleet.token("m1", True)
    fleet.health("m1", msg)
    fleet.alarm("m1", {"parameter": "Ra", "kind": "rul", "previous": "normal",
                       "level": "warning", "t": 488.0})
    (m,) = fleet.snapshot()["machines"]
    assert m["alarms"]["Ra"]["level"] == "normal"
    assert m["alarms"]["Ra"]["rul"]["level"] == "warning"
    assert m["quality"]["problems"] == {"windows_abandoned": 2, "driver_gaps": 1}
    from rich.console import Console

    buf = io.StringIO()
    Console(file=buf, width=400).print(render(fleet.snapshot(), title="fleet"))  # unfolded
    text = buf.getvalue()
    assert "Ra RUL WARNING since t=488 s" in text
    assert "last: Ra RUL normal -> warning at 488 s" in text
    assert "alarms: none" not in text and "driver_polls" not in text
    assert "driver_duplicates" not in text and "driver_gaps 1" in text


def test_machines_on_their_own_ports_are_watched_with_a_connect_each() -> None:
    """Issue 24: the hydraulic example is a peer on its own port (7448) beside the default one
    (7447), and never appeared in a plain `watch` (7447). As docs/operating.md says: one
    `--connect` per port lists both; a watch of one port lists only the machine there (no
    scouting: a peer does not tell of the other). Two peers, each a machine on its own port
    (its token and its latest window, as a daemon declares them)."""
    eps = [endpoint(free_port()), endpoint(free_port())]
    sessions, held = [], []
    try:
        for name, ep in (("dc-motor-sim", eps[0]), ("hydraulic-sim", eps[1])):
            s = zsession("peer", listen=[ep])
            sessions.append(s)
            doc = json.dumps(_msg(name, 4))
            held.append(s.liveliness().declare_token(f"twinwatch/{name}/alive"))
            held.append(s.declare_queryable(
                f"twinwatch/{name}/health",
                lambda q, doc=doc, name=name: q.reply(f"twinwatch/{name}/health", doc)))
        both = _twinwatch("watch", "--connect", eps[0], "--connect", eps[1], "--once",
                          "--json", "--wait", "3")
        assert both.returncode == 0, both.stderr
        found = {m["machine"]: m["window"] for m in json.loads(both.stdout)["machines"]}
        assert found == {"dc-motor-sim": 4, "hydraulic-sim": 4}, found
        one = _twinwatch("watch", "--connect", eps[0], "--once", "--json", "--wait", "3")
        assert one.returncode == 0, one.stderr
        assert [m["machine"] for m in json.loads(one.stdout)["machines"]] == ["dc-motor-sim"]
    finally:
        for h in held:
            h.undeclare()
        for s in sessions:
            s.close()


def test_watch_finds_the_configured_machines_on_their_own_ports(tmp_path: Any) -> None:
    """Issue 37: `watch` missed a machine publishing on another port unless given `--connect`
    for it. `--config` with a gateway's directory watches every machine configured there, on
    the endpoint its [zenoh] table listens on (0.0.0.0 read as loopback), with their key
    prefix; one whose daemon does not run is skipped with a note, the others are listed."""
    eps = [endpoint(free_port()), endpoint(free_port())]
    down = free_port()
    gateway = tmp_path / "gateway"
    gateway.mkdir()
    for name, ep in (("m1", eps[0]), ("m2", eps[1].replace("127.0.0.1", "0.0.0.0")),
                     ("m3", endpoint(down))):
        (gateway / f"{name}.toml").write_text(
            f'[machine]\nname = "{name}"\n\n[zenoh]\nlisten = ["{ep}"]\nkey_prefix = "plant/a"\n')
    (gateway / "m4.toml").write_text('[machine]\nname = "m4"\n\n[zenoh]\nenabled = false\n')
    sessions, held = [], []
    try:
        for name, ep in (("m1", eps[0]), ("m2", eps[1])):
            s = zsession("peer", listen=[ep])
            sessions.append(s)
            doc = json.dumps(_msg(name, 4))
            held.append(s.liveliness().declare_token(f"plant/a/{name}/alive"))
            held.append(s.declare_queryable(
                f"plant/a/{name}/health",
                lambda q, doc=doc, name=name: q.reply(f"plant/a/{name}/health", doc)))
        r = _twinwatch("watch", "--config", str(gateway), "--once", "--json", "--wait", "3")
        assert r.returncode == 0, r.stderr
        found = {m["machine"]: m["window"] for m in json.loads(r.stdout)["machines"]}
        assert found == {"m1": 4, "m2": 4}, found
        assert f"nothing answers at {endpoint(down)} (m3.toml): not watched" in r.stderr
        assert "Traceback" not in r.stderr
        one = _twinwatch("watch", "--config", str(gateway / "m2.toml"), "--once", "--json",
                         "--wait", "3")
        assert one.returncode == 0, one.stderr
        assert [m["machine"] for m in json.loads(one.stdout)["machines"]] == ["m2"]
    finally:
        for h in held:
            h.undeclare()
        for s in sessions:
            s.close()


def test_the_configured_endpoints_are_read_from_the_zenoh_tables(tmp_path: Any) -> None:
    """What `watch --config` connects to: the shipped examples' ports (7447, the hydraulic
    ones' 7448 and 7449, the OPC UA ones' 7450 and 7451, the CANopen one's 7453, the TLS
    example's router), a client's router, none for a machine whose Zenoh output is off; a
    bad table is one line."""
    import click

    from twinwatch.cli.watch import config_endpoints, watch_endpoint

    found, prefixes = config_endpoints(ROOT / "config")
    assert set(found) == {f"tcp/127.0.0.1:{p}" for p in (*range(7447, 7452), 7453)} | {
        "tls/localhost:7447"}, found
    assert found["tcp/127.0.0.1:7448"] == ["hydraulic-modbus-sim.toml"]
    assert prefixes == {"twinwatch"}
    client = tmp_path / "client.toml"
    client.write_text('[zenoh]\nmode = "client"\nlisten = []\nconnect = ["tcp/10.0.0.2:7447"]\n')
    assert config_endpoints(client) == ({"tcp/10.0.0.2:7447": ["client.toml"]}, {"twinwatch"})
    assert watch_endpoint("tcp/[::]:7447") == "tcp/[::1]:7447"
    assert watch_endpoint("tcp/0.0.0.0:7448#iface=eth0") == "tcp/127.0.0.1:7448"
    bad = tmp_path / "bad.toml"
    bad.write_text('[zenoh]\nlistn = ["tcp/127.0.0.1:7447"]\n')
    with pytest.raises(click.BadParameter, match=r"bad.toml: zenoh.listn: "):
        config_endpoints(bad)
    r = _twinwatch("watch", "--config", str(bad), "--once")
    assert r.returncode == 2 and "zenoh.listn" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize(("kwargs", "named"), [({"history": 0}, "history 0"),
                                               ({"alarm_history": -1}, "alarm_history -1")])
def test_a_bad_history_request_is_refused_naming_it(kwargs: dict[str, int], named: str) -> None:
    """Each of the two counts is refused under its own name (a bad alarm_history was once
    reported as history), before any subscriber is declared."""
    from twinwatch.watch.subscription import WatchError

    with pytest.raises(WatchError, match=named):
        FleetWatcher(None, Fleet(), **kwargs)  # type: ignore[arg-type]
