"""Shared fixtures: plant windows and paths to ../shared data."""

from __future__ import annotations

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
