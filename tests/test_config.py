"""Configuration: every example config is valid, bad keys are named, the CLI checks them."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from twinwatch.cli import main
from twinwatch.config.loader import ConfigError, default_config, load_config

from .conftest import ROOT, SHARED

EXAMPLES = sorted((ROOT / "config").glob("*.toml"))


def test_every_example_config_is_checked():
    assert {p.name for p in EXAMPLES} >= {"dc-motor-sim.toml", "dc-motor-motoshield.toml",
                                          "dc-motor-odrive.toml"}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_example_config_passes_check_config(path: Path):
    if "shared" in path.read_text() and not SHARED.exists():
        pytest.skip("../shared not present")
    result = CliRunner().invoke(main, ["check-config", str(path)])
    assert result.exit_code == 0, result.output
    assert "OK" in result.output


def test_default_config_is_the_sample_config_and_the_sim_example():
    out = CliRunner().invoke(main, ["sample-config"]).output
    assert out == (ROOT / "config" / "dc-motor-sim.toml").read_text()
    cfg = default_config()
    assert cfg.driver.type == "simulated"
    assert cfg.driver.plant.scenario == "resistance_degradation"  # type: ignore[union-attr]
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7447"]
    assert cfg.recording.path == "twinwatch.rrd"


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bad.toml"
    p.write_text(text)
    return p


BASE = (ROOT / "config" / "dc-motor-sim.toml").read_text()


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (("[estimation]", "[estimation]\nestimat = ['Ra']"), "estimation.estimat: unknown key"),
        (('scenario = "resistance_degradation"', 'scenario = "melting"'),
         "driver.plant.scenario: Input should be"),
        (("window = 200", "window = 2"), "acquisition.window"),
        (('estimate = ["Ra", "D", "Ke", "La", "J"]', 'estimate = ["Ra", "Rb"]'),
         "estimation.estimate: unknown parameter 'Rb'"),
        (('name = "dc-motor-sim"', 'name = "dc motor/1"'), "machine.name"),
        (("Ra = [1.0, 30.0]", "Ra = [30.0, 1.0]"), "bounds.Ra"),
        (('listen = ["tcp/127.0.0.1:7447"]', 'listen = ["127.0.0.1"]'), "zenoh.listen"),
    ],
)
def test_bad_config_refuses_and_names_the_key(tmp_path: Path, edit, key):
    old, new = edit
    assert old in BASE
    path = _write(tmp_path, BASE.replace(old, new, 1))
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert key in str(exc.value)
    result = CliRunner().invoke(main, ["check-config", str(path)])
    assert result.exit_code == 1
    assert key in result.output


def test_check_config_reports_a_missing_file_and_bad_toml(tmp_path: Path):
    r = CliRunner().invoke(main, ["check-config", str(tmp_path / "nope.toml")])
    assert r.exit_code == 1 and "cannot read" in r.output
    r = CliRunner().invoke(main, ["check-config", str(_write(tmp_path, "[machine\n"))])
    assert r.exit_code == 1 and "not valid TOML" in r.output


def test_run_refuses_a_bad_config_without_starting(tmp_path: Path):
    path = _write(tmp_path, BASE.replace("[zenoh]", "[zenoh]\nmulticast = true"))
    r = CliRunner().invoke(main, ["run", str(path), "--duration", "1"])
    assert r.exit_code != 0 and "zenoh.multicast: unknown key" in r.output


def test_console_script_is_installed():
    exe = shutil.which("twinwatch", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("twinwatch is not installed in this environment (pip install -e .)")
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "check-config" in out.stdout
