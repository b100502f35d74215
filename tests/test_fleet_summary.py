"""The fleet summary (issue 39, item 1): what it says of a window's health message, when a
machine publishes it (on change, at least every ``[zenoh] summary_interval``), and that a late
joiner through a router gets every machine's latest (the summary publisher's cache and the
latest-get), on loopback with free ports and scouting off.
"""

from __future__ import annotations

import contextlib
import json
import time
from types import SimpleNamespace
from typing import Any

import pytest
from pydantic import ValidationError

from twinwatch.config.loader import ConfigError, load_config
from twinwatch.sinks.zenoh import HealthPublisher, ZenohConfig
from twinwatch.twin.health import read_health
from twinwatch.twin.summary import fleet_summary, summary_changed
from twinwatch.watch.summaries import SummaryWatcher, machines_key

from .helpers.fleet import FakeSession, health, summary
from .helpers.net import endpoint, free_port, router_on, wait_for, zsession
from .helpers.paths import ROOT


# -- what it says ------------------------------------------------------------------------------
def test_a_summary_holds_state_alarms_fault_rul_and_deviations_in_a_few_hundred_bytes() -> None:
    s = summary(status="fault", raised=True, level="warning")
    assert s["state"] == "alarm"  # the fault's probability alarm is raised
    assert s["alarms"] == {"Ra": {"level": "warning", "rul": "normal"}}
    assert s["deviation"] == {"Ra": -1.2}  # the ruled parameters only
    assert s["diagnosis"] == {"status": "fault", "fault": "winding_short", "probability": 0.9,
                              "part": "armature winding",
                              "action": "measure the armature resistance",
                              "urgency": "high", "alarm": True}
    assert s["rul"] == {"parameter": "Ra", "status": "predicted", "median_s": 5000.0,
                        "low_s": 4000.0, "high_s": 7000.0}
    assert (s["machine"], s["box"], s["run"], s["window"]) == ("m1", "gw-a", "r1", 10)
    assert len(json.dumps(s, separators=(",", ":"))) < 700
    assert summary(level="warning")["state"] == "warning"
    assert summary(rul_level="alarm")["state"] == "alarm"
    assert summary(status="check_function")["state"] == "check_function"
    assert summary()["state"] == "normal"
    assert summary()["diagnosis"]["fault"] is None  # no fault: no part, no action
    crossed = summary(rul={"status": "crossed"})["rul"]
    assert (crossed["status"], crossed["median_s"], crossed["low_s"]) == ("crossed", 0.0, 0.0)
    none = summary(rul={"status": "not_reached"})
    assert none["rul"] is None


def test_a_summary_reads_an_older_message_without_the_parts() -> None:
    s = fleet_summary(read_health({"schema": 6, "machine": "m1", "run": "r", "window": 1}),
                      box="b", wall=0.0)
    assert (s["state"], s["alarms"], s["diagnosis"], s["rul"]) == ("normal", {}, None, None)


def test_what_counts_as_a_change() -> None:
    base = summary()
    assert summary_changed(None, base)
    assert not summary_changed(base, summary(window=11, ra_dev=-1.3))  # drift: the interval
    assert summary_changed(base, summary(level="warning"))
    assert summary_changed(base, summary(status="fault"))
    assert summary_changed(base, summary(status="fault", raised=True))
    moved = {"status": "predicted", "rul_s": 4000.0, "low_s": 3000.0, "high_s": 6000.0}
    assert summary_changed(base, summary(rul=moved))  # 20 % sooner
    near = {"status": "predicted", "rul_s": 4800.0, "low_s": 3800.0, "high_s": 6000.0}
    assert not summary_changed(base, summary(rul=near))  # 4 %


# -- the configuration -------------------------------------------------------------------------
def test_summary_interval_is_checked_naming_the_key(tmp_path: Any) -> None:
    assert ZenohConfig().summary_interval == 60.0
    assert ZenohConfig(summary_interval=5).summary_interval == 5.0
    for bad in (0, -1, "often"):
        with pytest.raises(ValidationError, match="summary_interval"):
            ZenohConfig(summary_interval=bad)
    path = tmp_path / "m.toml"
    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    path.write_text(text.replace("[zenoh]", "[zenoh]\nsummary_interval = 0", 1))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    # one line naming the key (under the file's heading, as every bad key is said)
    assert "zenoh.summary_interval: Input should be greater than 0" in str(err.value)
    assert len(str(err.value).strip().splitlines()) == 2


# -- when it goes out, and a late joiner -------------------------------------------------------
def test_published_on_change_and_at_least_every_interval_and_a_late_joiner_gets_each_latest(
        ) -> None:
    ep = endpoint(free_port())
    with router_on(ep):
        cfg = ZenohConfig(mode="client", connect=[ep], summary_interval=3600.0, box="gw-a")
        pubs = {m: HealthPublisher(cfg, m) for m in ("m1", "m2", "m3")}
        try:
            pub = pubs["m1"]
            assert pub.publish_summary(summary(window=1), now=0.0)
            assert not pub.publish_summary(summary(window=2), now=10.0)  # no change
            assert pub.publish_summary(summary(window=3, level="warning"), now=11.0)
            assert not pub.publish_summary(summary(window=4, level="warning"), now=12.0)
            assert pub.publish_summary(summary(window=5, level="warning"), now=3611.0)
            assert pub.summaries == 3
            # the window pipeline's call: the health, then the summary (its first: a change)
            doc = health("m2", 7, status="fault", raised=True)
            pubs["m2"].write(SimpleNamespace(health=read_health(doc),  # type: ignore[arg-type]
                                             health_json=json.dumps(doc), events=[]))
            assert pubs["m2"].summaries == 1
            pubs["m3"].publish_summary(summary(machine="m3", window=9))
            # a watcher joining now, through the router, holds each machine's latest
            with zsession("client", connect=[ep]) as session, \
                    SummaryWatcher(session) as watcher:
                watcher.settle(10.0, expected=3)
                got = {m: (r.summary["window"], r.summary["state"])
                       for m, r in watcher.received.items()}
                assert got == {"m1": (5, "warning"), "m2": (7, "alarm"), "m3": (9, "normal")}
                assert watcher.received["m2"].summary["box"] == "gw-a"
                # a new summary reaches it live
                pubs["m3"].publish_summary(summary(machine="m3", window=12, level="alarm"))
                wait_for(lambda: watcher.received["m3"].summary["window"] == 12, 10.0,
                         "m3's new summary")
                # the full health only when asked
                full = watcher.health("m2")
                assert full is not None and full.window == 7
                # and the latest answers a plain get on the summary key
                replies = [json.loads(r.ok.payload.to_string())
                           for r in session.get("twinwatch/*/summary", timeout=5.0)
                           if r.ok is not None]
                assert sorted(r["machine"] for r in replies) == ["m1", "m2", "m3"]
        finally:
            for p in pubs.values():
                p.close()


def test_the_watcher_declares_each_machine_s_own_key_and_gets_each_summary_once() -> None:
    """Issue 39: the router that delivers to a fleet client computed the route of every
    summary anew (58 % of its CPU in zenoh's Resource::get_matches, growing with the fleet:
    a route is cached only for a key that has a subscriber on that very key). The watcher
    declares one, doing nothing, for each machine it holds; each summary still reaches
    ``on_summary`` once, and closing undeclares them."""
    ep = endpoint(free_port())
    with router_on(ep):
        cfg = ZenohConfig(mode="client", connect=[ep], summary_interval=3600.0)
        pubs = {m: HealthPublisher(cfg, m) for m in ("m1", "m2")}
        seen: list[tuple[str, int]] = []
        try:
            for m, p in pubs.items():
                p.publish_summary(summary(machine=m, window=1))
            with zsession("client", connect=[ep]) as session:
                watcher = SummaryWatcher(session, on_summary=lambda m, s: seen.append(
                    (m, s["window"])))
                with watcher:
                    watcher.settle(10.0, expected=2)
                    wait_for(lambda: all(watcher._exact.get(m) is not None
                                         for m in ("m1", "m2")), 10.0, "the exact keys")
                    for w in (2, 3):
                        pubs["m1"].publish_summary(summary(machine="m1", window=w,
                                                           level="warning" if w == 2 else
                                                           "alarm"))
                    wait_for(lambda: ("m1", 3) in seen, 10.0, "m1's window 3")
                    time.sleep(0.5)
                    assert sorted(seen) == [("m1", 1), ("m1", 2), ("m1", 3), ("m2", 1)], seen
                assert watcher._exact == {}
        finally:
            for p in pubs.values():
                p.close()


class _Republishing(FakeSession):
    """A session whose summary subscriber gets m1's latest before ``declare_subscriber``
    returns, as from a publisher's matching listener that republishes at once
    (``HealthPublisher._on_summary_matching``), and whose get answers m1 the same again."""

    def __init__(self) -> None:
        super().__init__()
        self.declared: list[str] = []
        self.latest = summary(machine="m1", window=1)

    def declare_subscriber(self, key: str, callback: Any) -> Any:
        self.declared.append(key)
        if key == "twinwatch/*/summary":
            text = json.dumps(self.latest)
            callback(SimpleNamespace(key_expr="twinwatch/m1/summary",
                                     payload=SimpleNamespace(to_string=lambda: text)))
        return super().declare_subscriber(key, callback)

    def get(self, key: str, handler: Any, **kw: Any) -> None:
        self.gets.append(key)
        self.reply(handler, "m1", self.latest)
        handler.drop()


def test_a_summary_that_comes_while_the_watcher_subscribes_gets_its_exact_key() -> None:
    """The summary a publisher's matching listener republishes can reach the watcher before
    its ``declare_subscriber`` returned; the machine still gets its own key's subscriber (it
    did not in 4 of 300 runs of the test above on a loaded box: the get's reply was the same
    summary, held already)."""
    session = _Republishing()
    with SummaryWatcher(session) as watcher:  # type: ignore[arg-type]
        assert watcher.queried.wait(5.0)
        assert sorted(watcher.received) == ["m1"]
        assert "twinwatch/m1/summary" in session.declared
        assert watcher._exact.get("m1") is not None


def test_the_machines_selected_by_a_key_expression() -> None:
    assert machines_key("twinwatch", "line1-$*") == "twinwatch/line1-$*/summary"
    from twinwatch.errors import WatchError

    for bad in ("a/b", "**", ""):
        with pytest.raises(WatchError, match="machines"):
            machines_key("twinwatch", bad)


def test_a_key_expression_filters_the_machines_followed() -> None:
    ep = endpoint(free_port())
    with router_on(ep):
        cfg = ZenohConfig(mode="client", connect=[ep])
        pubs = {m: HealthPublisher(cfg, m) for m in ("line1-a", "line1-b", "line2-a")}
        try:
            for m, p in pubs.items():
                p.publish_summary(summary(machine=m))
            with zsession("client", connect=[ep]) as session, \
                    SummaryWatcher(session, machines="line1-$*") as watcher:
                watcher.settle(10.0, expected=2)
                time.sleep(0.5)
                assert sorted(watcher.received) == ["line1-a", "line1-b"]
        finally:
            for p in pubs.values():
                p.close()


def test_after_a_router_outage_the_watcher_gets_each_machines_latest_again() -> None:
    """The summaries published while the router was down never reach the watcher when they
    are sent; once the router is back each machine's latest does: each publisher sends it
    again when the watcher's subscription is reachable again (``summaries_resent``), and
    the watcher asks the machines whose tokens came back (the asks are the fake sessions'
    tests below: here the resent summary often comes first)."""
    from .helpers.net import Router

    ep = endpoint(free_port())
    router = Router(ep)
    router.start()
    pubs = {m: HealthPublisher(ZenohConfig(mode="client", connect=[ep]), m)
            for m in ("m1", "m2")}
    session = zsession("client", connect=[ep])
    try:
        with SummaryWatcher(session) as watcher:
            for m, p in pubs.items():
                p.publish_summary(summary(machine=m, window=1))
            watcher.settle(10.0, expected=2)
            assert watcher.queried.wait(10.0)
            asked = watcher.asked
            router.stop()
            time.sleep(1.0)
            for m, p in pubs.items():  # state changes nobody hears
                assert p.publish_summary(summary(machine=m, window=2, level="alarm"))
            router.start()
            wait_for(lambda: all(r.summary["window"] == 2
                                 for r in watcher.received.values()), 20.0,
                     "each machine's latest after the router came back")
            assert {r.summary["state"] for r in watcher.received.values()} == {"alarm"}
            assert all(p.counters()["summaries_resent"] >= 1 for p in pubs.values())
            assert watcher.asked >= asked
    finally:
        session.close()
        for p in pubs.values():
            p.close()
        router.stop()


def test_machines_back_from_a_router_are_asked_by_their_box_not_the_whole_fleet() -> None:
    """A router's boxes back at once: one get per box whose machines came back (the others'
    machines are not asked again); a few machines one by one; flat keys one get for all."""
    boxed = SummaryWatcher(object(), prefix="twinwatch/*", machines="line1-$*")  # type: ignore[arg-type]
    many = {f"gw-{b}/line1-m{j:02d}" for b in ("a", "b") for j in range(15)}
    assert boxed._reask_keys(many) == ["twinwatch/gw-a/line1-$*/summary",
                                       "twinwatch/gw-b/line1-$*/summary"]
    assert boxed._reask_keys({"gw-a/m1", "gw-b/m2"}) == ["twinwatch/gw-a/m1/summary",
                                                          "twinwatch/gw-b/m2/summary"]
    flat = SummaryWatcher(object(), prefix="twinwatch")  # type: ignore[arg-type]
    assert flat._reask_keys({f"m{j:02d}" for j in range(30)}) == ["twinwatch/*/summary"]


class _LateQueryables(FakeSession):
    """A session whose gets find no machine's queryable for the first ``silent`` asks after
    the start (a router back: the tokens came before its queryables were known)."""

    def __init__(self, silent: int) -> None:
        super().__init__()
        self.silent = silent
        self.latest = summary(machine="m1", window=2, level="alarm")

    def get(self, key: str, handler: Any, **kw: Any) -> None:
        self.gets.append(key)
        if len(self.gets) > 1 + self.silent:  # the first ask, then the silent ones
            self.reply(handler, "m1", self.latest)
        handler.drop()


def _held_then_back(watcher: SummaryWatcher) -> None:
    """``m1`` held at window 1, then its token appears again (a router back)."""
    import zenoh

    assert watcher.queried.wait(5.0)
    watcher.put("m1", summary(machine="m1", window=1))
    watcher._on_token(SimpleNamespace(kind=zenoh.SampleKind.PUT,  # type: ignore[arg-type]
                                      key_expr="twinwatch/m1/alive"))


def test_a_machine_back_that_does_not_answer_is_asked_again_until_it_does(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from twinwatch.watch import summaries

    monkeypatch.setattr(summaries, "REASK_RETRIES_S", (0.2, 0.4, 0.8, 1.6))

    session = _LateQueryables(silent=2)
    with SummaryWatcher(session) as watcher:  # type: ignore[arg-type]
        _held_then_back(watcher)
        wait_for(lambda: watcher.received["m1"].summary["window"] == 2, 10.0,
                 "the machine's latest, asked again after no answer")
        assert session.gets == ["twinwatch/*/summary"] + ["twinwatch/m1/summary"] * 3
        time.sleep(1.5)  # answered: not asked again
        assert len(session.gets) == 4
    # a machine that never answers is asked a bounded number of times
    session = _LateQueryables(silent=100)
    with SummaryWatcher(session) as watcher:  # type: ignore[arg-type]
        _held_then_back(watcher)
        wait_for(lambda: len(session.gets) == 6, 15.0, "five asks of the machine back")
        time.sleep(2.0)
        assert len(session.gets) == 6 and watcher.received["m1"].summary["window"] == 1


def test_a_gateway_listing_two_routers_goes_to_the_second_when_its_router_dies() -> None:
    """[zenoh] connect = [its router, a second]: the router it uses is killed, the gateway
    reaches the watcher through the other (docs/fleet.md: two routers per box)."""
    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    router_a = zsession("router", listen=[ep_a])
    router_b = zsession("router", listen=[ep_b], connect=[ep_a])
    pub = HealthPublisher(ZenohConfig(mode="client", connect=[ep_a, ep_b],
                                      summary_interval=0.01), "m1")  # each window sent
    session = zsession("client", connect=[ep_b])
    try:
        with SummaryWatcher(session) as watcher:
            window = iter(range(1, 1000))

            def latest_is_new() -> bool:
                w = next(window)
                assert pub.publish_summary(summary(machine="m1", window=w))
                time.sleep(0.2)
                held = watcher.received.get("m1")
                return held is not None and held.summary["window"] == w

            wait_for(latest_is_new, 10.0, "m1's summary through router A then B")
            router_a.close()
            wait_for(latest_is_new, 20.0, "m1's summary through router B alone")
            got = [r.ok for r in session.get("twinwatch/m1/summary", timeout=5.0)
                   if r.ok is not None]
            assert len(got) == 1  # its queryable answers through B too
    finally:
        session.close()
        pub.close()
        router_b.close()
        with contextlib.suppress(Exception):
            router_a.close()


@pytest.mark.parametrize("shared", [False, True], ids=["own session", "gateway"])
def test_the_latest_summary_is_sent_again_when_a_subscriber_is_reachable_again(
        shared: bool) -> None:
    """A box on two routers whose router dies: its session fails over to the other, and the
    latest summary of each machine is sent again as soon as a subscriber is reachable, so a
    watcher on the far router holds it without a get (the gets to a box went unanswered for
    20-80 s while a 10 000-machine mesh settled, docs/fleet.md). A machine of its own session
    listens on its summary publisher; a gateway's machines share one listener (the
    session's: QueryDispatch)."""
    from twinwatch.sinks.base import SharedResources

    ep_a, ep_b = endpoint(free_port()), endpoint(free_port())
    router_a = zsession("router", listen=[ep_a])
    router_b = zsession("router", listen=[ep_b], connect=[ep_a])
    res = SharedResources() if shared else None
    cfg = ZenohConfig(mode="client", connect=[ep_a, ep_b])
    pubs = {m: HealthPublisher(cfg, m, shared=res) for m in (("m1", "m2") if shared else ("m1",))}
    session = zsession("client", connect=[ep_b])
    got: dict[str, list[int]] = {m: [] for m in pubs}

    def on(sample: Any) -> None:
        doc = json.loads(sample.payload.to_string())
        got[doc["machine"]].append(doc["window"])

    sub = session.declare_subscriber("twinwatch/*/summary", on)
    try:
        def each_heard() -> bool:
            for m, p in pubs.items():
                p.publish_summary(summary(machine=m, window=len(got[m]) + 1))
            time.sleep(0.2)
            return all(got.values())

        # a deadline against a hang: two routers, a client on both and one on B join in
        # about a second alone, but took more than 10 s once under the CI's other worker
        wait_for(each_heard, 60.0, "each machine's summary through A then B")
        before = {m: len(w) for m, w in got.items()}
        resent = {m: p.counters()["summaries_resent"] for m, p in pubs.items()}
        router_a.close()
        wait_for(lambda: all(len(got[m]) > before[m] for m in pubs), 20.0,
                 "each latest summary sent again through B")
        for m, p in pubs.items():  # the same latest: nobody asked, nothing new published
            assert got[m][-1] == got[m][before[m] - 1], got
            assert p.counters()["summaries_resent"] > resent[m]
        if shared:  # one listener for the session, none of the machines' own
            assert all(p._matching is None for p in pubs.values())
    finally:
        sub.undeclare()
        session.close()
        for p in pubs.values():
            p.close()
        router_b.close()
        with contextlib.suppress(Exception):
            router_a.close()


class _Fleet(FakeSession):
    """A session whose first ask finds nothing; later gets answer each machine's latest
    (``latest``) that the key reaches: m1's box moved to another router, m2's did not, and
    m2's window 2 was lost meanwhile."""

    def __init__(self) -> None:
        super().__init__()
        self.latest = {m: summary(machine=m, window=2, level="alarm") for m in ("m1", "m2")}

    def get(self, key: str, handler: Any, **kw: Any) -> None:
        self.gets.append(key)
        if len(self.gets) > 1:
            for m, doc in self.latest.items():
                if key in ("twinwatch/*/summary", f"twinwatch/{m}/summary"):
                    self.reply(handler, m, doc)
        handler.drop()


def test_after_machines_came_back_every_machines_latest_is_asked_again(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A router died: m1's token came back through another router, m2's never went, but the
    mesh lost m2's window 2 while it recomputed its routes (at 10 000 machines: 716 summaries
    of boxes moved and not, held again only at the machines' next periodic summary, 71.5 s
    after the kill). After the machines back are asked, every machine's latest is asked once
    more :data:`SWEEP_AFTER_S` later, and m2's lost window arrives; a summary held is not
    taken twice. One daemon back alone (restarted) is not worth a sweep of the fleet."""
    from twinwatch.watch import summaries

    monkeypatch.setattr(summaries, "SWEEP_AFTER_S", 0.3)
    # one daemon back (a restart) is asked alone, the fleet not swept
    with SummaryWatcher(_Fleet()) as watcher:  # type: ignore[arg-type]
        _held_then_back(watcher)
        wait_for(lambda: watcher.received["m1"].summary["window"] == 2, 5.0, "m1 asked back")
        time.sleep(0.8)
        assert watcher.swept == 0
    monkeypatch.setattr(summaries, "SWEEP_MIN_MACHINES", 1)  # here: m1 stands for a router's
    session = _Fleet()
    got: list[tuple[str, int]] = []
    with SummaryWatcher(session, on_summary=lambda m, s: got.append(  # type: ignore[arg-type]
            (m, s["window"]))) as watcher:
        assert watcher.queried.wait(5.0)
        watcher.put("m2", summary(machine="m2", window=1))
        _held_then_back(watcher)
        wait_for(lambda: watcher.received["m1"].summary["window"] == 2, 5.0, "m1 asked back")
        wait_for(lambda: watcher.swept == 1, 5.0, "the sweep")
        assert watcher.received["m2"].summary["window"] == 2
        assert session.gets == ["twinwatch/*/summary", "twinwatch/m1/summary",
                                "twinwatch/*/summary"]
        assert got == [("m2", 1), ("m1", 1), ("m1", 2), ("m2", 2)]
        time.sleep(0.8)  # no token came again: no further sweep
        assert len(session.gets) == 3 and watcher.swept == 1
