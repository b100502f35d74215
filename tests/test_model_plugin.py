"""Adding a machine is one model module plus one config: a twin model that lives in another
package, registered through the ``twinwatch.models`` entry-point group, brings its own
estimation defaults (what to estimate, and a tie), and is monitored from a TOML file that does
not say what to estimate, with no change to twinwatch (issue 11).

The machine: a heated wall of two identical layers (a first-order thermal RC model). The heater
power P and the ambient temperature Ta drive it, the wall temperature T is measured:

    C dT/dt = P - (T - Ta) / (R_in + R_out)

R_in and R_out are not separable from T alone; the layers are of one material, so the model
ties R_out to R_in (its estimation defaults: estimate R_in and C, R_out tied to R_in). The
recording is a CSV replayed by the built-in file driver.
"""

from __future__ import annotations

import csv
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

MODEL = '''
"""A third-party twin: a heated wall of two identical layers."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinwatch.twin.model import EstimationDefaults, OutputSpec, ParameterSpec, TwinModel


@dataclass
class ThermalWall(TwinModel):
    def __post_init__(self) -> None:
        self.parameters = (
            ParameterSpec("R_in", "K/W", 0.05, "inner layer thermal resistance",
                          "a rise: fouling or insulation damage"),
            ParameterSpec("R_out", "K/W", 0.05, "outer layer thermal resistance"),
            ParameterSpec("C", "J/K", 600.0, "heat capacity of the wall"),
        )
        self.inputs = ("P", "Ta")
        self.outputs = (OutputSpec("T", "K", 1.0),)

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        return EstimationDefaults(("R_in", "C"), {"R_out": "R_in"})

    def simulate(self, theta, window, terms=None):
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        r = theta[:, 0] + theta[:, 1]
        c = theta[:, 2]
        t, p, ta = window.t, window["P"], window["Ta"]
        out = np.empty((theta.shape[0], window.n, 1))
        temp = np.full(theta.shape[0], window["T"][0])
        out[:, 0, 0] = temp
        with np.errstate(all="ignore"):
            for k in range(window.n - 1):   # exact for inputs held over each step
                decay = np.exp(-(t[k + 1] - t[k]) / (r * c))
                steady = ta[k] + p[k] * r
                temp = steady + (temp - steady) * decay
                out[:, k + 1, 0] = temp
        return out
'''

ENTRY_POINTS = """
[twinwatch.models]
thermal_wall = twdemo_model.wall:ThermalWall
"""

CONFIG = """
[machine]
name = "oven-wall"
model = "thermal_wall"

[machine.parameters]          # nameplate (the wall has fouled and thinned since)
R_in = 0.04
R_out = 0.04
C = 600.0

[acquisition]
sample_period = 1.0
window = 200

[estimation]                  # no estimate, no tie: the model's
bounds = { R_in = [0.005, 0.5], C = [50.0, 5000.0] }
time_budget = 2.0

[driver]
type = "file"
path = "wall.csv"
time_column = "t"

[driver.columns]
P = { column = "heater_W" }
Ta = { column = "ambient_K" }
T = { column = "wall_K" }

[zenoh]
enabled = false

[recording]
enabled = false

[state]
enabled = false
"""

R_LAYER, CAPACITY = 0.05, 500.0  # the truth the recording is made with


def _recording(path: Path, seconds: int = 600) -> None:
    """The wall under a heater switched every 10 s, ambient drifting, sampled every 1 s."""
    r = 2 * R_LAYER
    temp = 293.15
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "heater_W", "ambient_K", "wall_K"])
        for k in range(seconds):
            p = 400.0 if (k // 10) % 2 == 0 else 50.0
            ta = 293.15 + 2.0 * math.sin(2 * math.pi * k / 600)
            w.writerow([k, p, ta, repr(temp)])
            steady = ta + p * r
            temp = steady + (temp - steady) * math.exp(-1.0 / (r * CAPACITY))


@pytest.fixture
def site(tmp_path: Path) -> Path:
    site = tmp_path / "site"
    pkg = site / "twdemo_model"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "wall.py").write_text(MODEL)
    info = site / "twdemo_model-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: twdemo-model\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    return site


def _twinwatch(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, CI="true", PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]))
    return subprocess.run([sys.executable, "-m", "twinwatch", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=300)


def test_a_plugin_model_brings_its_estimation_defaults(tmp_path: Path, site: Path) -> None:
    cfg = tmp_path / "wall.toml"
    cfg.write_text(CONFIG)
    _recording(tmp_path / "wall.csv")
    ok = _twinwatch(site, "check-config", str(cfg), cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr
    assert "thermal_wall 'oven-wall', file driver, estimating R_in, C" in ok.stdout

    # the defaults are defaults: a config that estimates R_out as well must untie it
    bad = tmp_path / "bad.toml"
    bad.write_text(CONFIG.replace("bounds =", 'estimate = ["R_in", "R_out", "C"]\ntie = '
                                  '{ R_out = "R_in" }\nbounds ='))
    res = _twinwatch(site, "check-config", str(bad), cwd=tmp_path)
    assert res.returncode == 1
    assert "tie.R_out: a tied parameter cannot also be estimated" in res.stderr


def test_a_plugin_model_is_monitored_from_toml(tmp_path: Path, site: Path) -> None:
    cfg = tmp_path / "wall.toml"
    cfg.write_text(CONFIG)
    _recording(tmp_path / "wall.csv")
    res = _twinwatch(site, "run", str(cfg), "--no-progress", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "3 windows estimated" in res.stdout
    # the fouled wall: each layer 0.05 K/W against a 0.04 K/W nameplate (+25 %)
    line = next(ln for ln in res.stdout.splitlines() if ln.strip().startswith("R_in"))
    m = re.search(r"R_in\s+=\s+(\S+)\s+K/W\s+\(([+-]\d+\.\d+) % vs nominal 0\.04\) estimated",
                  line)
    assert m, line
    assert float(m.group(1)) == pytest.approx(R_LAYER, rel=1e-3)
    assert float(m.group(2)) == pytest.approx(25.0, abs=0.1)
    r_out = next(ln for ln in res.stdout.splitlines() if ln.strip().startswith("R_out"))
    assert "tied to R_in" in r_out and re.search(r"=\s+0\.05\b", r_out), r_out
    # C: 500 J/K against a 600 J/K nameplate (found in the first window, then held there
    # while the windows that follow do not determine it better)
    c_line = next(ln for ln in res.stdout.splitlines() if ln.strip().startswith("C "))
    m = re.search(r"C\s+=\s+(\S+)\s+J/K\s+\(([+-]\d+\.\d+) % vs nominal 600\)", c_line)
    assert m, c_line
    assert float(m.group(1)) == pytest.approx(CAPACITY, rel=1e-3)
