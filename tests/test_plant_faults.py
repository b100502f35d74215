"""Faults injected in the simulated plants (twinwatch/plant/faults.py, the DC motor's and the
hydraulic actuator's ``sensor_faults``, ``parameter_faults`` and ``supply_fault``): each changes
what it says, when it says, and nothing else."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig, SetpointSchedule
from twinwatch.plant.faults import FaultProfile, ParameterFaultConfig, SupplyFaultConfig
from twinwatch.plant.hydraulic import HydraulicPlant, HydraulicPlantConfig

DC_CHANNELS = ("Va", "ia", "omega", "Tload", "setpoint")


def _dc(duration: float = 6.0, **kw: Any) -> tuple[DCMotorPlant, dict[str, np.ndarray]]:
    kw.setdefault("scenario", "nominal")
    kw.setdefault("noise", {"ia": 1.0, "omega": 1.0})
    plant = DCMotorPlant(DCMotorPlantConfig(duration=duration, **kw))
    n = int(round(duration / plant.sample_period))
    samples = [plant.next_sample() for _ in range(n)]
    out = {ch: np.array([s.values[ch] for s in samples]) for ch in DC_CHANNELS}
    out["t"] = np.array([s.t for s in samples])
    return plant, out


def _hyd(duration: float = 6.0, **kw: Any) -> tuple[HydraulicPlant, dict[str, np.ndarray]]:
    kw.setdefault("scenario", "nominal")
    plant = HydraulicPlant(HydraulicPlantConfig(duration=duration, **kw))
    n = int(round(duration / plant.sample_period))
    samples = [plant.next_sample() for _ in range(n)]
    out = {ch: np.array([s.values[ch] for s in samples]) for ch in plant.channels}
    out["t"] = np.array([s.t for s in samples])
    return plant, out


# -- the profile --------------------------------------------------------------------------------

def test_profile_step_ramp_repair_and_intermittence():
    assert FaultProfile(start=10.0).size(9.99) == 0.0
    assert FaultProfile(start=10.0).size(10.0) == 1.0
    ramp = FaultProfile(start=10.0, ramp=20.0)
    assert [ramp.size(t) for t in (10.0, 15.0, 30.0, 100.0)] == [0.0, 0.25, 1.0, 1.0]
    repaired = FaultProfile(start=10.0, end=50.0)
    assert [repaired.size(t) for t in (49.99, 50.0, 80.0)] == [1.0, 0.0, 0.0]
    inter = FaultProfile(start=10.0, period=20.0, duty=0.25)
    assert [inter.size(t) for t in (10.0, 14.9, 15.0, 29.9, 30.0, 35.1)] == \
        [1.0, 1.0, 0.0, 0.0, 1.0, 0.0]


def test_parameter_fault_change_is_percent_or_absolute_never_both():
    pf = ParameterFaultConfig(parameter="Ra", change=-12.0, start=0.0)
    assert pf.delta(6.5, 1.0) == pytest.approx(-0.78)
    assert ParameterFaultConfig(parameter="Tc", absolute=0.004).delta(0.0, 1.0) == 0.004
    for kw in ({}, {"change": 1.0, "absolute": 1.0}):
        with pytest.raises(ValidationError, match="change, absolute: give exactly one"):
            ParameterFaultConfig(parameter="Ra", **kw)
    with pytest.raises(ValidationError, match="end"):
        ParameterFaultConfig(parameter="Ra", change=1.0, start=10.0, end=5.0)
    with pytest.raises(ValidationError, match="chnage"):
        ParameterFaultConfig(parameter="Ra", chnage=1.0)  # type: ignore[call-arg]
    assert SupplyFaultConfig(ratio=0.9, start=0.0, ramp=10.0).factor(5.0) == pytest.approx(0.95)


# -- DC motor: sensors --------------------------------------------------------------------------

def test_an_inactive_fault_changes_nothing_at_all():
    """A fault that starts after the run: every sample bit for bit the plant without faults
    (the kernel's new terms are neutral)."""
    later = {"start": 100.0}
    _, base = _dc()
    _, same = _dc(sensor_faults=[{"channel": "ia", "kind": "gain", "gain": 1.1, **later}],
                  parameter_faults=[{"parameter": "Ra", "change": -12.0, **later},
                                    {"parameter": "misalignment", "absolute": 5.0, **later}],
                  supply_fault={"ratio": 0.9, **later})
    for ch in DC_CHANNELS:
        assert np.array_equal(base[ch], same[ch]), ch


@pytest.mark.parametrize("channel", ["Va", "ia", "omega"])
def test_dc_sensor_gain_changes_its_reported_channel_only(channel: str):
    fault = {"channel": channel, "kind": "gain", "gain": 1.1, "start": 2.0}
    _, base = _dc()
    _, bad = _dc(sensor_faults=[fault])
    on = base["t"] >= 2.0
    assert np.array_equal(bad[channel][~on], base[channel][~on])
    assert bad[channel][on] == pytest.approx(1.1 * base[channel][on], rel=1e-12)
    for ch in DC_CHANNELS:
        if ch != channel:  # the plant and its drive read the true value: nothing else moves
            assert np.array_equal(bad[ch], base[ch]), ch


def test_dc_sensor_gain_drifts_linearly_over_its_ramp_within_its_duration():
    fault = {"channel": "ia", "kind": "gain", "gain": 1.2, "start": 1.0, "ramp": 2.0,
             "duration": 4.0}
    _, base = _dc()
    _, bad = _dc(sensor_faults=[fault])
    ratio = bad["ia"][1:] / base["ia"][1:]  # the motor starts at rest: ia(0) = 0
    t = base["t"][1:]
    want = np.where((t >= 1.0) & (t < 5.0), 1.0 + 0.2 * np.clip((t - 1.0) / 2.0, 0.0, 1.0),
                    1.0)
    assert ratio == pytest.approx(want, rel=1e-12)
    assert ratio[np.searchsorted(t, 2.0)] == pytest.approx(1.1)


@pytest.mark.parametrize(("channel", "offset"), [("Va", 0.5), ("ia", 0.1), ("omega", -0.3)])
def test_dc_sensor_offset_adds_to_its_channel_only(channel: str, offset: float):
    fault = {"channel": channel, "kind": "offset", "offset": offset, "start": 2.0}
    _, base = _dc()
    _, bad = _dc(sensor_faults=[fault])
    on = base["t"] >= 2.0
    assert bad[channel][on] - base[channel][on] == pytest.approx(np.full(on.sum(), offset),
                                                                 abs=1e-12)
    assert np.array_equal(bad[channel][~on], base[channel][~on])
    assert all(np.array_equal(bad[ch], base[ch]) for ch in DC_CHANNELS if ch != channel)


def test_sensor_fault_keys_are_checked_and_named():
    with pytest.raises(ValidationError, match="gain: a gain fault needs its gain"):
        DCMotorPlantConfig(sensor_faults=[{"channel": "ia", "kind": "gain", "start": 0.0}])
    with pytest.raises(ValidationError, match="offset: only for kind 'offset'"):
        DCMotorPlantConfig(sensor_faults=[{"channel": "ia", "kind": "gain", "gain": 1.1,
                                           "offset": 0.1, "start": 0.0}])
    with pytest.raises(ValidationError, match="ramp: only a gain or an offset drifts"):
        DCMotorPlantConfig(sensor_faults=[{"channel": "ia", "kind": "frozen", "ramp": 1.0,
                                           "start": 0.0}])
    with pytest.raises(ValidationError, match=r"sensor_faults\[0\].channel: unknown channel"):
        DCMotorPlantConfig(sensor_faults=[{"channel": "i_a", "kind": "offset", "offset": 1.0,
                                           "start": 0.0}])
    with pytest.raises(ValidationError, match="gian"):
        DCMotorPlantConfig(sensor_faults=[{"channel": "ia", "kind": "gain", "gian": 1.1,
                                           "start": 0.0}])


# -- DC motor: parameters, supply, shaft forcing -------------------------------------------------

@pytest.mark.parametrize(("fault", "same"), [
    ({"parameter": "Ra", "change": -12.0}, {"Ra": 6.5 * 0.88}),
    ({"parameter": "D", "change": 25.0}, {"D": 0.00143 * 1.25}),
    ({"parameter": "J", "change": 50.0}, {"J": 0.001171 * 1.5}),
    ({"parameter": "La", "change": 10.0}, {"La": 0.673 * 1.1}),
    ({"parameter": "Ke", "change": -10.0}, {"Ke": 0.038 * 0.9, "Kt": 0.038 * 0.9}),
    ({"parameter": "Tc", "absolute": 0.004}, {"coulomb_friction": 0.004}),
    ({"parameter": "load", "change": 40.0}, {"load_coefficient": 0.006 * 1.4}),
])
def test_dc_parameter_fault_from_zero_is_the_plant_with_that_parameter(
        fault: dict[str, Any], same: dict[str, float]):
    """A step at t = 0 runs the plant exactly as one configured with the faulted value (Ke
    moves Kt with it: the field), and truth() says so."""
    plant, bad = _dc(parameter_faults=[{**fault, "start": 0.0}])
    ref_plant, ref = _dc(**same)
    for ch in DC_CHANNELS:
        assert bad[ch] == pytest.approx(ref[ch], rel=1e-9, abs=1e-12), ch
    got, want = plant.truth(3.0), ref_plant.config
    assert (got.Ra, got.La, got.J, got.Ke, got.Kt, got.D, got.Tc, got.load) == pytest.approx(
        (want.Ra, want.La, want.J, want.Ke, want.Kt, want.D, want.coulomb_friction,
         want.load_coefficient))


def test_dc_parameter_fault_ramps_repairs_and_comes_and_goes():
    plant = DCMotorPlant(DCMotorPlantConfig(scenario="nominal", parameter_faults=[
        {"parameter": "Ra", "change": -12.0, "start": 60.0, "ramp": 60.0, "end": 200.0},
        {"parameter": "load", "change": 40.0, "start": 10.0, "period": 20.0, "duty": 0.5}]))
    assert [plant.truth(t).Ra for t in (59.0, 90.0, 120.0, 199.0, 200.0)] == pytest.approx(
        [6.5, 6.5 * 0.94, 6.5 * 0.88, 6.5 * 0.88, 6.5])
    assert [plant.truth(t).load for t in (9.0, 10.0, 19.9, 20.0, 30.0)] == pytest.approx(
        [0.006, 0.0084, 0.0084, 0.006, 0.0084])
    assert plant.truth(90.0).D == 0.00143 and plant.truth(90.0).Ke == 0.038


def test_dc_parameter_faults_are_checked_and_named():
    with pytest.raises(ValidationError, match=r"parameter_faults\[0\].parameter: unknown "
                                              r"parameter 'R_a'"):
        DCMotorPlantConfig(parameter_faults=[{"parameter": "R_a", "change": 1.0}])
    with pytest.raises(ValidationError, match=r"parameter_faults\[0\].change: Tc is 0 at "
                                              r"nominal.*give absolute \[N m\]"):
        DCMotorPlantConfig(parameter_faults=[{"parameter": "Tc", "change": 10.0}])


def test_dc_supply_sag_reaches_the_motor_not_the_reported_voltage():
    """Steady state at a constant set-point (La di/dt ~ 0): without the fault Va = Ra ia + Ke
    omega; with ratio 0.9 the motor's voltage balance holds on 0.9 Va (Eq. 11), the reported
    Va being the drive's command (which rises to make up for it)."""
    sp = SetpointSchedule(steps=[(0.0, 10.0)])
    _, base = _dc(duration=40.0, setpoint=sp, noise={})
    plant, bad = _dc(duration=40.0, setpoint=sp, noise={},
                     supply_fault={"ratio": 0.9, "start": 0.0})
    k = -1
    for run, ratio in ((base, 1.0), (bad, 0.9)):
        balance = ratio * run["Va"][k] - 6.5 * run["ia"][k] - 0.038 * run["omega"][k]
        assert abs(balance) < 1e-3 * run["Va"][k]
    assert bad["Va"][k] > 1.05 * base["Va"][k]            # the drive makes up for the sag
    assert bad["omega"][k] == pytest.approx(base["omega"][k], rel=0.03)  # and the speed
    assert plant.truth(20.0).supply == 0.9 and plant.truth(20.0).Ra == 6.5


@pytest.mark.parametrize(("parameter", "harmonic"), [("unbalance", 1.0),
                                                     ("misalignment", 2.0)])
def test_dc_shaft_forcing_is_at_its_harmonic_of_the_shaft_speed(parameter: str,
                                                                harmonic: float):
    """The speed's change from the forcing oscillates at 1x (unbalance) or 2x (misalignment)
    the shaft's rotation frequency."""
    sp = SetpointSchedule(steps=[(0.0, 10.0)])
    _, base = _dc(duration=60.0, setpoint=sp, noise={})
    plant, bad = _dc(duration=60.0, setpoint=sp, noise={}, parameter_faults=[
        {"parameter": parameter, "absolute": 5.0, "start": 20.0}])
    assert np.array_equal(bad["omega"][:2000], base["omega"][:2000])
    tail = slice(3000, 6000)  # 30-60 s: settled
    diff = bad["omega"][tail] - base["omega"][tail]
    diff = diff - diff.mean()
    spec = np.abs(np.fft.rfft(diff * np.hanning(diff.size)))
    freq = np.fft.rfftfreq(diff.size, 0.01)
    peak = freq[int(np.argmax(spec[1:])) + 1]
    shaft_hz = float(np.mean(bad["omega"][tail])) / (2 * math.pi)
    assert peak == pytest.approx(harmonic * shaft_hz, rel=0.05)
    assert getattr(plant.truth(30.0), parameter) == 5.0


# -- hydraulic actuator ------------------------------------------------------------------------

@pytest.mark.parametrize(("channel", "fault"), [
    ("p", {"kind": "gain", "gain": 1.1}), ("x", {"kind": "offset", "offset": 0.02}),
    ("x", {"kind": "frozen"})])
def test_hydraulic_sensor_fault_changes_its_reported_channel_only(channel: str,
                                                                  fault: dict[str, Any]):
    _, base = _hyd(noise={"x": 0.5, "p": 0.5})
    plant, bad = _hyd(noise={"x": 0.5, "p": 0.5},
                      sensor_faults=[{"channel": channel, "start": 2.0, **fault}])
    on = base["t"] >= 2.0
    if fault["kind"] == "gain":
        assert bad[channel][on] == pytest.approx(1.1 * base[channel][on], rel=1e-12)
    elif fault["kind"] == "offset":
        assert bad[channel][on] - base[channel][on] == pytest.approx(
            np.full(on.sum(), 0.02), abs=1e-12)
    else:
        assert np.all(bad[channel][on] == base[channel][on][0])
    assert np.array_equal(bad[channel][~on], base[channel][~on])
    for ch in plant.channels:
        if ch != channel:
            assert np.array_equal(bad[ch], base[ch]), ch


@pytest.mark.parametrize(("fault", "same"), [
    ({"parameter": "q_pump", "change": -10.0}, {"q_pump": 0.018}),
    ({"parameter": "D", "change": 25.0}, {"D": 125.0}),
    ({"parameter": "mass", "change": 10.0}, {"mass": 1100.0}),
    ({"parameter": "F_resist", "absolute": 1000.0}, {"F_resist": 1000.0}),
    ({"parameter": "leak", "absolute": 0.2}, {"scenario": "internal_leak", "fault_start": 0.0,
                                             "leak_coefficient": 0.2}),
])
def test_hydraulic_parameter_fault_from_zero_is_the_plant_with_that_parameter(
        fault: dict[str, Any], same: dict[str, Any]):
    plant, bad = _hyd(parameter_faults=[{**fault, "start": 0.0}])
    _, ref = _hyd(**same)
    for ch in plant.channels:  # F_load follows the mass: a load cell reads the true load
        assert bad[ch] == pytest.approx(ref[ch], rel=1e-9, abs=1e-15), ch


def test_hydraulic_coulomb_friction_opposes_the_motion():
    """From its onset the friction adds F_c sign(v)/A_piston to the pressure (Eq. 16 with a
    Coulomb force): the reference rises over the first 50 s, so +F_c/A."""
    _, base = _hyd(duration=40.0)
    plant, bad = _hyd(duration=40.0, parameter_faults=[
        {"parameter": "friction", "absolute": 1000.0, "start": 10.0}])
    a = plant.config.A_piston
    assert np.array_equal(bad["p"][:1000], base["p"][:1000])
    assert bad["p"][2000:] - base["p"][2000:] == pytest.approx(
        np.full(2000, 1000.0 / a), rel=0.01)
    assert plant.truth(20.0).friction == 1000.0 and plant.truth(5.0).friction == 0.0


def test_hydraulic_faults_are_checked_and_named():
    with pytest.raises(ValidationError, match=r"parameter_faults\[0\].parameter: unknown "
                                              r"parameter 'q'"):
        HydraulicPlantConfig(parameter_faults=[{"parameter": "q", "change": 1.0}])
    with pytest.raises(ValidationError, match=r"parameter_faults\[0\].change: leak is 0"):
        HydraulicPlantConfig(parameter_faults=[{"parameter": "leak", "change": 1.0}])
    with pytest.raises(ValidationError, match=r"sensor_faults\[0\].channel: unknown channel"):
        HydraulicPlantConfig(sensor_faults=[{"channel": "pressure", "kind": "frozen",
                                             "start": 0.0}])
