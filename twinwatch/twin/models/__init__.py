"""The machines: one module per twin model, and the model registry.

A new machine is one :class:`~twinwatch.twin.model.TwinModel` subclass in one module plus one line
in :data:`BUILTIN_MODELS` (or, from another package, an entry in the ``twinwatch.models``
entry-point group: ``name = "package.module:Class"``); nothing in the daemon changes.

May import :mod:`twinwatch.twin.model` (the contract), :mod:`twinwatch.io.drive` (how a drive's
controller runs) and this room; never the estimation, the discovery or anything outside the twin.
"""

from __future__ import annotations

import dataclasses
import types
import typing
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
    bad = _booleans_for_numbers(cls, options or {})
    if bad:
        raise ValueError(f"bad option for model {name!r}: " + "; ".join(
            f"{key} = {value!r}: a boolean is not a number" for key, value in bad))
    try:
        return cls(**(options or {}))
    except TypeError as exc:
        raise ValueError(f"bad option for model {name!r}: {exc}") from exc



def _number_types(annotation: Any) -> set[type]:
    """The plain types an option's annotation admits (unions and ``Annotated`` unwrapped)."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _number_types(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return {t for a in typing.get_args(annotation) for t in _number_types(a)}
    return {annotation} if isinstance(annotation, type) else set()


def _booleans_for_numbers(cls: type, options: Mapping[str, Any]) -> list[tuple[str, Any]]:
    """Options given ``true``/``false`` where the model's dataclass field takes a number (``int``
    or ``float``, not ``bool``): Python would take them as 1 and 0."""
    if not dataclasses.is_dataclass(cls):
        return []
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - an unresolvable annotation: nothing to check against
        return []
    bad = []
    for key, value in options.items():
        admitted = _number_types(hints.get(key))
        if isinstance(value, bool) and bool not in admitted and admitted & {int, float}:
            bad.append((key, value))
    return bad
