"""When to act (issue 17): trend and remaining useful life of the estimated parameters, the RUL
alarms, the adaptive window.

Unit tests on the paper's degradation laws (NOTES.md: Ra(t) = 6.5 - 0.044 (exp(0.003 (t - 160))
- 1), its -10 % alarm threshold 5.85 ohm crossed at 1079.5 s), a real Kalman filter of the
estimator for the window's share of the fused evidence, and the daemon end to end: a short run
in the fast lane, the paper's 1200 s scenarios in the slow lane (the issue's acceptance figures:
from halfway between the onset and the crossing, the median crossing within 10 % and the 95 %
interval covering it in at least 90 % of the windows).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from twinwatch.config.alarms import AlarmConfig, AlarmRule
from twinwatch.config.loader import default_config, validate_config
from twinwatch.daemon.alarms import AlarmEvaluator
from twinwatch.daemon.ringbuffer import RingBuffer
from twinwatch.daemon.runner import Daemon
from twinwatch.twin.estimation.fusion import FusionConfig, ParameterFusion
from twinwatch.twin.health import (
    CrossingHealth,
    HealthMessage,
    ParameterHealth,
    RulHealth,
    TrendHealth,
    trend_line,
)
from twinwatch.twin.prognostics import (
    AdaptiveWindowConfig,
    Evidence,
    Prognostics,
    PrognosticsConfig,
    Thresholds,
    fused_share,
)
from twinwatch.twin.prognostics.degradation import bin_evidence, fit_models, refit_models, select
from twinwatch.twin.prognostics.metrics import alpha_lambda_pass, score_profile
from twinwatch.twin.prognostics.rul import (
    crossing_times,
    draw_trajectories,
    first_crossings,
    format_crossing,
    predict_crossing,
    sort_order,
)
from twinwatch.twin.prognostics.trend import (
    ParameterTrend,
    TrendSettings,
    monotonicity,
    trendability,
)
from twinwatch.twin.prognostics.window import WindowController

RA0, RA_DROP, RATE, ONSET = 6.5, 0.044, 0.003, 160.0
RA_ALARM = RA0 * 0.9  # the default rule's -10 %
T_ALARM = ONSET + math.log(1 + (RA0 - RA_ALARM) / RA_DROP) / RATE  # 1079.5 s
RA_THRESHOLDS = Thresholds(RA0 * 1.05, RA0 * 0.95, RA0 * 1.1, RA0 * 0.9)


def paper_ra(t: np.ndarray | float) -> np.ndarray:
    """The paper's resistance degradation (NOTES.md, scenario 1)."""
    return RA0 - RA_DROP * (np.exp(RATE * np.maximum(np.asarray(t) - ONSET, 0.0)) - 1.0)


def test_the_issues_crossing_time() -> None:
    assert T_ALARM == pytest.approx(1079.5, abs=0.1)
    assert paper_ra(T_ALARM) == pytest.approx(RA_ALARM)


# -- degradation models -------------------------------------------------------------------------

def test_exact_evidence_of_the_paper_law_gives_its_model_onset_rate_and_crossing() -> None:
    """Noise-free windows (the estimator's 0.01 % stated error) up to 620 s (halfway from the
    onset to the crossing): an exponential from 160 s with r = 0.003 /s, and the -10 %
    threshold crossed at 1079.5 s to within a second."""
    t = np.arange(1.0, 620.0, 2.0)
    y = paper_ra(t)
    s = 1e-4 * y
    best, pairs = select(fit_models(t, y, s))
    assert best is not None and best.kind == "exponential"
    assert best.onset == pytest.approx(ONSET, abs=1.0)
    assert best.r == pytest.approx(RATE, rel=1e-3)
    assert best.m == pytest.approx(-RA_DROP * RATE * math.exp(RATE * (t[-1] - ONSET)), rel=1e-3)
    cr = predict_crossing(best, "alarm", None, RA_ALARM, t_end=620.0, interval=0.95,
                          draws=2000, rng=np.random.default_rng(0), mixture=pairs)
    assert cr.status == "predicted"
    assert cr.t == pytest.approx(T_ALARM, abs=1.0)
    assert cr.t_low is not None and cr.t_high is not None
    assert cr.t_low <= T_ALARM <= cr.t_high


def test_noisy_evidence_intervals_cover_the_true_crossing() -> None:
    """0.3 % noise per window (3 times the estimator's with 1 % sensor noise), 40 seeds, at
    700 s: the 95 % interval contains 1079.5 s and the median is within 10 % of it in at least
    90 % of them (the evidence decides; the truth is never used)."""
    rng = np.random.default_rng(3)
    t = np.arange(1.0, 700.0, 2.0)
    covered = within = 0
    for seed in range(40):
        y = paper_ra(t) * (1 + 0.003 * np.random.default_rng(seed).standard_normal(t.size))
        best, pairs = select(fit_models(*bin_evidence(t, y, 0.003 * y, 120)))
        assert best is not None
        cr = predict_crossing(best, "alarm", None, RA_ALARM, t_end=700.0, interval=0.95,
                              draws=2000, rng=rng, mixture=pairs)
        covered += cr.t_low is not None and cr.t_low <= T_ALARM and (
            cr.t_high is None or cr.t_high >= T_ALARM)
        within += cr.t is not None and abs(cr.t - T_ALARM) <= 0.1 * T_ALARM
    assert covered >= 36 and within >= 36, (covered, within)


def test_an_onset_soon_after_it_is_not_taken_as_known_to_a_fraction_of_a_second() -> None:
    """Soon after the onset (186 s: 13 windows of degradation after 80 flat ones, 0.004 %
    noise per window, about the CANopen example's): the onset, between two windows 2 s apart
    and in noise, is not located to better than half a second, and the growth rate's error
    is not under-stated. Before, the information's raw eigenvalues spanned more than the
    pseudo-inverse's cut-off (the onset in s, the level in ohm, the drift rate in ohm/s): a
    direction was dropped with zero variance, the onset "known" to 1e-4 s, and on the
    example a RUL ALARM "in 103 s (72-192 s)" was raised at 186 s for a crossing at 1080 s."""
    t = np.arange(1.0, 186.0, 2.0)
    for seed in range(10):
        y = paper_ra(t) + 2.5e-4 * np.random.default_rng(seed).standard_normal(t.size)
        fits = fit_models(t, y, np.full(t.size, 2.5e-4))
        for f in fits:
            if f.onset is not None:
                assert f.std("t0") > 0.5, (seed, f.kind, f.std("t0"))
        exp = next(f for f in fits if f.kind == "exponential" and f.onset is not None)
        assert abs(exp.r - RATE) < 3 * exp.std("r"), (seed, exp.r, exp.std("r"))


def test_both_levels_read_one_sample_of_the_trajectories() -> None:
    """The warning and the alarm of a window are read from the same Monte Carlo draws: every
    draw reaches the warning (-5 %) no later than the alarm (-10 %), and the window's
    published times keep that order (0.3 % noise, the paper's law up to 700 s)."""
    prog = Prognostics(("Ra",), {"Ra": RA0}, PrognosticsConfig(), {"Ra": RA_THRESHOLDS})
    rng = np.random.default_rng(5)
    p = None
    for t in np.arange(1.0, 700.0, 2.0):
        v = float(paper_ra(t)) * (1 + 0.003 * rng.standard_normal())
        p = prog.update({"Ra": Evidence(t, v, 0.003 * v)}, t_end=t + 1.0)["Ra"]
    assert p is not None and p.rul is not None and p.rul.status == "degrading"
    warning, alarm = p.rul.warning, p.rul.alarm
    assert warning is not None and alarm is not None
    assert warning.samples is not None and alarm.samples is not None
    assert warning.samples.shape == alarm.samples.shape == (2000,)
    assert np.all(warning.samples <= alarm.samples)
    assert np.isfinite(warning.samples).mean() >= np.isfinite(alarm.samples).mean()
    assert warning.t is not None and alarm.t is not None and warning.t < alarm.t
    with pytest.raises(ValueError, match="trajectories or a generator"):
        predict_crossing(prog.trends["Ra"].fit, "alarm", None, RA_ALARM, t_end=700.0,
                         interval=0.95, draws=2000)


def test_the_quantiles_from_the_previous_windows_order_are_the_partitions() -> None:
    """The RUL's median and interval read from the draws sorted through a hint (the previous
    window's order, a stale one, none) are the partition's, bit for bit, with draws that
    never cross (inf) among them; the hint only makes the sort cheaper."""
    t = np.arange(1.0, 700.0, 2.0)
    y = paper_ra(t) * (1 + 0.003 * np.random.default_rng(2).standard_normal(t.size))
    best, pairs = select(fit_models(*bin_evidence(t, y, 0.003 * y, 120)))
    assert best is not None
    normals = np.random.default_rng(9).standard_normal((2000, 4))
    times = first_crossings(draw_trajectories(best, pairs, 2000, normals=normals), 700.0,
                            [(None, RA_ALARM), (None, 0.1 * RA_ALARM)])
    times[1][::7] = np.inf  # some draws never get there
    previous = sort_order(times[0])
    assert np.all(times[0][previous][:-1] <= times[0][previous][1:])
    for samples in times:
        plain = predict_crossing(best, "alarm", None, RA_ALARM, t_end=700.0, interval=0.95,
                                 draws=2000, times=samples)
        for hint in (previous, np.arange(2000)[::-1].copy(), None, np.arange(3)):
            ranked = samples[sort_order(samples, hint)]
            assert np.all(ranked[:-1] <= ranked[1:])
            cr = predict_crossing(best, "alarm", None, RA_ALARM, t_end=700.0, interval=0.95,
                                  draws=2000, times=samples, order=sort_order(samples, hint))
            assert (cr.t, cr.t_low, cr.t_high, cr.probability) == (
                plain.t, plain.t_low, plain.t_high, plain.probability)
    assert plain.t_high is None  # the far threshold's interval is open: a real inf case


def test_a_warm_refit_finds_the_grid_searchs_fits() -> None:
    """The models refitted from the last window's optimum (no grid search) on the next
    window's evidence, 0.3 % noise: the same models, as good a fit (chi-square), the same
    level, rate and growth (to a small fraction of their standard errors; an onset's chi-square
    is flat to within 0.01 over a few seconds), and the same choice."""
    t = np.arange(1.0, 622.0, 2.0)
    y = paper_ra(t) * (1 + 0.003 * np.random.default_rng(5).standard_normal(t.size))
    s = 0.003 * y
    before = fit_models(*bin_evidence(t[:-1], y[:-1], s[:-1], 120))
    full = fit_models(*bin_evidence(t, y, s, 120))
    warm = refit_models(before, *bin_evidence(t, y, s, 120))
    assert [f.label.split(" from")[0] for f in warm] == [f.label.split(" from")[0]
                                                         for f in full]
    for f, g in zip(full, warm, strict=True):
        assert g.chi2 <= f.chi2 + 0.05, (f.label, f.chi2, g.chi2)
        for p in ("c", "m", "r"):
            if p in f.free:
                assert abs(g._get(p) - f._get(p)) <= 0.2 * f.std(p), (f.label, p)
        if f.onset is not None:
            assert g.onset == pytest.approx(f.onset, abs=10.0)
    assert select(warm)[0].label.split(" from")[0] == select(full)[0].label.split(" from")[0]


def test_a_trend_takes_the_evidence_it_predicts_by_an_update_and_refits_when_asked() -> None:
    """A flat trend, 0.3 % noise: the evidence within ``skip_z`` (1 standard error, about 68 %
    of it) is taken by the update (the fit kept, advanced to the latest evidence), but at the
    grid search every tenth; while the horizon drops evidence, at every second evidence only
    (an update does not remove it). The updated fit is the fit: the flat and the line's level
    and rate within a fifth of their standard errors of the models fitted again to the same
    evidence. A drift (exact evidence) is detected after its onset, within 40 s, and no later
    than by a trend refitted every window (``skip_z`` below 0: never an update)."""
    calls = []

    def counting(settings: TrendSettings) -> ParameterTrend:
        trend = ParameterTrend("Ra", settings)
        refit = trend.refit

        def counted(t_now: float, *, full: bool = False) -> None:
            fit = trend.fit
            refit(t_now, full=full)
            calls.append(trend.fit is fit and fit is not None and fit.t_ref == trend.t[-1])
        trend.refit = counted  # type: ignore[method-assign]
        return trend

    rng = np.random.default_rng(2)
    t = np.arange(1.0, 400.0, 2.0)
    flat = RA0 * (1 + 0.003 * rng.standard_normal(t.size))
    compared = 0
    for horizon, most, least in ((3600.0, 80, 50), (100.0, 45, 20)):
        calls.clear()
        trend = counting(TrendSettings(min_span=60.0, horizon=horizon))
        for tt, v in zip(t, flat, strict=True):
            trend.add(Evidence(tt, v, 0.003 * RA0))
            trend.refit(tt)
            if horizon > 1000.0 and tt > 300.0 and calls[-1]:
                # an update: against the models fitted again to all the evidence
                again = {g.label: g for g in fit_models(*bin_evidence(
                    np.asarray(trend.t), np.asarray(trend.y), np.asarray(trend.s), 120),
                    t_ref=trend.t[-1], onset=False)}
                for f in trend.fits:
                    if f.label not in ("none", "linear"):
                        continue  # an exponential on flat evidence has optima of any curvature
                    g = again[f.label]
                    for p in f.free:
                        assert abs(f._get(p) - g._get(p)) <= 0.2 * g.std(p), (f.label, p)
                    compared += 1
        updated = calls[-100:].count(True)
        assert least <= updated <= most, (horizon, updated)
        assert trend.fit is not None and not trend.degrading()
        rate, sd = trend.fit.rate_at(trend.t[-1])
        assert abs(rate) <= 3 * sd
    assert compared >= 20

    detected = {}
    for skip_z in (-1.0, TrendSettings().skip_z):
        trend = ParameterTrend("Ra", TrendSettings(min_span=60.0, skip_z=skip_z))
        for tt in t:
            trend.add(Evidence(tt, float(paper_ra(tt)), 1e-4 * RA0))
            trend.refit(tt)
            if trend.degrading():
                detected[skip_z] = tt
                break
    assert all(ONSET < tt < ONSET + 40.0 for tt in detected.values()), detected
    assert detected[TrendSettings().skip_z] <= detected[-1.0], detected


def test_a_fit_without_a_finite_covariance_is_fitted_again_not_updated() -> None:
    """The update needs the fit's covariance: a fit whose covariance is not finite (its
    information matrix singular) takes the next evidence by a fit to the evidence, and
    comes out finite."""
    trend = ParameterTrend("Ra", TrendSettings(min_span=60.0))
    t = np.arange(1.0, 198.0, 2.0)
    for tt in t[:-1]:
        trend.add(Evidence(tt, RA0, 0.003 * RA0))
        trend.refit(tt)
    assert trend.fit is not None and len(t) % 10  # the next is not a grid search
    for f in trend.fits:
        f.cov = np.full_like(f.cov, np.inf)
    trend.add(Evidence(t[-1], RA0, 0.003 * RA0))
    assert trend.innovation(Evidence(t[-1] + 2.0, RA0, 0.003 * RA0)) == 0.0
    fit = trend.fit
    trend.refit(t[-1])
    assert trend.fit is not fit and trend.fit is not None
    assert np.isfinite(trend.fit.cov).all() and trend.fit.t_ref == t[-1]


def test_flat_noisy_evidence_is_not_degrading_in_any_window() -> None:
    """300 windows of a constant parameter with 0.3 % noise (a nominal run): never
    "degrading", never a RUL."""
    prog = Prognostics(("Ra",), {"Ra": RA0}, PrognosticsConfig(), {"Ra": RA_THRESHOLDS})
    rng = np.random.default_rng(11)
    for k in range(300):
        t = 2.0 * k + 1.0
        v = RA0 * (1 + 0.003 * rng.standard_normal())
        p = prog.update({"Ra": Evidence(t, v, 0.003 * RA0)}, t_end=t + 1.0)["Ra"]
        assert not p.trend.degrading, k
        assert p.rul is not None and p.rul.status in ("insufficient", "not_degrading")
        assert p.rul.alarm is None


def test_a_part_replaced_restarts_the_trend_and_an_onset_bends_it() -> None:
    """Exact evidence: the onset of the degradation at 160 s is a kink the trend follows (no
    restart); the part replaced at 760 s (Ra back to 6.5 ohm, the law again) restarts it within
    two windows, reported with its size; the new trend degrades again later."""
    prog = Prognostics(("Ra",), {"Ra": RA0}, PrognosticsConfig(), {"Ra": RA_THRESHOLDS})
    restarts = []
    for k in range(600):
        t = 2.0 * k + 1.0
        age = t - ONSET if t < 760.0 else t - 760.0
        v = float(RA0 - RA_DROP * (math.exp(RATE * max(age, 0.0)) - 1.0))
        p = prog.update({"Ra": Evidence(t, v, 1e-4 * v)}, t_end=t + 1.0)["Ra"]
        if p.trend.restarted:
            restarts.append(t)
            assert p.trend.restart is not None
            assert p.trend.restart.step == pytest.approx(RA0 - paper_ra(t - 2.0), rel=0.05)
    assert len(restarts) == 1 and 760.0 <= restarts[0] <= 764.0, restarts
    assert p.trend.degrading and p.trend.since_t is not None and p.trend.since_t >= 760.0


def test_a_clock_that_goes_back_restarts_the_trend() -> None:
    """A recording replayed again, a simulated plant restarted: the evidence of the other
    time line is dropped, never mixed in."""
    prog = Prognostics(("Ra",), {"Ra": RA0}, PrognosticsConfig(), {"Ra": RA_THRESHOLDS})
    for k in range(30):
        prog.update({"Ra": Evidence(2.0 * k + 1, RA0, 1e-3)}, t_end=2.0 * k + 2)
    p = prog.update({"Ra": Evidence(1.0, RA0, 1e-3)}, t_end=2.0)["Ra"]
    assert p.trend.restarted and p.trend.evidence == 1
    assert p.trend.restart is not None and "clock went back" in p.trend.restart.reason


def test_crossing_times_closed_form() -> None:
    c, m, r = np.array([6.5, 6.5, 6.5, 5.0]), np.array([-0.001, -0.001, 0.001, -0.001]), \
        np.array([0.0, 0.003, 0.0, 0.0])
    out = crossing_times(c, m, r, 0.0, 5.85, -1)
    assert out[0] == pytest.approx(650.0)                          # linear
    assert out[1] == pytest.approx(math.log(1 + 0.003 * 650.0) / 0.003)  # exponential
    assert math.isinf(out[2])                                      # drifting away
    assert out[3] == 0.0                                           # already beyond it


def _numpy_crossing_times(c, m, r, tau0, threshold, direction):  # type: ignore[no-untyped-def]
    """The numpy expression crossing_times compiled (issue 58), kept as the reference."""
    lin = np.abs(r) < 1e-12
    safe_r = np.where(lin, 1.0, r)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        level_now = c + m * np.where(lin, tau0, np.expm1(np.clip(r * tau0, -700, 700))
                                     / safe_r)
        q = (threshold - c) / m
        arg = 1.0 + r * q
        tau_exp = np.where(arg > 0, np.log(np.where(arg > 0, arg, 1.0)) / safe_r, np.inf)
        tau = np.where(lin, q, tau_exp)
        tau = np.where(np.isfinite(tau) & (m != 0) & (tau >= 0), tau, np.inf)
    out = np.maximum(tau - tau0, 0.0)
    return np.where((level_now - threshold) * direction >= 0, 0.0, out)


@pytest.mark.parametrize("direction,threshold", [(-1, 5.85), (1, 7.15)])
def test_crossing_times_are_the_numpy_expression(direction: int, threshold: float) -> None:
    """The compiled crossing times are the numpy closed form's, to rounding, on draws around
    the paper's resistance law, with the edge cases: no drift, a line, a saturating
    exponential, NaN draws, already beyond the threshold."""
    rng = np.random.default_rng(1)
    n = 5000
    c = 6.5 + 0.3 * rng.standard_normal(n)
    m = 1e-3 * rng.standard_normal(n)
    r = np.where(rng.uniform(size=n) < 0.2, 0.0, 0.003 + 0.004 * rng.standard_normal(n))
    m[:5], r[5:10], c[10:12], m[12] = 0.0, 1e-13, np.nan, np.nan
    for tau0 in (0.0, 37.5):
        got = crossing_times(c, m, r, tau0, threshold, direction)
        want = _numpy_crossing_times(c, m, r, tau0, threshold, direction)
        np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
        np.testing.assert_array_equal(got == 0.0, want == 0.0)
        fin = np.isfinite(want)
        np.testing.assert_allclose(got[fin], want[fin], rtol=1e-12)
        # every kind of answer is in the sample: a real comparison, not all "never"
        assert 0 < int(np.sum(got == 0.0)) < int(np.sum(fin & (got > 0))) < n - 100


def test_format_says_what_to_plan() -> None:
    assert format_crossing(360.0, 240.0, 540.0) == "6 min (4-9 min)"
    assert format_crossing(45.0, 30.0, 61.0) == "45 s (30-61 s)"
    assert format_crossing(7.2e3, 5.0e3, None) == "2 h (1.4 h - never)"


def test_history_scores() -> None:
    assert monotonicity(np.arange(10.0)) == 1.0
    assert monotonicity(np.array([1.0, 2.0, 1.0, 2.0, 1.0])) == 0.0
    assert trendability(np.arange(10.0), -np.arange(10.0)) == pytest.approx(1.0)
    assert trendability(np.arange(3.0), np.ones(3)) is None


def test_alpha_lambda_and_profile_scores() -> None:
    # at t = 600 with t_eol = 1000: the cone is 1000 +- 80
    assert alpha_lambda_pass(600.0, np.array([950.0, 1010.0, 1070.0, 2000.0]), None, 1000.0)
    assert not alpha_lambda_pass(600.0, np.array([900.0, 910.0, 1010.0]), None, 1000.0)
    times = [500.0, 700.0, 900.0]
    sc = score_profile(times, [1000.0, 1080.0, 995.0], [900.0, 1050.0, 950.0],
                       [1100.0, 1200.0, None], [None, None, None], t_eol=1000.0, t_onset=0.0)
    assert sc.windows == 3 and sc.coverage == pytest.approx(2 / 3)
    assert sc.within == 1.0 and sc.alpha_lambda == pytest.approx(2 / 3)


# -- the window's share of the fused evidence --------------------------------------------------

def test_the_windows_share_of_the_fusion_is_its_own_estimate() -> None:
    """A linear measurement fused by the estimator's own Kalman filter (trend model): the share
    recovered from the prediction and the update is the window's measurement and its variance
    (exact for a linear problem); a parameter the window does not inform has none."""
    fusion = ParameterFusion(("a", "b"), np.array([2.0, 3.0]), FusionConfig())
    z = np.log(np.array([2.2, 3.0]))
    sigma = 0.01  # the window's 1-sigma on ln a
    for t, informed in ((1.0, True), (3.0, True), (5.0, False)):
        prior = fusion.predict(t)
        cols = np.array([0]) if informed else np.array([], dtype=int)

        def linearize(x: np.ndarray, cols: np.ndarray = cols) -> tuple[np.ndarray, np.ndarray]:
            jac = np.zeros((1, cols.size))
            if cols.size:
                jac[0, 0] = 1.0
            return jac, np.array([x[0] - z[0]]) if cols.size else np.zeros(1)

        fusion.update(t, linearize, np.array([sigma**2]), 0, cols=cols)
        share = fused_share(("a", "b"), prior, (fusion.state.mean, fusion.state.cov))
        if informed:
            assert share["a"][0] == pytest.approx(2.2, rel=1e-6)
            assert share["a"][1] == pytest.approx(sigma, rel=1e-3)
        else:
            assert "a" not in share
        assert "b" not in share


# -- adaptive window ---------------------------------------------------------------------------

def test_the_window_shortens_on_drift_and_lengthens_when_quiet() -> None:
    cfg = AdaptiveWindowConfig(enabled=True, min_window=100, max_window=800)
    ctl = WindowController(cfg, 200, 0.01)
    # Ra drifts 0.003 ohm/s: 0.006 ohm in a 2 s window, 6 times its 0.001 ohm standard error
    c = ctl.decide(200, {"Ra": (-0.003, 0.001)}, None)
    assert c.next == 100 and "Ra drifts" in c.reason and c.used_reason == "the configured window"
    c = ctl.decide(100, {"Ra": (-0.003, 0.001)}, None)
    assert c.next == 100  # the lower bound
    quiet = [ctl.decide(100, {"Ra": (0.0, 0.001)}, None) for _ in range(3)]
    assert [q.next for q in quiet] == [100, 100, 150] and "quiet" in quiet[-1].reason
    c = ctl.decide(150, {"Ra": (0.0, 0.001)}, 5.0)
    assert c.next == 100 and "residual" in c.reason


def test_the_ring_buffer_takes_the_requested_length_at_the_next_window() -> None:
    ring = RingBuffer(("x",), window=4, capacity=16)
    out = [ring.append(0.01 * k, {"x": float(k)}) for k in range(2)]
    ring.request_window(6)  # during a window: it keeps its length
    out += [ring.append(0.01 * k, {"x": float(k)}) for k in range(2, 10)]
    done = [w for w in out if w is not None]
    assert [w.n for w in done] == [4, 6] and done[1].t[0] == pytest.approx(0.04)
    with pytest.raises(ValueError, match="does not fit"):
        ring.request_window(17)


# -- configuration and alarms ------------------------------------------------------------------

def test_rul_rules_and_the_adaptive_window_are_validated_naming_the_key() -> None:
    with pytest.raises(ValidationError, match="rul_warning"):
        AlarmRule(alarm=10.0, rul_warning=60.0, rul_alarm=120.0)
    data = default_config().model_dump(mode="json")
    data["acquisition"]["adaptive"] = {"enabled": True, "min_window": 300, "max_window": 800}
    with pytest.raises(Exception, match="acquisition.*window: 200 samples is outside"):
        validate_config(data)
    rule = AlarmRule(warning=5.0, alarm=10.0)
    th = rule.thresholds_si(6.5)
    assert th.alarm_low == pytest.approx(5.85) and th.warning_high == pytest.approx(6.825)


def _rul_health(window: int, rul_s: float | None, status: str = "degrading",
                high: float = 1.1) -> HealthMessage:
    """Ra's RUL ``rul_s`` with the interval 0.7 to ``high`` times it."""
    t_end = 2.0 * window + 1.99
    crossing = None if rul_s is None else CrossingHealth(
        threshold=5.85, status="predicted", t=t_end + rul_s, t_low=t_end + 0.7 * rul_s,
        t_high=t_end + high * rul_s, rul_s=rul_s, low_s=0.7 * rul_s, high_s=high * rul_s,
        wall=None, wall_low=None, wall_high=None, probability=1.0)
    p = ParameterHealth(
        value=6.3, unit="ohm", nominal=6.5, deviation_pct=-3.0, status="estimated", held=False,
        reason=None, rel_std_pct=0.01,
        trend=TrendHealth(model="exponential", onset=160.0, since_t=1.0, evidence=100,
                          level=6.3, level_std=1e-3, rate=-1e-3, rate_low=-1.1e-3,
                          rate_high=-0.9e-3, rate_pct_per_h=-55.0, growth=0.003,
                          degrading=status == "degrading", model_weight=1.0,
                          monotonicity=1.0, trendability=1.0, restarted=False, restart=None,
                          restarts=0, window_evidence=None),
        rul=RulHealth(status=status, warning=None, alarm=crossing,  # type: ignore[arg-type]
                      method="monte_carlo", draws=2000, interval=0.95))
    return HealthMessage.model_construct(machine="m1", model="dc_motor", window=window,
                                         t_start=2.0 * window, t_end=t_end, samples=200,
                                         parameters={"Ra": p})


def test_rul_alarm_raises_with_the_deviation_alarms_durations_and_says_what_to_plan() -> None:
    rule = AlarmRule(warning=5.0, alarm=10.0, rul_warning=600.0, rul_alarm=120.0,
                     raise_after_s=4.0, raise_after_windows=2, clear_after_s=4.0,
                     clear_after_windows=2)
    ev = AlarmEvaluator(AlarmConfig(parameters={"Ra": rule}))
    events: list[dict[str, Any]] = []
    for k, rul in enumerate([900.0, 700.0, 500.0, 480.0, 460.0, 360.0, 100.0, 90.0, 80.0]):
        events += ev.update(_rul_health(k, rul))
    assert [(e["kind"], e["window"], e["level"]) for e in events] == [
        ("rul", 3, "warning"), ("rul", 7, "alarm")]
    msg = events[0]["message"]
    assert "RUL WARNING: Ra reaches its alarm threshold (5.85 ohm) in 8 min (5.6-8.8 min)" \
        in msg, msg
    assert ev.state()["Ra"]["rul"]["level"] == "alarm"
    assert ev.state()["Ra"]["level"] == "normal"  # the deviation's own state is untouched
    # not degrading any more (a part replaced): cleared after the durations; an insufficient
    # RUL (right after a restart) is no evidence
    more = ev.update(_rul_health(9, None, "insufficient"))
    more += ev.update(_rul_health(10, None, "not_degrading"))
    more += ev.update(_rul_health(11, None, "not_degrading"))
    assert [(e["window"], e["level"]) for e in more] == [(11, "normal")]
    # a restart resumes the level from the state snapshot
    ev2 = AlarmEvaluator(AlarmConfig(parameters={"Ra": rule}))
    ev2.restore({"Ra": {**ev.state()["Ra"], "rul": {"level": "warning", "since_t": 3.0,
                                                     "since_window": 1, "rul_s": 400.0}}})
    assert ev2.state()["Ra"]["rul"]["level"] == "warning"


def test_a_rul_level_is_raised_only_on_an_interval_that_agrees() -> None:
    """Issue 56: a weak early trend, its median near but its interval reaching far beyond the
    rule's horizon (the CANopen example at 180 s: "79 s (49-752 s)", raised, cleared 40 s
    later) raises nothing, however long; the same median with its interval within the horizon
    raises; an active level is not cleared by an interval that widens, only by its RUL."""
    rule = AlarmRule(warning=5.0, alarm=10.0, rul_warning=600.0, rul_alarm=180.0,
                     raise_after_s=10.0, clear_after_s=30.0)
    ev = AlarmEvaluator(AlarmConfig(parameters={"Ra": rule}))
    events: list[dict[str, Any]] = []
    for k in range(20):  # 40 s of "79 s (55-752 s)": the interval reaches past 600 s
        events += ev.update(_rul_health(k, 79.0, high=752.0 / 79.0))
    assert events == [] and ev.state()["Ra"]["rul"]["level"] == "normal"
    for k in range(20, 30):  # the same median, the interval within the horizon
        events += ev.update(_rul_health(k, 79.0, high=1.5))
    assert [(e["window"], e["level"]) for e in events] == [(24, "alarm")]
    for k in range(30, 50):  # the interval widens again, the RUL stays short: kept
        events += ev.update(_rul_health(k, 79.0, high=752.0 / 79.0))
    assert len(events) == 1 and ev.state()["Ra"]["rul"]["level"] == "alarm"
    # with rul_basis low, the early end is read once the interval agrees
    low = AlarmRule(warning=5.0, alarm=10.0, rul_warning=600.0, rul_alarm=180.0,
                    raise_after_s=10.0, rul_basis="low")
    ev = AlarmEvaluator(AlarmConfig(parameters={"Ra": low}))
    got = [e for k in range(10) for e in ev.update(_rul_health(k, 240.0, high=2.0))]
    assert [(e["window"], e["level"]) for e in got] == [(4, "alarm")]  # 168 s, within 480 s


# -- end to end --------------------------------------------------------------------------------

def _daemon_run(tmp_path: Path | None = None, **plant: Any) -> Daemon:
    cfg = default_config()
    cfg.estimation.time_budget = 60.0
    for k, v in plant.items():
        setattr(cfg.driver.plant, k, v)  # type: ignore[union-attr]
    kwargs: dict[str, Any] = {"publish": False, "record": False}
    if tmp_path is not None:
        cfg.state.path = str(tmp_path / "state.sqlite")  # type: ignore[attr-defined]
        kwargs["persist"] = True
    with Daemon(cfg, **kwargs) as daemon:
        daemon.run()
    return daemon


def test_daemon_publishes_trend_and_rul_and_resumes_them(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """120 s of a motor degrading from 0 s through the daemon: Ra's trend is an exponential,
    degrading, with a finite RUL to both thresholds in plant and wall time; the summary line
    says it; a restart resumes the trends from the state database."""
    monkeypatch.chdir(tmp_path)
    daemon = _daemon_run(tmp_path, duration=120.0, fault_start=0.0)
    last = daemon.latest_health
    assert last is not None
    ra = last.parameters["Ra"]
    assert ra.trend is not None and ra.trend.degrading and ra.trend.model == "exponential"
    assert ra.trend.rate is not None and ra.trend.rate < 0
    assert ra.rul is not None and ra.rul.status == "degrading" and ra.rul.alarm is not None
    assert ra.rul.alarm.status == "predicted" and ra.rul.alarm.wall is not None
    assert ra.rul.alarm.rul_s is not None and ra.rul.alarm.t is not None
    assert ra.rul.alarm.t == pytest.approx(last.t_end + ra.rul.alarm.rul_s)
    line = trend_line("Ra", ra)
    assert line is not None and "alarm (5.85 ohm) in" in line
    assert last.parameters["Kt"].trend is None  # tied: no trend
    assert last.acquisition is not None and last.acquisition.window == 200
    assert not last.acquisition.adaptive
    # a restart resumes the trends from the evidence the stored windows published
    cfg = default_config()
    cfg.state.path = str(tmp_path / "state.sqlite")  # type: ignore[attr-defined]
    with Daemon(cfg, publish=False, record=False, persist=True, resume=True) as again:
        assert again.adapter.prognostics is not None
        trend = again.adapter.prognostics.trends["Ra"]
        assert trend.evidence == ra.trend.evidence and trend.since_t == ra.trend.since_t
        assert trend.fit is not None and trend.fit.kind == "exponential" and trend.degrading()


# -- the paper's scenarios (slow) --------------------------------------------------------------

def _scores(daemon: Daemon, t_eol: float) -> tuple[float, float, int]:
    """(share within 10 % of the true crossing, share covered, windows) from lambda = 0.5."""
    hist = daemon.health_history
    sc = score_profile([h.t_end for h in hist],
                       [h.parameters["Ra"].rul.alarm.t if h.parameters["Ra"].rul
                        and h.parameters["Ra"].rul.alarm else None for h in hist],
                       [h.parameters["Ra"].rul.alarm.t_low if h.parameters["Ra"].rul
                        and h.parameters["Ra"].rul.alarm else None for h in hist],
                       [h.parameters["Ra"].rul.alarm.t_high if h.parameters["Ra"].rul
                        and h.parameters["Ra"].rul.alarm else None for h in hist],
                       [None] * len(hist), t_eol=t_eol, t_onset=ONSET)
    return sc.within, sc.coverage, sc.windows


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_paper_resistance_degradation_rul(noise: float) -> None:
    """The issue's criterion: from halfway between the onset and the -10 % crossing (620 s),
    the median crossing within 10 % of 1079.5 s and its interval covering it in >= 90 % of the
    windows; the RUL alarm is raised before the deviation alarm; a RUL level once raised is
    never cleared (Ra only degrades: a clear is a flicker, issue 56)."""
    daemon = _daemon_run(noise={"ia": noise, "omega": noise} if noise else {})
    within, covered, n = _scores(daemon, T_ALARM)
    assert n >= 200 and within >= 0.9 and covered >= 0.9, (within, covered, n)
    rank = {"normal": 0, "warning": 1, "alarm": 2}
    levels = [(h.t_end, rank[a.rul.level]) for h in daemon.health_history
              if (a := h.alarms.get("Ra")) is not None and a.rul is not None]
    assert all(b >= a for (_, a), (_, b) in zip(levels, levels[1:], strict=False)), [
        (t, lv) for (t, lv), (_, prev) in zip(levels[1:], levels, strict=False) if lv < prev]
    alarm = daemon.latest_health.alarms["Ra"]  # type: ignore[union-attr]
    assert alarm.level == "alarm" and alarm.rul is not None and alarm.rul.level == "alarm"
    assert alarm.rul.since_t is not None and alarm.since_t is not None
    assert alarm.rul.since_t < alarm.since_t


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_nominal_run_is_not_degrading_in_any_window(noise: float) -> None:
    daemon = _daemon_run(scenario="nominal", noise={"ia": noise, "omega": noise} if noise
                         else {})
    hist = daemon.health_history
    assert len(hist) == 600
    for h in hist:
        for name, p in h.parameters.items():
            assert p.trend is None or not p.trend.degrading, (h.window, name)
        assert h.parameters["Ra"].rul is not None
        assert h.parameters["Ra"].rul.status != "degrading"


@pytest.mark.slow
def test_a_part_replaced_mid_run_restarts_the_trend_within_5_windows() -> None:
    daemon = _daemon_run(fault_period=600.0, noise={"ia": 1.0, "omega": 1.0})
    hist = daemon.health_history
    step = next(i for i, h in enumerate(hist) if h.t_end >= 760.0)
    restarted = [i for i, h in enumerate(hist) if h.parameters["Ra"].trend is not None
                 and h.parameters["Ra"].trend.restarted]
    assert restarted and step <= restarted[0] < step + 5, (step, restarted)
    assert len(restarted) == 1
    ra = hist[-1].parameters["Ra"].trend
    assert ra is not None and ra.since_t is not None and ra.since_t >= 758.0


def _profile_scores(hist: list[HealthMessage], name: str, t_eol: float
                    ) -> tuple[float, float, int]:
    def cr(h: HealthMessage) -> CrossingHealth | None:
        rul = h.parameters[name].rul
        return rul.alarm if rul is not None else None

    sc = score_profile([h.t_end for h in hist], [c.t if (c := cr(h)) else None for h in hist],
                       [c.t_low if (c := cr(h)) else None for h in hist],
                       [c.t_high if (c := cr(h)) else None for h in hist],
                       [None] * len(hist), t_eol=t_eol, t_onset=ONSET)
    return sc.within, sc.coverage, sc.windows


@pytest.mark.slow
def test_bearing_wear_rul_with_1_percent_noise() -> None:
    """D under bearing wear (D(t) = 0.00143 + 0.00003806 (exp(0.003 (t - 160)) - 1)), a +50 %
    alarm rule: crossed at 1155.0 s; from halfway on, within 10 % and covered in >= 90 %."""
    cfg = default_config()
    cfg.estimation.time_budget = 60.0
    cfg.driver.plant.scenario = "bearing_wear"  # type: ignore[union-attr]
    cfg.driver.plant.noise = {"ia": 1.0, "omega": 1.0}  # type: ignore[union-attr]
    cfg.alarms.parameters["D"] = AlarmRule(warning=20.0, alarm=50.0)
    with Daemon(cfg, publish=False, record=False) as daemon:
        daemon.run()
    t_eol = ONSET + math.log(1 + 0.5 * 0.00143 / 0.00003806) / RATE
    assert t_eol == pytest.approx(1155.0, abs=0.1)
    within, covered, n = _profile_scores(daemon.health_history, "D", t_eol)
    assert n >= 200 and within >= 0.9 and covered >= 0.9, (within, covered, n)


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 0.001])
def test_hydraulic_fluid_degradation_rul(noise: float) -> None:
    """The hydraulic example over Modbus (D(t) = 100 + 36.5 (exp(0.003 (t - 160)) - 1), its
    +50 % alarm crossed at 447.6 s), noise-free and with 0.001 % noise on x and p (D held in
    every window: the prediction rests on each window's share of the fused evidence); from
    halfway on, within 10 % and covered in >= 90 %. (At 0.5 % noise the data cannot say it:
    README, "When to act".)"""
    from twinwatch.config.loader import load_config
    from twinwatch.drivers.simulated_modbus import SimulatedModbusDriver

    cfg = load_config(Path(__file__).resolve().parents[1] / "config" /
                      "hydraulic-modbus-sim.toml")
    cfg.driver.port = 0  # type: ignore[attr-defined]
    cfg.driver.plant.noise = {"x": noise, "p": noise} if noise else {}  # type: ignore[attr-defined]
    with SimulatedModbusDriver(cfg.driver) as driver:  # type: ignore[arg-type]
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
    t_eol = ONSET + math.log(1 + 50.0 / 36.5) / RATE
    within, covered, n = _profile_scores(daemon.health_history, "D", t_eol)
    assert n >= 60 and within >= 0.9 and covered >= 0.9, (within, covered, n)


def test_a_minute_of_evidence_is_no_trend_however_steep() -> None:
    """Issue 23 item 6: a trend (its model, its rate, degrading or not, the RUL) needs
    evidence spanning ``[prognostics] min_span`` (60 s) since the start or a restart, not
    only ``min_evidence`` windows. A 60 s replay of a real drive read D at -4.03e+03 %/h from
    15 windows of 4 s; here windows of 2 s fall 1 % a minute, exact: no rate before 60 s
    of evidence, a degrading trend once it spans them."""
    prog = Prognostics(("Ra",), {"Ra": RA0}, PrognosticsConfig(), {"Ra": RA_THRESHOLDS})
    for k in range(90):
        t = 2.0 * k + 1.0
        v = RA0 * (1.0 - 0.01 * t / 60.0)
        p = prog.update({"Ra": Evidence(t, v, 1e-5 * v)}, t_end=t + 1.0)["Ra"]
        if t - 1.0 < 60.0:
            assert p.trend.model is None and p.trend.rate is None, (t, p.trend)
            assert not p.trend.degrading
            assert p.rul is not None and p.rul.status == "insufficient"
    assert p.trend.degrading and p.trend.rate is not None and p.trend.rate < 0
    off = Prognostics(("Ra",), {"Ra": RA0}, PrognosticsConfig(min_span=0.0),
                      {"Ra": RA_THRESHOLDS})
    for k in range(20):  # the check is the span: without it, 40 s give a trend
        t = 2.0 * k + 1.0
        q = off.update({"Ra": Evidence(t, RA0 * (1.0 - 0.01 * t / 60.0), 1e-5)}, t_end=t + 1)
    assert q["Ra"].trend.degrading


def test_a_degenerate_exponential_stepped_far_ahead_keeps_its_chi_square_at_least_zero() -> None:
    """The state a PWM drive's trend reached on the fault matrix (pwm/load_inertia_change,
    J+50 %, noise-free): an exponential of growth rate 6.5/s whose drift and growth rates are
    perfectly anti-correlated, stepped 4 s ahead twice (exp(r tau) = 1.7e11). The predicted
    level's variance, F P F^T, cancels below zero in floating point; the second step's
    chi-square was then negative, ``rms_norm`` took its square root, and four windows'
    processing raised. The step now reads a negative predicted variance as 0: the point's
    chi-square is huge (the model does not predict it) and the model loses the comparison."""
    from twinwatch.twin.prognostics.degradation import DegradationFit

    fit = DegradationFit("exponential", 93.99000000000001, 4.918299606471166e-08,
                         -0.2189958527031023, 6.460832309695061, 93.99000000000001,
                         free=("c", "m", "r", "t0"))
    fit.cov = np.array([
        [5.624796665975771e-19, -2.0530507830811564e-18, 2.5199089063571454e-17,
         2.2117600458083287e-14],
        [-2.0530507830811564e-18, 0.00012982993857619697, -0.001831927668599472,
         -2.342074004757557],
        [2.5199089063571454e-17, -0.001831927668599472, 0.025848883699584404,
         33.047144915248474],
        [2.2117600458083287e-14, -2.342074004757557, 33.047144915248474,
         129206.14427163341]])
    fit.chi2, fit.n, fit.scale, fit.long_run = 41.50367382556392, 24, 2.075183691278196, 1.0
    chi2 = [fit.advance(97.99000000000001, 4.9183369148312153e-08, 9.222454806192759e-10),
            fit.advance(101.99000000000001, 4.918335988625797e-08, 9.825137533687872e-10)]
    assert all(math.isfinite(c) and c >= 0.0 for c in chi2), chi2
    assert math.isfinite(fit.rms_norm) and fit.rms_norm > 1e3    # it predicts nothing
