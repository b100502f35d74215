"""Sample configurations, one per driver, printed by ``twinwatch sample-config [--driver X]``.

Each sample is a complete, valid configuration that documents every key of every table it uses
(optional keys commented out with their default): a header, the machine's tables,
``[acquisition]``, the driver's tables, then the outputs' (each other installed output's
``[outputs.<name>]`` commented out). A built-in ships its part in ``samples/`` beside this
module (``driver_<name>.toml``, ``common.toml``); a plug-in's is generated from its
configuration model (:meth:`twinwatch.drivers.Driver.sample`,
:meth:`twinwatch.sinks.base.Sink.sample`). The machine's tables are a driver's
``sample_model``'s. The ``simulated`` sample is the built-in default (``default.toml``,
``config/dc-motor-sim.toml``); tests keep them equal.
"""

from __future__ import annotations

from pathlib import Path

from twinwatch.drivers import DRIVERS, get_driver_class
from twinwatch.errors import PluginError
from twinwatch.sinks import HISTORIC_TABLES, SINKS, output_key, sink_class

__all__ = ["driver_names", "sample_config"]

_DIR = Path(__file__).with_name("samples")

_HEADER = """\
# twinwatch: {what}.
#
# `twinwatch sample-config --driver {driver}` printed this file; `twinwatch sample-config
# --driver {drivers}` prints the others. Every key is
# optional unless marked required; commented-out keys show their default; unknown keys are
# errors. Check a file with `twinwatch check-config FILE`; run it with `twinwatch run FILE`.
"""

_DEFAULT_HEADER = """\
# twinwatch: the simulated DC motor (paper Section 5.2) over a virtual CAN bus.
#
# This is the built-in default of `twinwatch run` (no config argument) and the output of
# `twinwatch sample-config`; `twinwatch sample-config --driver {drivers}`
# prints a complete example for each other driver. Every key is optional unless marked
# required; commented-out keys show their default; unknown keys are errors.
"""

_DEFAULT_DRIVER = "simulated"


def driver_names() -> list[str]:
    """Every driver a sample can be printed for: the driver registry's names."""
    return DRIVERS.names()


def _part(name: str) -> str:
    return (_DIR / f"{name}.toml").read_text(encoding="utf-8").rstrip() + "\n"


def _driver_part(driver: str) -> tuple[str, str, str, str]:
    """(machine part, machine name, what the sample runs, the ``[driver]`` part)."""
    cls = get_driver_class(driver)
    own = _DIR / f"driver_{driver}.toml"
    part = own.read_text(encoding="utf-8").rstrip() + "\n" if own.is_file() else cls.sample(
        driver)
    machine = cls.sample_machine or f"{cls.sample_model.replace('_', '-')}-{driver}"
    what = cls.sample_title or (cls.__doc__ or driver).strip().splitlines()[0].rstrip(".")
    return cls.sample_model, machine, what, part


def _outputs_part() -> str:
    """The outputs configured under ``[outputs.<name>]`` (plug-ins): each one's commented
    sample table, or why it is not available."""
    parts = []
    for name in SINKS:
        if name in HISTORIC_TABLES:
            continue
        try:
            parts.append(sink_class(name).sample(output_key(name)).rstrip() + "\n")
        except PluginError as exc:
            parts.append(f"# [{output_key(name)}]: not available: {exc}\n")
    return "\n".join(parts)


def sample_config(driver: str = _DEFAULT_DRIVER) -> str:
    """The sample configuration for ``driver`` (TOML text).

    Raises:
        KeyError: no driver of that name (see :func:`driver_names`), or no sample of the
            machine it monitors.
    """
    if driver not in DRIVERS:
        raise KeyError(f"unknown driver {driver!r}; known: {', '.join(driver_names())}")
    machine, name, what, driver_part = _driver_part(driver)
    if not (_DIR / f"{machine}.toml").is_file():
        raise KeyError(f"no sample of the {machine!r} machine (the {driver!r} driver's "
                       f"sample_model)")
    others = "|".join(n for n in driver_names() if n != _DEFAULT_DRIVER)
    header = (_DEFAULT_HEADER.format(drivers=others) if driver == _DEFAULT_DRIVER else
              _HEADER.format(what=what, driver=driver, drivers="|".join(driver_names())))
    parts = [header, _part(machine), _part("acquisition"), driver_part, _part("common")]
    outputs = _outputs_part()
    if outputs:
        parts.append(outputs)
    text = "\n".join(parts)
    text = text.replace('name = "dc-motor-sim"', f'name = "{name}"', 1)
    text = text.replace('name = "hydraulic-sim"', f'name = "{name}"', 1)
    if "@PLANT_DBC@" in text:
        # the simulated plant's DBC, shipped as package data beside the plant
        dbc = Path(__file__).resolve().parents[1] / "plant" / "dcmotor.dbc"
        text = text.replace("@PLANT_DBC@", str(dbc))
    return text
