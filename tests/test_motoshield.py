"""The DC motor twin on a real recording: AutomationShield MotoShield, aprbsResult.mat
(../shared/data/motoshield, CC BY-NC-ND 4.0, read in place), through
config/dc-motor-motoshield.toml and the file driver."""

from __future__ import annotations

import numpy as np

from twinwatch.config.loader import load_config
from twinwatch.daemon.runner import Daemon

from .conftest import ROOT, shared_path


def test_motoshield_recording_every_window_estimated_plausibly_and_stably():
    shared_path("data", "motoshield", "aprbsResult.mat")
    cfg_path = ROOT / "config" / "dc-motor-motoshield.toml"
    cfg = load_config(cfg_path)
    with Daemon(cfg, base_dir=cfg_path.parent, publish=False, record=False) as daemon:
        daemon.run()
        hist = list(daemon.history)
        counters = daemon.counters()
    # 4801 samples at 0.02 s in windows of 200: 24 windows, none lost, none failed.
    assert len(hist) == 24
    assert counters["numeric_failures"] == 0 and counters["windows_abandoned"] == 0
    ke = np.array([h["parameters"]["Ke"]["value"] for h in hist])
    ke_estimated = [not h["parameters"]["Ke"]["held"] for h in hist]
    assert all(ke_estimated)  # the speed response determines Ke in every window
    # Physically plausible: a small motor, about 900 rad/s at 4.7 V -> Ke ~ 0.005 V s/rad.
    assert np.all((ke > 0.004) & (ke < 0.0055))
    spread = (np.percentile(ke, 75) - np.percentile(ke, 25)) / np.median(ke)
    assert spread < 0.10, spread
    # Every window publishes its fit; the linear model fits this motor only roughly.
    nrmse = np.array([h["nrmse"] for h in hist])
    assert np.all(np.isfinite(nrmse)) and np.median(nrmse) < 0.2
    for h in hist:
        assert set(h["rmse"]) == {"ia", "omega"}
        for p in h["parameters"].values():
            assert p["value"] > 0  # every published parameter is physical
