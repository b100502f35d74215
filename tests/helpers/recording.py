"""A Rerun recorder on made-up windows, and the ``rerun`` CLI that checks its files."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from twinwatch.sinks.rerun import RecordingConfig, RerunRecorder

RERUN_CLI = Path(sys.executable).with_name("rerun")
OUTPUTS = ("ia", "omega")
PARAMETERS = {"Ra": "ohm", "La": "H", "J": "kg m^2"}
N = 200  # samples per window
DT = 0.01  # sample period [s]
TIMEOUT = 60.0


def rerun_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    if not RERUN_CLI.exists():
        pytest.skip(f"rerun CLI not found at {RERUN_CLI}")
    return subprocess.run(
        [str(RERUN_CLI), *map(str, args)],
        env={**os.environ, "CI": "true"},
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )


def window(k: int) -> dict[str, Any]:
    """Arguments of log_window for window ``k`` (200 samples at 10 ms, starting at 2k s)."""
    t = k * N * DT + DT * np.arange(N)
    return {
        "t": t,
        "measured": {"ia": np.sin(t), "omega": 100 * np.cos(t)},
        "simulated": {"ia": 0.9 * np.sin(t), "omega": 99 * np.cos(t)},
        "parameters": {"Ra": 1.2 + 0.1 * k, "La": np.float64(2e-3), "J": 1e-4},
        "health": {"machine": "m1", "window": k, "status": "ok", "rmse": np.float32(0.05)},
    }


def recorder(path: Path, machine: str = "m1") -> RerunRecorder:
    return RerunRecorder(
        RecordingConfig(path=str(path)), machine, outputs=OUTPUTS, parameters=PARAMETERS
    )
