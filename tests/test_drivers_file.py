"""FileDriver on CSV written here and on the real MotoShield recording; the driver registry."""

from __future__ import annotations

import math
import time
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.io
from pydantic import ValidationError

import twinwatch.drivers as drivers
import twinwatch.plugins
from twinwatch.drivers import (
    Driver,
    DriverInitializationError,
    DriverOperationError,
    EndOfStream,
    Sample,
    create_driver,
    get_driver_class,
)
from twinwatch.drivers.file import FileDriver, FileDriverConfig
from twinwatch.plugins import Registry

REPO = Path(__file__).resolve().parents[1]
APRBS_MAT = REPO.parent / "shared" / "data" / "motoshield" / "aprbsResult.mat"
APRBS_TS = 0.02  # [s], MotoShield sample period (not stored in the file)
APRBS_N = 4801


# Thread leaks fail every test: see the autouse fixture in tests/conftest.py.


def replay(driver: Driver) -> list[Sample]:
    """Every sample until EndOfStream, which must then stay raised."""
    samples: list[Sample] = []
    with pytest.raises(EndOfStream):
        while True:
            sample = driver.read(0)
            assert sample is not None, "as fast as possible: never None"
            samples.append(sample)
    with pytest.raises(EndOfStream):
        driver.read(0)
    return samples


CSV = """time_ms,u,y,i
0,3.0,10.5,0.12
20,3.5,,0.13
40,abc,12.5,0.14
60,4.0,13.5
80,4.5,nan,0.16
"""


def csv_config(path: str, **overrides: Any) -> dict[str, Any]:
    config: dict[str, Any] = {
        "type": "file",
        "path": path,
        "sample_period": 0.02,
        "columns": {
            "Va": {"column": "u", "unit": "V"},
            "omega": {"column": "y", "scale": 2 * math.pi / 60, "unit": "rad/s"},
            "ia": {"column": "i", "scale": 1e3, "offset": -100.0, "unit": "mA"},
        },
    }
    config.update(overrides)
    return config


@pytest.fixture
def csv_file(tmp_path: Path) -> Path:
    path = tmp_path / "run.csv"
    path.write_text(CSV)
    return path


# -- CSV ----------------------------------------------------------------------------------


def test_csv_replay_scales_and_counts_empty_cells(csv_file: Path) -> None:
    config = csv_config("run.csv")  # relative to base_dir
    with create_driver(config, base_dir=csv_file.parent) as driver:
        assert isinstance(driver, FileDriver)
        assert driver.channels == ("Va", "omega", "ia")
        assert driver.sample_period == 0.02 and driver.n_rows == 5
        samples = replay(driver)
        stats = driver.stats.as_dict()
    assert [s.t for s in samples] == [k * 0.02 for k in range(5)]
    assert samples[0].values == {
        "Va": 3.0,
        "omega": 10.5 * 2 * math.pi / 60,
        "ia": 0.12 * 1e3 - 100.0,
    }
    assert math.isnan(samples[1].values["omega"])  # empty cell
    assert math.isnan(samples[2].values["Va"])  # not a number
    assert math.isnan(samples[3].values["ia"])  # short row
    assert math.isnan(samples[4].values["omega"])  # "nan"
    assert stats == {
        "frames": 5,
        "samples": 5,
        "bad_frames": 0,
        "bad_values": 4,
        "gaps": 0,
        "errors": 0,
    }


def test_csv_time_column_in_ms_and_inferred_period(csv_file: Path) -> None:
    config = csv_config(str(csv_file), time_column="time_ms", time_scale=1e-3)
    del config["sample_period"]
    with FileDriver(FileDriverConfig.model_validate(config)) as driver:
        assert driver.sample_period == pytest.approx(0.02)
        assert [s.t for s in replay(driver)] == [0.0, 0.02, 0.04, 0.06, 0.08]


def test_csv_start_stop_are_row_indices_and_keep_the_clock(csv_file: Path) -> None:
    config = FileDriverConfig.model_validate(csv_config(str(csv_file), start=1, stop=3))
    with FileDriver(config) as driver:
        assert driver.n_rows == 2
        assert [s.t for s in replay(driver)] == [0.02, 0.04]


def test_csv_missing_column_names_the_key_and_the_columns(csv_file: Path) -> None:
    config = csv_config(str(csv_file))
    config["columns"]["omega"] = {"column": "Y"}
    with pytest.raises(DriverInitializationError) as info:
        create_driver(config, base_dir=REPO)
    assert str(info.value) == (
        "columns.omega: column 'Y' not in run.csv; did you mean 'y'? available: i, time_ms, u, y"
    )


def test_csv_realtime_is_paced_by_the_sample_period(csv_file: Path) -> None:
    config = FileDriverConfig.model_validate(csv_config(str(csv_file), realtime=True))
    with FileDriver(config) as driver:
        start = time.monotonic()
        assert driver.read(0) is not None  # row 0 is due at once
        assert driver.read(0) is None  # row 1 is due 20 ms later
        n = 1
        with pytest.raises(EndOfStream):
            while True:
                n += driver.read(1.0) is not None
        elapsed = time.monotonic() - start
    assert n == 5
    assert elapsed >= 0.079  # paced by the sample period: 5 rows span 0.08 s


def test_csv_realtime_wakes_once_per_pace_slack_never_early(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A real-time replay of 10 ms rows sleeps about once per PACE_SLACK, not once a row (a
    sleep a row cost 74 us of CPU a row), and delivers no row before it is due."""
    import twinwatch.drivers.file as file_mod

    data = tmp_path / "fast.csv"
    data.write_text("t,u\n" + "".join(f"{k * 0.01!r},{k}.0\n" for k in range(31)))
    sleeps: list[float] = []
    real_sleep = time.sleep

    def counted(s: float) -> None:
        sleeps.append(s)
        real_sleep(s)

    monkeypatch.setattr(file_mod.time, "sleep", counted)
    config = FileDriverConfig.model_validate({
        "type": "file", "path": str(data), "time_column": "t", "realtime": True,
        "columns": {"Va": {"column": "u"}}})
    early = []
    with FileDriver(config) as driver:
        start = time.monotonic()
        with pytest.raises(EndOfStream):
            while True:
                s = driver.read(None)
                if s is not None and time.monotonic() - start < s.t - 1e-3:
                    early.append(s.t)
    assert not early
    assert 1 <= len(sleeps) <= 0.3 / file_mod.PACE_SLACK + 2, sleeps  # 30 before


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"sample_period": None}, "sample_period is required unless time_column is given"),
        ({"start": 3, "stop": 1}, "stop \\(1\\) is before start \\(3\\)"),
        ({"colums": {}}, "Extra inputs are not permitted"),
        ({"format": "xlsx"}, "format"),
        ({"columns": {}}, "columns"),
    ],
)
def test_invalid_config_is_refused(change: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        FileDriverConfig.model_validate(csv_config("run.csv", **change))
    with pytest.raises(DriverInitializationError, match="invalid file driver config"):
        create_driver(csv_config("run.csv", **change), base_dir=REPO)


def test_unknown_suffix_and_missing_file_fail_at_construction(tmp_path: Path) -> None:
    (tmp_path / "run.parquet").write_bytes(b"PAR1")
    with pytest.raises(DriverInitializationError, match="format: cannot tell the format"):
        create_driver(csv_config("run.parquet"), base_dir=tmp_path)
    with pytest.raises(DriverInitializationError, match="path: file .*nope.csv' not found"):
        create_driver(csv_config("nope.csv"), base_dir=tmp_path)


def test_closed_driver_refuses_to_read(csv_file: Path) -> None:
    driver = FileDriver(FileDriverConfig.model_validate(csv_config(str(csv_file))))
    driver.close()
    driver.close()
    with pytest.raises(DriverOperationError):
        driver.read(0)


# -- the real MotoShield recording ---------------------------------------------------------


def aprbs_config() -> dict[str, Any]:
    if not APRBS_MAT.is_file():
        pytest.skip(f"../shared/data not present: {APRBS_MAT} is missing")
    return {
        "type": "file",
        # relative to the repository root, as a config file at the root would say it
        "path": "../shared/data/motoshield/aprbsResult.mat",
        "sample_period": APRBS_TS,
        "columns": {
            "Va": {"column": "u", "unit": "V"},
            "omega": {"column": "y", "unit": "rad/s"},
            "ia": {"column": "ifltr", "unit": "A"},
        },
    }


def test_motoshield_aprbs_recording_replays_exactly() -> None:
    config = aprbs_config()
    mat = scipy.io.loadmat(APRBS_MAT)
    with create_driver(config, base_dir=REPO) as driver:
        assert driver.sample_period == APRBS_TS
        samples = replay(driver)
        assert driver.stats.samples == APRBS_N and driver.stats.bad_values == 0
    assert len(samples) == APRBS_N
    t = np.array([s.t for s in samples])
    np.testing.assert_array_equal(t, np.arange(APRBS_N) * APRBS_TS)
    assert samples[-1].t == pytest.approx(96.0)  # 4800 * 0.02 s
    for channel, variable in (("Va", "u"), ("omega", "y"), ("ia", "ifltr")):
        got = np.array([s.values[channel] for s in samples])
        np.testing.assert_array_equal(got, mat[variable].ravel())
    va = [s.values["Va"] for s in samples]
    assert 2.88 <= min(va[:-1]) and max(va) <= 4.66  # the APRBS levels [V]
    assert va[-1] == 0.0  # the recording ends with the motor switched off


def test_motoshield_missing_variable_lists_the_variables() -> None:
    config = aprbs_config()
    config["columns"]["ia"] = {"column": "i_filtered"}
    with pytest.raises(DriverInitializationError) as info:
        create_driver(config, base_dir=REPO)
    message = str(info.value)
    assert message.startswith("columns.ia: variable 'i_filtered' not in aprbsResult.mat;")
    assert message.endswith("available: i, ifltr, u, y")


def test_mat_without_time_vector_needs_a_period(tmp_path: Path) -> None:
    scipy.io.savemat(tmp_path / "m.mat", {"u": np.ones((4, 1)), "y": np.arange(3.0)})
    config: dict[str, Any] = {"type": "file", "path": "m.mat", "columns": {"Va": {"column": "u"}}}
    with pytest.raises(DriverInitializationError, match="sample_period is required"):
        create_driver(config, base_dir=tmp_path)
    config |= {"sample_period": 0.5, "columns": {"Va": {"column": "u"}, "omega": {"column": "y"}}}
    with pytest.raises(DriverInitializationError, match="'y' has 3 samples, 'u' has 4"):
        create_driver(config, base_dir=tmp_path)


# -- the registry -------------------------------------------------------------------------


def test_registry_knows_the_builtin_drivers() -> None:
    assert set(drivers.BUILTIN_DRIVERS) >= {"can", "file", "simulated", "modbus"}
    assert drivers.BUILTIN_DRIVERS["simulated"] == "twinwatch.drivers.simulated:SimulatedDriver"
    assert drivers.DRIVERS.names()[:len(drivers.BUILTIN_DRIVERS)] == list(drivers.BUILTIN_DRIVERS)
    assert get_driver_class("file") is FileDriver
    assert get_driver_class("can").__name__ == "CanDriver"


def test_unknown_and_unavailable_drivers(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(DriverInitializationError, match="unknown driver 'profinet'; known drivers"):
        create_driver({"type": "profinet"}, base_dir=REPO)
    with pytest.raises(DriverInitializationError, match="has no 'type'"):
        create_driver({"path": "x.csv"}, base_dir=REPO)
    registry = Registry("driver", "twinwatch.none",
                        {"broken": "twinwatch_no_such_module:Broken", "file": "math:pi"},
                        base=lambda: Driver)
    monkeypatch.setattr(drivers, "DRIVERS", registry)
    with pytest.raises(DriverInitializationError,
                       match="driver 'broken' not available: No module named "
                             "'twinwatch_no_such_module'. Is the package that provides "
                             "twinwatch_no_such_module installed"):
        create_driver({"type": "broken"}, base_dir=REPO)
    with pytest.raises(DriverInitializationError, match="math.pi is not a "
                       "twinwatch.drivers.base.Driver subclass"):
        get_driver_class("file")


def test_entry_points_extend_but_do_not_replace(monkeypatch: pytest.MonkeyPatch,
                                                caplog: pytest.LogCaptureFixture) -> None:
    plugins = [
        EntryPoint("replay2", "twinwatch.drivers.file:FileDriver", drivers.ENTRY_POINT_GROUP),
        EntryPoint("can", "evil.module:Bus", drivers.ENTRY_POINT_GROUP),
    ]
    monkeypatch.setattr(twinwatch.plugins, "entry_points", lambda group: plugins)
    drivers.DRIVERS.cache_clear()
    try:
        table = drivers.DRIVERS.table()
        assert table["replay2"] == "twinwatch.drivers.file:FileDriver"
        assert table["can"] == "twinwatch.drivers.can:CanDriver"
        assert get_driver_class("replay2") is FileDriver
        assert "entry point can = 'evil.module:Bus' ignored: 'can' is a built-in driver" \
            in caplog.text
    finally:
        drivers.DRIVERS.cache_clear()
