"""The fleet's question from the summaries (issue 39, items 2 and 4): ``twinwatch watch --fleet``
ranks machines by urgency, filters them, counts them by box, lists a screen's worth and counts
the rest; ``twinwatch fleet report`` lists exactly the machines due within the horizon, with
the part and the action. Publishers are the daemon's Zenoh output (clients of a router on
loopback, a free port, scouting off), the summaries synthetic.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from twinwatch.cli import main
from twinwatch.sinks.zenoh import HealthPublisher, ZenohConfig
from twinwatch.twin.health import read_health
from twinwatch.twin.summary import fleet_summary
from twinwatch.watch.ranking import (
    Received,
    due,
    fleet_view,
    parse_duration,
    service_report,
    urgency,
)

from .helpers.fleet import health
from .helpers.net import endpoint, free_port, router_on

DAY = 86400.0


def rul(days_low: float, days: float | None = None, days_high: float | None = None
        ) -> dict[str, Any]:
    days = days_low * 1.5 if days is None else days
    return {"status": "predicted", "rul_s": days * DAY, "low_s": days_low * DAY,
            "high_s": None if days_high is None else days_high * DAY}


#: machine -> (box, health keywords, due within 7 days?)
FLEET: dict[str, tuple[str, dict[str, Any], bool]] = {
    "a-rul-3d": ("gw-a", {"rul": rul(3)}, True),
    "a-rul-6.9d": ("gw-a", {"rul": rul(6.9, 9, 12)}, True),
    "a-rul-8d": ("gw-a", {"rul": rul(8, 12)}, False),
    "a-crossed": ("gw-a", {"rul": {"status": "crossed"}, "level": "alarm"}, True),
    "b-fault-alarm": ("gw-b", {"rul": rul(300), "status": "fault", "raised": True}, True),
    "b-fault-high": ("gw-b", {"rul": rul(300), "status": "fault", "probability": 0.6}, True),
    "b-fault-high-unlikely": ("gw-b", {"rul": rul(300), "status": "fault",
                                       "probability": 0.3}, False),
    "b-fault-medium": ("gw-b", {"rul": rul(300), "status": "fault", "urgency": "medium",
                                "probability": 0.9}, False),
    "c-check": ("gw-c", {"rul": rul(300), "status": "check_function"}, True),
    "c-warning": ("gw-c", {"rul": rul(30), "level": "warning"}, False),
    "c-normal": ("gw-c", {"rul": rul(300)}, False),
    "c-not-degrading": ("gw-c", {"rul": {"status": "not_reached"}}, False),
}
DUE = sorted(m for m, (_, _, d) in FLEET.items() if d)


def summaries(now: float = 1e6) -> dict[str, Received]:
    return {m: Received(fleet_summary(read_health(health(m, **kw)), box=box, wall=now), now)
            for m, (box, kw, _) in FLEET.items()}


def test_machines_rank_by_alarm_then_diagnosis_then_rul() -> None:
    ranked = [e["machine"] for e in fleet_view(summaries(), 1e6)["machines"]]
    # state alarm: the fault alarm (the diagnosis urges most) before the crossed threshold
    assert ranked[:2] == ["b-fault-alarm", "a-crossed"]
    assert ranked[2] == "c-check"  # check function next
    assert ranked[3] == "c-warning"
    # normal: the diagnosis' urgency first, then the RUL median (sooner first, none last)
    assert ranked[4:] == ["b-fault-high", "b-fault-medium", "a-rul-3d", "a-rul-6.9d",
                          "a-rul-8d", "b-fault-high-unlikely", "c-normal", "c-not-degrading"]
    keys = [urgency(r.summary) for r in summaries().values()]
    assert sorted(keys) == sorted(keys, key=lambda k: k)  # a total order


def test_the_view_filters_counts_by_box_and_lists_a_screens_worth() -> None:
    got = summaries()
    view = fleet_view(got, 1e6, limit=3)
    assert (view["machines_total"], view["matched"], view["shown"], view["more"]) == (
        12, 12, 3, 9)
    assert view["states"] == {"alarm": 2, "check_function": 1, "warning": 1, "normal": 8}
    assert view["boxes"]["gw-b"] == {"machines": 4, "alarm": 1, "warning": 0,
                                     "check_function": 0, "normal": 3, "stale": 0,
                                     "first": "b-fault-alarm"}
    alarm = fleet_view(got, 1e6, states=["alarm", "warning"])
    assert sorted(e["machine"] for e in alarm["machines"]) == ["a-crossed", "b-fault-alarm",
                                                                 "c-warning"]
    assert fleet_view(got, 1e6, models=["hydraulic_actuator"])["matched"] == 0
    late = fleet_view(got, 1e6 + 200.0, states=["stale"], stale_after=180.0)
    assert late["matched"] == 12 and late["machines"][0]["seen"] == "stale"


def test_the_report_lists_exactly_the_machines_due() -> None:
    rows = service_report(summaries(), 1e6, 7 * DAY)
    assert sorted(r["machine"] for r in rows) == DUE
    by = {r["machine"]: r for r in rows}
    assert by["b-fault-alarm"]["part"] == "armature winding"
    assert by["b-fault-alarm"]["action"] == "measure the armature resistance"
    assert by["b-fault-alarm"]["why"] == "diagnosis"
    assert by["a-rul-3d"]["why"] == "rul" and by["a-rul-3d"]["rul_low_s"] == 3 * DAY
    assert by["a-rul-3d"]["part"] == "the part behind Ra"
    assert by["a-crossed"]["why"] == "rul+alarm"
    assert by["c-check"]["part"] == "sensors and model"
    # an 8-day RUL is due in a 9-day horizon, and after 1.5 days of age in a 7-day one
    assert "a-rul-8d" in {r["machine"] for r in service_report(summaries(), 1e6, 9 * DAY)}
    old = summaries(now=1e6 - 1.5 * DAY)
    assert "a-rul-8d" in {r["machine"] for r in service_report(old, 1e6, 7 * DAY)}
    assert due(old["c-normal"].summary, 7 * DAY, 1.5 * DAY) == []


def test_a_summary_s_age_counts_from_when_it_was_made_not_from_when_it_arrived() -> None:
    """A summary asked with a get arrives now but was made up to a summary interval ago: its
    RUL has run down since (benchmarks/bench_fleet.py at 10 000 machines: counted from the
    arrival, fleet report missed 20 of 3378 machines due within 5 min). A box's clock ahead of
    the client's makes no summary younger than its arrival; staleness is the link's, counted
    from the arrival."""
    made = 1e6 - 1.5 * DAY
    fetched = {m: Received(fleet_summary(read_health(health(m, **kw)), box=box, wall=made), 1e6)
               for m, (box, kw, _) in FLEET.items()}
    rows = {r["machine"]: r for r in service_report(fetched, 1e6, 7 * DAY)}
    assert "a-rul-8d" in rows and rows["a-rul-8d"]["age_s"] == 1.5 * DAY
    assert rows["a-rul-3d"]["rul_low_s"] == 1.5 * DAY
    view = {e["machine"]: e for e in fleet_view(fetched, 1e6)["machines"]}
    assert view["c-normal"]["age_s"] == 1.5 * DAY and view["c-normal"]["seen"] == "alive"
    ahead = summaries(now=1e6 + 3600.0)  # made "an hour from now" by the box's clock
    ahead = {m: Received(r.summary, 1e6) for m, r in ahead.items()}
    assert {r["machine"] for r in service_report(ahead, 1e6 + 60.0, 7 * DAY)} == set(DUE)
    assert all(r["age_s"] == 60.0 for r in service_report(ahead, 1e6 + 60.0, 7 * DAY))


def test_durations() -> None:
    assert [parse_duration(x) for x in ("7d", "12h", "30min", "30m", "90s", "60", "1w")] == [
        7 * DAY, 43200.0, 1800.0, 1800.0, 90.0, 60.0, 7 * DAY]
    for bad in ("soon", "-1d", "inf"):
        with pytest.raises(ValueError):
            parse_duration(bad)


# -- the commands, through a router ------------------------------------------------------------
@pytest.fixture
def published() -> Any:
    ep = endpoint(free_port())
    with router_on(ep):
        pubs = []
        try:
            for m, (box, kw, _) in FLEET.items():
                pub = HealthPublisher(ZenohConfig(mode="client", connect=[ep], box=box), m)
                pubs.append(pub)
                doc = health(m, **kw)
                pub.publish(doc)  # the full health stays behind, fetched when asked
                pub.publish_summary(fleet_summary(read_health(doc), box=box,
                                                  wall=__import__("time").time()))
            yield ep
        finally:
            for p in pubs:
                p.close()


def test_fleet_report_through_a_router_lists_exactly_the_machines_made_due(
        published: str, tmp_path: Path) -> None:
    runner = CliRunner()
    out = runner.invoke(main, ["fleet", "report", "--connect", published, "--horizon", "7d",
                               "--json", "-", "--expect", str(len(FLEET)), "--wait", "15"])
    assert out.exit_code == 0, out.output
    doc = json.loads(out.stdout)
    assert doc["machines"] == len(FLEET)
    assert sorted(r["machine"] for r in doc["rows"]) == DUE
    path = tmp_path / "due.csv"
    out = runner.invoke(main, ["fleet", "report", "--connect", published, "--horizon", "9d",
                               "--csv", str(path), "--expect", str(len(FLEET))])
    assert out.exit_code == 0, out.output
    rows = list(csv.DictReader(path.open()))
    assert sorted(r["machine"] for r in rows) == sorted([*DUE, "a-rul-8d"])
    assert {r["machine"]: r["part"] for r in rows}["b-fault-high"] == "armature winding"
    text = runner.invoke(main, ["fleet", "report", "--connect", published,
                                "--expect", str(len(FLEET))])
    assert text.exit_code == 0 and f"{len(DUE)} of {len(FLEET)} machines" in text.output
    bad = runner.invoke(main, ["fleet", "report", "--horizon", "soon"])
    assert bad.exit_code == 2 and "not a duration" in bad.output


def test_watch_fleet_ranks_filters_groups_and_fetches_the_full_health_when_asked(
        published: str) -> None:
    runner = CliRunner()
    base = ["watch", "--fleet", "--connect", published, "--once", "--wait", "15"]
    out = runner.invoke(main, [*base, "--json", "--limit", "4"])
    assert out.exit_code == 0, out.output
    view = json.loads(out.stdout)
    assert view["machines_total"] == len(FLEET) and view["more"] == len(FLEET) - 4
    assert [m["machine"] for m in view["machines"]] == ["b-fault-alarm", "a-crossed",
                                                         "c-check", "c-warning"]
    out = runner.invoke(main, [*base, "--json", "--state", "warning", "--machines", "c-$*"])
    assert [m["machine"] for m in json.loads(out.stdout)["machines"]] == ["c-warning"]
    table = runner.invoke(main, [*base, "--limit", "2"])
    assert table.exit_code == 0, table.output
    assert "a-crossed" in table.output and "c-normal" not in table.output
    assert "and 10 more machines" in table.output
    boxes = runner.invoke(main, [*base, "--by-box"])
    assert "gw-a" in boxes.output and "gw-c" in boxes.output
    full = runner.invoke(main, ["watch", "--fleet", "--connect", published, "--show",
                                "b-fault-alarm", "--json"])
    assert full.exit_code == 0, full.output
    doc = json.loads(full.stdout)
    assert doc["machine"] == "b-fault-alarm" and doc["diagnosis"]["alarms"] == [
        "winding_short"]
    misuse = runner.invoke(main, ["watch", "--state", "alarm"])
    assert misuse.exit_code == 2 and "--fleet" in misuse.output


def test_a_fleet_laid_out_by_box_is_followed_with_a_wildcard_prefix() -> None:
    """Gateways whose ``[zenoh] key_prefix`` puts their box before their machines
    (``twinwatch/gw-a/<machine>``: a router matches a key chunk by chunk, and 10 000 machines
    in one chunk cost it quadratically, docs/fleet.md) are followed by ``--prefix
    'twinwatch/*'``: every machine once, named ``<box>/<machine>``, ranked, reported, its full
    health fetched by that name; the same machine name on two boxes is two machines."""
    ep = endpoint(free_port())
    layout = {"gw-a": ["a-crossed", "c-normal"], "gw-b": ["b-fault-alarm", "c-normal"]}
    with router_on(ep):
        pubs = []
        try:
            for box, machines in layout.items():
                for m in machines:
                    pub = HealthPublisher(ZenohConfig(mode="client", connect=[ep], box=box,
                                                      key_prefix=f"twinwatch/{box}"), m)
                    pubs.append(pub)
                    doc = health(m, **FLEET[m][1])
                    pub.publish(doc)
                    pub.publish_summary(fleet_summary(read_health(doc), box=box,
                                                      wall=__import__("time").time()))
            runner = CliRunner()
            out = runner.invoke(main, ["watch", "--fleet", "--connect", ep, "--prefix",
                                       "twinwatch/*", "--once", "--json", "--wait", "15"])
            assert out.exit_code == 0, out.output
            view = json.loads(out.stdout)
            assert [m["machine"] for m in view["machines"]] == [
                "gw-b/b-fault-alarm", "gw-a/a-crossed", "gw-a/c-normal", "gw-b/c-normal"]
            rep = runner.invoke(main, ["fleet", "report", "--connect", ep, "--prefix",
                                       "twinwatch/*", "--json", "-", "--expect", "4"])
            assert rep.exit_code == 0, rep.output
            assert sorted(r["machine"] for r in json.loads(rep.stdout)["rows"]) == [
                "gw-a/a-crossed", "gw-b/b-fault-alarm"]
            full = runner.invoke(main, ["watch", "--fleet", "--connect", ep, "--prefix",
                                        "twinwatch/*", "--show", "gw-b/b-fault-alarm",
                                        "--json"])
            assert full.exit_code == 0, full.output
            assert json.loads(full.stdout)["machine"] == "b-fault-alarm"
            bad = runner.invoke(main, ["watch", "--fleet", "--connect", ep, "--prefix",
                                       "*/twinwatch", "--once"])
            assert bad.exit_code != 0 and "a chunk after the first may be a whole *" in (
                bad.output)
            full_health = runner.invoke(main, ["watch", "--connect", ep, "--prefix",
                                               "twinwatch/*", "--once"])
            assert full_health.exit_code != 0 and "goes with watch --fleet" in (
                full_health.output)
        finally:
            for p in pubs:
                p.close()


def test_a_subscriber_per_machine_only_when_the_machines_share_one_chunk() -> None:
    """Under one chunk (``twinwatch/<machine>``) a router matches each put against every
    machine unless a subscriber sits on the machine's own key; under their boxes' chunks
    (``twinwatch/*``) 10 000 such subscribers left a far client with each machine's first
    summary only (docs/fleet.md), so none are declared there unless asked."""
    from twinwatch.watch.session import prefix_base
    from twinwatch.watch.summaries import SummaryWatcher

    assert SummaryWatcher(object()).exact  # type: ignore[arg-type]
    boxed = SummaryWatcher(object(), prefix="twinwatch/*")  # type: ignore[arg-type]
    assert not boxed.exact and boxed.key == "twinwatch/*/*/summary"
    assert SummaryWatcher(object(), prefix="acme/*", exact=True).exact  # type: ignore[arg-type]
    assert prefix_base("acme/plant1/*/line") == "acme/plant1"


# -- issue 56: the worst parameter, a stopped daemon's machines, waiting for the fleet ---------
def _drifting(machine: str, d_dev: float, ra_dev: float = 0.0) -> dict[str, Any]:
    doc = health(machine, ra_dev=ra_dev)
    doc["parameters"]["D"]["deviation_pct"] = d_dev
    doc["parameters"]["D"]["value"] = 0.00143 * (1 + d_dev / 100)
    return doc


def test_the_worst_parameter_by_its_own_threshold() -> None:
    """D +20 % without a rule (5 %: share 4) outranks Ra nominal; with its own rule at 50 %
    (bearing wear), D +20 % (0.4 of it) is below Ra -3 % (0.6 of Ra's 5 %)."""
    from twinwatch.sinks.base import AlarmBands
    from twinwatch.sinks.zenoh import worst_parameter

    ra = {"Ra": AlarmBands(warning_high=5.0, warning_low=-5.0, alarm_high=10.0,
                           alarm_low=-10.0)}
    assert worst_parameter(read_health(_drifting("m", 20.0)), ra) == {
        "parameter": "D", "deviation_pct": 20.0, "threshold_pct": None, "share": 4.0}
    both = {**ra, "D": AlarmBands(warning_high=50.0, alarm_high=100.0)}
    worst = worst_parameter(read_health(_drifting("m", 20.0, ra_dev=-3.0)), both)
    assert worst is not None and (worst["parameter"], worst["share"]) == ("Ra", 0.6)
    # a side the rule does not watch counts nothing (D falling, its rule high only)
    worst = worst_parameter(read_health(_drifting("m", -20.0)), both)
    assert worst is not None and worst["parameter"] == "Ra"


def test_watch_fleet_shows_d_plus_20_on_a_machine_whose_ra_is_nominal() -> None:
    """Issue 56's done-when: the daemon's Zenoh output sends the worst parameter with the
    summary and `watch --fleet` leads the deviation column with it (before: Ra +0.00 %
    only, the machine looking healthy)."""
    import types

    from twinwatch.sinks.base import AlarmBands, SinkContext

    ep = endpoint(free_port())
    with router_on(ep):
        ctx = SinkContext(machine="m-d20", model="dc_motor", alarm_bands={"Ra": AlarmBands(
            warning_high=5.0, warning_low=-5.0, alarm_high=10.0, alarm_low=-10.0)})
        pub = HealthPublisher.open("zenoh", ZenohConfig(mode="client", connect=[ep],
                                                        box="gw-a"), ctx)
        try:
            doc = _drifting("m-d20", 20.0)
            pub.write(types.SimpleNamespace(health=read_health(doc), health_json=json.dumps(
                doc), events=[]))  # type: ignore[arg-type]
            runner = CliRunner()
            base = ["watch", "--fleet", "--connect", ep, "--once", "--wait", "15"]
            out = runner.invoke(main, [*base, "--json"])
            assert out.exit_code == 0, out.output
            (m,) = json.loads(out.stdout)["machines"]
            assert m["worst"] == {"parameter": "D", "deviation_pct": 20.0,
                                  "threshold_pct": None, "share": 4.0}
            table = runner.invoke(main, base, terminal_width=200)
        finally:
            pub.close()
    row = next(line for line in table.output.splitlines() if "m-d20" in line)
    assert "D +20.00 %" in row and row.index("D +20.00 %") < row.index("Ra +0.00 %"), row


def test_a_stopped_daemons_machines_are_stale_at_once_from_their_token() -> None:
    """Issue 56: a daemon that stops takes its liveliness token with it: its machine is shown
    stale at once (before: current for 180 s, 3 summary intervals); the other stays alive, and
    a machine back (its token again) is alive again."""
    import time

    from twinwatch.watch.summaries import following

    ep = endpoint(free_port())
    with router_on(ep):
        pubs = {}
        for m in ("m-stays", "m-stops"):
            pubs[m] = HealthPublisher(ZenohConfig(mode="client", connect=[ep], box="gw-a"), m)
            pubs[m].publish_summary(fleet_summary(read_health(health(m)), box="gw-a",
                                                  wall=time.time()))
        try:
            with following([ep], "client", "twinwatch") as summaries:
                summaries.settle(15, expected=2)

                def seen() -> dict[str, str]:
                    view = fleet_view(summaries.received, time.time())
                    return {r["machine"]: r["seen"] for r in view["machines"]}

                assert seen() == {"m-stays": "alive", "m-stops": "alive"}
                pubs.pop("m-stops").close()
                deadline = time.monotonic() + 20
                while seen()["m-stops"] != "stale" and time.monotonic() < deadline:
                    summaries.wait(0.2)
                assert seen() == {"m-stays": "alive", "m-stops": "stale"}
                rows = fleet_view(summaries.received, time.time())["machines"]
                gone = {r["machine"]: r["gone_s"] for r in rows}
                assert gone["m-stays"] is None and gone["m-stops"] is not None
                again = HealthPublisher(ZenohConfig(mode="client", connect=[ep], box="gw-a"),
                                        "m-stops")
                pubs["m-stops"] = again
                deadline = time.monotonic() + 20
                while seen()["m-stops"] != "alive" and time.monotonic() < deadline:
                    summaries.wait(0.2)
                assert seen() == {"m-stays": "alive", "m-stops": "alive"}
        finally:
            for p in pubs.values():
                p.close()


def test_watch_fleet_waits_for_the_network_and_the_first_summary_saying_so() -> None:
    """Issue 56: `watch --fleet` before any daemon is up waits (before: exit 1 at once), one
    line for the network not answering yet and one for the first summary, then follows."""
    import threading
    import time

    from twinwatch.cli.watch import fleet_following

    from .helpers.net import Router

    ep = endpoint(free_port())
    router = Router(ep)
    lines: list[str] = []
    pubs: list[HealthPublisher] = []

    def sleep(delay: float) -> None:  # the network's first retry: the router comes up
        if router.session is None:
            router.start()
        time.sleep(min(delay, 0.1))

    def publish_later() -> None:
        pub = HealthPublisher(ZenohConfig(mode="client", connect=[ep], box="gw-a"), "m-late")
        pubs.append(pub)
        pub.publish_summary(fleet_summary(read_health(health("m-late")), box="gw-a",
                                          wall=time.time()))

    def say(line: str) -> None:
        lines.append(line)
        if "first fleet summary" in line:  # connected, nothing yet: a daemon starts now
            threading.Thread(target=publish_later).start()

    try:
        with fleet_following((ep,), "client", "twinwatch", "*", wait=True, say=say,
                             sleep=sleep) as summaries:
            got = sorted(summaries.received)
    finally:
        for p in pubs:
            p.close()
        router.stop()
    assert got == ["m-late"]
    assert len(lines) == 2, lines
    assert lines[0].startswith("twinwatch: waiting for the fleet: cannot connect to " + ep)
    assert lines[1].startswith("twinwatch: waiting for the first fleet summary on "
                               "twinwatch/*/summary")
