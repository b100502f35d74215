"""Commissioning (issue 9 item 4): ``twinwatch identify`` fits the baseline on a training range
of a recording and scores it on a validation range it was not fitted to."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
from twinwatch.twin.estimation.estimator import EstimationConfig, PSOSettings
from twinwatch.twin.estimation.identify import (
    IdentifyConfig,
    fit_percent,
    identify,
    parameters_block,
)
from twinwatch.twin.model import WindowData
from twinwatch.twin.models.dcmotor import DCMotorTwin

TRUE = {"Ra": 7.2, "Ke": 0.041}


def _recording(seconds: float, noise: dict[str, float]) -> WindowData:
    plant = DCMotorPlant(DCMotorPlantConfig(scenario="nominal", duration=seconds, Ra=TRUE["Ra"],
                                            Ke=TRUE["Ke"], Kt=TRUE["Ke"], noise=noise, seed=2))
    ss = []
    while True:
        try:
            ss.append(plant.next_sample())
        except Exception:  # noqa: BLE001 - EndOfStream ends the plant
            break
    return WindowData(t=np.array([s.t for s in ss]),
                      channels={c: np.array([s.values[c] for s in ss]) for c in ss[0].values})


def _split(w: WindowData) -> tuple[WindowData, WindowData]:
    h = w.n // 2
    cut = [WindowData(t=w.t[a:b], channels={c: v[a:b] for c, v in w.channels.items()})
           for a, b in ((0, h), (h, w.n))]
    return cut[0], cut[1]


def test_fit_percent_is_matlab_compare() -> None:
    y = np.sin(np.linspace(0, 6, 100))
    assert fit_percent(y, y) == pytest.approx(100.0)
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0)
    assert fit_percent(y, y + 0.1 * (y - y.mean())) == pytest.approx(90.0)


def test_identified_baseline_covers_the_truth_and_fits_the_held_out_half() -> None:
    """A motor unlike the nameplate (Ra +11 %, Ke +8 %), 1 % noise: the training half gives Ra
    and Ke whose intervals cover the plant's values, and the twin fits the validation half."""
    w = _recording(80.0, {"ia": 1.0, "omega": 1.0})
    train, validation = _split(w)
    est = EstimationConfig(estimate=["Ra", "Ke"], tie={"Kt": "Ke"},
                           bounds={"Ra": (1.0, 30.0), "Ke": (0.01, 0.1)})
    cfg = IdentifyConfig(pso=PSOSettings(pop_size=10, max_generations=10), time_budget=5.0)
    r = identify(DCMotorTwin(), est, cfg, train, validation)
    for name, truth in TRUE.items():
        assert abs(math.log(r.values[name] / truth)) <= 3 * r.rel_std[name], (name, r.values)
        assert r.values[name] == pytest.approx(truth, rel=0.02)
    assert r.values["Kt"] == r.values["Ke"]
    for out in ("ia", "omega"):
        assert r.validation.fit_pct[out] > 80.0 and r.train.fit_pct[out] > 80.0  # 1 % noise
    block = parameters_block(r, "a test recording")
    assert "[machine.parameters]" in block and f"Ra = {r.values['Ra']:.6g}" in block
    assert "bounds = { Ra = [1, 30], Ke = [0.01, 0.1] }" in block


def test_ranges_are_checked() -> None:
    with pytest.raises(ValueError, match="train: need 0 <= start < end <= 1"):
        IdentifyConfig(train=(0.5, 0.2))
    with pytest.raises(ValueError, match="weights.ia: must be a finite number"):
        IdentifyConfig(weights={"ia": -1.0})


def test_identify_command_on_a_csv_recording(tmp_path: Path) -> None:
    """The command as a user runs it, on a CSV file replayed by the file driver: the report,
    the block with the bounds, the Rerun file of both fits; a gap in a range is refused."""
    w = _recording(30.0, {})
    path = tmp_path / "run.csv"
    with path.open("w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["time", "setpoint", "Va", "ia", "omega"])
        for k in range(w.n):
            out.writerow([f"{w.t[k]:.2f}", w["setpoint"][k], w["Va"][k], w["ia"][k],
                          w["omega"][k]])
    cfg = tmp_path / "machine.toml"
    cfg.write_text(f"""
[machine]
name = "bench"
[machine.parameters]
Ra = 6.5
[estimation]
estimate = ["Ra", "Ke"]
bounds = {{ Ra = [1.0, 30.0], Ke = [0.01, 0.1] }}
[identify]
time_budget = 3.0
pso = {{ pop_size = 8, max_generations = 5 }}
[driver]
type = "file"
path = "{path.name}"
format = "csv"
time_column = "time"
sample_period = 0.01
[driver.columns]
setpoint = {{ column = "setpoint" }}
Va = {{ column = "Va" }}
ia = {{ column = "ia" }}
omega = {{ column = "omega" }}
[zenoh]
enabled = false
[recording]
enabled = false
[state]
enabled = false
""")
    rrd = tmp_path / "fit.rrd"
    block = tmp_path / "params.toml"
    res = subprocess.run([sys.executable, "-m", "twinwatch", "identify", str(cfg),
                          "--record", str(rrd), "--output", str(block)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "fit % (100 (1 - |y - y_hat| / |y - mean(y)|))" in res.stdout
    assert "validation" in res.stdout and "[machine.parameters]" in res.stdout
    text = block.read_text()
    ra = float(text.split("Ra = ")[1].split()[0])
    assert ra == pytest.approx(TRUE["Ra"], rel=1e-3)  # noise-free: exact
    assert rrd.stat().st_size > 1000
    bad = subprocess.run([sys.executable, "-m", "twinwatch", "identify", str(cfg),
                          "--train", "0.6:0.2"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 78 and "train: need 0 <= start < end <= 1" in bad.stderr
