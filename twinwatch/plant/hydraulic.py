"""Simulated hydraulic actuator plant with its valve PID (paper Section 4.2 and 5.3).

The plant is the "real machine" of the paper's second case study: a constant-displacement pump
feeds a piston cylinder, a controlled valve returns fluid to the reservoir, and a 1000 kg load
sits on the piston. Equations (paper Eq. 6-10, 14-18; reading of ../shared/paper/NOTES.md), one
plant step j -> j+1 of dt = 1e-4 s::

    q_valve   = A_valve * sqrt(2 * p_j)                         (Eq. 6-7, density left out)
    v_{j+1}   = (q_pump - q_valve) / A_piston                   (Eq. 8, uses p_j)
    x_{j+1}   = x_j + dt * v_{j+1}                              (Eq. 14-15)
    p_{j+1}   = (1 + C) * (F_load + k_spring*x_{j+1} + D*v_{j+1} + F_resist
                           + F_c*sign(v_{j+1})) / A_piston    (Eq. 16; Eq. 18 with C != 0)

``v_{j+1}`` is the velocity over the step (the paper's ``v_{k-1}`` of Eq. 14); the same value
enters the damping force of Eq. 16. ``C`` is 0 except in the internal-leak scenario (or an
injected ``leak``). ``F_c`` is an injected Coulomb (dry) friction force on the rod, 0 unless a
``friction`` parameter fault sets it (the standard Coulomb model; B. Armstrong-Helouvry et
al., "A survey of models, analysis tools and compensation methods for the control of machines
with friction", Automatica 30(7), 1994).

**Injected faults** (for the diagnosis's fault-matrix benchmark, benchmarks/bench_diagnosis.py;
their time profile: :mod:`twinwatch.plant.faults`): ``[[driver.plant.parameter_faults]]``
moves a parameter of :data:`HYD_FAULT_PARAMETERS` (a changed mass moves the reported F_load,
as a load cell's would), evaluated every acquisition sample and held over its integration
steps; ``sensor_faults`` are the DC motor's (:class:`~twinwatch.plant.dcmotor.SensorFaultConfig`).

**Valve controller (Eq. 17).** A discrete PID with a filtered derivative, forward-Euler form
``A = e*(Kp + Ki*Ts/(z-1) + Kd*N/(1 + N*Ts/(z-1)))``::

    e      = x - x_ref                      (opening the valve lowers the piston: NOTES.md)
    d      = N*(Kd*e - f)                   (derivative through the filter state f)
    u      = Kp*e + I + d
    A      = clip(u, 0, A_max)
    I     += Ki*Ts*e   unless A is clamped and e pushes further into the clamp (anti-windup)
    f     += Ts*d

**Where the PID runs: every plant step (Ts = 1e-4 s).** The paper calls Ts in Eq. 17 "the
integration time step", and with these gains the loop is only stable at that rate: the plant
gain is dv/dA = -sqrt(2p)/A_piston ~ -1620 m/s per m^2, so the integral loop oscillates at
sqrt(1620*Ki) ~ 75 rad/s with damping ratio ~ 0.006; run every 10 ms (0.75 rad per period)
the forward-Euler integral is unstable. Consequence for the twin: the valve area changes
within a sample, so :class:`twinwatch.twin.models.hydraulic.HydraulicActuatorTwin`
interpolates it linearly between samples by default.

**The controller as a drive runs it** (``drive``, ``[driver.plant.drive]``,
:class:`~twinwatch.twin.models.hydraulic.ValveDriveConfig`; the update of :mod:`twinwatch.io.drive`
with action ``direct``): without the table the plant is the PID above every step, bit for bit;
the paper's gains are unstable from a 0.2 ms period on (docs/hydraulic.md;
tests/test_hydraulic_drive.py).

**Reference and start.** x_ref(t) = offset + amplitude*sin(2*pi*f*t) (0.5 m + 0.45 m at
0.005 Hz: the offset is our choice, so the piston stays in its stroke). The plant starts in
steady tracking: x_0 = x_ref(0), the integrator holding the area that gives v = dx_ref/dt.

**Scenarios** (onset ``fault_start`` = 160 s, time of the step start ``t_j = j*dt``):

* ``nominal``: Table 4 parameters throughout.
* ``fluid_degradation``: D(t) = D + 36.5*(exp(0.003*(t - 160)) - 1) for t >= 160 s (about 200
  N/(m/s) at 600 s; NOTES.md's reading of the paper's ramp).
* ``internal_leak``: C = ``leak_coefficient`` (0.2) for t >= 160 s (Eq. 18).


A sample at t_k reports the state reached at t_k (x, p), the valve area the controller applies
from t_k on, F_load and x_ref(t_k). Measurement noise (percent of reading, Gaussian) is applied
to the reported values only, never to the plant state or the controller's input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field, StrictFloat, StrictInt, model_validator

from twinwatch._table import StrictTable
from twinwatch.io.drive import LoopConfig, ValveDriveConfig
from twinwatch.io.sample import Sample
from twinwatch.plant._pid import pid_tick
from twinwatch.plant.dcmotor import SensorFaultConfig
from twinwatch.plant.faults import ParameterFaultConfig, SimulatedPlant, check_plant_table

GRAVITY = 9.81  # m/s^2
DEGRADATION_GAIN = 36.5  # N/(m/s), D(t) = D + 36.5*(exp(0.003*(t - t_fault)) - 1)
DEGRADATION_RATE = 0.003  # 1/s

Scenario = Literal["nominal", "fluid_degradation", "internal_leak"]
_SCENARIO_CODE = {"nominal": 0, "fluid_degradation": 1, "internal_leak": 2}

#: The paper's Eq. 17 gains (kp, ki, kd, n_filter), the defaults of the plant's PID.
_PAPER_GAINS = (0.000346, 3.513406, 0.000119, 2.076743)

#: Measured channels, in the order the plant reports them.
CHANNELS: tuple[str, ...] = ("x", "p", "A_valve", "F_load", "x_ref")
#: Units of :data:`CHANNELS`.
CHANNEL_UNITS: dict[str, str] = {"x": "m", "p": "Pa", "A_valve": "m^2", "F_load": "N",
                                 "x_ref": "m"}

#: Parameters a ``[[driver.plant.parameter_faults]]`` entry of the hydraulic actuator may move,
#: with their unit: ``leak`` is C of Eq. 18 (nominal 0, or ``leak_coefficient`` from the
#: internal-leak scenario's onset: an injected leak adds to it), ``friction`` a Coulomb force
#: opposing the rod's motion (nominal 0); both and F_resist (nominal 0) need ``absolute``.
HYD_FAULT_PARAMETERS: dict[str, str] = {
    "D": "N/(m/s)", "q_pump": "m^3/s", "k_spring": "N/m", "mass": "kg", "F_resist": "N",
    "leak": "1", "friction": "N"}


class HydraulicPlantConfig(StrictTable):
    """Configuration of the simulated hydraulic actuator (table ``[driver.plant]``).

    Defaults are the paper's Table 4 and Eq. 17 values (NOTES.md).
    """

    scenario: Scenario = "fluid_degradation"
    duration: StrictFloat = Field(600.0, gt=0, description="simulated time [s]")
    sample_period: StrictFloat = Field(0.01, gt=0, description="acquisition period [s]")
    step: StrictFloat = Field(1e-4, gt=0, description="integration step (and the PID's period "
                              "without a drive table) [s]")
    k_spring: StrictFloat = Field(200.0, ge=0, description="spring constant [N/m]")
    D: StrictFloat = Field(100.0, ge=0, description="damping coefficient [N/(m/s)]")
    q_pump: StrictFloat = Field(0.02, gt=0, description="pump flow [m^3/s]")
    A_max: StrictFloat = Field(1e-4, gt=0, description="largest valve cross-section [m^2]")
    A_piston: StrictFloat = Field(0.196349375, gt=0, description="piston area [m^2]")
    F_resist: StrictFloat = Field(0.0, description="internal resistance force [N]")
    mass: StrictFloat = Field(1000.0, gt=0, description="load mass [kg]; F_load = mass*9.81")
    kp: StrictFloat = Field(_PAPER_GAINS[0], description="PID proportional gain [m^2/m]")
    ki: StrictFloat = Field(_PAPER_GAINS[1], description="PID integral gain [m^2/(m s)]")
    kd: StrictFloat = Field(_PAPER_GAINS[2], description="PID derivative gain [m^2 s/m]")
    n_filter: StrictFloat = Field(_PAPER_GAINS[3], gt=0,
                                  description="PID derivative filter N [1/s]")
    ref_offset: StrictFloat = Field(0.5, description="position reference offset [m]")
    ref_amplitude: StrictFloat = Field(0.45, description="position reference amplitude [m]")
    ref_frequency: StrictFloat = Field(0.005, ge=0, description="position reference frequency [Hz]")
    fault_start: StrictFloat = Field(160.0, ge=0, description="scenario onset [s]")
    leak_coefficient: StrictFloat = Field(0.2, gt=-1, description="C of Eq. 18 (internal_leak)")
    noise: dict[str, StrictFloat] = Field(
        default_factory=dict,
        description="channel -> Gaussian noise standard deviation, percent of reading",
    )
    drive: ValveDriveConfig | None = Field(
        None, description="the valve controller as it runs (update period with the area held, "
        "limits, anti-windup; twinwatch.twin.models.hydraulic.ValveDriveConfig); default: the PID "
        "kp, ki, kd, n_filter above every step, clamped to [0, A_max]")
    sensor_faults: list[SensorFaultConfig] = Field(
        default_factory=list, description="sensor faults: a reported channel frozen, "
        "saturated, off by a gain or an offset (possibly drifting) for a while")
    parameter_faults: list[ParameterFaultConfig] = Field(
        default_factory=list, description="changes of the plant's physical parameters over "
        "time (step, drift, repair, intermittent; twinwatch.plant.faults): parameter one of D, "
        "q_pump (the pump's delivery), k_spring, mass, F_resist [N], leak (C of Eq. 18), "
        "friction (a Coulomb force on the rod [N]); F_resist, leak and friction need absolute")
    seed: StrictInt = 0

    @property
    def drive_config(self) -> ValveDriveConfig:
        """The valve controller: ``drive``, or the paper's PID (``kp``, ``ki``, ``kd``,
        ``n_filter``) every step, clamped to [0, A_max]."""
        return self.drive or ValveDriveConfig(valve=LoopConfig(
            kp=self.kp, ki=self.ki, kd=self.kd, n_filter=self.n_filter, output_min=0.0,
            output_max=self.A_max, anti_windup="clamping", action="direct"))

    @model_validator(mode="after")
    def _check(self) -> HydraulicPlantConfig:
        check_plant_table(self, CHANNELS, HYD_FAULT_PARAMETERS, {"noise": self.noise})
        if self.drive is not None:
            if (self.kp, self.ki, self.kd, self.n_filter) != _PAPER_GAINS:
                raise ValueError("kp, ki, kd, n_filter: with a [drive] table set the gains "
                                 "there (drive.valve.kp, ...)")
            try:
                self.drive.ticks(self.step)
            except ValueError as exc:
                raise ValueError(f"drive.{exc}") from None
            lo, hi = self.drive.limits(self.A_max)
            for key, lim in (("output_min", lo), ("output_max", hi)):
                if not 0.0 <= lim <= self.A_max:
                    raise ValueError(f"drive.valve.{key}: {lim:g} m^2 is outside the valve's "
                                     f"range [0, A_max = {self.A_max:g}]")
            if not lo < hi:
                raise ValueError(f"drive.valve.output_min must be < output_max, got "
                                 f"[{lo:g}, {hi:g}]")
        return self

    @property
    def F_load(self) -> float:  # noqa: N802 - the paper's symbol
        """Load force [N]: the mass's weight."""
        return self.mass * GRAVITY

    def fault_nominals(self) -> dict[str, float]:
        """The nominal value of each parameter a parameter fault may move (its unit:
        :data:`HYD_FAULT_PARAMETERS`; ``leak`` is the injected part of C, nominal 0)."""
        return {"D": self.D, "q_pump": self.q_pump, "k_spring": self.k_spring,
                "mass": self.mass, "F_resist": self.F_resist, "leak": 0.0, "friction": 0.0}


@njit(cache=True, nogil=True)
def _pid(state, loop, r, period):  # pragma: no cover - compiled
    """One update of the valve controller (:mod:`twinwatch.io.drive`, paper Eq. 17) on the
    reference ``r``; ``state = [x, p, I, f, A]``: sets A, advances I and f. ``loop``: the
    packed loop (limits resolved)."""
    state[4], state[2], state[3] = pid_tick(loop, state[2], state[3], r, state[0], period)


@njit(cache=True, nogil=True)
def _advance(state, j0, n_sub, dt, prm, scenario, t_fault, c_leak, loop, m,
             ph):  # pragma: no cover - compiled
    """Advance ``state = [x, p, I, f, A]`` by ``n_sub`` plant steps from step index ``j0``.

    ``prm = [k_spring, D0, q_pump, A_max, A_piston, F_resist, F_load, ref_offset,
    ref_amplitude, ref_frequency, C_injected, F_c]``; ``loop``: the packed valve controller,
    updated at the steps j >= ``ph`` with (j - ph) % ``m`` == 0. On entry ``state[4]`` is the
    area applied over step j0; on exit it is the area applied from step j0 + n_sub on.
    """
    ks, d0, qp, ap, fr, fl = prm[0], prm[1], prm[2], prm[4], prm[5], prm[6]
    r0, r1, rf = prm[7], prm[8], prm[9]
    c_inj, f_c = prm[10], prm[11]
    period = m * dt
    x, p = state[0], state[1]
    for s in range(n_sub):
        t = (j0 + s) * dt
        d = d0
        c = c_inj
        if t >= t_fault:
            if scenario == 1:
                d = d0 + DEGRADATION_GAIN * (math.exp(DEGRADATION_RATE * (t - t_fault)) - 1.0)
            elif scenario == 2:
                c += c_leak
        v = (qp - state[4] * math.sqrt(2.0 * p)) / ap
        x = x + dt * v
        fric = 0.0
        if f_c != 0.0:
            fric = f_c if v > 0.0 else (-f_c if v < 0.0 else 0.0)
        p = (1.0 + c) * (fl + ks * x + d * v + fr + fric) / ap
        state[0], state[1] = x, p
        j = j0 + s + 1
        if j >= ph and (j - ph) % m == 0:
            t_next = t + dt
            ref = r0 + r1 * math.sin(2.0 * math.pi * rf * t_next)
            _pid(state, loop, ref, period)


@dataclass
class HydraulicTruth:
    """The plant's true fault parameters at a time (for tests and benchmarks).

    Attributes:
        D: damping coefficient [N/(m/s)].
        C: leak coefficient of Eq. 18 (0 without a leak).
        q_pump: pump delivery [m^3/s].
        k_spring: spring constant [N/m].
        mass: load mass [kg].
        F_resist: resistance force [N].
        friction: Coulomb friction force on the rod [N].
    """

    D: float
    C: float
    q_pump: float = math.nan
    k_spring: float = math.nan
    mass: float = math.nan
    F_resist: float = 0.0
    friction: float = 0.0


class HydraulicPlant(SimulatedPlant):
    """The simulated hydraulic actuator; one call to :meth:`next_sample` per sample.

    Args:
        config: plant configuration (defaults: the paper's fluid-degradation scenario).

    Raises:
        EndOfStream: from :meth:`next_sample` after ``config.duration`` seconds.
    """

    channels = CHANNELS

    def __init__(self, config: HydraulicPlantConfig | None = None) -> None:
        self.config = config or HydraulicPlantConfig()
        c = self.config
        super().__init__(c)
        self._prm = np.array([c.k_spring, c.D, c.q_pump, c.A_max, c.A_piston, c.F_resist,
                              c.F_load, c.ref_offset, c.ref_amplitude, c.ref_frequency, 0.0,
                              0.0])
        drive = c.drive_config
        self._loop = drive.pack(c.A_max)
        self._m, self._ph = drive.ticks(c.step)
        self._scenario = _SCENARIO_CODE[c.scenario]
        # Start in steady tracking: on the reference, moving with it, the integrator holding
        # the area that gives that velocity (bumpless start).
        truth = self.truth(0.0)
        self._apply_faults(0.0)
        x0 = self.reference(0.0)
        v0 = 2.0 * math.pi * c.ref_frequency * c.ref_amplitude
        fric = math.copysign(truth.friction, v0) if v0 != 0.0 else 0.0
        p0 = (1.0 + truth.C) * (truth.mass * GRAVITY + truth.k_spring * x0 + truth.D * v0
                                + truth.F_resist + fric) / c.A_piston
        i0 = (truth.q_pump - v0 * c.A_piston) / math.sqrt(2.0 * p0)
        lo, hi = drive.limits(c.A_max)
        self._state = np.array([x0, p0, i0, 0.0, min(max(i0, lo), hi)])
        if self._ph == 0:  # the first update at t = 0, on the reference: e = 0
            _pid(self._state, self._loop, x0, self._m * c.step)

    def reference(self, t: float) -> float:
        """Position reference x_ref(t) [m]."""
        c = self.config
        return c.ref_offset + c.ref_amplitude * math.sin(2.0 * math.pi * c.ref_frequency * t)

    def truth(self, t: float) -> HydraulicTruth:
        """The plant's true parameters at plant time ``t`` [s], faults and scenario included."""
        c = self.config
        on = t >= c.fault_start
        ramp = math.exp(DEGRADATION_RATE * (t - c.fault_start)) - 1.0 if on else 0.0
        v = self._faulted(t)
        d = v["D"] + DEGRADATION_GAIN * ramp if c.scenario == "fluid_degradation" else v["D"]
        leak = c.leak_coefficient if (c.scenario == "internal_leak" and on) else 0.0
        return HydraulicTruth(D=d, C=leak + v["leak"], q_pump=v["q_pump"],
                              k_spring=v["k_spring"], mass=v["mass"], F_resist=v["F_resist"],
                              friction=v["friction"])

    def _apply_faults(self, t: float) -> None:
        """Set the compiled plant's parameters for the sample period from ``t`` [s]."""
        if not self.config.parameter_faults:
            return
        v = self._faulted(t)
        prm = self._prm
        prm[0], prm[1], prm[2], prm[5] = v["k_spring"], v["D"], v["q_pump"], v["F_resist"]
        prm[6] = v["mass"] * GRAVITY
        prm[10], prm[11] = v["leak"], v["friction"]

    def next_sample(self) -> Sample:
        """Report the sample at the current time, then advance the plant one sample period.

        Returns:
            A sample with x [m], p [Pa], A_valve [m^2] (applied from this sample on),
            F_load [N] and x_ref [m].
        """
        c = self.config
        self._check_end()
        t = self.t
        x, p, _, _, a = (float(v) for v in self._state)
        self._apply_faults(t)
        values = {"x": x, "p": p, "A_valve": a, "F_load": float(self._prm[6]),
                  "x_ref": self.reference(t)}
        self._report(values, t, {})
        _advance(self._state, self._k * self.n_sub, self.n_sub, c.step, self._prm,
                 self._scenario, c.fault_start, c.leak_coefficient, self._loop, self._m,
                 self._ph)
        self._k += 1
        return Sample(t=t, values=values)
