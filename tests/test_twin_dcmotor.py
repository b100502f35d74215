"""The DC motor twin (paper Eq. 11-12) against the simulated plant and its own claims."""

from __future__ import annotations

import numpy as np
import pytest

from twinwatch.plant.dcmotor import DCMotorPlantConfig, SetpointSchedule
from twinwatch.twin.model import composite_zoh, zoh_propagate
from twinwatch.twin.models.dcmotor import DCMotorTwin

from .helpers.plant import plant_windows

STEP = SetpointSchedule(steps=[(0.0, 10.0), (3.0, 15.0)])


def _measured(twin: DCMotorTwin, win) -> np.ndarray:
    return np.column_stack([win[o] for o in twin.output_names])


def test_closed_loop_twin_reproduces_the_plant_exactly():
    _, wins = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=10,
                                               setpoint=STEP), 2)
    twin = DCMotorTwin()
    for win in wins:
        y = twin.simulate(twin.nominal_vector()[None, :], win)[0]
        meas = _measured(twin, win)
        rel = np.abs(y - meas).max(axis=0) / np.abs(meas).max(axis=0)
        assert rel.max() < 1e-11, rel


def test_open_loop_twin_with_held_voltage_is_biased():
    """Why closed loop is the default for a drive whose PI runs faster than acquisition."""
    _, wins = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=10,
                                               setpoint=STEP), 1, skip=1)
    twin = DCMotorTwin(structure="open_loop")
    y = twin.simulate(twin.nominal_vector()[None, :], wins[0])[0]
    meas = _measured(twin, wins[0])
    rel = np.abs(y - meas).max(axis=0) / np.abs(meas).max(axis=0)
    assert rel.max() > 1e-4


def test_composite_zoh_equals_explicit_sub_stepping():
    twin = DCMotorTwin()
    theta = twin.nominal_vector()[None, :] * np.array([[1.1, 0.9, 1.2, 1.0, 1.0, 0.8]])
    a, b = twin.step_matrices(theta, 1e-4)
    phi, gamma = composite_zoh(a, b, 100)
    x = np.array([1.0, 5.0, 20.0])
    u = np.array([10.0, 0.0, 3.0, -2.0])  # set-point, Tload, f_omega, f_ia
    x_loop = x.copy()
    for _ in range(100):
        x_loop = a[0] @ x_loop + b[0] @ u
    np.testing.assert_allclose(phi[0] @ x + gamma[0] @ u, x_loop, rtol=1e-13)


def test_swarm_shape_and_blown_up_particles_do_not_raise():
    _, wins = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=4), 1)
    twin = DCMotorTwin()
    theta = np.repeat(twin.nominal_vector()[None, :], 15, axis=0)
    theta[3, 1] = 1e-9  # La -> 0: the explicit scheme explodes
    y = twin.simulate(theta, wins[0])
    assert y.shape == (15, 200, 3)
    assert np.all(np.isfinite(y[0]))
    assert not np.all(np.isfinite(y[3]))


def test_viscous_load_makes_J_Kt_D_indistinguishable():
    """With Tload = c*omega, scaling J and Kt by s and D -> s*(D+c)-c gives the same outputs
    when Ke is not tied to Kt: estimating all six at once is ill-posed (the issue's finding)."""
    _, wins = plant_windows(DCMotorPlantConfig(scenario="nominal", duration=10,
                                               setpoint=STEP), 1, skip=1)
    twin = DCMotorTwin()
    th = twin.nominal_vector()
    s = 1.7
    th2 = th.copy()
    th2[2] *= s  # J
    th2[4] *= s  # Kt
    th2[5] = s * (th[5] + 0.006) - 0.006  # D
    y1 = twin.simulate(th[None, :], wins[0])[0]
    y2 = twin.simulate(th2[None, :], wins[0])[0]
    np.testing.assert_allclose(y1, y2, rtol=1e-9, atol=1e-12)


def test_sample_period_must_be_a_multiple_of_the_sub_step():
    with pytest.raises(ValueError, match="whole multiple"):
        DCMotorTwin().n_sub(0.01005)


def test_fault_period_replaces_the_part_and_a_non_physical_run_is_refused():
    """``fault_period``: the degradation law restarts at each maintenance. The plant's kernel
    and its ``truth`` agree across a restart: the twin with the true Ra reproduces the window
    after the restart, the twin with the Ra just before it does not."""
    cfg = DCMotorPlantConfig(scenario="resistance_degradation", fault_start=0.0,
                             fault_period=600.0, duration=610.0, setpoint=STEP)
    plant, (win,) = plant_windows(cfg, 1, skip=300)  # [600, 602) s
    before, after = plant.truth(599.99).Ra, plant.truth(601.0).Ra
    assert before == pytest.approx(6.5 - 0.044 * (np.exp(1.8) - 1), rel=1e-4)  # 6.28 ohm
    assert after == pytest.approx(6.5, abs=2e-4)
    assert plant.truth(1201.0).Ra == pytest.approx(after)  # periodic
    twin = DCMotorTwin()
    meas = _measured(twin, win)
    i_ra = twin.parameter_names.index("Ra")

    def worst(ra: float) -> float:
        theta = twin.nominal_vector()
        theta[i_ra] = ra
        y = twin.simulate(theta[None, :], win)[0]
        return float((np.abs(y - meas).max(axis=0) / np.abs(meas).max(axis=0)).max())

    assert worst(after) < 1e-4 < 1e-2 < worst(before)
    # without a maintenance the paper's law reaches 0 ohm 1667 s after onset: refused
    with pytest.raises(ValueError, match="duration: under resistance_degradation .* fault_period"):
        DCMotorPlantConfig(scenario="resistance_degradation", duration=2000.0)
    DCMotorPlantConfig(scenario="resistance_degradation", duration=21600.0, fault_period=1200.0)


def test_the_compiled_window_equals_the_sub_step_map_composed_then_run():
    """``zoh_propagate`` (one compiled call) gives the numbers of ``composite_zoh`` followed by
    the recursion ``x[k+1] = Gamma u[k] + Phi x[k]`` summed in that order, bit for bit, with
    shared and per-particle meta-model terms."""
    rng = np.random.default_rng(3)
    twin = DCMotorTwin()
    theta = twin.nominal_vector()[None, :] * np.exp(0.1 * rng.standard_normal((3, 6)))
    a, b = twin.step_matrices(theta, 1e-4)
    phi, gamma = composite_zoh(a, b, 100)
    n_samples = 40
    x0 = rng.standard_normal((3, 3))
    drive, tload = rng.standard_normal(n_samples), 1e-3 * rng.standard_normal(n_samples)
    for f_w, f_i in ((np.zeros((1, n_samples)), np.zeros((1, n_samples))),
                     (rng.standard_normal((3, n_samples)), rng.standard_normal((3, n_samples)))):
        x = zoh_propagate(a, b, 100, x0, drive, tload, f_w, f_i)
        for q in range(3):
            qu = 0 if f_w.shape[0] == 1 else q
            ref = [list(x0[q])]
            for k in range(n_samples - 1):
                u = (drive[k], tload[k], f_w[qu, k], f_i[qu, k])
                row = []
                for i in range(3):
                    acc = 0.0
                    for j in range(4):
                        acc += gamma[q, i, j] * u[j]
                    for j in range(3):
                        acc += phi[q, i, j] * ref[-1][j]
                    row.append(acc)
                ref.append(row)
            np.testing.assert_array_equal(x[q], np.array(ref))
    # inputs that do not fit the matrices are refused, not read past their ends
    with pytest.raises(ValueError, match=r"expected b \(3, 3, 4\)"):
        zoh_propagate(a[:, :, :], b[:, :, :3], 100, x0, drive, tload, f_w, f_i)
    with pytest.raises(ValueError, match=r"terms \(1 or 3, 40\)"):
        zoh_propagate(a, b, 100, x0, drive, tload, f_w[:2], f_i[:2])
