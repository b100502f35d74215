"""Simulated DC motor plant with its PI speed drive (paper Section 5.1-5.2).

The plant is the "real machine" of the paper's virtual environment: Eq. 11-12 integrated at
1e-4 s, a PI speed controller (Kp 0.3, Ki 0.1) updated every plant step as in a drive, set-point
steps among 0-20 rad/s, load torque Tload = 0.006*omega, and the paper's fault scenarios
(formulas from ../shared/paper/NOTES.md):

* ``nominal``: Table 3 parameters throughout.
* ``resistance_degradation``: Ra(t) = 6.5 - 0.044*(exp(0.003*(t-160)) - 1) for t >= 160 s.
* ``bearing_wear``: D(t) = 0.00143 + 0.00003806*(exp(0.003*(t-160)) - 1) for t >= 160 s.
* ``unbalanced_shaft``: omega gets + dt*5*sin(10*t) every step (Eq. 13: the paper fixes the
  frequency at 10 rad/s whatever the shaft's speed). With ``unbalance_follows_shaft`` the
  forcing follows the shaft instead: + dt*5*sin(angle), the angle the shaft has turned (a real
  unbalance, at 1x the shaft speed: ISO 21940-11); ``unbalance_frequency`` is then unused.
* ``dead_zone`` (not in the paper: a change its twin has no term for): from ``fault_start`` the
  drive's power stage has a dead zone of ``dead_zone_threshold`` b [V]: the armature receives
  ``dz(Va) = 0`` while ``|Va| <= b`` and ``Va - b*sign(Va)`` beyond (G. Tao and P. V.
  Kokotovic, *Adaptive Control of Systems with Actuator and Sensor Nonlinearities*, Wiley
  1996). The reported Va stays the drive's command; the motor receives less.

With ``fault_period`` the degradation restarts every ``fault_period`` seconds after its onset
(the part is replaced at each maintenance), so long runs stay within the law's physical range.
The paper's Ra law reaches 0 ohm 1667 s after onset; a run whose resistance would fall below
10 % of nominal is refused.

One plant step (dt = 1e-4 s), in this order::

    if the drive updates now (every ``drive.period``; every step by default):
        Va  = the drive's speed loop on (setpoint, omega)        (twinwatch.io.drive)
              [through its current loop on (speed loop output, ia)]
    Va_m   = dz(Va) with scenario dead_zone from fault_start, else Va
    Va_m  *= s(t)                          a supply fault: the motor receives s times Va
    ia    += dt*(Va_m - Ra*ia - Ke*omega)/La                         (Eq. 11)
    ia     = max(ia, 0)                    with power_stage = "unidirectional"
    omega += dt*(Kt*ia - Tload - D*omega - Tc*sign(omega))/J [+ dt*5*sin(10*t)]  (Eq. 12 / 13)
                                                    [or + dt*5*sin(angle): follows the shaft]
             [+ dt*(a1*sin(angle) + a2*sin(2*angle)): injected unbalance and misalignment]
    angle += dt*omega

**Injected faults** (for the diagnosis's fault-matrix benchmark, benchmarks/bench_diagnosis.py;
their time profiles: :mod:`twinwatch.plant.faults`): ``[[driver.plant.parameter_faults]]``
moves a parameter of :data:`DC_FAULT_PARAMETERS` (a1: ``unbalance``, 1x the shaft speed: ISO
21940-11; a2: ``misalignment``, 2x: Bloch and Budris, *Pump User's Handbook*), evaluated every
acquisition sample and held over its integration steps; ``[driver.plant.supply_fault]`` scales
the voltage the motor receives, s(t), while the reported Va stays the drive's command. The
numba kernel reads the parameters from the array it is handed: no recompilation.

The drive (:class:`~twinwatch.io.drive.DriveConfig`, ``[driver.plant.drive]``) updates every
``period`` and holds its output in between, clamped with anti-windup, with an optional inner
current loop; without a ``drive`` table it is the paper's PI (``kp``, ``ki``) every step.

A sample at t_k reports the state reached at t_k (through the sensor filters), the voltage the
drive applies from t_k on (after an update at t_k), the set-point in force from t_k on and Tload
= c_load*omega. Measurement noise (percent of reading, Gaussian) and quantisation are applied to
the reported values only, never to the plant state or the drive's feedback. The loop over plant
steps is compiled with numba.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit
from pydantic import (
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    model_validator,
)

from twinwatch._table import StrictTable
from twinwatch.io.drive import DriveConfig, LoopConfig
from twinwatch.io.sample import Sample
from twinwatch.plant._pid import pid_tick
from twinwatch.plant.faults import (
    ParameterFaultConfig,
    SimulatedPlant,
    SupplyFaultConfig,
    check_plant_table,
)

Scenario = Literal["nominal", "resistance_degradation", "bearing_wear", "unbalanced_shaft",
                   "dead_zone"]
_SCENARIO_CODE = {"nominal": 0, "resistance_degradation": 1, "bearing_wear": 2,
                  "unbalanced_shaft": 3, "dead_zone": 4}

#: Measured channels, in the order the plant reports them.
CHANNELS: tuple[str, ...] = ("Va", "ia", "omega", "Tload", "setpoint")


class SetpointSchedule(StrictTable):
    """Speed set-point schedule.

    Either explicit ``steps`` ([[t_s, value_rad_s], ...], first at t = 0) or a seeded random
    schedule: levels drawn from ``levels`` (never the current one), each held for a whole number
    of seconds drawn uniformly from [dwell_min, dwell_max]. The PI loop settles in tens of
    seconds, so dwells of 20-60 s let the motor approach steady state (our choice; the paper only
    says "at different times").
    """

    steps: list[tuple[StrictFloat, StrictFloat]] | None = None
    initial: StrictFloat = Field(10.0, description="set-point from t = 0 [rad/s]")
    levels: list[StrictFloat] = Field(default_factory=lambda: [5.0, 10.0, 15.0, 20.0])
    dwell_min: StrictFloat = Field(20.0, gt=0)
    dwell_max: StrictFloat = Field(60.0, gt=0)
    seed: StrictInt = 1

    @model_validator(mode="after")
    def _check(self) -> SetpointSchedule:
        if self.dwell_max < self.dwell_min:
            raise ValueError("dwell_max must be >= dwell_min")
        if self.steps is not None:
            if not self.steps or self.steps[0][0] != 0:
                raise ValueError("steps must start at t = 0")
            times = [s[0] for s in self.steps]
            if any(b <= a for a, b in zip(times, times[1:], strict=False)):
                raise ValueError("steps must have increasing times")
        if len(self.levels) < 2 and self.steps is None:
            raise ValueError("levels needs at least two values")
        return self

    def build(self, duration: float) -> tuple[np.ndarray, np.ndarray]:
        """Return (change times [s], values [rad/s]) covering [0, duration]."""
        if self.steps is not None:
            arr = np.asarray(self.steps, dtype=float)
            return arr[:, 0], arr[:, 1]
        rng = np.random.default_rng(self.seed)
        times, values = [0.0], [self.initial]
        t = 0.0
        while t < duration:
            t += float(rng.integers(int(self.dwell_min), int(self.dwell_max) + 1))
            choices = [v for v in self.levels if v != values[-1]]
            times.append(t)
            values.append(float(rng.choice(choices)))
        return np.asarray(times), np.asarray(values)


class SensorFaultConfig(StrictTable):
    """A sensor fault of the simulated plant (``[[driver.plant.sensor_faults]]``): from
    ``start`` for ``duration`` seconds (to the end of the run without one) the reported
    ``channel`` is

    * ``frozen``: it repeats its reading at the onset;
    * ``saturated``: clipped at ``level``, from above with ``side = "high"``, from below with
      ``"low"``;
    * ``gain``: ``reported = g * value`` (a wrong scale: a shunt or a tachometer constant off);
    * ``offset``: ``reported = value + o`` [the channel's unit] (a zero error).

    A gain or offset may grow linearly from nothing to full over ``ramp`` seconds after
    ``start`` (a drift: ``g(t) = 1 + f (gain - 1)``, ``o(t) = f offset``, ``f = min(1, (t -
    start)/ramp)``). Applied to the reported value after noise and quantisation; the plant
    itself and its drive (which reads its own feedback) are untouched."""

    channel: str
    kind: Literal["frozen", "saturated", "gain", "offset"]
    start: StrictFloat = Field(ge=0, description="onset [s]")
    duration: StrictFloat | None = Field(None, gt=0, description="how long [s] (None: to the "
                                         "end of the run)")
    level: StrictFloat | None = Field(
        None, description="saturated: the reading clips at this value "
        "[the channel's unit]")
    side: Literal["high", "low"] = Field("high", description="saturated: clips readings above "
                                         "(high) or below (low) the level")
    gain: StrictFloat | None = Field(None, description="gain: reported = gain * value at full "
                                     "size (e.g. 1.1: reads 10 % high)")
    offset: StrictFloat | None = Field(None, description="offset: reported = value + offset at "
                                       "full size [the channel's unit]")
    ramp: StrictFloat = Field(0.0, ge=0, description="gain, offset: seconds from start to full "
                              "size, growing linearly (a drift; 0: a step)")

    @model_validator(mode="after")
    def _check(self) -> SensorFaultConfig:
        if self.kind == "saturated" and self.level is None:
            raise ValueError("level: a saturated sensor needs the level it clips at")
        if self.kind == "gain" and self.gain is None:
            raise ValueError("gain: a gain fault needs its gain (reported = gain * value)")
        if self.kind == "offset" and self.offset is None:
            raise ValueError("offset: an offset fault needs its offset (reported = value + "
                             "offset)")
        for key in ("gain", "offset", "level"):
            wanted = {"gain": "gain", "offset": "offset", "level": "saturated"}[key]
            if getattr(self, key) is not None and self.kind != wanted:
                raise ValueError(f"{key}: only for kind {wanted!r} (this fault is "
                                 f"{self.kind!r})")
        if self.ramp > 0 and self.kind not in ("gain", "offset"):
            raise ValueError(f"ramp: only a gain or an offset drifts (this fault is "
                             f"{self.kind!r})")
        return self

    def active(self, t: float) -> bool:
        """Whether the fault acts at plant time ``t`` [s]."""
        return self.start <= t and (self.duration is None or t < self.start + self.duration)

    def apply(self, value: float, t: float, frozen: dict[int, float]) -> float:
        """The reported value at plant time ``t`` [s] given the sensor's ``value`` (after noise
        and quantisation); ``frozen`` keeps a frozen sensor's reading (by fault)."""
        if not self.active(t):
            return value
        if self.kind == "frozen":
            return frozen.setdefault(id(self), value)
        if self.kind == "saturated":
            assert self.level is not None
            return min(value, self.level) if self.side == "high" else max(value, self.level)
        f = 1.0 if self.ramp <= 0 else min(1.0, (t - self.start) / self.ramp)
        if self.kind == "gain":
            assert self.gain is not None
            return (1.0 + f * (self.gain - 1.0)) * value
        assert self.offset is not None
        return value + f * self.offset


#: Parameters a ``[[driver.plant.parameter_faults]]`` entry of the DC motor may move, with
#: their unit: ``Ke`` moves Ke and Kt together (the field: in SI units Kt = Ke), ``load`` the
#: load coefficient c_load, ``Tc`` the Coulomb friction torque, ``unbalance`` and
#: ``misalignment`` a forcing on d(omega)/dt at 1x and 2x the shaft's angle (these three
#: usually 0 at nominal: give ``absolute``).
DC_FAULT_PARAMETERS: dict[str, str] = {
    "Ra": "ohm", "La": "H", "J": "kg m^2", "Ke": "V s/rad (and Kt, N m/A)", "D": "N m s/rad",
    "Tc": "N m", "load": "N m s/rad", "unbalance": "rad/s^2", "misalignment": "rad/s^2"}


class DCMotorPlantConfig(StrictTable):
    """Configuration of the simulated DC motor plant (table ``[driver.plant]``)."""

    scenario: Scenario = "resistance_degradation"
    duration: StrictFloat = Field(1200.0, gt=0, description="simulated time [s]")
    sample_period: StrictFloat = Field(0.01, gt=0, description="acquisition period [s]")
    step: StrictFloat = Field(1e-4, gt=0, description="integration step [s]")
    Ra: StrictFloat = Field(6.5, gt=0)
    La: StrictFloat = Field(0.673, gt=0)
    J: StrictFloat = Field(0.001171, gt=0)
    Ke: StrictFloat = Field(0.038, gt=0)
    Kt: StrictFloat = Field(0.038, gt=0)
    D: StrictFloat = Field(0.00143, ge=0)
    load_coefficient: StrictFloat = Field(0.006, ge=0, description="Tload = c*omega [N m s/rad]")
    kp: StrictFloat = 0.3
    ki: StrictFloat = 0.1
    fault_start: StrictFloat = Field(160.0, ge=0, description="scenario onset [s]")
    fault_period: StrictFloat | None = Field(
        None, gt=0, description="restart the degradation every this many seconds after its "
        "onset (a maintenance replaces the part); None: it runs on to the end")
    unbalance_amplitude: StrictFloat = Field(5.0, description="Eq. 13 amplitude [rad/s^2]")
    unbalance_frequency: StrictFloat = Field(10.0, description="Eq. 13 frequency [rad/s]")
    unbalance_follows_shaft: StrictBool = Field(
        False, description="scenario unbalanced_shaft: the forcing follows the shaft, "
        "unbalance_amplitude*sin(shaft angle), at 1x the shaft speed (a real unbalance); "
        "false: the paper's Eq. 13 at the fixed unbalance_frequency")
    dead_zone_threshold: StrictFloat = Field(
        2.0, gt=0, description="scenario dead_zone: the drive applies no voltage while |Va| is "
        "below this, and |Va| less this beyond [V] (Tao and Kokotovic 1996)")
    setpoint: SetpointSchedule = Field(default_factory=SetpointSchedule)
    noise: dict[str, StrictFloat] = Field(
        default_factory=dict,
        description="channel -> Gaussian noise standard deviation, percent of reading",
    )
    quantisation: dict[str, StrictFloat] = Field(
        default_factory=dict, description="channel -> quantisation step in the channel's unit"
    )
    drive: DriveConfig | None = Field(
        None, description="the drive as it runs (update period, limits, anti-windup, current "
        "loop; twinwatch.io.drive); default: the PI kp/ki above, updated every step")
    coulomb_friction: StrictFloat = Field(0.0, ge=0, description="Coulomb friction torque Tc [N m]")
    power_stage: Literal["bidirectional", "unidirectional"] = Field(
        "bidirectional", description="unidirectional: the armature current cannot reverse "
        "(one switch and a freewheeling diode)")
    current_filter: StrictFloat | None = Field(
        None, gt=0, description="time constant [s] of a first-order low-pass filter on the "
        "reported current")
    speed_filter: StrictFloat | None = Field(
        None, gt=0, description="time constant [s] of a first-order low-pass filter on the "
        "reported speed")
    encoder_cpr: StrictInt | None = Field(
        None, ge=1, description="encoder counts per revolution: the reported speed is the "
        "count of the last sample period times 2*pi/(cpr*sample_period)")
    sensor_faults: list[SensorFaultConfig] = Field(
        default_factory=list, description="sensor faults: a reported channel frozen, "
        "saturated, off by a gain or an offset (possibly drifting) for a while (for tests of "
        "the estimator's data-quality checks and of the diagnosis)")
    parameter_faults: list[ParameterFaultConfig] = Field(
        default_factory=list, description="changes of the plant's physical parameters over "
        "time (step, drift, repair, intermittent; twinwatch.plant.faults): parameter one of Ra, "
        "La, J, Ke (Ke and Kt together: the field), D, Tc (Coulomb friction [N m]), load "
        "(c_load), unbalance and misalignment (a forcing on d(omega)/dt at 1x and 2x the shaft's "
        "angle [rad/s^2]); Tc, unbalance and misalignment need absolute (their nominal is 0)")
    supply_fault: SupplyFaultConfig | None = Field(
        None, description="the motor receives ratio times the drive's voltage (a sagging "
        "supply) while the reported Va stays the drive's command")
    seed: StrictInt = 0

    @property
    def drive_config(self) -> DriveConfig:
        """The drive: ``drive``, or the paper's PI (``kp``, ``ki``) updated every step."""
        return self.drive or DriveConfig(speed=LoopConfig(kp=self.kp, ki=self.ki))

    def fault_nominals(self) -> dict[str, float]:
        """The nominal value of each parameter a parameter fault may move (its unit:
        :data:`DC_FAULT_PARAMETERS`)."""
        return {"Ra": self.Ra, "La": self.La, "J": self.J, "Ke": self.Ke, "D": self.D,
                "Tc": self.coulomb_friction, "load": self.load_coefficient,
                "unbalance": 0.0, "misalignment": 0.0}

    @model_validator(mode="after")
    def _check(self) -> DCMotorPlantConfig:
        check_plant_table(self, CHANNELS, DC_FAULT_PARAMETERS,
                          {"noise": self.noise, "quantisation": self.quantisation})
        try:
            self.drive_config.ticks(self.step)
        except ValueError as exc:
            raise ValueError(f"drive.{exc}") from None
        if self.drive is not None and (self.kp, self.ki) != (0.3, 0.1):
            raise ValueError("kp, ki: with a [drive] table set the gains there "
                             "(drive.speed.kp, drive.speed.ki)")
        if self.scenario == "resistance_degradation":
            age = self.duration - self.fault_start
            if self.fault_period is not None:
                age = min(age, self.fault_period)
            ra_min = self.Ra - RA_DROP * _ramp(age)
            if ra_min < 0.1 * self.Ra:
                raise ValueError(
                    f"duration: under resistance_degradation Ra(t) = Ra - 0.044 (exp(0.003 (t - "
                    f"fault_start)) - 1) falls to {ra_min:.3g} ohm by the end of the run, below "
                    f"10 % of Ra (the plant is no longer a motor); shorten the run or set "
                    f"fault_period (e.g. 1200 s: the part is replaced every 20 min)")
        return self


#: The paper's degradation laws (NOTES.md): Ra(t) = Ra - RA_DROP*x, D(t) = D + D_RISE*x with
#: x = exp(RATE*age) - 1, age = t - fault_start [s] (modulo fault_period when set).
RA_DROP = 0.044          # ohm
D_RISE = 0.00003806      # N m s/rad
RATE = 0.003             # 1/s


def _ramp(age: float) -> float:
    """x = exp(RATE*age) - 1 of the degradation laws; 0 before the onset (age < 0)."""
    return math.exp(RATE * age) - 1.0 if age >= 0 else 0.0


# State vector of the compiled plant (indices).
_IA, _W, _IS, _FS, _IC, _FC, _VA, _IREF, _ANGLE, _FI, _FW, _LAST = range(12)


@njit(cache=True, nogil=True)
def _tick(state, j, sp, speed, current, has_current, m, mc, ph, dt):  # pragma: no cover
    """Run the drive's updates due at step ``j`` (once per step: ``state[_LAST]``)."""
    if state[_LAST] == j:
        return
    state[_LAST] = j
    if j >= ph and (j - ph) % m == 0:
        u, state[_IS], state[_FS] = pid_tick(speed, state[_IS], state[_FS], sp, state[_W],
                                              m * dt)
        if has_current:
            state[_IREF] = u
        else:
            state[_VA] = u
    if has_current and j >= ph and (j - ph) % mc == 0:
        state[_VA], state[_IC], state[_FC] = pid_tick(current, state[_IC], state[_FC],
                                                       state[_IREF], state[_IA], mc * dt)


@njit(cache=True, nogil=True)
def _advance(state, k0, n_sub, dt, sp, p, scenario, t_fault, period, unb_a,  # pragma: no cover
             unb_w, speed, current, has_current, m, mc, ph, stage, tc, tau_i, tau_w, dz_b):
    """Advance the plant ``state`` (see the ``_IA``... indices) by ``n_sub`` steps from step
    index ``k0``, the drive updating when due.

    ``p = [Ra0, La, J, Ke, Kt, D0, c_load, supply, a1, a2]`` (``supply``: the share of the
    stage's voltage the motor receives; ``a1``, ``a2``: forcings on d(omega)/dt [rad/s^2] at 1x
    and 2x the shaft's angle); ``state`` is updated in place.
    """
    ra0, la, j, ke, kt, d0, c = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
    supply, a1, a2 = p[7], p[8], p[9]
    for s in range(n_sub):
        k = k0 + s
        _tick(state, k, sp, speed, current, has_current, m, mc, ph, dt)
        t = k * dt
        ra = ra0
        d = d0
        age = t - t_fault
        if period > 0.0 and age > 0.0:
            age = age % period
        if scenario == 1 and t >= t_fault:
            ra = ra0 - RA_DROP * (math.exp(RATE * age) - 1.0)
        elif scenario == 2 and t >= t_fault:
            d = d0 + D_RISE * (math.exp(RATE * age) - 1.0)
        ia, w = state[_IA], state[_W]
        va = state[_VA]
        if scenario == 4 and t >= t_fault:  # the drive's dead zone: dz(Va, b)
            va = va - dz_b if va > dz_b else (va + dz_b if va < -dz_b else 0.0)
        va *= supply
        ia = ia + dt * (va - ra * ia - ke * w) / la
        if stage == 1 and ia < 0.0:
            ia = 0.0
        fric = 0.0
        if tc > 0.0:
            fric = tc if w > 0.0 else (-tc if w < 0.0 else 0.0)
        w_new = w + dt * (kt * ia - c * w - d * w - fric) / j
        if scenario == 3:
            if math.isnan(unb_w):  # follows the shaft: once per turn of its angle
                w_new += dt * unb_a * math.sin(state[_ANGLE] + dt * w)
            else:
                w_new += dt * unb_a * math.sin(unb_w * (t + dt))
        if a1 != 0.0 or a2 != 0.0:  # injected unbalance (1x) and misalignment (2x)
            angle = state[_ANGLE] + dt * w
            w_new += dt * (a1 * math.sin(angle) + a2 * math.sin(2.0 * angle))
        state[_IA], state[_W] = ia, w_new
        state[_ANGLE] += dt * w_new
        if tau_i > 0.0:
            state[_FI] += dt / tau_i * (ia - state[_FI])
        if tau_w > 0.0:
            state[_FW] += dt / tau_w * (w_new - state[_FW])


@dataclass
class PlantTruth:
    """The plant's true parameters at a time (for tests and benchmarks).

    Attributes:
        Ra: armature resistance [ohm].
        D: viscous friction [N m s/rad].
        La: armature inductance [H].
        J: inertia [kg m^2].
        Ke: back-EMF constant [V s/rad].
        Kt: torque constant [N m/A].
        Tc: Coulomb friction torque [N m].
        load: load coefficient c_load [N m s/rad] (Tload = load*omega).
        unbalance: forcing at 1x the shaft's angle [rad/s^2] (the injected one; the scenario
            ``unbalanced_shaft``'s is ``unbalance_amplitude``).
        misalignment: forcing at 2x the shaft's angle [rad/s^2].
        supply: the share of the drive's voltage the motor receives (1: all of it).
    """

    Ra: float
    D: float
    La: float = math.nan
    J: float = math.nan
    Ke: float = math.nan
    Kt: float = math.nan
    Tc: float = 0.0
    load: float = math.nan
    unbalance: float = 0.0
    misalignment: float = 0.0
    supply: float = 1.0


class DCMotorPlant(SimulatedPlant):
    """The simulated DC motor plant; one call to :meth:`next_sample` per acquisition sample.

    Raises:
        EndOfStream: from :meth:`next_sample` after ``config.duration`` seconds.
    """

    channels = CHANNELS

    def __init__(self, config: DCMotorPlantConfig | None = None) -> None:
        self.config = config or DCMotorPlantConfig()
        c = self.config
        super().__init__(c)
        self._p = np.array([c.Ra, c.La, c.J, c.Ke, c.Kt, c.D, c.load_coefficient, 1.0, 0.0,
                            0.0])
        self._tc = c.coulomb_friction
        self._scenario = _SCENARIO_CODE[c.scenario]
        self._sp_times, self._sp_values = c.setpoint.build(c.duration)
        drive = c.drive_config
        self._speed = drive.speed.pack()
        self._current = (drive.current or LoopConfig()).pack()
        self._has_current = drive.current is not None
        self._m, self._mc, self._ph = drive.ticks(c.step)
        # The motor starts at rest, the drive's states at zero (see the _IA... indices).
        self._state = np.zeros(12)
        self._state[_LAST] = -1.0
        self._counts = 0  # encoder count at the last sample

    def setpoint_at(self, t: float) -> float:
        idx = int(np.searchsorted(self._sp_times, t + 1e-9, side="right")) - 1
        return float(self._sp_values[max(idx, 0)])

    def truth(self, t: float) -> PlantTruth:
        """The plant's true parameters at plant time ``t`` [s], faults and scenario included."""
        c = self.config
        age = t - c.fault_start
        if c.fault_period is not None and age > 0:
            age %= c.fault_period
        x = _ramp(age) if t >= c.fault_start else 0.0
        v = self._faulted(t)
        ra = v["Ra"] - RA_DROP * x if c.scenario == "resistance_degradation" else v["Ra"]
        d = v["D"] + D_RISE * x if c.scenario == "bearing_wear" else v["D"]
        ke_scale = v["Ke"] / c.Ke
        return PlantTruth(Ra=ra, D=d, La=v["La"], J=v["J"], Ke=v["Ke"], Kt=c.Kt * ke_scale,
                          Tc=v["Tc"], load=v["load"], unbalance=v["unbalance"],
                          misalignment=v["misalignment"],
                          supply=c.supply_fault.factor(t) if c.supply_fault else 1.0)

    def _apply_faults(self, t: float) -> None:
        """Set the compiled plant's parameters for the sample period from ``t`` [s]."""
        c = self.config
        if c.parameter_faults:
            v = self._faulted(t)
            p = self._p
            p[0], p[1], p[2], p[3] = v["Ra"], v["La"], v["J"], v["Ke"]
            p[4] = c.Kt * v["Ke"] / c.Ke
            p[5], p[6], p[8], p[9] = v["D"], v["load"], v["unbalance"], v["misalignment"]
            self._tc = v["Tc"]
        if c.supply_fault is not None:
            self._p[7] = c.supply_fault.factor(t)

    def next_sample(self) -> Sample:
        """Report the sample at the current time, then advance the plant one sample period."""
        c = self.config
        self._check_end()
        t = self.t
        sp = self.setpoint_at(t)
        j0 = self._k * self.n_sub
        st = self._state
        # The drive's update at t_k (if one is due) decides the voltage applied from t_k on.
        _tick(st, j0, sp, self._speed, self._current, self._has_current, self._m, self._mc,
              self._ph, c.step)
        w = float(st[_W])
        self._apply_faults(t)
        values = {"Va": float(st[_VA]),
                  "ia": float(st[_FI] if c.current_filter else st[_IA]),
                  "omega": float(st[_FW] if c.speed_filter else w),
                  "Tload": float(self._p[6]) * w, "setpoint": sp}
        if c.encoder_cpr:
            counts = math.floor(float(st[_ANGLE]) * c.encoder_cpr / (2 * math.pi))
            values["omega"] = ((counts - self._counts) * 2 * math.pi
                               / (c.encoder_cpr * c.sample_period))
            self._counts = counts
        if self._has_current:
            values["current_reference"] = float(st[_IREF])
        self._report(values, t, c.quantisation)
        _advance(st, j0, self.n_sub, c.step, sp, self._p, self._scenario, c.fault_start,
                 c.fault_period or 0.0, c.unbalance_amplitude,
                 math.nan if c.unbalance_follows_shaft else c.unbalance_frequency,
                 self._speed, self._current, self._has_current, self._m, self._mc, self._ph,
                 1 if c.power_stage == "unidirectional" else 0, self._tc,
                 c.current_filter or 0.0, c.speed_filter or 0.0, c.dead_zone_threshold)
        self._k += 1
        return Sample(t=t, values=values)
