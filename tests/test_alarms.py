"""Alarms on parameter drift: hysteresis, minimum durations, no flapping, held values ignored."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from twinwatch.daemon.alarms import AlarmConfig, AlarmEvaluator, AlarmRule
from twinwatch.twin.health import HealthMessage, ParameterHealth


def health(window: int, devs: dict[str, float | None], *,
           held: tuple[str, ...] = ()) -> HealthMessage:
    """The typed health message of window ``window`` (2 s, 200 samples) with the given
    deviations (only what the evaluator reads: the window, its times, the parameters)."""
    params = {}
    for name, dev in devs.items():
        nominal = 6.5
        params[name] = ParameterHealth(
            value=None if dev is None else nominal * (1 + dev / 100), unit="ohm",
            nominal=nominal, deviation_pct=dev,
            status="held" if name in held else "estimated", held=name in held,
            reason="held at last trusted value" if name in held else None, rel_std_pct=None)
    return HealthMessage.model_construct(
        machine="m1", model="dc_motor", window=window, t_start=2.0 * window,
        t_end=2.0 * window + 1.99, samples=200, parameters=params)


def run(ev: AlarmEvaluator, devs: list[float | None], *, start: int = 0,
        held: set[int] | None = None) -> list[dict[str, Any]]:
    out = []
    for k, d in enumerate(devs):
        w = start + k
        out += ev.update(health(w, {"Ra": d}, held=("Ra",) if held and w in held else ()))
    return out


def quick(**kw: Any) -> AlarmEvaluator:
    rule = dict(warning=5.0, alarm=10.0, hysteresis=1.0, raise_after_s=4.0,
                raise_after_windows=2, clear_after_s=4.0, clear_after_windows=2)
    rule.update(kw)
    return AlarmEvaluator(AlarmConfig(parameters={"Ra": AlarmRule(**rule)}))


def test_escalation_warning_alarm_and_clear() -> None:
    ev = quick()
    events = run(ev, [0, 0, 6, 6, 6, 11, 11, 8, 8, 2, 2])
    assert [(e["window"], e["previous"], e["level"]) for e in events] == [
        (3, "normal", "warning"),    # 2 windows = 4 s beyond +5 %
        (6, "warning", "alarm"),     # 2 windows beyond +10 %
        (8, "alarm", "warning"),     # 8 % < 10 - 1: back inside the alarm band for 4 s
        (10, "warning", "normal"),   # 2 % < 5 - 1
    ]
    assert events[0]["threshold_pct"] == 5.0 and events[1]["threshold_pct"] == 10.0
    assert events[2]["threshold_pct"] == 10.0 and events[3]["threshold_pct"] == 5.0
    assert events[1]["since_t"] == 10.0 and events[1]["t"] == 13.99
    json.dumps(events)  # publishable as is


def test_jump_straight_to_alarm() -> None:
    ev = quick()
    events = run(ev, [0, 12, 12])
    assert [(e["previous"], e["level"]) for e in events] == [("normal", "alarm")]


def test_hysteresis_keeps_the_level_until_inside_threshold_minus_hysteresis() -> None:
    ev = quick()
    assert [e["level"] for e in run(ev, [5.5, 5.5])] == ["warning"]
    # 4.5 % is below the 5 % threshold but not below 5 - 1 = 4 %: stays warning, for ever
    assert run(ev, [4.5] * 50, start=2) == []
    assert ev.state()["Ra"]["level"] == "warning"
    assert [e["level"] for e in run(ev, [3.9, 3.9], start=52)] == ["normal"]


def test_minimum_duration_before_raising_and_clearing() -> None:
    ev = quick(raise_after_s=10.0, raise_after_windows=1, clear_after_s=20.0)
    # 4 windows = 8 s beyond the alarm threshold, then back: nothing raised
    assert run(ev, [12, 12, 12, 12, 0]) == []
    assert ev.state()["Ra"] == {"level": "normal", "since_t": None, "since_window": None,
                                "deviation_pct": 0, "pending": None,
                                "pending_since_t": None, "pending_windows": None}
    # 5 windows = 10 s: raised at the 5th
    events = run(ev, [12] * 5, start=5)
    assert [(e["window"], e["level"]) for e in events] == [(9, "alarm")]
    # clearing needs 20 s = 10 windows inside
    assert run(ev, [0] * 9, start=10) == []
    assert ev.state()["Ra"]["pending"] == "normal"
    assert [(e["window"], e["level"]) for e in run(ev, [0], start=19)] == [(19, "normal")]


def test_negative_drift_and_one_sided_thresholds() -> None:
    """The paper's resistance degradation lowers Ra: a low-side rule raises, a high-only
    rule does not."""
    low = AlarmEvaluator(AlarmConfig(parameters={"Ra": AlarmRule(
        warning_low=-5, alarm_low=-10, raise_after_s=0, raise_after_windows=1)}))
    high = AlarmEvaluator(AlarmConfig(parameters={"Ra": AlarmRule(
        warning_high=5, raise_after_s=0, raise_after_windows=1)}))
    devs: list[float | None] = [-2.0, -6.0, -14.6]
    e = run(low, devs)
    assert [(x["level"], x["threshold_pct"]) for x in e] == [("warning", -5), ("alarm", -10)]
    assert "below nominal" in e[1]["message"]
    assert run(high, devs) == []


def _noisy_walk(seed: int, n: int) -> list[float | None]:
    """A deviation drifting slowly from 3 % to 7 % through the 5 % threshold, with estimation
    noise of 0.4 points and a small random walk on top (seeded)."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0, 0.05, n))
    walk -= np.linspace(0, walk[-1], n)  # keep the trend, remove the walk's end offset
    return [float(x) for x in np.linspace(3, 7, n) + walk + rng.normal(0, 0.4, n)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_flapping_near_threshold(seed: int) -> None:
    devs = _noisy_walk(seed, 600)  # 20 minutes of windows
    naive = quick(hysteresis=0.0, raise_after_s=0, raise_after_windows=1, clear_after_s=0,
                  clear_after_windows=1)
    flaps = run(naive, devs)
    assert len(flaps) > 20  # without hysteresis and durations it does flap
    ev = AlarmEvaluator(AlarmConfig(parameters={"Ra": AlarmRule(warning=5, alarm=10)}))
    events = run(ev, devs)   # defaults: 1 point hysteresis, 10 s / 3 windows, 30 s to clear
    assert [(e["previous"], e["level"]) for e in events] == [("normal", "warning")]


def test_held_values_are_not_evidence() -> None:
    ev = quick()
    # held windows far beyond the alarm threshold raise nothing
    assert run(ev, [20, 20, 20, 20], held={0, 1, 2, 3}) == []
    assert ev.state()["Ra"]["deviation_pct"] is None
    # null (non-finite) deviations are not evidence either
    assert run(ev, [None, None], start=4) == []
    # a warning run is not interrupted by held windows in between (time still counts)
    events = run(ev, [6, 0, 0, 6], start=6, held={7, 8})
    assert [(e["window"], e["level"]) for e in events] == [(9, "warning")]
    # and a held in-range value does not clear it
    assert run(ev, [0, 0, 0], start=10, held={10, 11, 12}) == []
    assert ev.state()["Ra"]["level"] == "warning"


def test_parameters_without_rule_or_absent_are_ignored() -> None:
    ev = quick()
    assert ev.update(health(0, {"D": 50.0})) == []
    disabled = AlarmEvaluator(AlarmConfig(enabled=False, parameters={
        "Ra": AlarmRule(warning=5, raise_after_s=0, raise_after_windows=1)}))
    assert disabled.update(health(0, {"Ra": 50.0})) == []


def test_message_tells_what_happened_and_what_to_do() -> None:
    ev = AlarmEvaluator(AlarmConfig(parameters={"Ra": AlarmRule(
        alarm=10, raise_after_s=0, raise_after_windows=1,
        action="check the armature winding temperature and the brushes")}),
        meanings={"Ra": "armature resistance"})
    (e,) = ev.update(health(3, {"Ra": -14.6}))
    assert e["message"] == (
        "m1: ALARM: Ra (armature resistance) is 14.60 % below nominal (5.551 ohm vs nominal "
        "6.5 ohm) since plant time 6 s, beyond the alarm threshold -10 %: check the armature "
        "winding temperature and the brushes")


def test_state_snapshot_and_restore() -> None:
    ev = quick()
    run(ev, [6, 6, 6])
    snap = ev.state()
    assert snap["Ra"]["level"] == "warning" and snap["Ra"]["since_window"] == 1
    again = quick()
    again.restore(json.loads(json.dumps(snap)))
    assert again.state()["Ra"]["level"] == "warning"
    # the restored warning is not raised again
    assert run(again, [6, 6], start=3) == []


def test_a_restart_mid_evidence_run_keeps_the_run() -> None:
    """Issue 37: a restart while the evidence for a raise was running started the run again
    from nothing, lagging the alarm by up to raise_after_s. The snapshot carries the run (when
    it began, its windows); restored, the alarm is raised when it would have been without the
    restart (window 4, 10 s after the run began at 0 s), not 10 s after the restart."""
    def first_raise(restart_at: int | None) -> int:
        ev = quick(raise_after_s=10.0, raise_after_windows=1)
        for w in range(12):
            if w == restart_at:
                snap = json.loads(json.dumps(ev.state()))
                ev = quick(raise_after_s=10.0, raise_after_windows=1)
                ev.restore(snap)
            events = run(ev, [12], start=w)
            if events:
                return int(events[0]["window"])
        return -1

    assert first_raise(None) == 4
    assert first_raise(3) == 4
    snap = quick(raise_after_s=10.0, raise_after_windows=1)
    run(snap, [12, 12])
    assert snap.state()["Ra"]["pending_since_t"] == 0.0
    assert snap.state()["Ra"]["pending_windows"] == 2


@pytest.mark.parametrize(("rule", "key"), [
    ({"warning": 5, "hysterisis": 1}, "hysterisis"),
    ({"warning": 5, "alarm": 4}, "alarm"),
    ({"warning": 5, "warning_high": 6}, "warning"),
    ({"warning_low": 5}, "warning_low"),
    ({"warning": 2, "hysteresis": 2}, "hysteresis"),
    ({"hysteresis": 1}, "no threshold"),
])
def test_bad_rule_rejected_naming_the_key(rule: dict[str, Any], key: str) -> None:
    with pytest.raises(ValidationError) as exc:
        AlarmConfig.model_validate({"parameters": {"Ra": rule}})
    text = str(exc.value)
    assert key in text
    assert "parameters.Ra" in text


def test_rules_checked_against_the_model() -> None:
    cfg = AlarmConfig.model_validate({"parameters": {"Rb": {"warning": 5}}})
    with pytest.raises(ValueError, match=r"alarms\.parameters\.Rb: unknown parameter"):
        cfg.check_against(["Ra", "La", "J", "Ke", "Kt", "D"])
    tied = AlarmConfig.model_validate({"parameters": {"Kt": {"warning": 5}}})
    with pytest.raises(ValueError, match=r"alarms\.parameters\.Kt: Kt is not estimated"):
        tied.check_against(["Ra", "Kt"], estimated=["Ra", "D", "Ke", "La", "J"])
    with pytest.raises(ValidationError, match="enabeld"):
        AlarmConfig.model_validate({"enabeld": True})


def test_every_example_that_says_it_is_the_default_run_has_its_alarm_rules() -> None:
    """Issue 56: the examples whose header says they run as config/dc-motor-sim.toml (the
    Sparkplug, MQTT, TLS, CANopen and OPC UA ones) carry its [alarms] table, the RUL rule
    included (before: the Sparkplug and MQTT ones lacked rul_warning and rul_alarm, 3 alarm
    lines instead of the README's 5; the TLS one had no [alarms] at all)."""
    import re
    import tomllib
    from pathlib import Path

    config = Path(__file__).resolve().parents[1] / "config"
    default = tomllib.loads((config / "dc-motor-sim.toml").read_text())["alarms"]
    assert default["parameters"]["Ra"]["rul_alarm"] == 180.0
    claims = []
    for path in sorted(config.glob("*.toml")):
        text = path.read_text()
        head = "".join(line for line in text.splitlines(keepends=True)[:20]
                       if line.startswith("#"))
        if path.name != "dc-motor-sim.toml" and re.search(
                r"[Aa]s config/dc-motor-sim\.toml|Same plant, scenario and twin", head):
            claims.append(path.name)
            assert tomllib.loads(text).get("alarms") == default, path.name
    assert {"dc-motor-sim-sparkplug.toml", "dc-motor-sim-mqtt.toml",
            "dc-motor-sim-tls.toml"} <= set(claims), claims
