"""Interpretable diagnosis: from the windows' data to the failing part and what to do (the
paper's open last step, Section 6).

* :mod:`~twinwatch.twin.diagnosis.library`: the fault library per machine model, as data
  (shipped TOML, extended by ``[diagnosis]``): each fault mode a change of the twin;
* :mod:`~twinwatch.twin.diagnosis.hypotheses`: a change's twin and its sensitivity on one
  window, and its evidence over the windows since its change point;
* :mod:`~twinwatch.twin.diagnosis.engine`: this machine's healthy baseline and every fault
  mode's twin, window after window (:class:`~twinwatch.twin.diagnosis.engine.HypothesisBank`);
* :mod:`~twinwatch.twin.diagnosis.inference`: the posterior over the fault modes with the
  evidence for and against each (:class:`Diagnoser`).

docs/diagnosis.md describes the library's format, the method and its figures.
"""

from __future__ import annotations

from twinwatch.twin.diagnosis.inference import Diagnoser, shaft_speed
from twinwatch.twin.diagnosis.library import (
    DiagnosisConfig,
    FaultLibrary,
    FaultMode,
    load_library,
    shipped_library,
)

__all__ = ["Diagnoser", "DiagnosisConfig", "FaultLibrary", "FaultMode", "load_library",
           "shaft_speed", "shipped_library"]
