"""The simulated DC motor's samples cut into windows, for twin-level tests (no bus)."""

from __future__ import annotations

import numpy as np

from twinwatch.plant.dcmotor import DCMotorPlant, DCMotorPlantConfig
from twinwatch.twin.model import WindowData


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
