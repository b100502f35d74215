"""Acquisition drivers and their registry.

Like python-can's ``can/interfaces/__init__.py``: a table maps a driver name (the ``type`` of a
``[driver]`` table) to the module and class implementing it, extended by the entry-point group
``twinwatch.drivers``; a driver's module is imported only when that driver is used.
:func:`validate_driver_config` is how the configuration loader validates a ``[driver]`` table.
Adding a driver: docs/extending.md. The base contract (:class:`Driver`, :class:`Sample`, the
errors) is re-exported here.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from twinwatch.drivers.base import (
    Driver,
    DriverConfig,
    DriverConfigError,
    DriverError,
    DriverInitializationError,
    DriverOperationError,
    DriverStats,
    EndOfStream,
    Sample,
)
from twinwatch.errors import PluginError
from twinwatch.plugins import Registry

logger = logging.getLogger(__name__)

__all__ = [
    "BUILTIN_DRIVERS",
    "DRIVERS",
    "ENTRY_POINT_GROUP",
    "Driver",
    "DriverConfig",
    "DriverConfigError",
    "DriverError",
    "DriverInitializationError",
    "DriverOperationError",
    "DriverStats",
    "EndOfStream",
    "Sample",
    "create_driver",
    "get_driver_class",
    "validate_driver_config",
]

#: Entry-point group through which other packages add drivers.
ENTRY_POINT_GROUP = "twinwatch.drivers"

#: Built-in drivers: name => "module:Class".
BUILTIN_DRIVERS: Mapping[str, str] = {
    "can": "twinwatch.drivers.can:CanDriver",
    "canopen": "twinwatch.drivers.canopen:CanopenDriver",
    "file": "twinwatch.drivers.file:FileDriver",
    "modbus": "twinwatch.drivers.modbus:ModbusDriver",
    "opcua": "twinwatch.drivers.opcua:OpcUaDriver",
    "simulated": "twinwatch.drivers.simulated:SimulatedDriver",
    "simulated_canopen": "twinwatch.drivers.simulated_canopen:SimulatedCanopenDriver",
    "simulated_modbus": "twinwatch.drivers.simulated_modbus:SimulatedModbusDriver",
    "simulated_opcua": "twinwatch.drivers.simulated_opcua:SimulatedOpcUaDriver",
}

#: The driver registry (:class:`twinwatch.plugins.Registry`): the built-ins and the entry points.
DRIVERS: Registry[Driver] = Registry("driver", ENTRY_POINT_GROUP, BUILTIN_DRIVERS,
                                     base=lambda: Driver)


def get_driver_class(name: str) -> type[Driver]:
    """Import and return the driver class registered as ``name``.

    Raises:
        DriverConfigError: no driver has that name (the message lists the known ones).
        DriverInitializationError: its module cannot be imported (a missing optional
            dependency: the message says what to install), or it does not define a
            :class:`Driver` subclass.
    """
    if name not in DRIVERS:
        raise DriverConfigError(f"unknown driver {name!r}; known drivers: "
                                f"{', '.join(sorted(DRIVERS.names()))}")
    try:
        return DRIVERS.load(name)
    except PluginError as exc:
        raise DriverInitializationError(str(exc)) from exc


def validate_driver_config(table: Mapping[str, Any] | DriverConfig) -> DriverConfig:
    """Validate a ``[driver]`` table with the model of the driver its ``type`` names.

    Only that driver's module is imported (a built-in one or an entry point's).

    Args:
        table: the raw table, or an already validated driver configuration (returned as is
            if it is an instance of the named driver's :attr:`~Driver.config_class`).

    Raises:
        DriverInitializationError: no ``type``, an unknown type (the message names the known
            ones), a driver that cannot be imported, or one that declares no config class.
        pydantic.ValidationError: the table does not fit the driver's model (each error's
            location is relative to the table, e.g. ``("signals", "ia", "message")``).
    """
    name = table.type if isinstance(table, DriverConfig) else table.get("type")
    if not isinstance(name, str):
        raise DriverInitializationError(
            f"required key is missing (the driver's name; known drivers: "
            f"{', '.join(sorted(DRIVERS.names()))})")
    cls = get_driver_class(name)
    model = getattr(cls, "config_class", None)
    if not (isinstance(model, type) and issubclass(model, DriverConfig)):
        raise DriverInitializationError(
            f"driver {name!r}: {cls.__module__}.{cls.__name__} declares no config_class "
            "(a twinwatch.drivers.DriverConfig subclass)")
    if isinstance(table, model):
        return table
    data = table.model_dump() if isinstance(table, DriverConfig) else table
    return model.model_validate(data)


def create_driver(config: Any, *, base_dir: Path, **kwargs: Any) -> Driver:
    """Create the driver that ``config`` describes.

    Args:
        config: a driver configuration model (with a ``type`` attribute, e.g.
            :class:`~twinwatch.drivers.can.CanDriverConfig`) or a raw mapping with a ``"type"``
            key (the ``[driver]`` table of a machine config).
        base_dir: directory against which relative paths in the configuration are resolved
            (the configuration file's directory).
        **kwargs: passed on to the driver's ``from_config`` (e.g. ``bus=`` for ``"can"``).

    Returns:
        An open driver; the caller closes it (or uses it as a context manager).

    Raises:
        DriverInitializationError: unknown or unavailable driver, invalid configuration, or
            the driver could not be opened.
    """
    name = config.get("type") if isinstance(config, Mapping) else getattr(config, "type", None)
    if not isinstance(name, str):
        raise DriverInitializationError("driver configuration has no 'type'")
    cls = get_driver_class(name)
    driver = cls.from_config(config, base_dir=base_dir, **kwargs)
    if not isinstance(driver, Driver):
        raise DriverInitializationError(f"driver {name!r}: from_config() returned {driver!r}")
    return driver
