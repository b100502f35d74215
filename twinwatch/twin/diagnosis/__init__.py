"""Interpretable diagnosis: from the twin's evidence to the failing part and what to do (the
paper's open last step, Section 6).

* :mod:`~twinwatch.twin.diagnosis.library`: the fault library per machine model, as data
  (shipped TOML, extended by ``[diagnosis]``);
* :mod:`~twinwatch.twin.diagnosis.evidence`: the evidence kinds a fault's signature lists
  (deviations, trends, terms, model check, output checks, sensors), each with the validation
  of its names and its likelihood, behind one registry (``EVIDENCE_KINDS``);
* :mod:`~twinwatch.twin.diagnosis.inference`: a noisy-OR network ranking the fault modes with
  their probabilities and the evidence for and against each (:class:`Diagnoser`).

docs/diagnosis.md describes the library's format, the inference and its priors.
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
