"""Discovery's trigger as a test on evidence (issue 23 item 2): the residual's whiteness, per
window and combined over windows, on a machine that is already running."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from twinwatch.config.loader import load_config
from twinwatch.twin.discovery.trigger import StructureEvidence, WindowStructure, residual_structure

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

KW = {"lags": 10, "min_nrmse": 0.002, "window_alpha": 1e-3}


def _white(seed: int, n: int = 199, sigma: float = 0.01) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, sigma, n)


def test_white_noise_is_not_structured_at_the_stated_rate() -> None:
    """1000 windows of white noise (two outputs at 1 % of their scale): p-values uniform, so
    about 0.1 % below window_alpha = 1e-3 and about 5 % below 0.05."""
    p = np.array([residual_structure(np.c_[_white(2 * k), _white(2 * k + 1)], ["ia", "omega"],
                                     **KW).p_value for k in range(1000)])
    assert (p < 1e-3).sum() <= 5
    assert 0.02 < (p < 0.05).mean() < 0.09


def test_a_periodic_error_twice_the_noise_is_structured() -> None:
    """The unbalanced shaft's signature: a sinusoid at 7 rad/s (period 90 samples) of RMS twice
    the noise's on the speed: its ratio to the noise level is 2.2, under the former criterion's
    3, and the whiteness test finds it beyond doubt."""
    t = np.arange(199) * 0.01
    omega = _white(1) + 0.02 * math.sqrt(2) * np.sin(7.0 * t + 0.3)
    s = residual_structure(np.c_[_white(0), omega], ["ia", "omega"], **KW)
    assert s.structured and s.worst == "omega" and s.p_value < 1e-20
    assert 2.0 < s.outputs["omega"].ratio < 2.6
    assert "omega residual" in s.describe() and "Ljung-Box" in s.describe()


def test_a_noise_free_output_is_left_to_the_measured_ones() -> None:
    """A controller's Va (no measurement noise, its residual the PI's smooth answer to the
    speed's noise) does not count while ia and omega are measured with noise; in a noise-free
    plant the outputs count by the size of their structure."""
    t = np.arange(199) * 0.01
    smooth = 0.004 * np.sin(3.0 * t)  # 0.28 % of the scale, above min_nrmse, no white noise
    s = residual_structure(np.c_[_white(0), _white(1), smooth], ["ia", "omega", "Va"], **KW)
    assert not s.structured and s.outputs["Va"].p_value == 1.0
    s = residual_structure(np.c_[smooth, smooth * 0.1, 1e-7 * np.sin(9 * t)],
                           ["ia", "omega", "Va"], **KW)
    assert s.structured and s.worst == "ia"
    tiny = residual_structure(np.c_[smooth * 0.1, smooth * 0.1], ["ia", "omega"], **KW)
    assert not tiny.structured  # 0.03 %: numerical error, below min_nrmse


def test_a_nan_in_the_residual_is_structured() -> None:
    e = np.c_[_white(0), _white(1)]
    e[5, 1] = math.nan
    assert residual_structure(e, ["ia", "omega"], **KW).structured


def test_no_single_window_triggers_two_do() -> None:
    """Fisher's method over K = 3 windows, each p floored at false_alarm = 1e-6: one window
    however extreme cannot trigger alone, two at the floor do, three at 1e-3 do, three at 1e-2
    do not; with K = 1 a single window decides."""
    def w(p: float) -> WindowStructure:
        return WindowStructure({}, p, p < 1e-3)

    ev = StructureEvidence(3, 1e-6)
    for p in (0.5, 0.5, 0.0):
        ev.add(w(p))
    assert not ev.triggered
    ev.add(w(0.0))
    assert ev.triggered
    ev.clear()
    for p in (1e-3, 1e-3, 1e-3):
        ev.add(w(p))
    assert ev.triggered
    ev.clear()
    for p in (1e-2, 1e-2, 1e-2):
        ev.add(w(p))
    assert not ev.triggered and ev.combined > 1e-6
    one = StructureEvidence(1, 1e-6)
    one.add(w(1e-9))
    assert one.triggered


def test_residual_ratio_is_accepted_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    from twinwatch.twin.discovery.search import DiscoveryConfig

    with caplog.at_level("WARNING"):
        DiscoveryConfig(residual_ratio=3.0)
    assert "residual_ratio is no longer used" in caplog.text


@pytest.mark.slow  # 30 windows through the adaptation worker's path, two seeds: about 10 s
@pytest.mark.parametrize("seed", [0, 1])
def test_a_moderate_fault_on_a_running_machine_is_found_within_60_s(seed: int) -> None:
    """Issue 23's case: 3 sin(7 t) rad/s^2, 1 % noise, the windows starting at 10 s (no
    start-up transient). The former criterion (normalised RMSE over 3x the noise, per window)
    flagged none of the 30 windows and discovery never ran; the term must be kept within 60 s,
    |a| within 5 % of 3 and b within 0.5 % of 7 at 60 s."""
    import bench_trigger as bt

    o = bt.detection(load_config(bt.CONFIG), seed, n=30)
    assert o["old"] == 0  # the former criterion: blind to it
    assert o["kept_s"] <= 60.0, o
    assert abs(o["a_end"] - 3.0) / 3.0 < 0.05 and abs(o["b_end"] - 7.0) / 7.0 < 0.005, o


@pytest.mark.slow  # 3 x 600 windows: about a minute
@pytest.mark.parametrize("noise", [0.0, 1.0, 2.0])
def test_nominal_runs_of_1200_s_keep_no_term(noise: float) -> None:
    """The nominal plant for 1200 s of plant time at 0, 1 and 2 % noise keeps no term; the
    searches the trigger starts stay rare (its stated rate is 1e-6 per window for white
    residuals; the twin's own estimation makes the residual slightly less than white)."""
    import bench_trigger as bt

    o = bt.false_alarms(load_config(bt.CONFIG), noise, 1200.0, seed=7)
    assert o["kept"] == 0, o
    assert o["ran"] <= 1, o
    assert o["structured"] <= 0.01 * o["windows"], o
