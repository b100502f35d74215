"""Health messages and fleet summaries as daemons publish them, and a Zenoh session stand-in
for the fleet watchers."""

from __future__ import annotations

import json
from types import SimpleNamespace
from typing import Any

from twinwatch.twin.health import read_health
from twinwatch.twin.summary import fleet_summary


def health(machine: str = "m1", window: int = 10, *, ra_dev: float = -1.2,
           level: str = "normal", rul_level: str = "normal", status: str = "no_fault",
           fault: str = "winding_short", urgency: str = "high", probability: float = 0.9,
           raised: bool = False, rul: dict[str, Any] | None = None) -> dict[str, Any]:
    """A health message as a daemon publishes it (the parts a summary reads)."""
    crossing = rul or {"status": "predicted", "rul_s": 5000.0, "low_s": 4000.0,
                       "high_s": 7000.0}
    return {
        "schema": 10, "machine": machine, "model": "dc_motor", "run": "r1", "window": window,
        "t_start": 2.0 * window, "t_end": 2.0 * window + 1.99, "samples": 200,
        "parameters": {
            "Ra": {"value": 6.5 * (1 + ra_dev / 100), "unit": "ohm", "nominal": 6.5,
                   "deviation_pct": ra_dev, "status": "estimated",
                   "rul": {"status": "degrading", "method": "monte_carlo",
                           "alarm": {"threshold": 5.85, **crossing}}},
            "D": {"value": 0.00143, "unit": "N m s/rad", "nominal": 0.00143,
                  "deviation_pct": 0.01, "status": "estimated"}},
        "alarms": {"Ra": {"level": level, "since_t": 0.0, "since_window": 0,
                          "deviation_pct": ra_dev, "pending": None,
                          "rul": {"level": rul_level, "since_t": 0.0, "since_window": 0,
                                  "rul_s": 5000.0, "pending": None}}},
        "diagnosis": {"status": status, "top": fault if status == "fault" else None,
                      "probability": probability, "no_fault": 1 - probability,
                      "unknown": 0.01, "unknown_terms": [], "shaft_speed": 18.5,
                      "library": "dc_motor (shipped)", "evidence": 2,
                      "alarms": [fault] if raised else [],
                      "faults": [{"id": fault, "component": "armature winding",
                                  "probability": probability,
                                  "action": "measure the armature resistance",
                                  "urgency": urgency, "source": "IEEE 43",
                                  "evidence_for": [], "evidence_against": []}]},
    }


def summary(**kw: Any) -> dict[str, Any]:
    return fleet_summary(read_health(health(**kw)), box="gw-a", wall=1000.0)


class FakeSession:
    """A session whose subscribers do nothing and whose gets are recorded (:meth:`get` in
    each subclass), answered with :meth:`reply`."""

    def __init__(self) -> None:
        self.gets: list[str] = []

    def declare_subscriber(self, key: str, callback: Any) -> Any:
        return SimpleNamespace(undeclare=lambda: None)

    def liveliness(self) -> Any:
        return self

    @staticmethod
    def reply(handler: Any, machine: str, doc: dict[str, Any]) -> None:
        """Reply ``doc`` on ``machine``'s summary key."""
        text = json.dumps(doc)
        sample = SimpleNamespace(key_expr=f"twinwatch/{machine}/summary",
                                 payload=SimpleNamespace(to_string=lambda: text))
        handler.callback(SimpleNamespace(ok=sample))
