"""``[zenoh] presence = "box"`` (issue 39, fifth round): a gateway's machines sharing a session
declare no liveliness token of their own; one token per box, ``<key_prefix>/@box/<box>/<zid>``,
stands for them. The fleet watcher asks a box's machines again when its token comes back, and
``twinwatch watch`` shows them alive while it is there and gone when it goes. Real Zenoh on
loopback (free ports, scouting off), except the fake session of the flat-keys case.
"""

from __future__ import annotations

import json
import time
from types import SimpleNamespace
from typing import Any

import pytest
import zenoh
from pydantic import ValidationError

from twinwatch.config.loader import ConfigError, load_config
from twinwatch.io.keys import box_chunk, box_token_key
from twinwatch.sinks.base import SharedResources
from twinwatch.sinks.zenoh import HealthPublisher, ZenohConfig
from twinwatch.watch.fleet import Fleet
from twinwatch.watch.subscription import FleetWatcher
from twinwatch.watch.summaries import SummaryWatcher

from .helpers.fleet import FakeSession, health, summary
from .helpers.net import endpoint, free_port, router_on, wait_for, zsession
from .helpers.paths import ROOT


def tokens(session: zenoh.Session, key: str) -> list[str]:
    """The liveliness tokens under ``key`` now."""
    return sorted(str(r.ok.key_expr) for r in session.liveliness().get(key, timeout=3.0)
                  if r.ok is not None)


def box_lists(session: zenoh.Session, key: str) -> list[dict[str, Any]]:
    """What the boxes' queryables under ``key`` answer."""
    return [json.loads(r.ok.payload.to_string()) for r in session.get(key, timeout=3.0)
            if r.ok is not None]


# -- the configuration -------------------------------------------------------------------------
def test_presence_is_per_machine_by_default_and_a_bad_value_is_refused_naming_the_key(
        tmp_path: Any) -> None:
    assert ZenohConfig().presence == "machine"
    assert ZenohConfig(presence="box").presence == "box"
    with pytest.raises(ValidationError, match="presence"):
        ZenohConfig(presence="rack")  # type: ignore[arg-type]
    path = tmp_path / "m.toml"
    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    path.write_text(text.replace("[zenoh]", '[zenoh]\npresence = "rack"', 1))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "zenoh.presence" in str(err.value) and "'machine' or 'box'" in str(err.value)


def test_a_box_s_token_key_is_one_plain_chunk_per_part() -> None:
    assert box_chunk("gw-line1") == "gw-line1"
    assert box_chunk("gw line/1*") == "gw_line_1_"
    key = box_token_key("twinwatch/gw-a", "gw a", "0123abcd")
    assert key == "twinwatch/gw-a/@box/gw_a/0123abcd"
    # no machine's key expression reaches it (@box is verbatim)
    assert not zenoh.KeyExpr("twinwatch/gw-a/*/alive").intersects(zenoh.KeyExpr(key))
    assert not zenoh.KeyExpr("twinwatch/gw-a/**").intersects(zenoh.KeyExpr(key))


# -- the gateway's declarations ----------------------------------------------------------------
def test_a_gateway_with_box_presence_declares_one_token_and_none_per_machine() -> None:
    ep = endpoint(free_port())
    with router_on(ep), zsession("client", connect=[ep]) as session:
        box_cfg = ZenohConfig(mode="client", connect=[ep], box="gw a", presence="box")
        shared = SharedResources()
        pubs = {m: HealthPublisher(box_cfg, m, shared=shared) for m in ("m1", "m2", "m3")}
        # a daemon of its own session keeps its machine's token, whatever the setting
        alone = HealthPublisher(box_cfg, "solo")
        # a gateway's machine asking for its own token next to them
        mine = HealthPublisher(box_cfg.model_copy(update={"presence": "machine"}), "m4",
                               shared=shared)
        try:
            assert len({p.session.zid() for p in pubs.values()} | {mine.session.zid()}) == 1
            # (declarations reach the router a moment after they are made)
            wait_for(lambda: tokens(session, "twinwatch/*/alive") == [
                "twinwatch/m4/alive", "twinwatch/solo/alive"], 5.0, "m4's and solo's tokens")
            zid = str(pubs["m1"].session.zid())
            key = f"twinwatch/@box/gw_a/{zid}"
            wait_for(lambda: tokens(session, "twinwatch/@box/**") == [key], 5.0,
                     "the box's one token")
            assert tokens(session, "twinwatch/*/alive") == ["twinwatch/m4/alive",
                                                            "twinwatch/solo/alive"]
            assert box_lists(session, "twinwatch/@box/*/*") == [
                {"box": "gw a", "machines": ["m1", "m2", "m3"]}]
            # the gateway's other answers are unchanged
            pubs["m2"].publish_summary(summary(machine="m2", window=3))
            got = [json.loads(r.ok.payload.to_string())["window"]
                   for r in session.get("twinwatch/m2/summary", timeout=3.0)
                   if r.ok is not None]
            assert got == [3]
            pubs.pop("m1").close()
            assert box_lists(session, key) == [{"box": "gw a", "machines": ["m2", "m3"]}]
            for p in pubs.values():
                p.close()
            wait_for(lambda: tokens(session, "twinwatch/@box/**") == [], 5.0,
                     "the box's token gone with its last machine")
        finally:
            for p in (*pubs.values(), alone, mine):
                p.close()


# -- the fleet watcher -------------------------------------------------------------------------
def test_a_watcher_asks_a_box_s_machines_again_when_its_token_comes_back(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Box keys (``twinwatch/<box>/<machine>``): a box that appears for the first time costs
    no ask (its summaries come live); when gw-a's session closes and opens again (a router
    died and its boxes moved), its machines are asked with one get for gw-a's key chunk, and
    counted toward a sweep as two machines' tokens; gw-b's, whose box never went, are not
    asked."""
    from twinwatch.watch import summaries

    monkeypatch.setattr(summaries, "REASK_ONE_BY_ONE", 1)  # two machines: by box
    monkeypatch.setattr(summaries, "SWEEP_MIN_MACHINES", 2)  # gw-a's two machines make a burst
    monkeypatch.setattr(summaries, "SWEEP_AFTER_S", 0.3)
    ep = endpoint(free_port())

    def gateway(box: str, machines: tuple[str, ...]) -> list[HealthPublisher]:
        cfg = ZenohConfig(mode="client", connect=[ep], key_prefix=f"twinwatch/{box}", box=box,
                          presence="box")
        shared = SharedResources()
        return [HealthPublisher(cfg, m, shared=shared) for m in machines]

    with router_on(ep), zsession("client", connect=[ep]) as session:
        watcher = SummaryWatcher(session, prefix="twinwatch/*")
        asks: list[tuple[list[str], set[str]]] = []
        get_all = watcher._get_all

        def recorded(keys: list[str], timeout: float) -> set[str]:
            answered = get_all(keys, timeout)
            asks.append((list(keys), answered))
            return answered

        watcher._get_all = recorded  # type: ignore[method-assign]
        gw_a: list[HealthPublisher] = []
        gw_b: list[HealthPublisher] = []
        with watcher:
            assert watcher.queried.wait(10.0)
            try:
                gw_a, gw_b = gateway("gw-a", ("m1", "m2")), gateway("gw-b", ("m3",))
                for p in (*gw_a, *gw_b):
                    p.publish_summary(summary(machine=p.machine, window=1))
                watcher.settle(10.0, expected=3)
                assert sorted(watcher.received) == ["gw-a/m1", "gw-a/m2", "gw-b/m3"]
                time.sleep(1.0)  # new boxes' tokens: nothing asked
                assert asks == [(["twinwatch/*/*/summary"], set())]
                for p in gw_a:
                    p.close()
                gw_a = gateway("gw-a", ("m1", "m2"))  # the box's session back, its latest
                for p in gw_a:  # held (its put may reach the watcher before the ask or not)
                    p.publish_summary(summary(machine=p.machine, window=2))
                wait_for(lambda: len(asks) >= 2, 10.0, "gw-a's machines asked again")
                assert asks[1] == (["twinwatch/gw-a/*/summary"], {"gw-a/m1", "gw-a/m2"})
                assert {m: r.summary["window"] for m, r in watcher.received.items()} == {
                    "gw-a/m1": 2, "gw-a/m2": 2, "gw-b/m3": 1}
                wait_for(lambda: watcher.swept == 1, 5.0, "a sweep after gw-a's burst")
            finally:
                for p in (*gw_a, *gw_b):
                    p.close()


def test_a_box_token_stands_for_the_machines_of_that_box_only_on_flat_keys() -> None:
    """Flat keys (``twinwatch/<machine>``, several boxes under one prefix): the box's token
    names the box (its summaries' ``box`` as a key chunk), so only its machines are asked."""
    session = FakeSession()
    session.get = lambda key, handler, **kw: (session.gets.append(key),  # type: ignore[attr-defined]
                                              handler.drop())
    with SummaryWatcher(session) as watcher:  # type: ignore[arg-type]
        assert watcher.queried.wait(5.0)
        watcher.put("m1", {**summary(machine="m1", window=1), "box": "gw a"})
        watcher.put("m2", {**summary(machine="m2", window=1), "box": "gw-b"})
        for kind, key in ((zenoh.SampleKind.DELETE, "twinwatch/@box/gw_a/z1"),
                          (zenoh.SampleKind.PUT, "twinwatch/@box/gw-c/z2"),  # none held
                          (zenoh.SampleKind.PUT, "twinwatch/@box/gw_a/z3")):
            watcher._on_box_token(SimpleNamespace(kind=kind,  # type: ignore[arg-type]
                                                  key_expr=key))
        wait_for(lambda: len(session.gets) == 2, 5.0, "m1 asked again")
        time.sleep(0.7)
        assert session.gets == ["twinwatch/*/summary", "twinwatch/m1/summary"]


# -- twinwatch watch ---------------------------------------------------------------------------
def test_watch_shows_a_box_s_machines_alive_while_its_token_is_there_and_gone_after() -> None:
    ep = endpoint(free_port())
    with router_on(ep), zsession("client", connect=[ep]) as session:
        cfg = ZenohConfig(mode="client", connect=[ep], box="gw-a", presence="box", cache=0)
        shared = SharedResources()
        pubs = [HealthPublisher(cfg, m, shared=shared) for m in ("m1", "m2")]
        fleet = Fleet()
        seen: list[tuple[str, bool]] = []
        try:
            with FleetWatcher(session, fleet, on_token=lambda m, p: seen.append((m, p))):
                def states() -> dict[str, str]:
                    return {m["machine"]: m["state"] for m in fleet.snapshot()["machines"]}

                wait_for(lambda: states() == {"m1": "alive", "m2": "alive"}, 5.0,
                         "the box's machines alive")
                # a machine added to the gateway after its box's token: its first window
                # has the boxes' machines asked again
                pubs.append(HealthPublisher(cfg, "m3", shared=shared))
                pubs[-1].publish(health("m3", 1))
                wait_for(lambda: states().get("m3") == "alive", 5.0, "m3 alive")
                for p in pubs:
                    p.close()
                wait_for(lambda: set(states().values()) == {"gone"}, 5.0,
                         "the box's machines gone with its token")
                assert sorted(seen) == [("m1", False), ("m1", True), ("m2", False),
                                        ("m2", True), ("m3", False), ("m3", True)]
        finally:
            for p in pubs:
                p.close()
