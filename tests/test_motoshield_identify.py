"""Commissioning on the real MotoShield recording (issue 9 item 4 and its done-when lines):
``twinwatch identify config/dc-motor-motoshield.toml`` fits the PWM DC motor twin on the first
half and beats the grey-box reference on the held-out second half; the daemon, run with that
baseline, publishes per-window estimates consistent with the commissioning intervals.

The recording is ../shared/data/motoshield/aprbsResult.mat (CC BY-NC-ND 4.0, read in place);
the tests skip when it is absent."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from twinwatch.config.loader import load_config
from twinwatch.daemon.commission import commission
from twinwatch.daemon.runner import Daemon
from twinwatch.twin.estimation.identify import Identification

from .conftest import ROOT, shared_path

CONFIG = ROOT / "config" / "dc-motor-motoshield.toml"
#: Held-out fit % of the grey-box linear reference (DE + least squares, issue 9): speed, current.
REFERENCE = {"omega": 71.5, "ia": 36.4}
#: The issue's targets on the held-out half.
TARGET = {"omega": 80.0, "ia": 50.0}


@pytest.fixture(scope="module")
def commissioned() -> tuple[Any, Identification]:
    """The identify command on the config, started from the model's generic defaults (the
    config's values came from this command: starting there would prove nothing), with one of
    the config's four starts (a quarter of its search budget)."""
    shared_path("data", "motoshield", "aprbsResult.mat")
    cfg = load_config(CONFIG)
    assert cfg.identify.starts == 4 and cfg.identify.pso.pop_size == 20
    cold = cfg.model_copy(update={
        "machine": cfg.machine.model_copy(update={"parameters": {}}),
        "identify": cfg.identify.model_copy(update={"starts": 1})})
    result, data = commission(cold, CONFIG.parent)
    assert data.t.size == 4801 and data.dropped == 0
    return cfg, result


def test_identify_beats_the_reference_on_the_held_out_half(commissioned):
    cfg, r = commissioned
    assert r.train.samples == 2400 and r.validation.samples == 2401
    for out in ("omega", "ia"):
        held_out = r.validation.fit_pct[out]
        assert held_out >= TARGET[out] and held_out > REFERENCE[out] + 10, (out, held_out)
        assert r.train.fit_pct[out] >= TARGET[out]
    # measured: speed 91.2 / 89.7 %, current 51.9 / 53.3 % (training / held out)
    assert r.validation.fit_pct["omega"] == pytest.approx(89.7, abs=1.0)
    assert r.validation.fit_pct["ia"] == pytest.approx(53.3, abs=1.0)
    # Both ranges are within the model error the monitoring accepts.
    assert r.train.check.passed and r.validation.check.passed
    # The speed pins Ke; the rest trade off with the current's unknown scale and the warm-up.
    assert r.rel_std["Ke"] < 0.1
    # The config's baseline is what this command gives (from any start: the same optimum).
    for name in r.estimated:
        nominal = cfg.machine.parameters[name]
        assert r.values[name] == pytest.approx(nominal, rel=0.01), (name, r.values[name])


def test_monitoring_with_the_baseline_is_consistent_with_the_commissioning(commissioned):
    """The daemon on the recording with the identified baseline: every window processed and
    trusted; each parameter a window estimates lies within the commissioning's 1-sigma interval
    and the window's own 2-sigma interval covers the commissioned value; what no window
    determines is fused, within the commissioning interval too."""
    cfg, r = commissioned
    with Daemon(cfg, base_dir=CONFIG.parent, publish=False, record=False) as daemon:
        daemon.run()
        hist = list(daemon.history)
        counters = daemon.counters()
    assert len(hist) == 24
    assert counters["windows_abandoned"] == 0 and counters["numeric_failures"] == 0
    assert all(h["trusted"] for h in hist)
    counts = {}
    for name in cfg.estimation.estimate:
        base = cfg.machine.parameters[name]
        sigma = r.rel_std[name]
        est = [h["parameters"][name] for h in hist
               if h["parameters"][name]["status"] == "estimated"]
        counts[name] = len(est)
        for p in est:
            dev = abs(math.log(p["value"] / base))
            assert dev <= sigma, (name, p["value"], base, sigma)
            assert dev <= 2 * p["rel_std_pct"] / 100, (name, p["value"], p["rel_std_pct"])
        fused = hist[-1]["parameters"][name]["fused"]
        assert abs(math.log(fused["value"] / base)) <= sigma
    # measured: Ke estimated in 21 windows (within -3.3 .. +4.1 % of the baseline, relative
    # standard error 1.5-9.8 %), D in 11 (-5.5 .. +1.7 %), J in 2, Ra in none (fused)
    assert counts["Ke"] >= 18 and counts["D"] >= 6
    ke = np.array([h["parameters"]["Ke"]["value"] for h in hist
                   if h["parameters"]["Ke"]["status"] == "estimated"])
    assert np.all(np.abs(ke / cfg.machine.parameters["Ke"] - 1) < 0.06)
