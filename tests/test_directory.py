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

from .helpers.cli import check_machine, cli, machine_config


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
    r = cli("identify", str(bad))  # the same message from every command that reads it
    assert f"{bad}: not UTF-8 text" in r.output and r.exit_code == 78


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


def _windows(m: object) -> int:
    d = m.supervisor.daemon  # type: ignore[attr-defined]
    return 0 if d is None else d.windows_estimated


@pytest.mark.slow
def test_a_renamed_file_keeps_its_machine_running(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    """``m1.toml`` -> ``line1-m1.toml`` then SIGHUP: a machine is its name, not its file, so it
    goes on under its new file: the same twin, run and window numbering (issue 37: it restarted
    from the nameplate values and the summary counted it twice). An edit made with the rename
    reloads it (the same run goes on). Before: stopped under the old file, started under the
    new one (a new run of a simulated plant, from the nameplate values)."""
    machines = tmp_path / "machines"
    machines.mkdir()
    machine_config(machines, "m1", port=None, duration=60.0)
    monkeypatch.chdir(tmp_path)
    caplog.set_level(logging.WARNING)
    gateway = Host(machines, read=load_config, check=check_machine, workers=1, stuck_after=30.0,
                   quiet_after=30.0, start_timeout=120)
    gateway.start()
    runner = __import__("threading").Thread(target=gateway.run, daemon=True)
    try:
        first = gateway.machines[machines / "m1.toml"]
        deadline = time.monotonic() + 60
        while _windows(first) < 1:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        daemon, run = first.supervisor.daemon, first.supervisor.daemon.run_id
        (machines / "m1.toml").rename(machines / "line1-m1.toml")
        gateway.reload()
        runner.start()
        deadline = time.monotonic() + 30
        while "renamed line1-m1.toml" not in caplog.text:
            assert time.monotonic() < deadline, caplog.text
            time.sleep(0.1)
        assert list(gateway.machines) == [machines / "line1-m1.toml"]
        assert gateway.machines[machines / "line1-m1.toml"] is first
        assert first.thread.is_alive() and first.supervisor.daemon is daemon
        assert "m1 goes on (m1.toml renamed line1-m1.toml)" in caplog.text
        n = _windows(first)
        # an edit with the next rename: a reload of the same machine, the same run
        path = machines / "line1-m1.toml"
        path.write_text(path.read_text() + "\n# moved to press 3\n")
        path.rename(machines / "press-m1.toml")
        gateway.reload()
        deadline = time.monotonic() + 60
        while first.supervisor.daemon is daemon or _windows(first) < 1:
            assert time.monotonic() < deadline, caplog.text
            assert first.lost is None, first.lost
            time.sleep(0.2)
        assert "m1 goes on (line1-m1.toml renamed press-m1.toml)" in caplog.text
        assert "m1 reloaded (press-m1.toml changed)" in caplog.text
        assert first.supervisor.daemon.run_id == run
        assert first.supervisor.daemon.ring.first_index >= n
    finally:
        gateway.stop()
        runner.join(60)
    summary = gateway.summary()
    assert summary.total is not None and summary.total.startswith(
        "twinwatch gateway: 1 machines, 1 ran, 0 lost"), summary.total
    assert [(m.name, m.file) for m in summary.machines] == [("m1", "press-m1.toml")]


def test_a_lost_machine_renamed_and_fixed_counts_once(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """A machine lost under ``m1.toml`` (its recording missing), its file renamed and fixed,
    SIGHUP: it runs under the new file and the summary counts one machine that ran, exit 0
    (before: "2 machines, 1 ran, 1 lost", exit 1: a machine was its file)."""
    from harness.sources import FILE_DRIVER, plant_csv

    machines = tmp_path / "machines"
    machines.mkdir()
    data = plant_csv(tmp_path / "plant.csv", 6.0)
    missing = FILE_DRIVER.format(path=tmp_path / "missing.csv")
    path = machine_config(machines, "m1", port=None, driver=missing)
    monkeypatch.chdir(tmp_path)
    gateway = Host(machines, read=load_config, check=check_machine, workers=1, start_timeout=60)
    gateway.start()
    try:
        assert gateway.machines[path].lost is not None
        path.write_text(path.read_text().replace(str(tmp_path / "missing.csv"), str(data)))
        path.rename(machines / "line1-m1.toml")
        gateway.reload()
        gateway.run()  # the reload starts it under its new file; it replays to the end
    finally:
        gateway.stop()
    summary = gateway.summary()
    assert [(m.name, m.file, m.lost is None) for m in summary.machines] == [
        ("m1", "m1.toml", False), ("m1", "line1-m1.toml", True)]
    assert summary.total == "twinwatch gateway: 1 machines, 1 ran, 0 lost", summary.total
    assert gateway.exit_status() == 0


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


def test_a_gateway_of_worker_processes_counts_a_renamed_machine_once(tmp_path: Path) -> None:
    """The worker processes' summaries name a renamed machine under its old file (an
    incarnation that ended before the rename) and its new one: one machine, by its current
    file; a removed file's machine still counts (before: "4 machines, 4 ran" for 3)."""
    from twinwatch.daemon.service import MachineSummary, RunSummary
    from twinwatch.daemon.workers import ProcessHost, Worker

    host = ProcessHost(tmp_path, workers=1)
    try:
        w = Worker(0, host)
        host.workers.append(w)
        w.files = [tmp_path / "line1-m1.toml", tmp_path / "m2.toml"]
        w.summaries = [
            RunSummary(machines=[MachineSummary(name="m1", file="m1.toml"),
                                 MachineSummary(name="m2", file="m2.toml"),
                                 MachineSummary(name="m3", file="m3.toml")], exit_status=0),
            RunSummary(machines=[MachineSummary(name="m1", file="line1-m1.toml"),
                                 MachineSummary(name="m2", file="m2.toml")], exit_status=0)]
        w.codes = [0, 0]
        total = host.summary().total
        assert total is not None and total.startswith(
            "twinwatch gateway: 3 machines, 3 ran, 0 lost"), total
    finally:
        w.close()
        host.close()
