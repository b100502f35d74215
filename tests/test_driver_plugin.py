"""Adding a driver is one module plus one registry line: a driver that lives in another package,
registered through the ``twinwatch.drivers`` entry-point group (an installed distribution's
``entry_points.txt``), is validated from a TOML file by its own config model and runs, with no
change to twinwatch (issue 11).

The plug-in is a real distribution on ``sys.path`` (a package and its ``*.dist-info``), used by
``twinwatch check-config`` and ``twinwatch run`` in a subprocess, as a user would install one.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from .helpers.plugins import DRIVER_PLUGIN

ROOT = Path(__file__).resolve().parents[1]

ENTRY_POINTS = """
[twinwatch.drivers]
plant_direct = twdemo_plugin.direct:PlantDirectDriver
"""


@pytest.fixture
def plugin_path(tmp_path: Path) -> Path:
    """A distribution ``twdemo-plugin`` (package + dist-info) in ``tmp_path/site``."""
    site = tmp_path / "site"
    pkg = site / "twdemo_plugin"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "direct.py").write_text(DRIVER_PLUGIN)
    info = site / "twdemo_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: twdemo-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    return site


def _config(tmp_path: Path, *, driver: str, duration: float = 1200.0) -> Path:
    text = (ROOT / "config" / "dc-motor-sim.toml").read_text()
    start = text.index("[driver]\n")
    end = text.index("[zenoh]\n")
    text = text[:start] + driver + "\n" + text[end:]
    text = text.replace("[zenoh]", "[zenoh]\nenabled = false")
    text = text.replace("[recording]", "[recording]\nenabled = false")
    text = text.replace("[state]", "[state]\nenabled = false")
    path = tmp_path / "plugin.toml"
    path.write_text(text)
    return path


def _twinwatch(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, CI="true",
               PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]))
    return subprocess.run([sys.executable, "-m", "twinwatch", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=300)


DRIVER = textwrap.dedent("""
    [driver]
    type = "plant_direct"

    [driver.plant]
    scenario = "nominal"
    duration = 6.0
""")


@pytest.mark.slow  # about 7 s on the shared 2-core box: out of the fast lane
def test_a_plugin_driver_is_validated_from_toml_and_probed(tmp_path: Path, plugin_path: Path):
    ok = _twinwatch(plugin_path, "check-config", str(_config(tmp_path, driver=DRIVER)),
                    cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr
    assert "plant_direct driver" in ok.stdout

    # its own keys are checked by its own model, errors name the full key
    bad = _twinwatch(plugin_path, "check-config", str(_config(
        tmp_path, driver=DRIVER.replace('"nominal"', '"melting"') + "colour = 'red'\n")),
        cwd=tmp_path)
    assert bad.returncode == 1
    assert "driver.plant.scenario: Input should be 'nominal'" in bad.stderr
    assert "driver.plant.colour: unknown key" in bad.stderr

    # the cross-check with [acquisition] goes through the driver's nominal_sample_period
    slow = _twinwatch(plugin_path, "check-config", str(_config(
        tmp_path, driver=DRIVER + "sample_period = 0.02\n")), cwd=tmp_path)
    assert slow.returncode == 1
    assert "driver sample period 0.02 s differs from acquisition.sample_period" in slow.stderr

    # safe_to_probe: check-config opens the driver, which checks what only it can
    probe = _twinwatch(plugin_path, "check-config", str(_config(
        tmp_path, driver=DRIVER.replace("[driver.plant]", 'licence_file = "lic.txt"\n\n'
                                        "[driver.plant]"))), cwd=tmp_path)
    assert probe.returncode == 1
    assert "driver: licence_file lic.txt not found" in probe.stderr


def test_an_unknown_driver_names_the_known_ones_including_plugins(tmp_path: Path,
                                                                  plugin_path: Path):
    res = _twinwatch(plugin_path, "check-config",
                     str(_config(tmp_path, driver='[driver]\ntype = "profinet"\n')), cwd=tmp_path)
    assert res.returncode == 1
    line = next(ln for ln in res.stderr.splitlines() if "driver.type" in ln)
    assert "unknown driver 'profinet'" in line
    for name in ("can", "file", "modbus", "opcua", "simulated", "simulated_modbus",
                 "simulated_opcua", "plant_direct"):
        assert re.search(rf"\b{name}\b", line), (name, line)


def test_a_plugin_driver_runs_from_toml(tmp_path: Path, plugin_path: Path):
    res = _twinwatch(plugin_path, "run", str(_config(tmp_path, driver=DRIVER)),
                     "--log-level", "info", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    # 6 s of plant time: 3 windows of 2 s; the progress bar's total is the driver's duration
    assert "3 windows estimated" in res.stdout
    assert "/6.0 s plant time" in res.stderr or "/6 s plant time" in res.stderr
    assert re.search(r"Ra\s+= 6\.5\d*\s+ohm\s+\([+-]0\.0\d % vs nominal 6\.5\) estimated",
                     res.stdout), res.stdout
