"""The reading check (twinwatch/twin/estimation/readings.py, issue 34): a wrong reading on a
healthy machine, told from a process fault by the healthy twin with that reading corrected.

Windows from the simulated plant (the default motor, closed loop, 1 % noise), each fault a
step at t = 0; the process fit is the adapter's own (Ra and D estimated)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.estimation.estimator import EstimationConfig
from twinwatch.twin.estimation.readings import ReadingCheck
from twinwatch.twin.models.dcmotor import DCMotorTwin

from .helpers.plant import plant_windows

NOISE = {"ia": 1.0, "omega": 1.0, "Va": 1.0}


def _check(skip: int = 5, **plant: Any) -> tuple[ReadingCheck, TwinAdapter]:
    """The reading check of the 4th window a fresh adapter reads (after ``skip`` windows)."""
    cfg = DCMotorPlantConfig(scenario="nominal", duration=60, noise=NOISE, seed=3, **plant)
    _, wins = plant_windows(cfg, 4, skip=skip)
    adapter = TwinAdapter(DCMotorTwin(), EstimationConfig(estimate=["Ra", "D"]))
    result = None
    for w in wins:
        result = adapter.process(w)
    assert result is not None and result.readings is not None
    return result.readings, adapter


def _best(r: ReadingCheck, output: str) -> float:
    x = r.outputs[output]
    return min(x.gain_nrmse, x.offset_nrmse)


def test_a_current_reading_gain_is_found_and_explains_the_window() -> None:
    """ia reported 1.1 x on a healthy motor: the check reads the gain within 0.5 % and the
    healthy twin with it corrected fits within 2 % of the process fit's nRMSE, while the
    nameplate twin alone and the other readings leave several times more."""
    r, _ = _check(sensor_faults=[{"channel": "ia", "kind": "gain", "gain": 1.1, "start": 0.0}])
    assert r.outputs["ia"].gain == pytest.approx(1.1, rel=5e-3)
    assert _best(r, "ia") <= 1.02 * r.fit_nrmse
    assert r.nominal_nrmse > 3.0 * r.fit_nrmse
    for other in ("omega", "Va"):
        assert _best(r, other) > 3.0 * r.fit_nrmse, other


def test_a_current_reading_offset_is_found() -> None:
    r, _ = _check(sensor_faults=[{"channel": "ia", "kind": "offset", "offset": 0.1, "start": 0.0}])
    assert r.outputs["ia"].offset == pytest.approx(0.1, rel=0.1)  # measured 0.106
    assert _best(r, "ia") <= 1.02 * r.fit_nrmse


def test_a_va_reading_offset_is_read_through_the_controller_it_starts() -> None:
    """The closed-loop twin starts its controller's integrator from the measured Va: a 0.5 V
    offset read from the reading alone comes out near 0.19 V (the integrator starts 0.5 V
    off and settles within the window); re-fed and fitted over every output, 0.47 V."""
    r, _ = _check(sensor_faults=[{"channel": "Va", "kind": "offset", "offset": 0.5, "start": 0.0}])
    assert r.outputs["Va"].offset == pytest.approx(0.5, rel=0.1)
    assert r.outputs["Va"].offset_nrmse <= 1.05 * r.fit_nrmse


def test_two_process_faults_are_not_a_current_reading() -> None:
    """A shorted winding with worn bearings (Ra -12 %, D +25 %) moves Ra down and D up as a
    current reading too high does; the healthy twin with the current reading corrected leaves
    more than twice the process fit's nRMSE (measured: 4 times)."""
    faults = [{"parameter": "Ra", "change": -12.0}, {"parameter": "D", "change": 25.0}]
    r, _ = _check(parameter_faults=faults)
    assert r.outputs["ia"].gain > 1.05  # it does look like a reading too high ...
    assert _best(r, "ia") > 2.0 * r.fit_nrmse  # ... which does not explain the window


def test_a_healthy_window_costs_one_simulation(monkeypatch: pytest.MonkeyPatch) -> None:
    """Nothing to explain (the nameplate twin fits as the estimate does): the readings are
    read off the one healthy simulation, no window is re-run."""
    from twinwatch.twin.estimation import readings

    calls = []
    real = readings._rerun

    def counted(*a: Any, **k: Any) -> Any:
        calls.append(a[3])
        return real(*a, **k)

    monkeypatch.setattr(readings, "_rerun", counted)
    r, _ = _check()
    assert r.nominal_nrmse <= readings.EXPLAIN * r.fit_nrmse
    assert calls == []
    assert all(abs(x.gain - 1.0) < 0.01 for x in r.outputs.values())
    calls.clear()
    _check(sensor_faults=[{"channel": "ia", "kind": "gain", "gain": 1.1, "start": 0.0}])
    assert sorted(set(calls)) == ["Va", "ia", "omega"]  # each a state or an input: re-run


def test_the_message_carries_the_check() -> None:
    """health.readings (schema 11) is the check as computed."""
    from twinwatch.twin.health import build_health

    gain = {"channel": "ia", "kind": "gain", "gain": 1.1, "start": 0.0}
    cfg = DCMotorPlantConfig(scenario="nominal", duration=30, noise=NOISE, seed=3,
                             sensor_faults=[gain])
    _, wins = plant_windows(cfg, 2, skip=2)
    model = DCMotorTwin()
    adapter = TwinAdapter(model, EstimationConfig(estimate=["Ra", "D"]))
    for w in wins:
        result = adapter.process(w)
    h = build_health(machine="m", model_name="dc_motor", run="r", model=model, window=wins[-1],
                     adaptation=result, nominal={})
    doc = h.as_dict()["readings"]
    assert doc["outputs"]["ia"]["gain"] == pytest.approx(result.readings.outputs["ia"].gain)
    assert set(doc) == {"nominal_nrmse", "fit_nrmse", "outputs"}
    assert np.isfinite(doc["fit_nrmse"])


def test_the_daemon_tests_the_readings_its_fault_library_names() -> None:
    """The default motor's library names the current reading (its sensor modes); the
    hydraulic library names none, so its daemon runs no check; diagnosis off, none."""
    from twinwatch.config.loader import default_config, load_config
    from twinwatch.daemon.window_worker import reading_outputs

    from .helpers.paths import ROOT

    cfg = default_config()
    assert reading_outputs(cfg) == ("ia",)
    cfg.diagnosis.enabled = False
    assert reading_outputs(cfg) == ()
    assert reading_outputs(load_config(ROOT / "config" / "hydraulic-modbus-sim.toml")) == ()
