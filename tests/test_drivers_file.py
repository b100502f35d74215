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


def _count_sleeps(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """The file driver's sleeps, each still slept, in a list filled as it asks them."""
    import twinwatch.drivers.file as file_mod

    sleeps: list[float] = []
    real_sleep = time.sleep

    def counted(s: float) -> None:
        sleeps.append(s)
        real_sleep(s)

    monkeypatch.setattr(file_mod.time, "sleep", counted)
    return sleeps


def _stamps(driver: FileDriver, blocks: bool) -> list[float]:
    """The time stamps of the next read's rows: one by one, or a block of up to 50 rows."""
    if not blocks:
        s = driver.read(None)
        return [] if s is None else [s.t]
    got = driver.read_block(None, 50)
    return [] if got is None else got[0].tolist()


@pytest.mark.parametrize("blocks", [False, True])
def test_csv_realtime_wakes_once_per_pace_slack_never_early(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, blocks: bool) -> None:
    """A real-time replay of 10 ms rows sleeps about once per PACE_SLACK, not once a row (a
    sleep a row cost 74 us of CPU a row), and delivers no row before it is due, read one by
    one or in blocks (:meth:`FileDriver.read_block`)."""
    import twinwatch.drivers.file as file_mod

    data = tmp_path / "fast.csv"
    data.write_text("t,u\n" + "".join(f"{k * 0.01!r},{k}.0\n" for k in range(31)))
    sleeps = _count_sleeps(monkeypatch)
    config = FileDriverConfig.model_validate({
        "type": "file", "path": str(data), "time_column": "t", "realtime": True,
        "columns": {"Va": {"column": "u"}}})
    early, seen = [], []
    with FileDriver(config) as driver:
        start = time.monotonic()
        with pytest.raises(EndOfStream):
            while True:
                stamps = _stamps(driver, blocks)
                seen += stamps
                early += [t for t in stamps if time.monotonic() - start < t - 1e-3]
        assert driver.stats.samples == driver.stats.frames == 31
    assert not early and seen == [k * 0.01 for k in range(31)]
    assert 1 <= len(sleeps) <= 0.3 / file_mod.PACE_SLACK + 2, sleeps  # 30 before


def test_the_acquisition_loop_wakes_for_a_real_time_replay_about_once_a_second(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The acquisition loop reads a real-time replay with its read timeout (READ_TIMEOUT_S,
    1 s) and the driver holds the rows due up to PACE_SLACK: 2.5 s of 10 ms rows in windows
    of 50 rows take 3 to 5 of the driver's sleeps (13 with both at 0.2 s: a wake-up costs a
    few tenths of a millisecond of CPU on a shared box), every window whole and none handed
    on before its last row is due. Under systemd's watchdog the loop reads at least twice
    per ping interval (``WatchdogSec=0.5``: every 0.125 s), its pings riding on its ticks."""
    import twinwatch.drivers.file as file_mod
    from twinwatch.config.loader import default_config
    from twinwatch.daemon.acquisition import READ_TIMEOUT_S, Acquisition
    from twinwatch.daemon.systemd import Notifier, Watchdog
    from twinwatch.twin.models import create_model

    assert (READ_TIMEOUT_S, file_mod.PACE_SLACK) == (1.0, 1.0)
    data = tmp_path / "plant.csv"
    data.write_text("t,setpoint,Va,ia,omega\n" + "".join(
        f"{k * 0.01!r},10.0,{3 + 0.01 * k!r},0.5,{0.1 * k!r}\n" for k in range(251)))
    cfg = default_config()
    cfg = cfg.model_copy(update={"acquisition": cfg.acquisition.model_copy(
        update={"window": 50})})
    config = FileDriverConfig.model_validate({
        "type": "file", "path": str(data), "time_column": "t", "realtime": True,
        "columns": {c: {"column": c} for c in ("setpoint", "Va", "ia", "omega")}})
    acq = Acquisition(cfg, create_model(cfg.machine.model, cfg.machine.options),
                      own_driver=True)
    assert acq.read_timeout() == READ_TIMEOUT_S
    sleeps = _count_sleeps(monkeypatch)
    late: list[float] = []    # each window's hand-over after its last row was due [s]
    lengths: list[int] = []
    start = time.monotonic()

    def submit(window: Any, block: bool) -> None:
        lengths.append(window.n)
        late.append(time.monotonic() - start - float(window.t[-1]))

    acq.open(FileDriver(config), base_dir=tmp_path, wait=False)
    try:
        acq.run(None, submit, lambda n: None)
    finally:
        acq.release()
    assert lengths == [50] * 5
    assert min(late) > -1e-3, late            # none before its last row is due
    assert 3 <= len(sleeps) <= 5, sleeps     # one a second, not one per 0.2 s (13)
    with Notifier(env={"NOTIFY_SOCKET": str(tmp_path / "absent"),
                       "WATCHDOG_USEC": "500000"}) as notifier:
        acq.watchdog = Watchdog(notifier)
        assert acq.read_timeout() == 0.125


def test_a_block_read_for_a_long_window_looks_at_a_bounded_stretch(tmp_path: Path) -> None:
    """A block read asked for more rows than the file's rest (a window longer than the run:
    ``bench_density.py --acquisition-only``) takes at most ``_BLOCK_ROWS`` of them, so each
    read costs the same however long the file (it checked the whole rest before: quadratic
    in the file's length); the blocks together are every row, in order."""
    import twinwatch.drivers.file as file_mod

    n = 2 * file_mod._BLOCK_ROWS + 7
    data = tmp_path / "long.csv"
    data.write_text("t,u\n" + "".join(f"{k * 0.01!r},{k}.0\n" for k in range(n)))
    config = FileDriverConfig.model_validate({
        "type": "file", "path": str(data), "time_column": "t",
        "columns": {"Va": {"column": "u"}}})
    sizes, values = [], []
    with FileDriver(config) as driver, pytest.raises(EndOfStream):
        while True:
            got = driver.read_block(None, 100_000)
            assert got is not None
            sizes.append(len(got[0]))
            values += got[1][:, 0].tolist()
    assert sizes == [file_mod._BLOCK_ROWS, file_mod._BLOCK_ROWS, 7]
    assert values == [float(k) for k in range(n)]


def test_csv_realtime_at_speed_10_is_paced_ten_times_faster_never_early(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``speed = 10``: 201 rows of 10 ms (2 s) are replayed in about 0.2 s of wall time, no
    row before its time stamp over 10 is due, and the driver asks to sleep about 0.2 s in all
    (a speed-1 replay asks 2 s; what it asks, not the wall time, so a loaded box cannot
    break it)."""
    import twinwatch.drivers.file as file_mod

    sleeps = _count_sleeps(monkeypatch)
    data = tmp_path / "fast.csv"
    data.write_text("t,u\n" + "".join(f"{k * 0.01!r},{k}.0\n" for k in range(201)))
    config = FileDriverConfig.model_validate({
        "type": "file", "path": str(data), "time_column": "t", "realtime": True,
        "speed": 10.0, "columns": {"Va": {"column": "u"}}})
    early, n = [], 0
    with FileDriver(config) as driver:
        start = time.monotonic()
        with pytest.raises(EndOfStream):
            while True:
                s = driver.read(None)
                if s is not None:
                    n += 1
                    if time.monotonic() - start < s.t / 10.0 - 1e-3:
                        early.append(s.t)
        elapsed = time.monotonic() - start
    assert n == 201 and not early
    assert elapsed >= 0.199  # paced: the last row is due 2 s / 10 after the first
    # the waits asked: 0.2 s and at most one PACE_SLACK of the recording (over the speed)
    # late each wake-up, far from 2 s
    assert sum(sleeps) < 0.2 + file_mod.PACE_SLACK / 10.0 * (len(sleeps) + 1) < 1.0, sleeps


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"sample_period": None}, "sample_period is required unless time_column is given"),
        ({"speed": 10.0}, "speed paces a realtime replay only"),
        ({"speed": 0.0}, "speed"),
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


# -- a CSV still being written ---------------------------------------------------------------

def _append(path: Path, text: str) -> None:
    with path.open("a") as f:
        f.write(text)


def test_follow_reads_the_rows_appended_as_they_are_written(tmp_path: Path) -> None:
    """``follow = true`` (issue 37: a CSV still being written was replayed only as far as it
    was at open, silently): the rows there at open, then each complete line appended, a line
    being written once it ends, the file's clock going on; no row for ``idle_timeout`` ends
    the replay as the end of a file does."""
    path = tmp_path / "logger.csv"
    path.write_text("time_ms,u,y,i\n0,3.0,10.5,0.12\n20,3.5,11.5,0.13\n")
    driver = FileDriver.from_config(csv_config(str(path), follow=True, idle_timeout=0.6))
    try:
        assert [s.values["Va"] for s in (driver.read(0), driver.read(0))] == [3.0, 3.5]
        assert driver.read(0) is None  # nothing new yet: not the end
        _append(path, "40,4.0,12.5,0.14\n60,4.5,13")  # the second line is being written
        got = driver.read(0.5)
        assert got is not None and (got.t, got.values["Va"]) == (pytest.approx(0.04), 4.0)
        assert driver.read(0.2) is None  # the partial line is not a row yet
        _append(path, ".5,0.15\n")
        got = driver.read(0.5)
        assert got is not None and got.values["omega"] == pytest.approx(13.5 * 2 * math.pi / 60)
        assert got.t == pytest.approx(0.06)  # t = k * sample_period, k the file's row
        assert driver.n_rows == 4
        start = time.monotonic()
        with pytest.raises(EndOfStream, match=r"no new row for 0.6 s \(driver.idle_timeout\) "
                                              r"after 4 rows"):
            while True:
                assert driver.read(0.1) is None
        assert 0.5 < time.monotonic() - start < 30.0  # ends on its own (a generous deadline)
    finally:
        driver.close()


def test_follow_ends_at_stop_and_when_the_file_is_replaced(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "logger.csv"
    path.write_text("time_ms,u,y,i\n0,3.0,10.5,0.12\n")
    driver = FileDriver.from_config(csv_config(str(path), follow=True, stop=3))
    try:
        assert driver.read(0) is not None and driver.read(0) is None
        _append(path, "20,3.5,11.5,0.13\n40,4.0,12.5,0.14\n60,4.5,13.5,0.15\n")
        assert [driver.read(0.5).values["Va"] for _ in range(2)] == [3.5, 4.0]  # type: ignore[union-attr]
        with pytest.raises(EndOfStream, match=r"driver.stop = 3"):
            driver.read(0)
    finally:
        driver.close()
    driver = FileDriver.from_config(csv_config(str(path), follow=True))
    try:
        assert len([driver.read(0) for _ in range(4)]) == 4
        path.write_text("time_ms,u,y,i\n0,1.0,1.0,0.1\n")  # truncated: a logger started over
        with pytest.raises(EndOfStream, match="truncated or replaced after 4 rows"):
            driver.read(0)
    finally:
        driver.close()
    assert caplog.text.count("was truncated or replaced while followed") == 1


def test_a_file_that_grew_after_it_was_opened_says_so_once_at_its_end(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Without ``follow``: the rows there at open are replayed; at the end, one warning says
    the file grew and how to read what was written since (before: nothing)."""
    path = tmp_path / "logger.csv"
    path.write_text("time_ms,u,y,i\n0,3.0,10.5,0.12\n")
    driver = FileDriver.from_config(csv_config(str(path)))
    try:
        _append(path, "20,3.5,11.5,0.13\n")
        assert len(replay(driver)) == 1
        with pytest.raises(EndOfStream):
            driver.read(0)
    finally:
        driver.close()
    said = [r.getMessage() for r in caplog.records if "grew" in r.getMessage()]
    assert said == ["logger.csv grew by 17 bytes after it was opened (still being written?): "
                    "the rows written since are not replayed; set driver.follow = true to "
                    "read them as they come"], said


@pytest.mark.parametrize(("change", "message"), [
    ({"idle_timeout": 5.0}, "idle_timeout applies to a followed file only"),
    ({"follow": True, "sample_period": None, "time_column": "time_ms"},
     "sample_period is required with follow = true"),
])
def test_follow_keys_refused_where_they_do_not_apply(change: dict[str, Any], message: str
                                                     ) -> None:
    with pytest.raises(ValidationError, match=message):
        FileDriverConfig.model_validate(csv_config("x.csv", **change))


def test_a_dumped_table_validates_again() -> None:
    """A table as dumped (every field, idle_timeout's default too) validates again: the
    fault-matrix benchmark rebuilds a file driver's table so, and refused it."""
    cfg = FileDriverConfig.model_validate(csv_config("x.csv"))
    assert FileDriverConfig.model_validate(cfg.model_dump()) == cfg


def test_follow_refuses_a_mat_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mat"
    scipy.io.savemat(path, {"u": np.ones(5), "y": np.ones(5), "i": np.ones(5)})
    with pytest.raises(DriverInitializationError, match="follow: run.mat is a MAT file"):
        FileDriver.from_config(csv_config(str(path), follow=True))


def test_twinwatch_run_follows_a_recording_as_it_is_written(tmp_path: Path) -> None:
    """``twinwatch run`` on a CSV a logger is writing (``follow = true``): the windows
    written after the start are estimated too, the run ends ``idle_timeout`` after the last
    row. Before: 2 of the 6 windows, the run ended at the rows there at start, silently."""
    import threading

    from harness.daemon import with_driver
    from harness.sources import FILE_DRIVER, plant_csv

    from .helpers.cli import cli

    lines = plant_csv(tmp_path / "plant.csv", 12.0).read_text().splitlines(keepends=True)
    live = tmp_path / "live.csv"
    live.write_text("".join(lines[:1 + 450]))  # the header and 4.5 s of rows
    driver = FILE_DRIVER.format(path=live).replace(
        "sample_period = 0.01\n", "sample_period = 0.01\nfollow = true\nidle_timeout = 2.0\n")
    cfg = with_driver(tmp_path, driver)

    def write() -> None:
        for k in range(1 + 450, len(lines), 150):  # 1.5 s of rows a tenth of a second
            time.sleep(0.1)
            _append(live, "".join(lines[k:k + 150]))

    writer = threading.Thread(target=write)
    writer.start()
    try:
        r = cli("run", str(cfg), "--no-progress")
    finally:
        writer.join()
    assert r.exit_code == 0, r.output
    assert "twinwatch: 6 windows estimated" in r.output, r.output
