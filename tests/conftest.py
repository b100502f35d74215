"""Shared fixtures: plant windows and paths to ../shared data."""

from __future__ import annotations

import signal
import threading
from pathlib import Path

import numpy as np
import pytest

from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
from twinwatch.twin.model import WindowData

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def shared_path(*parts: str) -> Path:
    """Path under ../shared, or skip the test with a clear reason if it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} not present: the shared data directory is not beside the repository")
    return p


def plant_windows(config: DCMotorPlantConfig, n_windows: int, *, skip: int = 0,
                  window: int = 200) -> tuple[DCMotorPlant, list[WindowData]]:
    """Run the plant and cut its samples into windows (no bus: for twin-level tests)."""
    plant = DCMotorPlant(config)
    for _ in range(skip * window):
        plant.next_sample()
    wins = []
    for k in range(n_windows):
        ss = [plant.next_sample() for _ in range(window)]
        wins.append(WindowData(
            t=np.array([s.t for s in ss]),
            channels={c: np.array([s.values[c] for s in ss]) for c in ss[0].values},
            index=skip + k))
    return plant, wins


@pytest.fixture(autouse=True)
def _no_leaked_threads():
    """Fail a test that leaves threads behind (as pymodbus' conftest does)."""
    before = set(threading.enumerate())
    yield
    leaked = [t for t in threading.enumerate()
              if t not in before and t.is_alive() and not t.name.startswith(("pydevd", "zenoh"))]
    for t in leaked:
        t.join(timeout=2.0)
    leaked = [t for t in leaked if t.is_alive()]
    assert not leaked, f"threads leaked: {[t.name for t in leaked]}"


#: What every test starts and ends with: SIGINT raises KeyboardInterrupt, SIGTERM and SIGHUP
#: their default action. Not what the session started with: a test run started as a background
#: job of a non-interactive shell (``pytest &``, a CI runner) inherits SIGINT ignored, and an
#: ignored signal stays ignored in every child process (a handled one is reset to its default
#: at exec), so the recorder and watch tests' children ignored the SIGINT they were sent.
_DISPOSITIONS = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL,
                 signal.SIGHUP: signal.SIG_DFL}


def _restore_dispositions() -> None:
    for n, h in _DISPOSITIONS.items():
        if signal.getsignal(n) is not h:
            signal.signal(n, h)


_restore_dispositions()


@pytest.fixture(autouse=True)
def _signal_dispositions_restored():
    """Give every test the signal dispositions of ``_DISPOSITIONS``, before and after it.
    `twinwatch run` invoked in-process (click's CliRunner) ends by ignoring SIGTERM and SIGINT
    at the OS level (``cli._ignore_late_stops``: a late stop must not kill a process that
    stopped cleanly); an ignored disposition is inherited by every child process. Restored
    *before* each test too: a module-scoped fixture that runs the CLI in-process
    (test_prognostics_resume, test_mqtt_docs) runs outside any test's own restore."""
    _restore_dispositions()
    yield
    _restore_dispositions()
