"""Twin model registry: model name in the config -> class.

A new machine plugs in here (or through the ``twinwatch.models`` entry-point group) with a
:class:`~twinwatch.twin.model.TwinModel` subclass; nothing in the daemon changes.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from twinwatch.twin.model import TwinModel

#: name -> (module, class)
BUILTIN_MODELS: dict[str, tuple[str, str]] = {
    "dc_motor": ("twinwatch.twin.models.dcmotor", "DCMotorTwin"),
    "hydraulic_actuator": ("twinwatch.twin.models.hydraulic", "HydraulicActuatorTwin"),
    "dc_motor_pwm": ("twinwatch.twin.models.pwm_dcmotor", "PWMDCMotorTwin"),
}


def available_models() -> dict[str, tuple[str, str]]:
    table = dict(BUILTIN_MODELS)
    for ep in entry_points(group="twinwatch.models"):
        module, _, cls = ep.value.partition(":")
        table[ep.name] = (module, cls)
    return table


def create_model(name: str, options: dict[str, Any] | None = None) -> TwinModel:
    """Instantiate the twin model ``name`` with its ``options`` (constructor keywords).

    Raises:
        ValueError: unknown model or bad option (the message names the option).
    """
    table = available_models()
    if name not in table:
        raise ValueError(f"unknown model {name!r}; available: {sorted(table)}")
    module, cls_name = table[name]
    cls = getattr(importlib.import_module(module), cls_name)
    try:
        model: TwinModel = cls(**(options or {}))
    except TypeError as exc:
        raise ValueError(f"bad option for model {name!r}: {exc}") from exc
    return model
