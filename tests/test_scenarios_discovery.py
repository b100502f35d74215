"""Unknown-component discovery over whole runs (paper Section 5.2.4; issue "Done when").

* Unbalanced shaft (Eq. 13), through the whole daemon path (plant -> virtual CAN -> driver ->
  ring buffer -> adaptation worker -> health): the published DT'' holds one periodic term of
  the right amplitude and frequency, and the worst speed error falls from about 0.5 rad/s (DT')
  to below 0.02 rad/s.
* Nominal and resistance-degradation runs of 300 windows, noise-free and with 1 % noise: no
  term is ever kept (no false discovery).

These are the slow lane's; the fast lane runs the unbalanced shaft through the daemon for 12
windows (the discovery, then the kept term re-validated and refined).
"""

from __future__ import annotations

import numpy as np
import pytest

from twinwatch.config.loader import load_config
from twinwatch.daemon.runner import Daemon
from twinwatch.drivers.simulated import SimulatedDriver
from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
from twinwatch.twin.adaptation import TwinAdapter
from twinwatch.twin.model import WindowData
from twinwatch.twin.models import create_model

from .helpers.paths import ROOT

CONFIG = ROOT / "config" / "dc-motor-unbalanced-sim.toml"


def _unbalanced(duration: float, uncapped: bool = False) -> list[dict]:  # type: ignore[type-arg]
    cfg = load_config(CONFIG)
    cfg.driver.plant.duration = duration  # type: ignore[union-attr]
    if uncapped:  # no wall-clock cap: the same result on a loaded machine
        cfg.estimation.time_budget = cfg.discovery.time_budget = 60.0
    with SimulatedDriver(cfg.driver) as driver:  # type: ignore[arg-type]
        with Daemon(cfg, driver=driver, publish=False, record=False) as daemon:
            daemon.run()
        history = list(daemon.history)
    assert daemon.numeric_failures == 0 and len(history) == round(duration / 2.0)
    return history


def test_unbalanced_shaft_is_discovered_through_the_daemon_in_a_few_windows() -> None:
    """The fast lane's discovery end to end: 24 s (12 windows). One search after the K = 3
    windows whose residual stays too large keeps the one periodic term of Eq. 13 (amplitude
    within 2 % of 5 rad/s^2, frequency within 0.5 % of 10 rad/s), every later window keeps
    and re-validates it, and DT'' explains the speed that DT' misses by about 0.5 rad/s."""
    history = _unbalanced(24.0, uncapped=True)
    found = [h for h in history if h["discovery"]["ran"]]
    assert len(found) == 1 and found[0]["window"] <= 5
    after = [h for h in history if h["window"] >= found[0]["window"]]
    assert len(after) >= 6
    for h in after:
        (term,) = h["terms"]
        assert term["kind"] == "periodic" and term["attach"] == "d(omega)/dt"
        assert abs(abs(term["params"]["a"]) - 5.0) / 5.0 < 0.02
        assert abs(abs(term["params"]["b"]) - 10.0) / 10.0 < 0.005
        assert h["residual"]["dt_prime"]["max_abs"]["omega"] > 0.4
        assert h["residual"]["dt_second"]["max_abs"]["omega"] < 0.02
    assert all(not h["terms"] for h in history if h["window"] < found[0]["window"])


@pytest.mark.slow
def test_unbalanced_shaft_is_discovered_and_kept() -> None:
    # uncapped: with the wall-clock budgets a loaded machine (load 4.7 on 2 cores) cut the
    # first search short, which kept a constant, switched it off and searched 5 times
    history = _unbalanced(200.0, uncapped=True)
    found = [h for h in history if h["discovery"]["ran"]]
    assert len(found) == 1, "one discovery, then the term is kept and re-validated"
    k0 = found[0]["window"]
    assert k0 <= 5  # after the K = 3 windows whose residual stays too large
    after = [h for h in history if h["window"] >= k0]
    worst_dt = []
    for h in after:
        (term,) = h["terms"]  # one term, no other
        assert term["kind"] == "periodic" and term["attach"] == "d(omega)/dt"
        assert abs(abs(term["params"]["a"]) - 5.0) / 5.0 < 0.02
        assert abs(abs(term["params"]["b"]) - 10.0) / 10.0 < 0.005
        assert "d" not in term["params"]
        assert "unbalanced shaft" in term["meaning"]
        worst_dt.append(h["residual"]["dt_prime"]["max_abs"]["omega"])
    worst_dt2 = np.array([h["residual"]["dt_second"]["max_abs"]["omega"] for h in after])
    # DT' (the physical twin alone) misses by about 0.5 rad/s, DT'' by < 0.02 rad/s.
    assert np.median(worst_dt) > 0.4
    assert np.mean(worst_dt2 < 0.02) >= 0.95
    # The physical parameters stay right with the term in place.
    last = history[-1]["parameters"]
    assert abs(last["Ra"]["deviation_pct"]) < 0.2 and abs(last["D"]["deviation_pct"]) < 0.5


@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "noise"), [
    ("nominal", 0.0), ("nominal", 1.0),
    ("resistance_degradation", 0.0), ("resistance_degradation", 1.0),
])
def test_no_false_discovery_over_300_windows(scenario: str, noise: float) -> None:
    """The adaptation worker's own path (TwinAdapter) on 300 plant windows: a term is never
    kept. (The bus path adds nothing to this claim and would triple the run time.)"""
    cfg = load_config(CONFIG)
    model = create_model(cfg.machine.model, cfg.machine.options)
    adapter = TwinAdapter(model, cfg.estimation, cfg.discovery)
    plant = DCMotorPlant(DCMotorPlantConfig(
        scenario=scenario, duration=601.0, noise={"ia": noise, "omega": noise} if noise else {},
        seed=7))
    kept = too_large = 0
    for k in range(300):
        samples = [plant.next_sample() for _ in range(200)]
        w = WindowData(t=np.array([s.t for s in samples]),
                       channels={c: np.array([s.values[c] for s in samples])
                                 for c in samples[0].values}, index=k)
        r = adapter.process(w)
        kept += bool(r.terms)
        too_large += r.too_large
    assert kept == 0
    # With noise, the exit criterion judges the residual against the noise it measures.
    assert too_large <= 3
