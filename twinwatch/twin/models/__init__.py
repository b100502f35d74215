"""The machines: one module per twin model, and the model registry.

A new machine is one :class:`~twinwatch.twin.model.TwinModel` subclass in one module plus one line
in :data:`BUILTIN_MODELS` (or, from another package, an entry in the ``twinwatch.models``
entry-point group: ``name = "package.module:Class"``); nothing in the daemon changes.

May import :mod:`twinwatch.twin.model` (the contract), :mod:`twinwatch.io.drive` (how a drive's
controller runs) and this room; never the estimation, the discovery or anything outside the twin.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from twinwatch.plugins import Registry
from twinwatch.twin.model import TwinModel

__all__ = ["BUILTIN_MODELS", "ENTRY_POINT_GROUP", "MODELS", "create_model", "get_model_class"]

#: Entry-point group through which other packages add machines.
ENTRY_POINT_GROUP = "twinwatch.models"

#: Built-in machines: name -> "module:Class".
BUILTIN_MODELS: Mapping[str, str] = {
    "dc_motor": "twinwatch.twin.models.dcmotor:DCMotorTwin",
    "hydraulic_actuator": "twinwatch.twin.models.hydraulic:HydraulicActuatorTwin",
    "dc_motor_pwm": "twinwatch.twin.models.pwm_dcmotor:PWMDCMotorTwin",
}

#: The model registry (:class:`twinwatch.plugins.Registry`).
MODELS: Registry[TwinModel] = Registry("model", ENTRY_POINT_GROUP, BUILTIN_MODELS,
                                       base=lambda: TwinModel)


def get_model_class(name: str) -> type[TwinModel]:
    """The twin model class registered as ``name``.

    Raises:
        twinwatch.errors.PluginError: (a ValueError) unknown model, or its module cannot be
            imported.
    """
    return MODELS.load(name)


def create_model(name: str, options: dict[str, Any] | None = None) -> TwinModel:
    """Instantiate the twin model ``name`` with its ``options`` (constructor keywords).

    Raises:
        ValueError: unknown model (:class:`~twinwatch.errors.PluginError`) or bad option (the
            message names the option).
    """
    cls = get_model_class(name)
    try:
        return cls(**(options or {}))
    except TypeError as exc:
        raise ValueError(f"bad option for model {name!r}: {exc}") from exc

