"""The health report: one JSON-serialisable message per window (paper Section 3.2: "the drift
of the estimates over time is the machine's health").

The message layout is documented in the README ("The health message"); keep both in step.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from twinwatch.twin.estimation import WindowEstimate
from twinwatch.twin.model import TwinModel, WindowData

if TYPE_CHECKING:
    from twinwatch.twin.adaptation import AdaptationResult

SCHEMA_VERSION = 2


def _num(x: float) -> float | None:
    """JSON has no NaN/inf: report them as null."""
    return float(x) if math.isfinite(x) else None


def build_health(
    *,
    machine: str,
    model_name: str,
    model: TwinModel,
    window: WindowData,
    estimate: WindowEstimate,
    nominal: Mapping[str, float],
    counters: Mapping[str, int] | None = None,
    adaptation: AdaptationResult | None = None,
    discovery_enabled: bool = False,
) -> dict[str, Any]:
    """Build the health message of one window.

    Args:
        machine: machine name (the Zenoh key segment).
        model_name: registry name of the twin model (``dc_motor``).
        model: the twin (for units).
        window: the estimated window (for its index and time span).
        estimate: the window's estimate.
        nominal: parameter -> nominal (nameplate) value the deviation is measured from.
        counters: daemon and driver counters (windows, overruns, bad frames, ...).
        adaptation: the window's adaptation (meta-model terms, DT' and DT'' residuals,
            discovery status); without it ``terms`` is empty.
        discovery_enabled: whether the machine's configuration enables discovery.

    Returns:
        A dict ready for ``json.dumps``: see the README for every field.
    """
    params: dict[str, Any] = {}
    for spec in model.parameters:
        value = estimate.values[spec.name]
        nom = float(nominal.get(spec.name, spec.nominal))
        held = spec.name in estimate.held
        rel = estimate.rel_std.get(spec.name)
        params[spec.name] = {
            "value": _num(value),
            "unit": spec.unit,
            "nominal": nom,
            "deviation_pct": _num((value / nom - 1.0) * 100.0) if nom else None,
            "held": held,
            "reason": estimate.held.get(spec.name),
            "rel_std_pct": _num(rel * 100.0) if rel is not None else None,
        }
    extra: dict[str, Any] = (adaptation.health_fields(discovery_enabled) if adaptation
                             else {"terms": [], "residual": None, "discovery": None})
    return {
        "schema": SCHEMA_VERSION,
        "machine": machine,
        "model": model_name,
        "window": int(window.index),
        "t_start": float(window.t[0]),
        "t_end": float(window.t[-1]),
        "samples": int(window.n),
        "parameters": params,
        "rmse": {k: _num(v) for k, v in estimate.rmse.items()},
        "nrmse": _num(estimate.nrmse),
        "trusted": estimate.trusted,
        "elapsed_s": estimate.elapsed_s,
        "generations": estimate.generations,
        "time_capped": estimate.time_capped,
        "evaluations": estimate.evaluations,
        **extra,
        "counters": dict(counters or {}),
    }


def summary_line(health: Mapping[str, Any]) -> str:
    """One line for logs and the Rerun text log: estimates, held ones marked with '='."""
    parts = []
    for name, p in health["parameters"].items():
        if p["reason"] and (p["reason"].startswith("fixed") or p["reason"].startswith("tied")):
            continue
        mark = "=" if p["held"] else ""
        dev = p["deviation_pct"]
        parts.append(f"{name}{mark}{p['value']:.5g} ({dev:+.2f}%)" if dev is not None
                     else f"{name}{mark}{p['value']}")
    nrmse = health.get("nrmse")
    rm = f"{nrmse:.2e}" if nrmse is not None else "n/a"
    terms = health.get("terms") or []
    extra = f" +{len(terms)} term{'s' if len(terms) > 1 else ''}" if terms else ""
    return (f"window {health['window']} [{health['t_start']:.2f}-{health['t_end']:.2f} s] "
            + " ".join(parts) + f"{extra} nRMSE {rm} in {health['elapsed_s'] * 1e3:.0f} ms")
