"""Local-first estimation (issue 19 item 1): the swarm runs at start, after a rejected local fit,
after a sudden change, after a roll-back and every ``swarm_every`` windows; otherwise the
trusted values are polished locally, to the same estimates the swarm path reaches. Timing is
benchmarks/bench_estimation.py's."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from twinwatch.plant.dcmotor import DCMotorPlantConfig
from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator
from twinwatch.twin.estimation.fusion import FusionConfig, ParameterFusion
from twinwatch.twin.models.dcmotor import DCMotorTwin

from .helpers.plant import plant_windows
from .helpers.twin import BOUNDS, DRIVE


def _windows(n: int, noise: dict[str, float] | None = None, skip: int = 80):  # type: ignore[no-untyped-def]
    cfg = DCMotorPlantConfig(scenario="resistance_degradation", duration=2 * (skip + n) + 10,
                             noise=noise or {}, seed=3)
    return plant_windows(cfg, n, skip=skip)


def test_local_windows_reach_the_swarm_paths_estimates() -> None:
    """Noise-free degradation, 8 windows: the first runs the swarm (start), the guard every 4
    windows, the rest polish locally without a swarm iteration; each window's published Ra
    equals the swarm-every-window estimator's to 1e-6 and is within the paper's 0.2 %."""
    plant, wins = _windows(8)
    local = Estimator(DCMotorTwin(), EstimationConfig(swarm_every=4, time_budget=60.0))
    swarm = Estimator(DCMotorTwin(), EstimationConfig(strategy="swarm", time_budget=60.0))
    searches = []
    for w in wins:
        a, b = local.estimate(w), swarm.estimate(w)
        searches.append((a.search, a.search_reason))
        assert b.search == "swarm" and b.search_reason == "every window" and b.generations > 0
        truth = plant.truth(float(w.t[w.n // 2])).Ra
        assert a.status["Ra"] == b.status["Ra"] == "estimated"
        assert a.values["Ra"] == pytest.approx(b.values["Ra"], rel=1e-6)
        assert a.values["Ra"] == pytest.approx(truth, rel=0.002)
        assert a.trusted == b.trusted
        if a.search == "local":
            assert a.generations == 0 and a.evaluations < b.evaluations
    assert searches == [("swarm", "start"), ("local", ""), ("local", ""), ("local", ""),
                        ("swarm", "guard"), ("local", ""), ("local", ""), ("local", "")]


def test_a_local_fit_failing_its_model_check_is_estimated_again_with_the_swarm() -> None:
    """An ideal PI twin on a drive that holds its output (the honesty case): the local fit
    fails its model check, is rejected, and the window is estimated with the swarm, which
    flags it as before (not trusted, intervals widened)."""
    _, wins = plant_windows(DCMotorPlantConfig(scenario="resistance_degradation",
                                               duration=2 * 90, drive=DRIVE, seed=5), 6,
                            skip=80)
    est = Estimator(DCMotorTwin(kp=2.0, ki=2.0), EstimationConfig(bounds=BOUNDS))
    runs = [est.estimate(w) for w in wins]
    assert runs[0].search_reason == "start"
    rejected = [e for e in runs[1:] if e.search_reason.startswith("rejected: ")]
    assert rejected, [e.search_reason for e in runs]
    for e in rejected:
        assert e.search == "swarm" and e.generations > 0
        assert "the model check failed" in e.search_reason or "nRMSE" in e.search_reason
    for e in runs:
        if not e.model_check.passed:  # flagged windows are never the local path's
            assert e.search == "swarm" and not e.trusted and e.model_check.widen > 1


def test_a_residual_beyond_the_noise_rejects_the_local_fit() -> None:
    """A trusted Ra far from the plant's (a sudden change the trusted values do not know) is
    polished locally; if that stops short, its nRMSE is beyond what the window's noise
    explains and the swarm runs in the same window. Either way the published Ra is right."""
    plant, wins = _windows(3, noise={"ia": 1.0, "omega": 1.0})
    est = Estimator(DCMotorTwin(), EstimationConfig(time_budget=60.0))
    est.estimate(wins[0])
    est.trusted[est.names.index("Ra")] *= 3.0
    est.trusted[est.names.index("J")] *= 0.25
    e = est.estimate(wins[1])
    truth = plant.truth(float(wins[1].t[100])).Ra
    assert e.values["Ra"] == pytest.approx(truth, rel=0.01)
    assert e.search == "local" or e.search_reason.startswith("rejected: ")
    # the test itself: white noise passes, a smooth residual five times its level does not
    problem = est.problem(wins[2])
    m = problem.local.residuals(problem.local.start(problem.start())).shape[1]
    est._swarm_nrmse = 0.0
    white = np.random.default_rng(0).normal(size=m) * 1e-2 / math.sqrt(m)
    assert est._residual_too_large(problem, white) == ""
    assert est._residual_too_large(problem, white + 5e-2 / math.sqrt(m)).startswith("nRMSE")
    est._swarm_nrmse = 0.05  # ... unless the last swarm window's fit was as large
    assert est._residual_too_large(problem, white + 5e-2 / math.sqrt(m)) == ""


def test_a_sudden_change_and_a_roll_back_run_the_swarm_next() -> None:
    """The fusion's jump flag (a window far beyond the fused prediction) and a roll-back by the
    adaptation each make the next window run the swarm."""
    _, wins = _windows(5)
    est = Estimator(DCMotorTwin(), EstimationConfig(time_budget=60.0))
    est.estimate(wins[0])
    snap = est.snapshot()
    assert est.estimate(wins[1]).search == "local"
    assert est.fusion is not None
    est.fusion.state.mean[0] += 0.3  # the fused Ra 35 % off, and sure of it
    est.fusion.state.cov[0, :] = est.fusion.state.cov[:, 0] = 0.0
    est.fusion.state.cov[0, 0] = 1e-8
    e2 = est.estimate(wins[2])
    assert e2.fusion_jump and e2.search == "local"
    e3 = est.estimate(wins[3])
    assert (e3.search, e3.search_reason) == ("swarm", "sudden change")
    est.rollback(snap)
    e4 = est.estimate(wins[4])
    assert (e4.search, e4.search_reason) == ("swarm", "rolled back")


def test_strategy_keys_are_checked() -> None:
    assert EstimationConfig().strategy == "local_first"
    with pytest.raises(ValidationError, match="strategy"):
        EstimationConfig(strategy="global")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="swarm_every"):
        EstimationConfig(swarm_every=-1)
    with pytest.raises(ValidationError, match="local_residual_ratio"):
        EstimationConfig(local_residual_ratio=1.0)
    # swarm_every = 0: only at start (and on the triggers)
    _, wins = _windows(3)
    est = Estimator(DCMotorTwin(), EstimationConfig(swarm_every=0, time_budget=60.0))
    assert [est.estimate(w).search for w in wins] == ["swarm", "local", "local"]


def test_fusion_step_tolerance_stops_within_a_share_of_the_standard_error() -> None:
    """A nonlinear window (residuals exp(x) - y): with ``step_tol`` 0.01 the filter stops after
    fewer linearisations, within 0.01 posterior standard errors of where it converges."""
    rng = np.random.default_rng(2)
    t = np.linspace(0.0, 1.0, 200)
    truth = np.array([0.3, -0.2])

    def model(x: np.ndarray) -> np.ndarray:
        return np.exp(x[0]) * np.exp(-np.exp(x[1]) * t)

    y = model(truth) + 0.01 * rng.normal(size=t.size)

    def run(step_tol: float) -> tuple[ParameterFusion, int]:
        calls = [0]

        def linearize(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            calls[0] += 1
            m = model(x)
            jac = np.column_stack([m, -np.exp(x[1]) * t * m])
            return jac, m - y

        f = ParameterFusion(("a", "b"), np.ones(2), FusionConfig(model="random_walk"))
        f.update(1.0, linearize, np.full(t.size, 1e-4), iterations=30, step_tol=step_tol)
        return f, calls[0]

    full, n_full = run(0.0)
    quick, n_quick = run(0.01)
    sd = np.sqrt(np.diag(full.state.cov))
    assert n_quick < n_full
    assert np.all(np.abs(quick.state.mean - full.state.mean) <= 0.01 * sd)
    np.testing.assert_allclose(np.diag(quick.state.cov), np.diag(full.state.cov), rtol=0.05)
