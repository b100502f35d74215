"""config/zenoh-site-router.json5, the router in front of a fleet mesh (issue 39).

Its access control keeps the boxes' advanced publishers' machinery (the full health's and the
alarms' cache queryables, publisher tokens and heartbeats: the ``@adv`` keys) off the mesh, and
lets through what a fleet view reads: the summaries, the machines' liveliness tokens, the
box's queryable (``watch --fleet --show``), the full health where subscribed. Checked on
loopback with the product's own publisher declaration, against a plain router that lets the
``@adv`` token through (so the test can fail).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import zenoh

from twinwatch.sinks.zenoh import ZenohConfig, declare_publisher

from .helpers.net import endpoint, free_port, wait_for
from .helpers.paths import ROOT

SITE_ROUTER = ROOT / "config" / "zenoh-site-router.json5"


def _router(ep: str, base: Path | None) -> zenoh.Session:
    """A router on ``ep``: from the sample file (its endpoints replaced) or plain."""
    conf = zenoh.Config() if base is None else zenoh.Config.from_file(str(base))
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps([ep]))
    conf.insert_json5("connect/endpoints", json.dumps([]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def _client(ep: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([ep]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def test_the_sample_binds_to_loopback_with_scouting_off() -> None:
    """As every default configuration of the project: 127.0.0.1, no multicast or gossip."""
    conf = zenoh.Config.from_file(str(SITE_ROUTER))
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    assert json.loads(conf.get_json("access_control/enabled")) is True


@pytest.mark.parametrize("base", [SITE_ROUTER, None], ids=["site-router", "plain-router"])
def test_the_site_router_keeps_the_advanced_publishers_off_and_lets_the_summary_through(
        base: Path | None) -> None:
    ep = endpoint(free_port())
    router = _router(ep, base)
    box = far = None
    try:
        box, far = _client(ep), _client(ep)
        summaries: list[str] = []
        far.declare_subscriber("twinwatch/*/*/summary", lambda s: summaries.append(
            s.payload.to_string()))
        cfg = ZenohConfig(mode="client", connect=[ep], cache=5, heartbeat=0.5)
        health = declare_publisher(box, "twinwatch/gw1/m1/health", cfg)
        token = box.liveliness().declare_token("twinwatch/gw1/m1/alive")
        summary = box.declare_publisher("twinwatch/gw1/m1/summary")
        time.sleep(0.5)  # the declarations reach the router
        health.put(json.dumps({"window": 0}))

        def sent() -> bool:
            summary.put(json.dumps({"machine": "m1", "window": 0}))
            return bool(summaries)

        wait_for(sent, 10, "the summary through the router")
        alive = [str(r.ok.key_expr) for r in far.liveliness().get("twinwatch/*/*/alive",
                                                                   timeout=2) if r.ok]
        adv = [str(r.ok.key_expr) for r in far.liveliness().get(
            "twinwatch/gw1/m1/health/@adv/**", timeout=2) if r.ok]
        assert alive == ["twinwatch/gw1/m1/alive"]
        # `watch --fleet --show gw1/m1`: the full health from the box's queryable crosses
        box_q = box.declare_queryable("twinwatch/gw1/**", lambda q: q.reply(
            "twinwatch/gw1/m1/health", json.dumps({"window": 0})))

        def shown() -> list[str]:  # once the queryable's declaration reached the router
            return [r.ok.payload.to_string() for r in far.get("twinwatch/gw1/m1/health",
                                                              timeout=1) if r.ok]

        assert wait_for(shown, 10, "the box's queryable through the router") == [
            '{"window": 0}']
        box_q.undeclare()
        if base is None:  # a plain router: the publisher's token crosses
            assert adv and adv[0].startswith("twinwatch/gw1/m1/health/@adv/pub/"), adv
        else:
            assert adv == []
        token.undeclare()
        health.undeclare()
        summary.undeclare()
    finally:
        for s in (far, box, router):
            if s is not None:
                s.close()
