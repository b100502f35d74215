"""How a drive's controller runs: the description shared by a closed-loop twin and a plant.

A real drive does not run its controller continuously: it samples its feedback every controller
period, computes a new output, and holds that output until the next update (zero-order hold),
clamped to what its power stage can deliver. A twin that updates the controller on every
integration sub-step, or not at all, is biased against such a drive (0.7-2.9 % on Ra).
:class:`LoopConfig` and :class:`DriveConfig` state the controller as the drive runs it; the twin
(:mod:`twinwatch.twin.models.dcmotor`, :mod:`twinwatch.twin.models.hydraulic`) and the
simulated plants (:mod:`twinwatch.plant`) each implement exactly this algorithm, in their own code.

**One update (tick)** of a loop, at time ``t_c = phase + j*period``, from the feedback ``y`` and the
reference ``r`` at ``t_c``::

    e      = r - y               (action "reverse", e.g. speed: more error, more voltage)
           = y - r               (action "direct", e.g. a valve that lowers the piston)
    d      = N*(kd*e - f)/(1 + c_d*N*T)     (derivative through its filter state f, paper Eq. 17)
    u_pid  = kp*e + I + c_i*ki*T*e + d + kff*r
    u      = clip(u_pid, output_min, output_max)
    I     += ki*T*e              unless anti-windup "clamping" and u_pid is beyond a limit with
                                 e pushing further into it
    I     += ki*T*e + (T/Tt)*(u - u_pid)     with anti-windup "back_calculation"
    f     += T*d

``T`` is the period; ``u`` is applied from ``t_c`` until the next tick. ``I`` is the integrator's
state in the output's unit (``I = ki*z`` with ``z`` the integral of the error up to the previous
tick). With a current loop, the speed loop's output is the current reference and the current
loop's output is the armature voltage; the current loop ticks every ``current_period``
(default: the drive's period).

**Integrator and filter methods** (``integrator_method``, ``filter_method``; MATLAB's Discrete
PID Controller block: ``C(z) = kp + ki*Fi(z) + kd*N/(1 + N*Fd(z))``, each formula ``Fi``, ``Fd``
one of forward Euler ``T/(z - 1)``, backward Euler ``T*z/(z - 1)`` or trapezoidal
``(T/2)*(z + 1)/(z - 1)``). In the update above ``c_i`` (the integrator's)
and ``c_d`` (the derivative filter's) are 0 for ``forward_euler`` (the default), 1 for
``backward_euler`` (a firmware that integrates before it computes its output) and 1/2 for
``trapezoidal``; the state update is the same for all three. With "clamping" the decision uses
``u_pid`` as computed and a clamped tick adds nothing to the state.

**Initial state of a window.** A twin starts every window from the measured state; the controller's
integrator is recovered from the measured output of the window's first tick (``I = u - kp*e -
c_i*ki*T*e - kff*r - d``; exact when a tick falls on the sample, which ``phase`` aligns).
While the output sits at a limit, the twin drives the plant with the measured output until the
first sample inside the limits, and restarts from the measured state there. The derivative
filter starts at rest (``f = kd*e``); with a current loop the speed loop's integrator is
recovered from the channel ``current_reference``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, StrictFloat, field_validator, model_validator

from twinwatch._table import StrictTable

FloatArray = NDArray[np.float64]

#: Anti-windup codes in :func:`LoopConfig.pack`.
ANTI_WINDUP = {"none": 0, "clamping": 1, "back_calculation": 2}

#: Discretisation methods (MATLAB's Discrete PID Controller: Integrator method, Filter method)
#: -> the share ``c`` of this tick's input in the integrator's output (module docstring).
METHODS = {"forward_euler": 0.0, "backward_euler": 1.0, "trapezoidal": 0.5}

#: Layout of :meth:`LoopConfig.pack` (the numba kernels read these positions).
PACKED = ("kp", "ki", "kd", "n_filter", "output_min", "output_max", "anti_windup",
          "tracking_time", "feedforward", "sign", "integrator_c", "filter_c")


class LoopConfig(StrictTable):
    """One discrete PID loop of a drive (see the module docstring for the update).

    Attributes:
        kp: proportional gain [output unit per error unit].
        ki: integral gain [output unit per (error unit * s)].
        kd: derivative gain [output unit * s per error unit]; needs ``n_filter``.
        n_filter: derivative filter coefficient N [1/s] (paper Eq. 17).
        output_min, output_max: output limits [output unit]; None: unlimited.
        anti_windup: ``clamping`` (stop integrating into a limit), ``back_calculation``
            (bleed the integrator with time constant ``tracking_time``) or ``none``.
        tracking_time: Tt [s] of back-calculation; default kp/ki (the integral time), or 1 s.
        feedforward: reference feed-forward gain kff [output unit per reference unit] (e.g. the
            back-EMF constant for a speed loop driving a voltage).
        action: ``reverse`` (e = r - y) or ``direct`` (e = y - r).
        integrator_method: how the integral is discretised (MATLAB's "Integrator method"):
            ``forward_euler`` (default: the output uses the integral up to the previous tick),
            ``backward_euler`` (up to and including this tick) or ``trapezoidal``.
        filter_method: the same for the derivative's filter (MATLAB's "Filter method").
    """

    kp: StrictFloat = Field(0.0, allow_inf_nan=False)
    ki: StrictFloat = Field(0.0, allow_inf_nan=False)
    kd: StrictFloat = Field(0.0, allow_inf_nan=False)
    n_filter: StrictFloat | None = Field(None, gt=0, allow_inf_nan=False)
    output_min: StrictFloat | None = Field(None, allow_inf_nan=False)
    output_max: StrictFloat | None = Field(None, allow_inf_nan=False)
    anti_windup: Literal["clamping", "back_calculation", "none"] = "clamping"
    tracking_time: StrictFloat | None = Field(None, gt=0, allow_inf_nan=False)
    feedforward: StrictFloat = Field(0.0, allow_inf_nan=False)
    action: Literal["reverse", "direct"] = "reverse"
    integrator_method: Literal["forward_euler", "backward_euler", "trapezoidal"] = \
        "forward_euler"
    filter_method: Literal["forward_euler", "backward_euler", "trapezoidal"] = "forward_euler"

    @model_validator(mode="after")
    def _check(self) -> LoopConfig:
        if self.kd != 0 and self.n_filter is None:
            raise ValueError("kd: a derivative needs its filter coefficient n_filter [1/s]")
        lo, hi = self.output_min, self.output_max
        if lo is not None and hi is not None and not lo < hi:
            raise ValueError(f"output_min must be < output_max, got [{lo}, {hi}]")
        return self

    @property
    def limited(self) -> bool:
        """Whether the output has a limit."""
        return self.output_min is not None or self.output_max is not None

    def pack(self) -> FloatArray:
        """The loop as floats for a compiled kernel, in :data:`PACKED` order (limits +-inf
        when absent)."""
        tt = self.tracking_time
        if tt is None:
            tt = abs(self.kp / self.ki) if self.ki != 0 and self.kp != 0 else 1.0
        return np.array([
            self.kp, self.ki, self.kd, self.n_filter or 0.0,
            -math.inf if self.output_min is None else self.output_min,
            math.inf if self.output_max is None else self.output_max,
            float(ANTI_WINDUP[self.anti_windup]), tt, self.feedforward,
            1.0 if self.action == "reverse" else -1.0,
            METHODS[self.integrator_method], METHODS[self.filter_method],
        ])


class DriveConfig(StrictTable):
    """A DC motor drive: speed loop, optional inner current loop, update period.

    Attributes:
        period: controller update period [s]: a whole number of integration sub-steps; the
            output is held between updates. None: every sub-step (an ideal fast drive: the
            paper's plant).
        phase: time of the first update after t = 0 [s], in [0, period) (the drive's clock
            against the acquisition's; 0 when they are aligned).
        speed: the speed loop (reference: the set-point [rad/s]; feedback: omega [rad/s];
            output: Va [V], or the current reference [A] with a current loop). Default: the
            paper's PI, Kp 0.3, Ki 0.1, unlimited.
        current: the inner current loop (reference: the speed loop's output [A]; feedback:
            ia [A]; output: Va [V]), or None.
        current_period: the current loop's period [s] (default: ``period``).
    """

    period: StrictFloat | None = Field(None, gt=0, allow_inf_nan=False)
    phase: StrictFloat = Field(0.0, ge=0, allow_inf_nan=False)
    speed: LoopConfig = Field(default_factory=lambda: LoopConfig(kp=0.3, ki=0.1))
    current: LoopConfig | None = None
    current_period: StrictFloat | None = Field(None, gt=0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _check(self) -> DriveConfig:
        if self.period is not None and self.phase >= self.period:
            raise ValueError(f"phase: must be in [0, period), got {self.phase} for period "
                             f"{self.period}")
        if self.current_period is not None and self.current is None:
            raise ValueError("current_period: set only with a current loop ([...drive.current])")
        return self

    @property
    def ideal(self) -> bool:
        """Updated every sub-step, unlimited, a PI speed loop alone: the linear drive the
        paper's plant runs (the twin composes it into one exact linear map per sample)."""
        s = self.speed
        return (self.period is None and self.current is None and not s.limited
                and s.kd == 0 and self.phase == 0)

    def ticks(self, sub_step: float) -> tuple[int, int, int]:
        """(speed period, current period, phase) in whole sub-steps.

        Raises:
            ValueError: a period or the phase is not a whole number of sub-steps (to 1e-6
                relative); the message names the key.
        """
        def whole(value: float, key: str) -> int:
            ratio = value / sub_step
            n = int(round(ratio))
            if abs(ratio - n) > 1e-6 * max(1.0, ratio) or (n < 1 and key != "phase"):
                raise ValueError(f"{key} = {value:g} s is not a whole number of integration "
                                 f"sub-steps ({sub_step:g} s)")
            return n

        m = whole(self.period, "period") if self.period is not None else 1
        mc = (whole(self.current_period, "current_period") if self.current_period is not None
              else m)
        ph = whole(self.phase, "phase") if self.phase else 0
        return m, mc, ph


__all__ = ["ANTI_WINDUP", "METHODS", "PACKED", "DriveConfig", "LoopConfig"]


#: The paper's valve PID (Eq. 17, NOTES.md): opening the valve lowers the piston, so the error
#: is e = x - x_ref (action ``direct``); clamping anti-windup at the valve's limits.
PAPER_VALVE_LOOP: dict[str, Any] = {"kp": 0.000346, "ki": 3.513406, "kd": 0.000119,
                                    "n_filter": 2.076743, "anti_windup": "clamping",
                                    "action": "direct"}


class ValveDriveConfig(StrictTable):
    """The valve controller as it runs (table ``drive``; :mod:`twinwatch.io.drive` semantics).

    One update every ``period`` from the position ``x`` [m] (feedback) and the reference
    ``x_ref`` [m]; the area [m^2] it computes is held until the next update (zero-order hold)
    and clamped to the loop's limits, by default the valve's own range [0, A_max].

    Attributes:
        period: update period [s], a whole number of integration steps; None: every step (the
            paper's plant, Eq. 17 with Ts the integration step).
        phase: time of the first update after t = 0 [s], in [0, period).
        valve: the PID (:class:`~twinwatch.io.drive.LoopConfig`); the keys a table leaves
            out take the paper's values (:data:`PAPER_VALVE_LOOP`: Kp 0.000346, Ki 3.513406,
            Kd 0.000119, N 2.076743, clamping, action ``direct``); ``output_min`` None: 0,
            ``output_max`` None: A_max (the valve's largest area).
    """

    period: StrictFloat | None = Field(None, gt=0, allow_inf_nan=False)
    phase: StrictFloat = Field(0.0, ge=0, allow_inf_nan=False)
    valve: LoopConfig = Field(default_factory=lambda: LoopConfig(**PAPER_VALVE_LOOP))

    @field_validator("valve", mode="before")
    @classmethod
    def _paper_gains(cls, value: Any) -> Any:
        """A partial table keeps the paper's values for the keys it leaves out."""
        if isinstance(value, Mapping):
            return {**PAPER_VALVE_LOOP, **value}
        return value

    @model_validator(mode="after")
    def _check(self) -> ValveDriveConfig:
        if self.period is not None and self.phase >= self.period:
            raise ValueError(f"phase: must be in [0, period), got {self.phase} for period "
                             f"{self.period}")
        return self

    def ticks(self, sub_step: float) -> tuple[int, int]:
        """(period, phase) in whole integration steps.

        Raises:
            ValueError: the period or the phase is not a whole number of steps (to 1e-6
                relative); the message names the key.
        """
        m, _, ph = DriveConfig(period=self.period, phase=self.phase).ticks(sub_step)
        return m, ph

    def limits(self, a_max: float) -> tuple[float, float]:
        """The controller's output limits [m^2]: the loop's, or the valve's range [0, a_max]."""
        v = self.valve
        return (0.0 if v.output_min is None else v.output_min,
                a_max if v.output_max is None else v.output_max)

    def pack(self, a_max: float) -> FloatArray:
        """The loop for a compiled kernel (:data:`PACKED` order), its limits resolved with
        :meth:`limits`."""
        packed = self.valve.pack()
        packed[4], packed[5] = self.limits(a_max)
        return packed
