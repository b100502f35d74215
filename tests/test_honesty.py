"""Honest numbers on machines the twin was not built around (issue 9 items 2, 3 and 6): the twin
configured for a plant variant is exact and its intervals cover the truth; configured wrongly it
says so (model check) instead of publishing a confident bias; evidence is fused across windows.
Short runs: the long figures are printed by benchmarks/bench_fidelity.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinwatch.io.drive import DriveConfig, LoopConfig
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
from twinwatch.twin.estimation.estimator import EstimationConfig, Estimator
from twinwatch.twin.estimation.fit import explained_dof, explained_rms
from twinwatch.twin.estimation.fusion import FusionConfig, ParameterFusion
from twinwatch.twin.estimation.statistics import (
    check_model,
    cross_correlation_test,
    ljung_box,
    quantum,
)
from twinwatch.twin.models.dcmotor import DCMotorTwin

from .helpers.plant import plant_windows
from .helpers.twin import BOUNDS, DRIVE, STEPS


def _run(twin: DCMotorTwin, noise: dict[str, float], n: int, skip: int = 80,
         scenario: str = "resistance_degradation", fusion: bool = True
         ) -> tuple[DCMotorPlant, list]:  # type: ignore[type-arg]
    cfg = DCMotorPlantConfig(scenario=scenario, duration=2 * (skip + n) + 10, drive=DRIVE,
                             noise=noise, seed=5)
    plant, wins = plant_windows(cfg, n, skip=skip)
    est = Estimator(twin, EstimationConfig(bounds=BOUNDS,
                                           fusion=FusionConfig(enabled=fusion)))
    runs = []
    for w in wins:
        before = est.trusted_values()
        e = est.estimate(w)
        for name, status in e.status.items():  # held means held at the last trusted value
            if status == "held":
                assert e.values[name] == pytest.approx(before[name], rel=1e-12), (w.index, name)
        runs.append((w, e))
    return plant, runs


def _honest(plant: DCMotorPlant, runs: list) -> tuple[int, int]:  # type: ignore[type-arg]
    """(windows publishing Ra 'estimated', of which honest: the truth within 2 standard
    errors, or the window flagged by its model check and not trusted)."""
    n = ok = 0
    for w, e in runs:
        if e.status["Ra"] != "estimated":
            continue
        n += 1
        truth = plant.truth(float(w.t[w.n // 2])).Ra
        flagged = not e.model_check.passed and not e.trusted
        ok += abs(math.log(e.values["Ra"] / truth)) <= 2 * e.rel_std["Ra"] or flagged
    return n, ok


# -- the statistics ----------------------------------------------------------------------------
def test_residual_tests_separate_white_noise_from_structure() -> None:
    rng = np.random.default_rng(0)
    white = rng.normal(size=400)
    smooth = np.sin(np.linspace(0, 6, 400)) + 0.1 * white
    assert ljung_box(white, 20)[1] > 0.01 and ljung_box(smooth, 20)[1] < 1e-6
    u = np.repeat(rng.normal(size=40), 10)  # a step-like input
    assert cross_correlation_test(white, u, 20)[1] > 0.01
    assert cross_correlation_test(0.5 * u + white, u, 20)[1] < 1e-6
    res = np.column_stack([white * 1e-3, smooth * 1e-3])
    check = check_model(res, ("a", "b"), None, alpha=0.01, lags=20, floor=1e-6)
    assert not check.passed and check.outputs["a"].passed and not check.outputs["b"].passed
    assert "residual of b not white" in check.reasons[0] and check.widen > 1
    # the same structure below the model-error floor is accepted model error
    assert check_model(res, ("a", "b"), None, alpha=0.01, lags=20, floor=1.0).passed


def test_quantum_is_the_step_of_a_reading_on_a_grid_and_nothing_else() -> None:
    rng = np.random.default_rng(1)
    ia = 1.0 + 0.3 * np.sin(np.linspace(0, 3, 200))  # A
    per_mille = 4000 * 1e-6  # a CiA 402 current: per mille of a 4000 mA rated current
    assert quantum(np.round(ia / per_mille) * per_mille) == pytest.approx(0.004, rel=1e-9)
    adc = 5.0 / 1023  # a 10-bit ADC with an offset: the grid need not pass through 0
    assert quantum(0.37 + np.round(ia / adc) * adc) == pytest.approx(adc, rel=1e-9)
    assert quantum(ia) == 0.0  # continuous
    assert quantum(ia + rng.normal(0, 1e-3, 200)) == 0.0
    assert quantum(np.round(ia / 1e-9) * 1e-9) == 0.0  # beyond QUANTUM_MAX_STEPS: continuous
    assert np.isnan(quantum(np.full(200, 0.004)))  # one value: the window cannot tell


def test_a_quantised_readings_rounding_is_not_taken_for_model_error() -> None:
    """A drive reporting its current in per mille of 4 A (the CANopen example's): the twin
    is exact, and the residual is the reading's rounding, up to 2 mA, which follows the
    current between two levels: not white. Counted as model error it failed the check in
    44 of the example's 150 windows. A gain error of 1 % (2.5 steps) still fails."""
    t = np.linspace(0.0, 2.0, 200)
    ia = 1.0 + 0.01 * np.sin(2 * np.pi * 0.25 * t)  # the twin's current, exact [A]
    step = 0.004
    meas = np.round(ia / step) * step
    scale = float(np.sqrt(np.mean(meas**2)))
    res = ((ia - meas) / scale)[1:, None]
    q = np.array([quantum(meas) / scale])
    bare = check_model(res, ("ia",), None, alpha=0.01, lags=20, floor=1e-4)
    assert not bare.passed and "not white" in bare.reasons[0]
    assert check_model(res, ("ia",), None, alpha=0.01, lags=20, floor=1e-4, quanta=q).passed
    wrong = (((1.0 + 0.01 * np.sin(2 * np.pi * 0.2 * t)) * ia - meas) / scale)[1:, None]
    check = check_model(wrong, ("ia",), None, alpha=0.01, lags=20, floor=1e-4, quanta=q)
    assert not check.passed and "the reading's step" in check.reasons[0], check.reasons


def test_a_noise_free_outputs_share_of_the_estimates_uncertainty_fails_alpha_of_windows() -> None:
    """A closed-loop drive's voltage is measured without noise: its residual is the trace of
    the other outputs' noise on the estimates, ``J d`` with ``d ~ N(0, C)``, smooth (never
    white), and one direction of the estimates dominates it. Its mean square is then a
    chi-square of about one degree, which exceeds four times its mean in 4.6 % of windows:
    the bound of twice the mean RMS failed the default motor's check in 14 of 301 windows at
    0.5 % noise (each then searched by the swarm). With the degrees the bound is the
    chi-square's 1 - alpha quantile; with many degrees it stays twice the mean."""
    n, rng = 200, np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, n)
    shapes = np.column_stack([np.sin(2.0 * t), t * t, np.exp(-3.0 * t)])  # (N, 3) smooth
    cov = np.diag([1.0, 1e-4, 1e-4]) * 1e-6  # one direction dominates
    jac = shapes / math.sqrt(n)  # the normalised residuals' Jacobian, one output
    explained = explained_rms(jac, cov, 1)
    dof = explained_dof(jac, cov, 1)
    assert 1.0 <= dof[0] < 1.05
    drawn = rng.multivariate_normal(np.zeros(3), cov, size=2000)
    old = new = 0
    for d in drawn:
        res = (shapes @ d)[:, None]
        assert ljung_box(res[:, 0], 20)[1] < 0.01  # structured, as a drive's voltage
        old += not check_model(res, ("Va",), None, alpha=0.01, lags=20, floor=1e-12,
                               explained=explained).passed
        new += not check_model(res, ("Va",), None, alpha=0.01, lags=20, floor=1e-12,
                               explained=explained, explained_dof=dof).passed
    assert 0.035 < old / drawn.shape[0] < 0.06  # P(chi2_1 > 4) = 0.0455
    assert new / drawn.shape[0] < 0.015  # alpha
    # a residual twice the quantile's size still fails
    res = (shapes @ (3.0 * np.sqrt(np.diag(cov)) * np.array([1.0, 0.0, 0.0])))[:, None]
    assert not check_model(res, ("Va",), None, alpha=0.01, lags=20, floor=1e-12,
                           explained=explained, explained_dof=dof).passed
    # many directions alike: the degrees are their number, the bound twice the mean RMS
    q, _ = np.linalg.qr(shapes)
    assert explained_dof(q, np.eye(3), 1)[0] == pytest.approx(3.0, rel=1e-9)


# -- configured for the variant: exact, and its intervals cover the truth ------------------------
def test_twin_configured_with_the_drive_is_exact_noise_free() -> None:
    plant, runs = _run(DCMotorTwin(drive=DRIVE), {}, 10)
    for w, e in runs:
        truth = plant.truth(float(w.t[w.n // 2])).Ra
        assert e.model_check.passed
        assert e.values["Ra"] == pytest.approx(truth, rel=0.002)  # the paper's 0.2 %


#: Windows and threshold of the coverage test: with perfect 2-sigma intervals (95.4 % coverage)
#: 100 windows fall below 85 % with probability 1.2e-5; intervals half as wide as they should
#: be (68.3 %) reach it with probability 1.1e-4 (binomial; 19 windows at 90 % failed a correct
#: interval 25 % of the time).
COVERAGE_WINDOWS, COVERAGE_MIN = 100, 0.85


def _coverage(plant: DCMotorPlant, runs: list, widen: float = 1.0  # type: ignore[type-arg]
              ) -> tuple[int, int]:
    """(windows publishing Ra 'estimated', of which the truth within 2 x ``widen`` standard
    errors)."""
    n = ok = 0
    for w, e in runs:
        if e.status["Ra"] == "estimated":
            n += 1
            truth = plant.truth(float(w.t[w.n // 2])).Ra
            ok += abs(math.log(e.values["Ra"] / truth)) <= 2 * widen * e.rel_std["Ra"]
    return n, ok


@pytest.mark.slow  # about 6 s on the shared 2-core box: out of the fast lane
def test_twin_configured_with_the_drive_is_honest_with_noise() -> None:
    """100 windows (fixed seeds): Ra's 2-sigma interval covers the plant's in at least 85 % of
    the windows publishing it, and the test can fail: the same intervals halved do not. Window
    82 is issue 15's: Ra +0.055 % published with 0.015 % (z = 3.75) by a Jacobian that
    straddled a jump of the drive's clamping anti-windup."""
    plant, runs = _run(DCMotorTwin(drive=DRIVE), {"ia": 1.0, "omega": 1.0}, COVERAGE_WINDOWS)
    flagged = sum(not e.model_check.passed for _, e in runs)
    assert flagged <= 0.1 * len(runs)  # few false alarms on a right model
    n, ok = _coverage(plant, runs)
    assert n >= 0.8 * len(runs) and ok >= COVERAGE_MIN * n, (n, ok)
    n, ok_half = _coverage(plant, runs, widen=0.5)
    assert ok_half < COVERAGE_MIN * n, (n, ok_half)  # a 2x-too-narrow interval fails
    w82, e82 = runs[2]
    assert w82.index == 82 and e82.status["Ra"] == "estimated"
    z82 = math.log(e82.values["Ra"] / plant.truth(float(w82.t[100])).Ra) / e82.rel_std["Ra"]
    assert abs(z82) < 2.0 and e82.rel_std["Ra"] > 0.0005
    for w, e in runs:
        truth = plant.truth(float(w.t[w.n // 2])).Ra
        assert e.values["Ra"] == pytest.approx(truth, rel=0.01)
        for name, rel in e.rel_std.items():  # the gate: never 'estimated' above max_rel_std
            if e.status[name] == "estimated":  # (the window's own: the floor is the twin's)
                assert math.sqrt(rel**2 - e.floor.get(name, 0.0) ** 2) <= 0.01 * (1 + 1e-9)


# -- configured wrongly: it says so -------------------------------------------------------------
def test_ideal_pi_twin_on_a_drive_that_holds_its_output_says_so() -> None:
    """The issue's finding (an ideal PI twin on a 1 kHz drive: a 0.7 % bias published with
    0.05 % confidence): the residual of the drive's voltage is not white, the window is
    flagged, not trusted, and its intervals widened, which holds Ra."""
    plant, runs = _run(DCMotorTwin(kp=2.0, ki=2.0), {}, 12)
    flagged = [e for _, e in runs if not e.model_check.passed]
    assert len(flagged) >= 0.75 * len(runs)
    for e in flagged:
        assert not e.trusted and e.model_check.widen > 1
        assert any("residual of Va" in r for r in e.model_check.reasons)
    n, ok = _honest(plant, runs)
    assert ok == n


def test_a_parameter_the_gate_holds_is_published_at_its_trusted_value() -> None:
    """A window whose failed model check widens Ra's interval past ``max_rel_std`` holds Ra:
    the published value is the last trusted one (``_run`` asserts it for every held
    parameter), not the window's estimate, and the others are re-fitted with it held."""
    _, runs = _run(DCMotorTwin(kp=2.0, ki=2.0), {}, 4, fusion=False)
    gated = [e for _, e in runs if "after the model check failed" in e.held.get("Ra", "")]
    assert gated and all(e.status["Ra"] == "held" for e in gated)
    for e in gated:  # the others' (marginal) intervals pass the gate
        assert all(math.sqrt(e.rel_std[n] ** 2 - e.floor.get(n, 0.0) ** 2) <= 0.01 * (1 + 1e-9)
                   for n, st in e.status.items() if st == "estimated")


def test_unmodelled_unidirectional_stage_is_flagged_where_it_acts() -> None:
    """A plant whose stage cannot reverse the current, the twin without it: every window in
    which the plant's current was blocked at 0 is flagged; configured with the stage, none."""
    drive = DriveConfig(period=0.001, speed=LoopConfig(kp=2.0, ki=1.0, output_min=-18.0,
                                                        output_max=18.0))
    cfg = DCMotorPlantConfig(scenario="nominal", duration=44.0, drive=drive, setpoint=STEPS,
                             power_stage="unidirectional", La=0.05)
    _, wins = plant_windows(cfg, 21)
    blocked = [w for w in wins if np.any(w["ia"] == 0.0) and w.index > 0]
    assert len(blocked) >= 1
    est = Estimator(DCMotorTwin(drive=drive), EstimationConfig(bounds=BOUNDS), {"La": 0.05})
    right = Estimator(DCMotorTwin(drive=drive, power_stage="unidirectional"),
                      EstimationConfig(bounds=BOUNDS), {"La": 0.05})
    for w in blocked:
        e = est.estimate(w)
        assert not e.model_check.passed and not e.trusted
        assert right.estimate(w).model_check.passed


# -- evidence across windows ---------------------------------------------------------------
def test_fusion_of_linear_evidence_is_the_batch_least_squares() -> None:
    """One linear window through the filter with a flat prior: the batch estimate and its
    covariance; a window that does not inform a parameter leaves it alone."""
    rng = np.random.default_rng(1)
    jac = rng.normal(size=(300, 3))
    truth = np.array([0.2, -0.1, 0.05])
    y = jac @ truth + 0.1 * rng.normal(size=300)
    f = ParameterFusion(("a", "b", "c"), np.ones(3),
                        FusionConfig(model="random_walk", initial_std=1e3))
    f.state.mean[:] = 0.0
    f.update(1.0, lambda x: (jac, jac @ x - y), np.full(300, 0.01))
    batch = np.linalg.lstsq(jac, y, rcond=None)[0]
    np.testing.assert_allclose(f.state.mean, batch, atol=1e-6)
    np.testing.assert_allclose(np.diag(f.state.cov), np.diag(np.linalg.inv(jac.T @ jac) * 0.01),
                               rtol=1e-4)
    # a window that informs only "a" leaves an uncorrelated "b" where it was
    g = ParameterFusion(("a", "b", "c"), np.ones(3),
                        FusionConfig(model="random_walk", initial_std=1e3))
    g.state.mean[:] = 0.0
    g.update(1.0, lambda x: (jac[:, :1], jac[:, :1] @ x[:1] - y), np.full(300, 0.01),
             cols=np.array([0]))
    assert g.state.mean[1] == 0.0 and g.state.cov[1, 1] >= 1e6
    assert g.state.cov[0, 0] < 1e-3


def _linear_window(level: float, sd: float, cols: tuple[int, ...] = (0,)) -> tuple[
        object, np.ndarray]:
    """A window that says ``level`` (ln) for each of ``cols`` with standard error ``sd``."""
    k = len(cols)

    def lin(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(k), x[list(cols)] - level
    return lin, np.full(k, sd * sd)


def test_a_sudden_change_moves_the_level_not_its_rate() -> None:
    """Issue 34: a window far beyond the prediction (a step of 10 % told with 0.1 %) inflates
    the levels it determines, not the rates: the filter follows the step at once and the
    fused value then stays put while no window informs it. Scaling the whole covariance (as
    before) let the step set a rate that later windows never corrected: the noise-free DC
    motor's fused Ke fell 0.3 %/s for 90 s, to -25 %."""
    f = ParameterFusion(("Ra", "Ke"), np.ones(2), FusionConfig())
    for k in range(30):          # settled at 0 from windows that inform both
        f.update(2.0 * k, *_linear_window(0.0, 0.001, (0, 1)), cols=np.array([0, 1]))
    jump = f.update(60.0, *_linear_window(math.log(1.1), 0.001), cols=np.array([0]))
    assert jump
    assert abs(f.state.mean[0] - math.log(1.1)) < 0.005
    assert abs(f.state.mean[2]) < 1e-4 and abs(f.state.mean[3]) < 1e-4   # the rates
    for k in range(31, 80):      # windows that fail their check: the filter only advances
        f.update(2.0 * k)
    assert abs(f.state.mean[0] - math.log(1.1)) < 0.01, f.state.mean
    assert abs(f.state.mean[1]) < 0.005, f.state.mean


def test_a_window_that_halves_a_determined_parameter_at_once_is_an_outlier() -> None:
    """Issue 34: a sudden change beyond a factor 2 (``JUMP_LIMIT``) in one window is the
    model's outlier (a parameter held at a wrong value pushing the others), not wear: the
    window is not fused (counted), the level stays; a step of 30 % is followed."""
    f = ParameterFusion(("D",), np.ones(1), FusionConfig())
    for k in range(20):
        f.update(2.0 * k, *_linear_window(0.0, 0.001))
    assert not f.update(40.0, *_linear_window(math.log(0.35), 0.001))
    assert f.outliers == 1 and abs(f.state.mean[0]) < 0.005
    assert f.last_outlier is not None and f.last_outlier[0] == "D"
    assert f.last_outlier[1] == pytest.approx(0.35, rel=0.05)   # said in the log line
    assert f.update(42.0, *_linear_window(math.log(1.3), 0.001))
    assert f.outliers == 1 and abs(f.state.mean[0] - math.log(1.3)) < 0.005


def test_a_step_beyond_a_factor_2_is_suspect_until_the_windows_keep_telling_it() -> None:
    """Issue 34: the window that would move D by more than a factor 2 at once is not fused
    and its estimates are published ``suspect`` naming the move (not ``estimated``: a
    position reading offset by 2 cm was fitted by the hydraulic twin with D x4.1 at nRMSE
    2e-6 and read as the fluid's degradation at 0.99), and the window is not trusted; when
    the windows keep telling the same step (``OUTLIER_RUN``, 3) it is the machine's: D x4
    at once (a seized bearing) is then estimated and fused at x4 (before, the fused D stayed
    at its nameplate for ever)."""
    from twinwatch.twin.estimation.fusion import OUTLIER_RUN

    cfg = DCMotorPlantConfig(scenario="nominal", duration=60, seed=1, parameter_faults=[
        {"parameter": "D", "change": 300.0, "start": 30.0, "ramp": 0.0}])
    plant, wins = plant_windows(cfg, 24)
    est = Estimator(DCMotorTwin(), EstimationConfig(bounds=BOUNDS))
    out = [est.estimate(w) for w in wins]
    d0 = plant.truth(0.0).D
    step = next(k for k, w in enumerate(wins) if w.t[-1] > 30.0)
    assert all(e.status["D"] == "estimated" for e in out[5:step])
    odd = [k for k, e in enumerate(out) if "an outlier of the model, not fused" in
           e.held.get("D", "")]
    assert odd and odd[0] == step and len(odd) == OUTLIER_RUN, odd
    for k in odd:
        assert out[k].status["D"] != "estimated" and not out[k].trusted
        assert out[k].fused["D"][0] == pytest.approx(d0, rel=0.01)
    assert "D would move by a factor 4 in one window" in out[odd[-1]].held["D"]
    for e in out[odd[-1] + 1:]:
        assert e.status["D"] == "estimated" and e.values["D"] == pytest.approx(4 * d0, rel=0.01)
        assert e.fused["D"][0] == pytest.approx(4 * d0, rel=0.01)


def test_fusion_follows_a_level_shift_told_by_windows_of_three_standard_errors() -> None:
    """Issue 34: a level that steps by 12 % while each window says so with a 3 % standard
    error (a PWM drive's Ra: innovations of 2-4 standard errors, never the 5 of the one-window
    jump test) is followed within a few windows by the windowed test
    (:data:`~twinwatch.twin.estimation.fusion.SHIFT_WINDOWS`); before it, the fused Ra stayed
    near -3 % for 20 windows. Windows at the old level raise nothing."""
    rng = np.random.default_rng(3)
    sd = 0.03

    def run(level: float, n: int) -> tuple[list[float], list[bool]]:
        f = ParameterFusion(("Ra",), np.ones(1), FusionConfig())
        means, jumps = [], []
        for k in range(n):
            true = level if k >= 20 else 0.0
            y = true + sd * rng.normal()
            jumps.append(f.update(2.0 * k, lambda x, y=y: (np.ones((1, 1)), x[:1] - y),
                                  np.array([sd * sd])))
            means.append(float(f.state.mean[0]))
        return means, jumps

    means, jumps = run(math.log(0.88), 40)
    assert not any(jumps[:20])
    assert any(jumps[20:26])                                  # seen within six windows
    assert all(abs(m - math.log(0.88)) < 0.03 for m in means[28:])
    flat, flat_jumps = run(0.0, 60)
    assert not any(flat_jumps) and max(abs(m) for m in flat[10:]) < 0.03, flat


def test_fused_d_tracks_bearing_wear_with_noise() -> None:
    """DC motor bearing wear (paper scenario 2), 1 % noise: the fused D follows the plant's
    within 2 % after the first minute, and its interval covers it."""
    cfg = DCMotorPlantConfig(scenario="bearing_wear", duration=400, fault_start=60.0,
                             noise={"ia": 1.0, "omega": 1.0}, seed=4)
    plant, wins = plant_windows(cfg, 40, skip=30)
    est = Estimator(DCMotorTwin(), EstimationConfig(bounds=BOUNDS))
    inside = covered = n = 0
    for w in wins:
        e = est.estimate(w)
        value, rel = e.fused["D"]
        truth = plant.truth(float(w.t[w.n // 2])).D
        n += 1
        inside += abs(value / truth - 1.0) <= 0.02
        covered += abs(math.log(value / truth)) <= 2 * rel
    assert inside >= 0.9 * n and covered >= 0.9 * n


def test_a_fit_that_does_not_explain_the_window_is_suspect() -> None:
    """A window whose final nRMSE exceeds ``trust_rmse`` does not update the trusted values;
    its estimates are not published ``estimated`` either (a TR plant fitted by a BE twin at
    1 % noise published Ra +87 % +- 0.08 % `estimated` at nRMSE 0.84, its model check
    passed). Here the rule itself: a trust_rmse below what 1 % noise leaves."""
    _, wins = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=12,
                                               noise={"ia": 1.0, "omega": 1.0}, seed=2), 2)
    est = Estimator(DCMotorTwin(), EstimationConfig(trust_rmse=1e-3))
    for w in wins:
        e = est.estimate(w)
        assert e.nrmse > 1e-3 and not e.trusted
        assert "estimated" not in e.status.values(), e.status
        assert any("the fit does not explain the window (nRMSE" in why
                   for why in e.held.values()), e.held


@pytest.mark.slow  # 150 windows of a mis-stated drive: about 15 s
def test_a_mis_stated_drive_never_publishes_a_misfit_as_estimated() -> None:
    """The TR plant fitted by a BE twin (benchmarks/bench_fidelity.py --only methods, 150
    windows), 1 % noise: from about window 200 the swarm lands far from the machine (nRMSE
    0.2-0.8 against 0.01 of noise) and Ra was published `estimated` off by -17 % to +87 %.
    Every window publishing Ra `estimated` now fits within trust_rmse, and none of them is
    more than 5 % off."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import bench_fidelity as bf

    n = 150
    cfg = DCMotorPlantConfig(scenario="resistance_degradation", duration=160 + 2 * n + 10,
                             drive=bf.method_drive("trapezoidal"),
                             noise={"ia": 1.0, "omega": 1.0}, seed=5,
                             setpoint=bf.METHOD_SETPOINT)  # type: ignore[arg-type]
    plant = DCMotorPlant(cfg)
    est = Estimator(DCMotorTwin(drive=bf.method_drive("backward_euler")),
                    EstimationConfig(bounds=bf.BOUNDS))
    worst = 0.0
    for w in bf.windows(plant, n, skip=80):
        e = est.estimate(w)
        if e.status["Ra"] == "estimated":
            assert e.nrmse <= est.config.trust_rmse
            truth = plant.truth(float(w.t[w.n // 2])).Ra
            worst = max(worst, abs(e.values["Ra"] / truth - 1.0))
    assert worst < 0.05, worst


def _methods_run(plant_method: str, twin_method: str, n: int
                 ) -> tuple[DCMotorPlant, list]:  # type: ignore[type-arg]
    """benchmarks/bench_fidelity.py --only methods, noise-free, the first ``n`` windows."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import bench_fidelity as bf

    cfg = DCMotorPlantConfig(scenario="resistance_degradation", duration=160 + 2 * n + 10,
                             drive=bf.method_drive(plant_method), seed=5,
                             setpoint=bf.METHOD_SETPOINT)  # type: ignore[arg-type]
    plant = DCMotorPlant(cfg)
    est = Estimator(DCMotorTwin(drive=bf.method_drive(twin_method)),
                    EstimationConfig(bounds=bf.BOUNDS))
    return plant, [(w, est.estimate(w)) for w in bf.windows(plant, n, skip=80)]


def test_a_mis_stated_drive_publishes_its_structural_error_in_the_interval() -> None:
    """Issue 23 item 5, the interval's floor (twinwatch/twin/estimation/floor.py): the FE
    plant fitted by the TR twin, noise-free. Window 34's check passed while five free
    parameters absorbed the tick of integral action (Ke -1.72 % +- 0.009 %); every later window
    held it and published Ra 0.052 % off with 0.012 %: covered in 20 of the 37 estimated of
    these 60 windows before the floor (24 % over 150). The scatter of the windows' Ke now
    widened Ra's interval (through its gain on the held Ke) to cover. Since the windows hold a
    never-trusted parameter the fusion contradicts at its fused value (issue 34), Ke is held
    where the windows put it and Ra's interval covers without the floor's widening (37 of 37);
    the matching twin's stays as narrow as its noise-free fit (median 2 sigma 0.025 %)."""
    plant, runs = _methods_run("forward_euler", "trapezoidal", 60)
    n, ok = _coverage(plant, runs)
    late = [e for w, e in runs if w.index >= 80 + 40 and e.status["Ra"] == "estimated"]
    assert late
    assert n >= 25 and ok >= 0.9 * n, (n, ok)
    plant, runs = _methods_run("forward_euler", "forward_euler", 60)
    n, ok = _coverage(plant, runs)
    half = [2 * e.rel_std["Ra"] for _, e in runs if e.status["Ra"] == "estimated"]
    assert n >= 55 and ok >= 0.9 * n, (n, ok)
    assert float(np.median(half)) < 0.0003, np.median(half)
