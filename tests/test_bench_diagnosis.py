"""The diagnosis's fault matrix (benchmarks/bench_diagnosis.py): its case table and the way it
judges a case (right, confident-wrong, time to alarm, Brier score)."""

from __future__ import annotations

import sys
from types import SimpleNamespace
from typing import Any

import pytest

from .helpers.paths import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_diagnosis as bench  # noqa: E402

#: Ids the lead adds to the libraries (issue 34); the rest must be the shipped libraries'.
NEW_IDS = {"current_sensor", "speed_sensor", "voltage_sensor", "supply_sag", "position_sensor",
           "pressure_sensor"}
ANSWERS = {"unknown", "check_function", "no_fault"}


def _d(status: str, top: str | None, p: float, faults: dict[str, float], unknown: float = 0.01,
       no_fault: float = 0.01) -> Any:
    fs = [SimpleNamespace(id=k, probability=v)
          for k, v in sorted(faults.items(), key=lambda kv: -kv[1])]
    return SimpleNamespace(status=status, top=top, probability=p, faults=fs, unknown=unknown,
                           no_fault=no_fault)


def _meta(**kw: Any) -> dict[str, Any]:
    base = {"name": "x", "category": "library", "onset": 10.0, "accept": ["winding_short"],
            "truth": ["winding_short"], "tolerate": []}
    return {**base, **kw}


def test_case_table_names_are_unique_and_answers_are_the_libraries():
    from twinwatch.twin.diagnosis.library import shipped_library

    cases = bench.cases()
    assert len({c.name for c in cases}) == len(cases)
    ids = {m: {f.id for f in shipped_library(model).faults}  # type: ignore[union-attr]
           for m, model in (("dc", "dc_motor"), ("pwm", "dc_motor_pwm"),
                            ("hyd", "hydraulic_actuator"))}
    for c in cases:
        assert c.accept, c.name
        assert c.accept | set(c.truth) | c.tolerate <= ids[c.machine] | NEW_IDS | ANSWERS, c.name
        if c.category == "library":
            assert c.accept & (ids[c.machine] | {"no_fault"}), c.name
        if c.category in ("sensor_supply", "off_library"):
            assert {"unknown", "check_function"} <= c.accept, c.name
        if c.category == "nominal":
            assert c.accept == {"no_fault"} and c.onset == 0.0
    cats = {c.category for c in cases}
    assert cats == {"library", "sensor_supply", "off_library", "nominal"}
    assert [c.name for c in bench.select(cases, "dc/winding_short/Ra-4%")] == \
        ["dc/winding_short/Ra-4%/n0", "dc/winding_short/Ra-4%/n1"]


def test_a_case_builds_the_shipped_config_with_its_fault():
    case = next(c for c in bench.cases() if c.name == "dc/winding_short/Ra-12%/n1")
    cfg = case.build()
    plant = cfg.driver.plant  # type: ignore[union-attr]
    assert cfg.machine.model == "dc_motor" and cfg.discovery.enabled
    assert plant.scenario == "nominal" and plant.noise == {"ia": 1.0, "omega": 1.0}
    [pf] = plant.parameter_faults
    assert (pf.parameter, pf.change, pf.start, pf.ramp) == ("Ra", -12.0, 60.0, 60.0)


def test_judge_right_alarm_and_confident_wrong():
    meta = _meta()
    ok = _d("fault", "winding_short", 0.9, {"winding_short": 0.9})
    wrong = _d("fault", "bearing_wear", 0.85, {"bearing_wear": 0.85})
    quiet = _d("no_fault", None, 0.9, {}, no_fault=0.9)
    # a wrong fault before the onset does not count; three named windows from 14 s
    series = [(2.0, wrong), (6.0, quiet), (12.0, ok), (14.0, quiet), (16.0, ok), (18.0, ok),
              (20.0, ok)]
    r = bench.judge(meta, series, ["winding_short", "bearing_wear"])
    assert r["right"] and r["final"] == "winding_short"
    assert not r["confident_wrong"] and r["max_wrong_p"] == 0.0
    assert r["alarm_s"] == pytest.approx(6.0)  # from the onset (10 s) to 16 s
    series.insert(3, (13.0, wrong))
    r = bench.judge(meta, series, ["winding_short", "bearing_wear"])
    assert r["confident_wrong"] and r["wrong_id"] == "bearing_wear"


def test_judge_tolerates_a_repaired_fault_but_wants_no_fault_at_the_end():
    meta = _meta(accept=["no_fault"], truth=["no_fault"], tolerate=["winding_short"])
    ws = _d("fault", "winding_short", 0.9, {"winding_short": 0.9})
    quiet = _d("no_fault", None, 0.95, {}, no_fault=0.95)
    r = bench.judge(meta, [(12.0, ws), (14.0, ws), (16.0, ws), (18.0, quiet)],
                    ["winding_short"])
    assert r["right"] and not r["confident_wrong"] and r["alarm_s"] == pytest.approx(2.0)
    r = bench.judge(meta, [(12.0, ws), (14.0, ws)], ["winding_short"])
    assert not r["right"]


def test_brier_score_is_over_every_outcome_and_a_missing_mode_is_unknown():
    ids = ["winding_short", "bearing_wear"]
    last = _d("unknown", None, 0.8, {"winding_short": 0.1}, unknown=0.8, no_fault=0.1)
    # a current-sensor case on a library without current_sensor: y = 1 on unknown
    meta = _meta(category="sensor_supply", accept=["current_sensor", "unknown",
                                                   "check_function"], truth=["current_sensor"])
    r = bench.judge(meta, [(20.0, last)], ids)
    want = ((0.1 - 0) ** 2 + 0.0 + (0.8 - 1) ** 2 + (0.1 - 0) ** 2) / 4
    assert r["brier"] == pytest.approx(want, abs=1e-4) and r["right"]
    # with the mode in the library, y = 1 moves to it
    r = bench.judge(meta, [(20.0, last)], [*ids, "current_sensor"])
    want = (0.1 ** 2 + 0.0 + 1.0 + 0.8 ** 2 + 0.1 ** 2) / 5
    assert r["brier"] == pytest.approx(want, abs=1e-4)


def test_a_nominal_run_is_judged_from_its_first_window():
    meta = _meta(category="nominal", onset=0.0, accept=["no_fault"], truth=["no_fault"])
    quiet = _d("no_fault", None, 0.95, {"bearing_wear": 0.01}, no_fault=0.95)
    blip = _d("no_fault", None, 0.7, {"bearing_wear": 0.25}, no_fault=0.7)
    r = bench.judge(meta, [(2.0, quiet), (4.0, quiet)], ["bearing_wear"])
    assert r["right"] and r["false_alarm"] is False
    r = bench.judge(meta, [(2.0, blip), (4.0, quiet)], ["bearing_wear"])
    assert r["right"] and r["false_alarm"] is True and not r["confident_wrong"]


def test_an_honest_split_naming_the_truth_is_right_and_one_without_it_is_not():
    """The diagnosis may name two modes the data cannot tell apart (``split``) and the check
    that can: the case is right when the split holds its top answer and an accepted one."""
    split = _d("fault", "supply_sag", 0.55, {"supply_sag": 0.55, "winding_short": 0.4})
    split.split = ["supply_sag", "winding_short"]
    r = bench.judge(_meta(), [(20.0, split)], ["winding_short", "supply_sag"])
    assert r["right"] and r["split"] == ["supply_sag", "winding_short"]
    other = _d("fault", "supply_sag", 0.55, {"supply_sag": 0.55, "bearing_wear": 0.4})
    other.split = ["supply_sag", "bearing_wear"]
    assert not bench.judge(_meta(), [(20.0, other)], ["winding_short", "supply_sag"])["right"]


def test_a_stuck_sensor_finding_counts_for_a_sensor_case_only_on_the_faulted_reading():
    """``sensor_named``: an omega offset of +10 rad/s holds the speed reading at 10 at
    standstill (flagged saturated there); ``sensor_fault`` ("check the named sensor") then names
    the right part. It is acceptable only when every reading flagged from the onset is one the
    case faults, never before the onset's flags count, and never for another category."""
    def h(t: float, *channels: str) -> Any:
        return SimpleNamespace(t_end=t, sensors=[SimpleNamespace(channel=c) for c in channels])

    meta = _meta(category="sensor_supply", accept=["speed_sensor_high", "unknown",
                                                   "check_function"],
                 truth=["speed_sensor_high"],
                 spec={"sensor_faults": [{"channel": "omega", "kind": "offset"}]})
    assert bench.sensor_named(meta, [h(4.0, "ia"), h(12.0, "omega"), h(14.0)])
    assert not bench.sensor_named(meta, [h(12.0, "omega"), h(14.0, "ia")])  # another reading
    assert not bench.sensor_named(meta, [h(4.0, "omega"), h(14.0)])  # only before the onset
    assert not bench.sensor_named({**meta, "category": "library"}, [h(12.0, "omega")])
    assert not bench.sensor_named({**meta, "spec": {}}, [h(12.0, "omega")])

    stuck = _d("fault", "sensor_fault", 0.75, {"sensor_fault": 0.75}, no_fault=0.2)
    ids = ["sensor_fault", "speed_sensor_high"]
    r = bench.judge(meta, [(20.0, stuck)], ids)
    assert not r["right"] and not r["accepted_also"]
    r = bench.judge(meta, [(20.0, stuck)], ids, also=["sensor_fault"])
    assert r["right"] and r["accepted_also"] and r["max_wrong_p"] < 0.75
    summary = bench.summarise([{**r, "brier": 0.1, "alarm_s": None, "false_alarm": None}])
    assert summary["acceptable_sensor_supply"] == [1, 1]
    assert summary["sensor_supply_by_stuck_sensor"] == ["x"]
