"""Examples that travel (issue 24): the ODrive example copied into a gateway's directory still
finds its shipped log, and its summary shows plant time a person can read.

The ODrive example's log is stamped by a bus adapter's clock (``time_source = "frame"``): its
plant time is seconds since the epoch (1763799999.999 s for the shipped log), which the summary
printed as ``[1763800058.00-1763800059.99 s]``; it now prints a UTC clock time.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from twinwatch.cli import main
from twinwatch.daemon.summary import alarm_lines, plant_moment, plant_span, window_lines
from twinwatch.drivers.can import CanDriverConfig

from .helpers.paths import ROOT, SHARED

EXAMPLE = ROOT / "config" / "dc-motor-odrive.toml"
ODRIVE_DBC = SHARED / "data" / "dbc" / "odrive-cansimple-0.6.10.dbc"


def test_the_odrive_log_is_found_from_any_directory(tmp_path: Path) -> None:
    """The example's log is the package's file wherever the configuration sits (before:
    ``../twinwatch/plant/...`` relative to config/, missing from a gateway's directory)."""
    table = tomllib.loads(EXAMPLE.read_text())["driver"]
    config = CanDriverConfig.model_validate(table)
    for where in (EXAMPLE.parent, tmp_path / "machines.d", Path("/etc/twinwatch")):
        log = config.required_files(where)["driver.log_file"]
        assert log.is_file(), f"{log} (config in {where})"
        assert log.name == "odrive-axis0.log.gz"
    # a plain relative path still resolves against the file's directory
    plain = config.model_copy(update={"log_file": Path("logs/a.log")})
    assert plain.required_files(tmp_path)["driver.log_file"] == tmp_path / "logs" / "a.log"


def test_check_config_passes_on_the_example_copied_into_a_gateway_directory(
        tmp_path: Path) -> None:
    if not ODRIVE_DBC.is_file():
        pytest.skip(f"../shared/data not present: {ODRIVE_DBC} is missing")
    machines = tmp_path / "machines.d"
    machines.mkdir()
    # the DBC is not shipped (it is ODrive's): a copy points dbc at it, as the file's comment says
    text = EXAMPLE.read_text().replace('dbc = "../../shared/data/dbc/odrive-cansimple-0.6.10.dbc"',
                                       f'dbc = "{ODRIVE_DBC}"')
    (machines / "odrive.toml").write_text(text)
    r = CliRunner().invoke(main, ["check-config", str(machines)])
    assert r.exit_code == 0, r.output
    assert "odrive-axis0.log.gz' opened" in r.output


def test_plant_time_from_a_wall_clock_reads_as_a_clock_time() -> None:
    assert plant_span(1198.0, 1199.99) == "1198.00-1199.99 s"
    assert plant_span(1763800058.0, 1763800059.99) == "2025-11-22 08:27:38.00-08:27:39.99 UTC"
    assert plant_span(1763855999.0, 1763856001.0) == (
        "2025-11-22 23:59:59.00-2025-11-23 00:00:01.00 UTC")
    assert plant_moment(1090.4) == "plant time 1090 s"
    assert plant_moment(1763800058.7) == "2025-11-22 08:27:38 UTC"


def test_the_summary_shows_a_readable_window_and_alarm_time() -> None:
    last = SimpleNamespace(window=29, t_start=1763800058.0, t_end=1763800059.99, nrmse=1e-3,
                           elapsed_s=0.05, parameters={},
                           alarms={"Ra": SimpleNamespace(level="warning", since_t=1763800040.0,
                                                         deviation_pct=-6.0, rul=None)})
    line = window_lines(last)[0]  # type: ignore[arg-type]
    assert line.startswith("last window 29 [2025-11-22 08:27:38.00-08:27:39.99 UTC]"), line
    assert "1763800058" not in line
    alarms = alarm_lines(last)[0]  # type: ignore[arg-type]
    assert "raised at 2025-11-22 08:27:20 UTC" in alarms, alarms
