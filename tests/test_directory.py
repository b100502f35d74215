"""A gateway's directory as a plant's first month leaves it (issue 26 item 2): a file renamed,
two files naming one machine, links and other files beside the configurations, a file that is
not UTF-8."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import pytest

from twinwatch.config.loader import load_config
from twinwatch.daemon.host import Host

from .test_fault_injection import cli
from .test_gateway import _check, machine_config


def test_two_files_naming_one_machine_the_first_by_file_name_always_runs(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    machines = tmp_path / "machines"
    machines.mkdir()
    for stem in ("b-second", "a-first"):
        path = machine_config(machines, "m", port=None, duration=4.0, realtime=False)
        path.rename(machines / f"{stem}.toml")
    monkeypatch.chdir(tmp_path)
    for _ in range(3):  # which one opened first decided it, start to start
        r = cli("run", str(machines), "--no-progress", "--workers", "1")
        assert "== m (a-first.toml): stopped" in r.output, r.output
        assert "== m (b-second.toml): lost: invalid configuration" in r.output
        assert "already monitored by a-first.toml" in r.output
        assert r.exit_code == 1


def test_a_file_that_is_not_utf8_is_a_configuration_error_naming_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    machines = tmp_path / "machines"
    machines.mkdir()
    machine_config(machines, "good", port=None, duration=4.0, realtime=False)
    bad = machines / "latin1.toml"
    bad.write_bytes('[machine]\nname = "Mühle"\n'.encode("latin-1"))
    monkeypatch.chdir(tmp_path)
    r = cli("run", str(machines), "--no-progress", "--workers", "1")
    assert "latin1.toml): lost: invalid configuration" in r.output, r.output
    assert f"{bad}: not UTF-8 text" in r.output
    assert "internal error" not in r.output
    r = cli("run", str(bad), "--no-progress")
    assert r.exit_code == 78
    assert f"{bad}: not UTF-8 text" in r.output
    r = cli("check-config", str(machines))
    assert f"{bad}: not UTF-8 text" in r.output and r.exit_code == 1


def test_every_entry_of_the_directory_is_run_lost_or_named_as_skipped(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
        ) -> None:
    machines = tmp_path / "machines"
    machines.mkdir()
    machine_config(machines, "m1", port=None, duration=4.0, realtime=False)
    os.symlink(tmp_path / "gone.toml", machines / "m2.toml")  # a link to nothing
    (machines / "m3.toml.bak").write_text("old")
    r = cli("check-config", str(machines))
    assert "m2.toml: skipped: a link to" in r.output and "does not exist" in r.output
    assert "m3.toml.bak: skipped: not a machine configuration" in r.output
    caplog.set_level(logging.WARNING)
    monkeypatch.chdir(tmp_path)
    r = cli("run", str(machines), "--no-progress", "--workers", "1")
    assert r.exit_code == 0, r.output
    text = caplog.text
    assert "m2.toml: skipped: a link to" in text
    assert "m3.toml.bak: skipped" in text


@pytest.mark.slow
def test_a_renamed_file_is_a_remove_then_an_add_in_one_reload(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    """``m1.toml`` -> ``line1-m1.toml`` then SIGHUP: the machine stops under its old file and
    starts under its new one in that reload (it used to be "already monitored" until the next
    SIGHUP: the old one still held the name while it finished its queued windows)."""
    machines = tmp_path / "machines"
    machines.mkdir()
    machine_config(machines, "m1", port=None, duration=60.0)
    monkeypatch.chdir(tmp_path)
    gateway = Host(machines, read=load_config, check=_check, workers=1, stuck_after=30.0,
                   quiet_after=30.0, start_timeout=120)
    gateway.start()
    try:
        first = gateway.machines[machines / "m1.toml"]

        def windows(m: object) -> int:
            d = m.supervisor.daemon  # type: ignore[attr-defined]
            return 0 if d is None else d.windows_estimated

        deadline = time.monotonic() + 60
        while windows(first) < 1:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        (machines / "m1.toml").rename(machines / "line1-m1.toml")
        gateway.reload()
        runner = __import__("threading").Thread(target=gateway.run, daemon=True)
        runner.start()
        deadline = time.monotonic() + 60
        while True:
            new = gateway.machines.get(machines / "line1-m1.toml")
            if new is not None and (new.lost is not None or windows(new) >= 1):
                break
            assert time.monotonic() < deadline, "the renamed machine never ran"
            time.sleep(0.2)
        assert new.lost is None, new.lost
        assert not first.thread.is_alive()
        assert list(gateway.machines) == [machines / "line1-m1.toml"]
    finally:
        gateway.stop()
        runner.join(60)


def test_a_failure_repeated_every_window_is_logged_once_then_counted(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
        ) -> None:
    """Issue 26: a machine whose every window raises logged one ERROR a window. Now: once,
    again when the failure changes (with how often the previous one repeated), and when
    windows are estimated again."""
    from twinwatch.config.loader import default_config
    from twinwatch.daemon.pipeline import WindowPipeline
    from twinwatch.daemon.runner import Daemon

    original = WindowPipeline.process
    calls = [0]

    def process(self: WindowPipeline, window: object) -> object:
        calls[0] += 1
        if calls[0] <= 4:
            raise FloatingPointError("the twin diverged")
        if calls[0] <= 6:
            raise ValueError("a NaN in the window")
        return original(self, window)  # type: ignore[arg-type]

    monkeypatch.setattr(WindowPipeline, "process", process)
    monkeypatch.chdir(tmp_path)
    cfg = default_config()
    cfg.driver.plant.duration = 18.0  # type: ignore[attr-defined]
    caplog.set_level(logging.WARNING)
    with Daemon(cfg, publish=False, record=False) as daemon:
        daemon.run()
    assert daemon.numeric_failures == 6
    failed = [r.getMessage() for r in caplog.records if "could not be estimated" in r.getMessage()]
    assert len(failed) == 2, failed  # the two different failures, once each
    assert "FloatingPointError: the twin diverged" in failed[0]
    assert "ValueError: a NaN in the window" in failed[1]
    text = caplog.text
    assert "the failure above repeated in 3 more windows (FloatingPointError" in text
    assert "repeated in 1 more windows (ValueError" in text
    assert "window 6 estimated again after 2 failed windows" in text
