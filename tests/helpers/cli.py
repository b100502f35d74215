"""The command line as the tests run it: in this process (click's runner) or as a subprocess,
and the machine configurations they run it on."""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from harness import ROOT
from harness.daemon import SIM, twinwatch_env
from twinwatch.cli import main
from twinwatch.config.preflight import check_runnable
from twinwatch.sinks.store import StateStore


def run_daemon(cfg: Path, cwd: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "twinwatch", "run", str(cfg), "--no-progress",
                             "--log-level", "info", *args], cwd=cwd, env=twinwatch_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def cli(*args: str) -> Any:
    """``twinwatch ARGS`` in this process (click's runner): exit code and output."""
    return CliRunner().invoke(main, list(args), catch_exceptions=True)


class DiskFull:
    """The state database's writes fail (as on a full disk) for the windows in ``windows``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, windows: range) -> None:
        self.windows = windows
        original = StateStore._flush

        def flush(store: StateStore, retry: bool = True) -> bool:
            if store._pending and store._pending[-1][2] in self.windows:
                return store._flush_failed(sqlite3.OperationalError(
                    "database or disk is full"))
            return original(store, retry)

        monkeypatch.setattr(StateStore, "_flush", flush)


def rerun_exe() -> str:
    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if exe is None:
        pytest.skip("the rerun CLI is not installed")
    return exe


def machine_config(directory: Path, name: str, *, port: int | None, duration: float = 1200.0,
                   realtime: bool = True, driver: str | None = None) -> Path:
    """The simulated motor's example configuration as machine ``name`` of a gateway: Zenoh on
    127.0.0.1:``port`` (None: off), no recording, the plant paced by the wall clock."""
    text = SIM.replace('name = "dc-motor-sim"', f'name = "{name}"')
    text = text.replace("duration = 1200.0", f"duration = {duration}")
    text = text.replace("realtime = false", f"realtime = {str(realtime).lower()}")
    text = text.replace("[recording]", "[recording]\nenabled = false")
    if port is None:
        text = text.replace("[zenoh]", "[zenoh]\nenabled = false")
    else:
        text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    if driver is not None:
        start, end = text.index("[driver]"), text.index("[zenoh]")
        text = text[:start] + driver.strip() + "\n\n" + text[end:]
    path = directory / f"{name}.toml"
    path.write_text(text)
    return path


def check_machine(cfg: Any, path: Path, work_dir: Path) -> None:
    check_runnable(cfg, str(path), base_dir=path.parent, cwd=work_dir)


def watch_daemon_config(name: str, connect: str, *, degraded: bool = False) -> str:
    text = SIM.replace('name = "dc-motor-sim"', f'name = "{name}"')
    text = text.replace('mode = "peer"  ', 'mode = "client"')
    text = text.replace('listen = ["tcp/127.0.0.1:7447"]', f'connect = ["{connect}"]')
    text = text.replace("\nconnect = []", "")
    text = text.replace("[recording]", "[recording]\nenabled = false")
    text = text.replace("realtime = false", "realtime = true")
    if degraded:  # Ra 13 % below the nameplate (the plant's is 6.5 ohm): alarm at once
        text = text.replace("Ra = 6.5          # ohm", "Ra = 7.5          # ohm")
        text = text.replace("raise_after_s = 10.0", "raise_after_s = 2.0")
        # the alarm rule's key only ([diagnosis] has a commented key of the same name)
        text = text.replace("# raise_after_windows = 3      # ... and at least",
                            "raise_after_windows = 1        # ... and at least")
        assert "raise_after_windows = 1 " in text
    assert f'connect = ["{connect}"]' in text and "realtime = true" in text
    return text


def watch_env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT), CI="true", COLUMNS="200")
