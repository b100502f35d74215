"""The sample a source delivers, and how it ends.

A source (an acquisition driver, :mod:`twinwatch.drivers`, or a simulated plant,
:mod:`twinwatch.plant`) delivers :class:`Sample` objects: one time stamp [s] and one value per
twin channel (for the DC motor ``Va``, ``ia``, ``omega``, ``Tload``, ``setpoint``). A finite
source (a file, a simulation of fixed duration) raises :class:`EndOfStream` after its last
sample. Channel names are the twin's, never the bus's; :class:`ScaledChannel` is how a source
value becomes a twin channel value.
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import ConfigDict, Field, StrictFloat

from twinwatch._table import StrictTable
from twinwatch.errors import DriverError, EndOfStream

__all__ = ["DriverError", "EndOfStream", "Sample", "ScaledChannel"]


@dataclass(frozen=True, slots=True)
class Sample:
    """One acquisition sample.

    Attributes:
        t: time stamp [s] on the source's clock (plant time for the simulated plant, the
            recording's time for a file, the frame's time stamp on a bus).
        values: twin channel name -> value in the twin's SI unit.
    """

    t: float
    values: dict[str, float]


class ScaledChannel(StrictTable):
    """How a source value becomes a twin channel value: ``value = raw * scale + offset``.

    Attributes:
        scale: factor to the twin's SI unit (e.g. 2*pi for rev/s -> rad/s).
        offset: added after scaling, in the twin's unit.
        unit: the twin channel's unit, for documentation and display.
    """

    model_config = ConfigDict(frozen=True)

    scale: StrictFloat = Field(default=1.0, allow_inf_nan=False)
    offset: StrictFloat = Field(default=0.0, allow_inf_nan=False)
    unit: str | None = None
