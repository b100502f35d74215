"""The paper's DC motor scenarios (Section 5.2.2-5.2.3) through the whole daemon path:
simulated plant -> DBC-encoded frames on a virtual CAN bus -> CAN driver -> ring buffer ->
adaptation worker -> health messages. The assertions are the issue's acceptance numbers.

Each paper run simulates 1200 s of plant time (600 windows) as fast as possible: about a minute
(the slow lane). The fast lane runs the same path on the first 60 s of a degradation that starts
at once.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from twinwatch.config.loader import default_config
from twinwatch.daemon.runner import Daemon
from twinwatch.drivers.simulated import SimulatedDriver
from twinwatch.plant.dcmotor import DCMotorPlant


def _run(scenario: str, noise: float, *, uncapped: bool = False, **plant: float
         ) -> tuple[DCMotorPlant, list[dict[str, Any]]]:
    cfg = default_config()
    if uncapped:  # no wall-clock cap on the swarm: the same result on a loaded machine
        cfg.estimation.time_budget = 60.0
    plant_cfg = cfg.driver.plant  # type: ignore[union-attr]
    plant_cfg.scenario = scenario  # type: ignore[assignment]
    plant_cfg.noise = {"ia": noise, "omega": noise} if noise else {}
    for key, value in plant.items():  # duration, fault_start
        setattr(plant_cfg, key, value)
    with SimulatedDriver(cfg.driver) as driver:  # type: ignore[arg-type]
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
        assert daemon.overruns == 0 and daemon.numeric_failures == 0
        assert driver.stats.bad_frames == 0 and driver.stats.gaps == 0
        return driver.plant, list(daemon.history)


def _errors(plant: DCMotorPlant, history: list[dict[str, Any]], name: str,
            since: float = 160.0) -> np.ndarray:
    """Published estimate vs the plant's value at the window's middle [%], from ``since`` [s]
    (the fault's onset) to the end."""
    out = []
    for h in history:
        if h["t_start"] < since:
            continue
        true = getattr(plant.truth(0.5 * (h["t_start"] + h["t_end"])), name)
        out.append((h["parameters"][name]["value"] / true - 1.0) * 100.0)
    return np.asarray(out)


def _held_when_undetermined(history: list[dict[str, Any]]) -> None:
    """Parameters the window cannot determine are held or fused (flag and reason), never
    published as this window's estimates: La and J only move in windows with a transient, Kt
    always follows Ke. A fused value carries the fused evidence's interval, within the gate."""
    held_la = sum(h["parameters"]["La"]["held"] for h in history)
    assert held_la > 0.8 * len(history)
    for h in history:
        for name, p in h["parameters"].items():
            assert p["held"] == (p["status"] != "estimated")
            if p["held"]:
                assert p["reason"], name
            if p["status"] in ("held", "tied", "fixed"):
                assert p["rel_std_pct"] is None
            elif p["status"] == "fused":  # the fusion's own gate, [estimation.fusion] max_rel_std
                assert p["rel_std_pct"] is not None and p["rel_std_pct"] <= 2.0
            else:
                assert p["rel_std_pct"] is not None and p["rel_std_pct"] <= 1.0
        assert h["parameters"]["Kt"]["status"] == "tied"
        assert h["parameters"]["Kt"]["reason"] == "tied to Ke"


def test_daemon_path_finds_and_follows_a_worn_ra_in_a_minute_of_plant_time():
    """The fast lane's end-to-end case, through the same path as the paper runs: a motor whose
    resistance is already 4.6 % below the nameplate (6.2 ohm against the twin's 6.5) and
    degrading from 0 s, 60 s of plant time (30 windows). From the nameplate, Ra is found and
    published within the paper's 0.2 % of the plant's in 95 % of the windows, and parameters a
    window cannot determine are held with their reason, never published as estimates."""
    plant, hist = _run("resistance_degradation", 0.0, uncapped=True, duration=60.0,
                       fault_start=0.0, Ra=6.2)
    assert len(hist) == 30
    err = _errors(plant, hist, "Ra", since=0.0)
    assert np.mean(np.abs(err) <= 0.2) >= 0.95, np.percentile(np.abs(err), [50, 95, 100])
    last = hist[-1]["parameters"]["Ra"]
    assert last["status"] == "estimated" and last["deviation_pct"] < -4.0
    _held_when_undetermined(hist)


@pytest.mark.slow
def test_resistance_degradation_ra_within_0p2_percent():
    plant, hist = _run("resistance_degradation", 0.0)
    assert len(hist) == 600
    err = _errors(plant, hist, "Ra")
    assert len(err) == 520
    assert np.mean(np.abs(err) <= 0.2) >= 0.95, np.percentile(np.abs(err), [50, 95, 100])
    # Ra really drifted to about 5.55 ohm and the twin followed it.
    assert hist[-1]["parameters"]["Ra"]["value"] == pytest.approx(5.55, abs=0.01)
    _held_when_undetermined(hist)


@pytest.mark.slow
def test_bearing_wear_d_within_0p5_percent():
    plant, hist = _run("bearing_wear", 0.0)
    err = _errors(plant, hist, "D")
    assert np.mean(np.abs(err) <= 0.5) >= 0.95, np.percentile(np.abs(err), [50, 95, 100])
    assert hist[-1]["parameters"]["D"]["value"] == pytest.approx(0.00225, rel=0.01)
    _held_when_undetermined(hist)


@pytest.mark.slow
def test_resistance_degradation_with_1_percent_noise_ra_within_1_percent():
    plant, hist = _run("resistance_degradation", 1.0)
    err = _errors(plant, hist, "Ra")
    assert np.mean(np.abs(err) <= 1.0) >= 0.95, np.percentile(np.abs(err), [50, 95, 100])


@pytest.mark.slow
def test_bearing_wear_with_1_percent_noise_d_within_2_percent():
    plant, hist = _run("bearing_wear", 1.0)
    err = _errors(plant, hist, "D")
    assert np.mean(np.abs(err) <= 2.0) >= 0.95, np.percentile(np.abs(err), [50, 95, 100])
