"""Sample configurations, one per driver, printed by ``twinwatch sample-config [--driver X]``.

Each sample is a complete, valid configuration that documents every key of every table it uses
(optional keys commented out with their default): a header, the machine's tables (``[machine]``,
``[estimation]``, ``[discovery]``, ``[alarms]``), ``[acquisition]``, the driver's ``[driver]``
tables, then ``[zenoh]``, ``[recording]`` and ``[state]``. The parts live in ``samples/`` beside
this module and are shared: the DC motor's tables serve the simulated, CAN and file samples, the
hydraulic actuator's the Modbus ones. The ``simulated`` sample is the built-in default
(``default.toml``, ``config/dc-motor-sim.toml``); tests keep them equal.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DRIVERS", "sample_config"]

_DIR = Path(__file__).with_name("samples")

#: driver -> (machine part, machine name, what the sample runs)
DRIVERS: dict[str, tuple[str, str, str]] = {
    "simulated": ("dc_motor", "dc-motor-sim",
                  "the simulated DC motor (paper Section 5.2) over a virtual CAN bus"),
    "can": ("dc_motor", "dc-motor-can", "a DC motor drive on a CAN bus"),
    "file": ("dc_motor", "dc-motor-recording", "a DC motor recording replayed from a file"),
    "modbus": ("hydraulic_actuator", "hydraulic-modbus",
               "a hydraulic actuator read from a Modbus device"),
    "simulated_modbus": ("hydraulic_actuator", "hydraulic-sim",
                         "the simulated hydraulic actuator (paper Section 5.3) over Modbus TCP"),
}

_HEADER = """\
# twinwatch: {what}.
#
# `twinwatch sample-config --driver {driver}` printed this file; `twinwatch sample-config
# --driver simulated|can|file|modbus|simulated_modbus` prints the others. Every key is
# optional unless marked required; commented-out keys show their default; unknown keys are
# errors. Check a file with `twinwatch check-config FILE`; run it with `twinwatch run FILE`.
"""

_DEFAULT_HEADER = """\
# twinwatch: the simulated DC motor (paper Section 5.2) over a virtual CAN bus.
#
# This is the built-in default of `twinwatch run` (no config argument) and the output of
# `twinwatch sample-config`; `twinwatch sample-config --driver can|file|modbus|simulated_modbus`
# prints a complete example for each other driver. Every key is optional unless marked
# required; commented-out keys show their default; unknown keys are errors.
"""


def _part(name: str) -> str:
    return (_DIR / f"{name}.toml").read_text(encoding="utf-8").rstrip() + "\n"


def sample_config(driver: str = "simulated") -> str:
    """The sample configuration for ``driver`` (TOML text).

    Raises:
        KeyError: no sample for that driver (see :data:`DRIVERS`).
    """
    machine, name, what = DRIVERS[driver]
    header = _DEFAULT_HEADER if driver == "simulated" else _HEADER.format(what=what,
                                                                           driver=driver)
    text = "\n".join([header, _part(machine), _part("acquisition"), _part(f"driver_{driver}"),
                      _part("common")])
    text = text.replace('name = "dc-motor-sim"', f'name = "{name}"', 1)
    text = text.replace('name = "hydraulic-sim"', f'name = "{name}"', 1)
    if "@PLANT_DBC@" in text:
        # the simulated plant's DBC, shipped as package data beside the plant
        dbc = Path(__file__).resolve().parents[1] / "plant" / "dcmotor.dbc"
        text = text.replace("@PLANT_DBC@", str(dbc))
    return text
