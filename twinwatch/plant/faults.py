"""Faults the simulated plants inject (``[[driver.plant.parameter_faults]]``, the sensor faults'
drift and ``[driver.plant.supply_fault]``): the shared time profile and its configuration.

A fault acts with a *size* ``f(t)`` in [0, 1] (0: absent, 1: full size)::

    f(t) = 0                                   t < start, or t >= end (repaired at end)
    f(t) = min(1, (t - start) / ramp)          a drift that grows linearly over ramp [s]
                                               (ramp = 0: a step at start)
    f(t) *= 1 if ((t - start) mod period) < duty * period else 0
                                               intermittent (period set): on for the first
                                               duty of each period after start

A parameter fault moves its parameter from the nominal value ``p0`` to ``p0 * (1 + f *
change / 100)`` (``change`` in percent at full size) or ``p0 + f * absolute`` (``absolute`` in
the parameter's unit: for a parameter whose nominal is 0, e.g. the DC motor's Coulomb friction
Tc). Several faults on one parameter add their changes. The plants evaluate the profile once
per acquisition sample and hold it over the sample's integration steps: a ramp is a staircase
of ``sample_period`` steps, which a window of seconds cannot tell from a line.

These are test injections (a part replaced or broken, wear, a load that comes and goes), not
laws from a reference.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from pydantic import Field, StrictFloat, model_validator

from twinwatch._table import StrictTable
from twinwatch.io.sample import EndOfStream

__all__ = ["FaultProfile", "ParameterFaultConfig", "SimulatedPlant", "SupplyFaultConfig",
           "check_plant_table"]


class FaultProfile(StrictTable):
    """When a fault acts and how it grows (see the module docstring for ``f(t)``)."""

    start: StrictFloat = Field(0.0, ge=0, description="onset [s of plant time]")
    ramp: StrictFloat = Field(0.0, ge=0, description="seconds from onset to full size: a "
                              "linear drift (0: a step at start)")
    end: StrictFloat | None = Field(None, gt=0, description="the fault is repaired at this "
                                    "time [s]: back to nominal (None: to the end of the run)")
    period: StrictFloat | None = Field(None, gt=0, description="intermittent: the fault is on "
                                       "for the first duty*period of every period [s] after "
                                       "start (None: continuously)")
    duty: StrictFloat = Field(0.5, gt=0, le=1, description="intermittent: the share of each "
                              "period the fault is on (0..1]")

    @model_validator(mode="after")
    def _check_profile(self) -> FaultProfile:
        if self.end is not None and self.end <= self.start:
            raise ValueError(f"end: {self.end:g} s must be after start ({self.start:g} s)")
        return self

    def size(self, t: float) -> float:
        """The fault's size f(t) in [0, 1] at plant time ``t`` [s]."""
        if t < self.start or (self.end is not None and t >= self.end):
            return 0.0
        age = t - self.start
        f = 1.0 if self.ramp <= 0.0 else min(1.0, age / self.ramp)
        if self.period is not None and (age % self.period) >= self.duty * self.period:
            return 0.0
        return f


class ParameterFaultConfig(FaultProfile):
    """A change of one physical parameter of the simulated plant
    (``[[driver.plant.parameter_faults]]``): the parameter moves by ``change`` percent of its
    nominal (or by ``absolute`` in its unit) at full size, with the profile's onset, ramp, end
    and intermittence. Exactly one of ``change`` and ``absolute``. Which parameters a plant
    accepts: its configuration's documentation."""

    parameter: str = Field(description="the plant parameter the fault moves")
    change: StrictFloat | None = Field(None, gt=-100, description="relative change at full "
                                       "size [% of the nominal value]")
    absolute: StrictFloat | None = Field(None, description="absolute change at full size "
                                         "[the parameter's unit]; for a parameter whose nominal "
                                         "is 0")

    @model_validator(mode="after")
    def _check_change(self) -> ParameterFaultConfig:
        if (self.change is None) == (self.absolute is None):
            raise ValueError("change, absolute: give exactly one (change in percent of the "
                             "nominal value, absolute in the parameter's unit)")
        return self

    def delta(self, nominal: float, t: float) -> float:
        """The change of the parameter at plant time ``t`` [s] from its ``nominal`` value [the
        parameter's unit]."""
        f = self.size(t)
        if f == 0.0:
            return 0.0
        if self.absolute is not None:
            return f * self.absolute
        return f * nominal * (self.change or 0.0) / 100.0


class SupplyFaultConfig(FaultProfile):
    """A supply that delivers less than the drive commands (``[driver.plant.supply_fault]``):
    the load receives ``1 + f(t) * (ratio - 1)`` times the commanded quantity while the reported
    command is unchanged (a sagging DC bus behind an open-loop voltage drive, a worn stage)."""

    ratio: StrictFloat = Field(gt=0, description="delivered over commanded at full size "
                               "(e.g. 0.9: 10 % sag)")

    def factor(self, t: float) -> float:
        """Delivered over commanded at plant time ``t`` [s]."""
        return 1.0 + self.size(t) * (self.ratio - 1.0)


def check_plant_table(config: Any, channels: tuple[str, ...], fault_parameters: Mapping[str, str],
                      per_channel: Mapping[str, Mapping[str, float]]) -> None:
    """The checks every simulated plant's table shares (called by its ``model_validator``).

    Args:
        config: the plant's table: ``sample_period`` and ``step`` [s], ``sensor_faults``,
            ``parameter_faults`` and ``fault_nominals()`` (parameter -> nominal value).
        channels: the plant's channels.
        fault_parameters: the parameters a fault may change -> their units.
        per_channel: the tables keyed by channel (``{"noise": config.noise, ...}``): known
            channels only, values >= 0.

    Raises:
        ValueError: the sample period is not a whole multiple of the step, a table names an
            unknown channel or parameter, or a fault changes by a percentage a parameter that
            is 0 at nominal.
    """
    ratio = config.sample_period / config.step
    if abs(ratio - round(ratio)) > 1e-6 * ratio or round(ratio) < 1:
        raise ValueError("sample_period must be a whole multiple of step")
    for name, table in per_channel.items():
        for ch, v in table.items():
            if ch not in channels:
                raise ValueError(f"{name}.{ch}: unknown channel; use one of {channels}")
            if v < 0:
                raise ValueError(f"{name}.{ch}: must be >= 0")
    for i, fault in enumerate(config.sensor_faults):
        if fault.channel not in channels:
            raise ValueError(f"sensor_faults[{i}].channel: unknown channel "
                             f"{fault.channel!r}; use one of {channels}")
    nominal = config.fault_nominals()
    for i, pf in enumerate(config.parameter_faults):
        if pf.parameter not in fault_parameters:
            raise ValueError(f"parameter_faults[{i}].parameter: unknown parameter "
                             f"{pf.parameter!r}; use one of {tuple(fault_parameters)}")
        if pf.change is not None and nominal[pf.parameter] == 0.0:
            raise ValueError(f"parameter_faults[{i}].change: {pf.parameter} is 0 at "
                             f"nominal, a percentage of it is nothing; give absolute "
                             f"[{fault_parameters[pf.parameter]}]")


class SimulatedPlant:
    """What the simulated plants share: the sample clock, the parameter faults' values and the
    reported values' noise, quantisation and sensor faults.

    Args:
        config: the plant's table (``sample_period``, ``step``, ``duration`` [s], ``seed``,
            ``noise``, ``sensor_faults``, ``parameter_faults``, ``fault_nominals()``).
    """

    config: Any

    def __init__(self, config: Any) -> None:
        self.sample_period = config.sample_period
        self.n_sub = int(round(config.sample_period / config.step))
        self._nominal: dict[str, float] = config.fault_nominals()
        self._frozen: dict[int, float] = {}  # a frozen sensor's reading
        self._k = 0  # sample index
        self._n_samples = int(round(config.duration / config.sample_period)) + 1
        self._rng = np.random.default_rng(config.seed)

    @property
    def t(self) -> float:
        """Plant time of the next sample [s]."""
        return self._k * self.sample_period

    def _check_end(self) -> None:
        """Raises :class:`EndOfStream` once the plant has reached its duration."""
        if self._k >= self._n_samples:
            raise EndOfStream(f"simulated plant reached its duration ({self.config.duration} s)")

    def _faulted(self, t: float) -> dict[str, float]:
        """Every parameter a parameter fault may move, at plant time ``t`` [s] (the nominal
        plus the faults' changes; the scenarios' laws not included)."""
        values = dict(self._nominal)
        for pf in self.config.parameter_faults:
            values[pf.parameter] += pf.delta(self._nominal[pf.parameter], t)
        return values

    def _report(self, values: dict[str, float], t: float,
                quantisation: Mapping[str, float]) -> None:
        """The reported ``values`` at ``t`` [s], in place: Gaussian noise (``config.noise``,
        percent of reading), then ``quantisation`` (channel -> step), then the sensor faults."""
        for ch, pct in self.config.noise.items():
            if pct > 0:
                values[ch] += float(self._rng.normal(0.0, pct / 100.0 * abs(values[ch])))
        for ch, q in quantisation.items():
            if q > 0:
                values[ch] = round(values[ch] / q) * q
        for fault in self.config.sensor_faults:
            values[fault.channel] = fault.apply(values[fault.channel], t, self._frozen)
