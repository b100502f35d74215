"""What the tests and the benchmarks run twinwatch with, as a user and a plant would: the
simulated machine's sources as real machines deliver them (:mod:`harness.sources`: CAN logs, a
socketcand gateway, a Modbus device, CSV files) and the daemon as the unit runs it
(:mod:`harness.daemon`: the example configuration made short, ``twinwatch run`` in a
subprocess, its state database read).

Shared by ``tests/`` and ``benchmarks/``, part of neither and not of the installed package
(``pyproject.toml`` packages ``twinwatch*`` only): a benchmark imports nothing of ``tests``,
and the tests' own helpers are in ``tests/helpers/``.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root."""

SHARED = ROOT.parent / "shared"
"""The shared data directory beside the repository (recordings, vendor DBCs), when present."""
