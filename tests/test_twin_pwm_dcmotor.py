"""The PWM DC motor twin (twin/models/pwm_dcmotor.py): the firmware's duty, the sampled current, the
window's measured initial state, the meta-model terms, bad particles, and commissioning it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twinwatch.commissioning.identify import identify
from twinwatch.config.identify import IdentifyConfig
from twinwatch.config.loader import ConfigError, load_config
from twinwatch.twin.estimation.estimator import EstimationConfig, PSOSettings
from twinwatch.twin.model import WindowData
from twinwatch.twin.models import create_model
from twinwatch.twin.models.pwm_dcmotor import (
    MOTOSHIELD_CURRENT_FILTER_A,
    MOTOSHIELD_CURRENT_FILTER_B,
    PWMDCMotorTwin,
)

from .helpers.paths import ROOT

TS = 0.02
TRUE = {"Ra": 120.0, "tau_e": 1.2e-4, "Ke": 0.0043, "Kt": 0.0043, "J": 1e-8, "D": 2.5e-8,
        "Tc": 1e-5, "Iq": 0.01, "a_adc": 0.9, "c_warm": 0.15, "tau_warm": 6.0, "r_warm": 1e-3}


def _motoshield(**kw: object) -> PWMDCMotorTwin:
    opts: dict[str, object] = dict(duty="motoshield", adc_phase=0.4609375, adc_phase_step=0.53125,
                                   adc_edge_window=66e-6, warmup="exp_linear",
                                   current_filter_b=MOTOSHIELD_CURRENT_FILTER_B,
                                   current_filter_a=MOTOSHIELD_CURRENT_FILTER_A)
    opts.update(kw)
    return PWMDCMotorTwin(**opts)  # type: ignore[arg-type]


def _aprbs(n: int, seed: int = 1) -> np.ndarray:
    """Amplitude-modulated pseudo-random binary command [V], held 0.2-2 s, from 0 (as the
    MotoShield recording: u in {0} U [2.9, 4.7])."""
    rng = np.random.default_rng(seed)
    u = np.empty(n)
    k = 0
    while k < n:
        hold = int(rng.integers(10, 100))
        u[k:k + hold] = 0.0 if rng.random() < 0.1 else rng.uniform(2.9, 4.7)
        k += hold
    u[:5] = 0.0
    return u


def _record(model: PWMDCMotorTwin, n: int, theta: dict[str, float], seed: int = 1
            ) -> WindowData:
    """A recording made by the twin itself from rest at t = 0 (speed and filter state 0)."""
    t = np.arange(n) * TS
    u = _aprbs(n, seed)
    w = WindowData(t=t, channels={"u": u, "omega": np.zeros(n), "ia": np.zeros(n)})
    y = model.simulate(model.nominal_vector(theta)[None], w)[0]
    return WindowData(t=t, channels={"u": u, "ia": y[:, 0], "omega": y[:, 1]})


def _cut(w: WindowData, a: int, b: int) -> WindowData:
    return WindowData(t=w.t[a:b], channels={c: v[a:b] for c, v in w.channels.items()})


def test_duty_is_the_motoshield_firmware_arithmetic():
    """actuatorWriteVolt: the 8-bit code floor(u^2*255/25) of an Arduino fast PWM, high for
    code + 1 of 256 counts; code 0 is analogWrite(0): constantly low."""
    model = _motoshield()
    u = np.array([0.0, 0.2, 0.32, 1.0, 2.9, 3.78681, 4.7, 5.0, 6.0])
    code = [int(x * x * 255 / 25) for x in np.minimum(u, 5.0)]
    want = [0.0 if c == 0 else (c + 1) / 256 for c in code]
    assert model.duty_cycle(u) == pytest.approx(want, abs=1e-15)
    assert PWMDCMotorTwin(duty="square").duty_cycle(np.array([2.5])) == pytest.approx([0.25])
    assert PWMDCMotorTwin(duty="linear").duty_cycle(np.array([2.5, 7.0])) == \
        pytest.approx([0.5, 1.0])


def test_current_phase_advances_17_32_of_a_period_per_sample():
    model = _motoshield(adc_phase_step=None)  # derived: frac(0.02 s * 976.5625 Hz) = 17/32
    t = np.arange(64) * TS
    ph = model.sample_phase(t, TS)
    assert ph[0] == 0.4609375
    assert np.diff(ph) % 1.0 == pytest.approx(np.full(63, 17 / 32))


def test_sampled_current_averages_to_the_discontinuous_conduction_current():
    """Sampled at phases spread over the PWM period, the on-time current (the rise from zero
    with tau_e) averages to g(d) (Vs - Ke omega)/Ra + Iq d, the period average the speed
    equation uses: the two current paths of the twin agree."""
    n = 20000
    u = np.full(n, 4.0)
    omega = np.full(n, 600.0)
    w = WindowData(t=np.arange(n) * TS, channels={"u": u, "omega": omega, "ia": np.zeros(n)})
    theta = dict(TRUE, J=1e3)  # a flywheel: the speed stays at 600 rad/s
    sampled = PWMDCMotorTwin(duty="motoshield", adc_phase=0.0, adc_phase_step=0.6180339887,
                             speed_measurement="instant")
    average = PWMDCMotorTwin(duty="motoshield", speed_measurement="instant")
    y_s = sampled.simulate(sampled.nominal_vector(theta)[None], w)[0]
    y_a = average.simulate(average.nominal_vector(theta)[None], w)[0]
    assert y_s[:, 1] == pytest.approx(600.0, rel=1e-6)
    d = float(average.duty_cycle(u[:1])[0])
    tpwm = 1 / 976.5625
    tau = theta["tau_e"]
    g = d - tau / tpwm * (1 - math.exp(-d * tpwm / tau))
    want = g * (5.0 - theta["Ke"] * 600.0) / theta["Ra"] + theta["Iq"] * d
    assert y_a[:, 0] == pytest.approx(want, rel=1e-6)
    assert np.mean(y_s[:, 0]) == pytest.approx(want, rel=2e-3)
    assert np.mean(y_s[:, 0] == 0) == pytest.approx(1 - d, abs=2e-3)  # off-time samples


def test_a_window_continues_exactly_from_its_measured_state():
    """Cut a recording anywhere: the window, started from its measured speed and the measured
    outputs of the firmware's filter (its state), and with the absolute time (PWM phase,
    warm-up), reproduces the recording exactly."""
    model = _motoshield(speed_measurement="instant")
    rec = _record(model, 1200, TRUE)
    theta = model.nominal_vector(TRUE)[None]
    for a in (200, 737):
        win = _cut(rec, a, a + 200)
        y = model.simulate(theta, win)[0]
        assert y[:, 1] == pytest.approx(win["omega"], rel=1e-9, abs=1e-9)
        assert y[:, 0] == pytest.approx(win["ia"], rel=1e-9, abs=1e-12)
    # The mean-speed output starts from 0.5 (y0 + y1): close, and the offset fixes the rest.
    avg = _motoshield()
    rec = _record(avg, 600, TRUE)
    win = _cut(rec, 300, 500)
    y = avg.simulate(avg.nominal_vector(TRUE)[None], win)[0]
    err = np.abs(y[1:, 1] - win["omega"][1:])
    assert err.max() < 0.02 * np.abs(win["omega"]).max()
    assert err[-50:].max() < 1e-3 * err.max() + 1e-9  # the initial error dies out


def test_the_speed_term_is_a_torque_per_inertia():
    """A constant d(omega)/dt term -Tc/J is exactly one more Coulomb torque (warm-up off)."""
    model = PWMDCMotorTwin(duty="motoshield", adc_phase=0.2)
    rec = _record(model, 400, TRUE)
    base = model.nominal_vector(TRUE)
    more = base.copy()
    more[model.parameter_names.index("Tc")] *= 2
    y2 = model.simulate(more[None], rec)[0]
    f = np.full(rec.n, -TRUE["Tc"] / TRUE["J"])
    yf = model.simulate(base[None], rec, terms={"d(omega)/dt": f})[0]
    assert yf == pytest.approx(y2, rel=1e-9, abs=1e-9)
    y1 = model.simulate(base[None], rec, terms={"ia": np.full(rec.n, 0.5)})[0]
    y0 = model.simulate(base[None], rec)[0]
    assert y1[:, 0] == pytest.approx(1.5 * y0[:, 0])  # unfiltered: the sample times 1 + U
    with pytest.raises(KeyError, match="d\\(ia\\)/dt"):
        model.simulate(base[None], rec, terms={"d(ia)/dt": f})


def test_bad_particles_give_nan_rows_and_never_raise():
    model = _motoshield()
    rec = _record(model, 300, TRUE)
    base = model.nominal_vector(TRUE)
    theta = np.repeat(base[None], 6, axis=0)
    names = model.parameter_names
    theta[1, names.index("J")] = 0.0
    theta[2, names.index("Ra")] = np.nan
    theta[3, names.index("tau_e")] = -1e-4
    theta[4, names.index("J")] = 1e-300  # stiff, but each sub-step is solved exactly: finite
    y = model.simulate(theta, rec, initial=np.zeros((6, 1)))
    assert y.shape == (6, 300, 2)
    for q in (0, 4, 5):
        assert np.all(np.isfinite(y[q]))
    for q in (1, 2, 3):
        assert np.all(np.isnan(y[q, 2:]))
    assert y[5] == pytest.approx(y[0])


def test_options_are_checked_and_named():
    for opts, key in (({"duty": "pwm"}, "duty"), ({"pwm_frequency": 0.0}, "pwm_frequency"),
                      ({"adc_phase": 1.5}, "adc_phase"), ({"adc_edge_window": 6e-5},
                                                          "adc_edge_window"),
                      ({"current_filter_b": [1.0]}, "current_filter_b"),
                      ({"current_filter_b": [1.0], "current_filter_a": [1.0, -1.5]},
                       "unstable"),
                      ({"warmup": "thermal"}, "warmup")):
        with pytest.raises(ValueError, match=key):
            create_model("dc_motor_pwm", opts)
    with pytest.raises(ValueError, match="sub-step"):
        PWMDCMotorTwin(sub_step=3e-3).check_sample_period(0.02)
    model = _motoshield()
    assert [p.name for p in model.parameters][-4:] == ["a_adc", "c_warm", "tau_warm", "r_warm"]
    assert PWMDCMotorTwin().parameter_names == ("Ra", "tau_e", "Ke", "Kt", "J", "D", "Tc", "Iq")


def test_identify_recovers_a_synthetic_motor_with_the_identify_table():
    """Commissioning on a recording made by the twin itself (the speed counted in encoder
    edges, as the MotoShield counts it): ``[identify] estimate`` and ``bounds`` widen what the
    monitoring estimates; the identified values cover the truth within their intervals."""
    model = _motoshield()
    rec = _record(model, 1600, TRUE, seed=3)
    # the encoder: 14 edges per turn counted over each sample (the angle is the mean speed's sum)
    edges = np.floor(np.cumsum(rec["omega"]) * TS / (2 * math.pi / 14))
    rec.channels["omega"] = np.diff(edges, prepend=0.0) * (2 * math.pi / 14 / TS)
    train, val = _cut(rec, 0, 800), _cut(rec, 800, 1600)
    start = dict(TRUE, Ke=0.005, Kt=0.005, J=2e-8, D=1e-8, Ra=60.0)
    est = EstimationConfig(estimate=["Ke"], tie={"Kt": "Ke"}, model_error=0.0)
    names = ["Ra", "Ke", "J", "D"]
    cfg = IdentifyConfig(estimate=names, bounds={"Ra": (10.0, 1000.0), "J": (1e-10, 1e-6)},
                         pso=PSOSettings(pop_size=10, max_generations=10), time_budget=20.0,
                         starts=2)
    r = identify(model, est, cfg, train, val, start)
    # Two starts: the second swarm continues the generator; the best training fit is kept.
    assert len(r.starts) == 2 and r.nrmse == min(r.starts)
    one = identify(model, est, cfg.model_copy(update={"starts": 1}), train, val, start)
    assert one.starts == [r.starts[0]] and r.nrmse <= one.nrmse
    assert r.estimated == names and r.values["Kt"] == r.values["Ke"]
    assert r.bounds["Ra"] == (10.0, 1000.0) and r.bounds["J"] == (1e-10, 1e-6)
    assert r.bounds["Ke"] == pytest.approx((0.001, 0.025))  # the default: nominal/5 .. *5
    for name in names:
        assert abs(math.log(r.values[name] / TRUE[name])) <= max(3 * r.rel_std[name], 1e-3), \
            (name, r.values[name], r.rel_std[name])
    assert r.values["Ke"] == pytest.approx(TRUE["Ke"], rel=0.01)
    assert r.validation.fit_pct["omega"] > 85 and r.validation.fit_pct["ia"] > 99  # counts cap it


def test_identify_table_names_a_bad_key(tmp_path):
    text = (ROOT / "config" / "dc-motor-motoshield.toml").read_text()
    text = text.replace('path = "../../shared', f'path = "{ROOT.parent}/shared')
    for old, new, key in (('estimate = ["Ra", "tau_e"', 'estimate = ["Rb", "tau_e"',
                           "identify.estimate: unknown parameter 'Rb'"),
                          ("bounds = { Ra = [3.0, 3000.0]", "bounds = { Ra = [3000.0, 3.0]",
                           "bounds.Ra: need 0 < low < high")):
        assert old in text
        p = tmp_path / "bad.toml"
        p.write_text(text.replace(old, new, 1))
        with pytest.raises(ConfigError, match=key.replace("(", "\\(")):
            load_config(p)
