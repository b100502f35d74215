"""The local fit's loops against scipy's ``least_squares``: the trust-region reflective loop
bit for bit; the admitted-only polish's Levenberg-Marquardt at the same optimum."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
from scipy.optimize import least_squares

from twinwatch.config.loader import load_config
from twinwatch.daemon.runner import Daemon
from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.plant.hydraulic import HydraulicPlant, HydraulicPlantConfig
from twinwatch.twin.estimation import _lm, _trf, fit
from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator
from twinwatch.twin.model import WindowData
from twinwatch.twin.models import create_model
from twinwatch.twin.models.dcmotor import DCMotorTwin

from .helpers.paths import ROOT, shared_path
from .helpers.plant import plant_windows
from .helpers.twin import HYDRAULIC_ESTIMATION


def _public(fun: Any, jac: Any, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray
            ) -> np.ndarray:
    x: np.ndarray = least_squares(
        fun, x0, jac=jac, bounds=(lower, upper), method="trf", x_scale=1.0, xtol=_trf.XTOL,
        ftol=_trf.FTOL, gtol=_trf.GTOL, max_nfev=_trf.MAX_NFEV).x
    return x


@pytest.fixture
def both(monkeypatch: pytest.MonkeyPatch) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """Every local fit the estimator runs, solved by both: (ours, scipy's, a bound active)."""
    pairs: list[tuple[np.ndarray, np.ndarray, bool]] = []
    ours = _trf.trust_region_reflective

    def spy(fun: Any, jac: Any, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray
            ) -> np.ndarray:
        x = ours(fun, jac, x0, lower, upper)
        ref = _public(fun, jac, x0, lower, upper)
        span = upper - lower
        near = bool(np.any(np.minimum(x - lower, upper - x) < 1e-6 * span))
        pairs.append((x, ref, near))
        return x

    monkeypatch.setattr(fit, "trust_region_reflective", spy)
    return pairs


def _windows_hydraulic(starts: tuple[float, ...]) -> list[WindowData]:
    plant = HydraulicPlant(HydraulicPlantConfig(scenario="fluid_degradation", duration=410,
                                                noise={"x": 0.001, "p": 0.001}, seed=1))
    out = []
    for start in starts:
        while plant.t < start - 1e-9:
            plant.next_sample()
        ss = [plant.next_sample() for _ in range(200)]
        out.append(WindowData(t=np.array([s.t for s in ss]),
                              channels={c: np.array([s.values[c] for s in ss])
                                        for c in ss[0].values}))
    return out


def _assert_same(pairs: list[tuple[np.ndarray, np.ndarray, bool]], at_least: int) -> None:
    assert len(pairs) >= at_least
    for ours, ref, _ in pairs:
        assert np.array_equal(ours, ref), (ours, ref)


def test_the_dc_motors_local_fits_are_scipys(both: list[Any]) -> None:
    _, wins = plant_windows(DCMotorPlantConfig(noise={"ia": 1.0, "omega": 1.0}, seed=3), 4,
                            skip=80)
    # the swarm's polish every window (a local window's goes to Levenberg-Marquardt)
    est = Estimator(DCMotorTwin(), EstimationConfig(strategy="swarm", time_budget=60.0))
    for w in wins:
        est.estimate(w)
    _assert_same(both, 4)


def test_the_hydraulic_actuators_local_fits_are_scipys(both: list[Any]) -> None:
    twin = create_model("hydraulic_actuator", {})
    # the swarm's polish every window (a local window's and the gate's refits go to
    # Levenberg-Marquardt)
    est = Estimator(twin, EstimationConfig(  # type: ignore[arg-type]
        **{**HYDRAULIC_ESTIMATION, "strategy": "swarm"}))
    for w in _windows_hydraulic((100.0, 300.0, 400.0)):
        est.estimate(w)
    _assert_same(both, 3)


def test_a_fit_whose_optimum_lies_beyond_a_bound_is_scipys() -> None:
    """The reflective step and the bound's strict feasibility: a quadratic whose minimum lies
    outside the box in one variable and inside in the other."""
    a = np.array([[2.0, 0.3], [0.1, 1.5], [0.4, -0.7]])
    target = np.array([3.0, -1.0, 0.5])

    def fun(x: np.ndarray) -> np.ndarray:
        r: np.ndarray = a @ x + 0.05 * np.sin(a @ x) - target
        return r

    def jac(x: np.ndarray) -> np.ndarray:
        out: np.ndarray = (1.0 + 0.05 * np.cos(a @ x))[:, None] * a
        return out

    lower, upper = np.array([-1.0, -1.0]), np.array([1.0, 0.5])
    x0 = np.array([0.1, 0.1])
    ours = _trf.trust_region_reflective(fun, jac, x0, lower, upper)
    assert np.array_equal(ours, _public(fun, jac, x0, lower, upper))
    assert ours[0] == pytest.approx(1.0, abs=1e-8)   # on its bound
    with pytest.raises(ValueError, match="outside"):
        _trf.trust_region_reflective(fun, jac, np.array([2.0, 0.0]), lower, upper)


@pytest.fixture
def both_lm(monkeypatch: pytest.MonkeyPatch) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """Every admitted-only polish the estimator runs, by the Levenberg-Marquardt loop and by
    ``least_squares``: (ours, scipy's, our cost, scipy's cost)."""
    pairs: list[tuple[np.ndarray, np.ndarray, float, float]] = []
    ours = _lm.levenberg_marquardt

    def spy(fun_jac: Any, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray
            ) -> tuple[np.ndarray, int]:
        x, calls = ours(fun_jac, x0, lower, upper)

        def fun(z: np.ndarray) -> np.ndarray:
            r: np.ndarray = fun_jac(z)[0]
            return r

        def jac(z: np.ndarray) -> np.ndarray:
            out: np.ndarray = fun_jac(z)[1].T
            return out

        ref = _public(fun, jac, x0, lower, upper)
        r, r_ref = fun(x), fun(ref)
        pairs.append((x, ref, float(r @ r), float(r_ref @ r_ref)))
        return x, calls

    monkeypatch.setattr(fit, "levenberg_marquardt", spy)
    return pairs


def _assert_same_optimum(pairs: list[tuple[np.ndarray, np.ndarray, float, float]],
                         at_least: int) -> None:
    """The same point to 1e-6 (ln-parameters: 1e-4 %, far inside any window's interval) and
    no worse a cost than scipy's beyond float64's sums."""
    assert len(pairs) >= at_least
    for x, ref, cost, cost_ref in pairs:
        assert np.max(np.abs(x - ref)) < 1e-6, (x, ref)
        assert cost <= cost_ref * (1 + 1e-9) + 1e-30, (cost, cost_ref)


def test_the_dc_motors_admitted_polishes_reach_scipys_optimum(both_lm: list[Any]) -> None:
    _, wins = plant_windows(DCMotorPlantConfig(noise={"ia": 1.0, "omega": 1.0}, seed=3), 8,
                            skip=80)
    est = Estimator(DCMotorTwin(), EstimationConfig(swarm_every=30, time_budget=60.0))
    for w in wins:
        est.estimate(w)
    _assert_same_optimum(both_lm, 5)


def test_the_hydraulic_actuators_admitted_polishes_reach_scipys_optimum(
        both_lm: list[Any]) -> None:
    twin = create_model("hydraulic_actuator", {})
    est = Estimator(twin, EstimationConfig(**HYDRAULIC_ESTIMATION))  # type: ignore[arg-type]
    for w in _windows_hydraulic((100.0, 102.0, 104.0, 106.0, 300.0, 302.0)):
        est.estimate(w)
    _assert_same_optimum(both_lm, 3)


def test_the_pwm_drives_admitted_polishes_and_gate_refits_reach_scipys_optimum(
        both_lm: list[Any]) -> None:
    """The MotoShield recording (../shared, real data) through its configuration: the PWM
    drive's gate refits the parameters it selects with the others held at their trusted
    values in most windows (the admitted set changes), by the same loop."""
    shared_path("data", "motoshield", "aprbsResult.mat")
    cfg_path = ROOT / "config" / "dc-motor-motoshield.toml"
    cfg = load_config(cfg_path)
    with Daemon(cfg, base_dir=cfg_path.parent, publish=False, record=False) as daemon:
        daemon.run()
    _assert_same_optimum(both_lm, 30)


def test_levenberg_marquardt_stops_on_a_bound_where_scipy_does() -> None:
    """A variable whose optimum lies beyond its bound is held on it, the other solved."""
    a = np.array([[2.0, 0.3], [0.1, 1.5], [0.4, -0.7]])
    target = np.array([3.0, -1.0, 0.5])

    def fun_jac(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = a @ x + 0.05 * np.sin(a @ x) - target
        return r, ((1.0 + 0.05 * np.cos(a @ x))[:, None] * a).T

    lower, upper = np.array([-1.0, -1.0]), np.array([1.0, 0.5])
    x0 = np.array([0.1, 0.1])
    ours, calls = _lm.levenberg_marquardt(fun_jac, x0, lower, upper)
    ref = _public(lambda x: fun_jac(x)[0], lambda x: fun_jac(x)[1].T, x0, lower, upper)
    assert ours[0] == 1.0                       # on its bound, exactly
    assert ours == pytest.approx(ref, abs=1e-8)
    assert 1 < calls < _trf.MAX_NFEV
    with pytest.raises(ValueError, match="outside"):
        _lm.levenberg_marquardt(fun_jac, np.array([2.0, 0.0]), lower, upper)


def test_levenberg_marquardt_solves_a_curved_valley_and_refuses_a_step_that_does_not_fall(
        ) -> None:
    """Rosenbrock's valley as least squares (r = (10 (y - x^2), 1 - x)) from (-1.2, 1): the
    linearisation overshoots at first, so steps are refused and the damping grows; the
    optimum (1, 1) is reached within the evaluation budget."""
    def fun_jac(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])
        j = np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])
        return r, j.T

    inf = np.full(2, np.inf)
    x, calls = _lm.levenberg_marquardt(fun_jac, np.array([-1.2, 1.0]), -inf, inf)
    assert x == pytest.approx([1.0, 1.0], abs=1e-9)
    assert calls < _trf.MAX_NFEV


def test_levenberg_marquardt_stops_on_a_jacobian_it_cannot_factor() -> None:
    """A Jacobian column of NaN (a twin whose difference row blew up) never factors: the loop
    stops at the start instead of raising the damping for ever."""
    def fun_jac(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.array([x[0] - 1.0, x[1]]), np.array([[1.0, 0.0], [np.nan, np.nan]])

    inf = np.full(2, np.inf)
    out: list[tuple[np.ndarray, int]] = []
    # in a thread, so that a loop that never ends fails the test instead of hanging the suite
    worker = threading.Thread(target=lambda: out.append(_lm.levenberg_marquardt(
        fun_jac, np.array([0.5, 0.5]), -inf, inf)), daemon=True)
    worker.start()
    worker.join(30.0)
    assert out, "the loop did not stop"
    x, calls = out[0]
    assert calls == 1 and np.array_equal(x, [0.5, 0.5])
