"""Per-window estimation (paper Section 3.2) on plant windows."""

from __future__ import annotations

import numpy as np
import pytest

from twinwatch.plant.dcmotor import DCMotorPlantConfig, SetpointSchedule
from twinwatch.twin.dcmotor import DCMotorTwin
from twinwatch.twin.estimation import EstimationConfig, Estimator, PSOSettings

from .conftest import plant_windows

TRUE = {"Ra": 6.5, "La": 0.673, "J": 0.001171, "Ke": 0.038, "D": 0.00143}


def _step_window():
    # A set-point step half a second into the window: a transient pins every parameter.
    cfg = DCMotorPlantConfig(scenario="nominal", duration=30,
                             setpoint=SetpointSchedule(steps=[(0.0, 10.0), (20.5, 15.0)]))
    return plant_windows(cfg, 1, skip=10)[1][0]


def _quasi_static_window():
    cfg = DCMotorPlantConfig(scenario="nominal", duration=200,
                             setpoint=SetpointSchedule(steps=[(0.0, 10.0)]))
    return plant_windows(cfg, 1, skip=90)[1][0]


def test_transient_window_determines_all_five_parameters():
    est = Estimator(DCMotorTwin(), EstimationConfig())
    # Start far from the truth: the swarm, not the warm start, must find it.
    est.trusted *= np.array([1.3, 0.7, 1.4, 1.2, 1.2, 0.6])
    r = est.estimate(_step_window())
    assert set(r.estimated) == set(TRUE)
    for name, true in TRUE.items():
        assert r.values[name] == pytest.approx(true, rel=1e-4), name
    assert r.values["Kt"] == r.values["Ke"]  # tied
    assert r.held == {"Kt": "tied to Ke"}
    assert r.nrmse < 1e-8


def test_quasi_static_window_holds_what_it_cannot_determine():
    est = Estimator(DCMotorTwin(), EstimationConfig())
    r = est.estimate(_quasi_static_window())
    assert set(r.estimated) == {"Ra", "D"}
    for name in ("Ke", "La", "J"):
        assert name in r.held and "held at last trusted value" in r.held[name]
        assert r.values[name] == pytest.approx(TRUE[name], rel=1e-12)
    assert r.values["Ra"] == pytest.approx(6.5, rel=1e-4)
    assert r.values["D"] == pytest.approx(0.00143, rel=1e-3)


def test_same_seed_same_result():
    win = _step_window()
    runs = [Estimator(DCMotorTwin(), EstimationConfig(seed=7)).estimate(win) for _ in range(2)]
    assert runs[0].values == runs[1].values
    assert runs[0].generations == runs[1].generations


def test_paper_pso_settings_without_polish_stall_short_of_the_best_fit():
    """pymoo PSO alone (Table 2 settings, no polish, few iterations) is less accurate than the
    default PSO + polish: the reason the polish exists."""
    win = _step_window()
    paper = EstimationConfig(polish=False, pso=PSOSettings(max_generations=50), seed=1,
                             max_rel_std=1.0)
    est = Estimator(DCMotorTwin(), paper)
    est.trusted *= 1.2
    r_paper = est.estimate(win)
    r_default = Estimator(DCMotorTwin(), EstimationConfig(seed=1)).estimate(win)
    assert r_default.nrmse < r_paper.nrmse / 100


def test_bad_config_names_the_parameter():
    with pytest.raises(ValueError, match=r"estimation.estimate: unknown parameter 'Rb'"):
        Estimator(DCMotorTwin(), EstimationConfig(estimate=["Rb"]))
    with pytest.raises(ValueError, match="bounds.Ra"):
        EstimationConfig(bounds={"Ra": (5.0, 1.0)})


def test_non_finite_window_is_refused():
    win = _quasi_static_window()
    win.channels["ia"][10] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        Estimator(DCMotorTwin(), EstimationConfig()).estimate(win)
