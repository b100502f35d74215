"""Independent plant simulators of the held-out validation set (issue 55, item 8).

Nothing here shares code with twinwatch: numpy and scipy only, no ``twinwatch`` import. The
plants are continuous-time systems integrated by another scheme than the twin's (explicit Euler
sub-steps composed exactly):

* the DC motors (:class:`DCPlant` without a PWM stage: the paper's motor, an industrial 60 V
  motor, two servo motors) are integrated by scipy's RK45 (Dormand-Prince 5(4), the default
  method of :func:`scipy.integrate.solve_ivp`, adaptive steps, ``rtol`` 1e-8) between the
  drive's updates, restarted at each update (:class:`_Stepper`); the drive (a speed PI on the
  voltage, its output held between updates, clamped, with clamping anti-windup) runs every
  ``drive.period``;
* the PWM drive (a DC motor on a switching H-bridge, center-aligned PWM) is simulated per
  switching interval by the exact solution: within an on or an off interval the motor is
  linear and its voltage constant, so the state follows the matrix exponential, evaluated in
  the motor's modal coordinates (no integrator at all; far cheaper than an ODE solver stopping
  at some 8000 switching instants a second);
* the hydraulic actuator (:func:`simulate_hydraulic`) is written as a continuous-time system:
  the fluid is incompressible, so the pressure is the algebraic solution of the force balance
  with the valve flow (a quadratic in sqrt(p), solved exactly at every instant, where the
  paper's Eq. 14-16 take the previous step's pressure), and the valve PID (paper Eq. 17's
  gains) is the continuous-time PID with its derivative filter and clamping anti-windup; the
  whole loop is one ODE integrated by ``solve_ivp`` (LSODA, ``rtol`` 1e-8).

The plants of one kind are simulated as a *batch* (:func:`simulate_dc`): the scenarios of one
plant (nominal, each parameter fault, each fault inside the speed loop) stacked into one state
vector and integrated together, which costs about what one scenario costs. The batch of a plant
is fixed by the case table (:mod:`benchmarks.heldout.cases`), so the data of a case never depend
on which other cases run.

Scenarios (:class:`Scenario`) carry what changes in the *plant*: parameters (:class:`Change`),
the supply, extra load torques, a dead zone in the power stage, and the sensor faults the
controller sees (a speed reading in the speed loop, a position reading in the valve loop). The
sensor faults of readings the controller does not use, and the measurement noise, are applied
to the logged channels afterwards (:func:`log_channels`).

Sampling every :data:`SAMPLE_PERIOD` s. A DC drive's log: ``Va`` (the drive's latest voltage
command, as drives report it: what the motor receives only when the supply is right),
``ia``, ``omega`` (instantaneous: a PWM drive's current includes its ripple), ``setpoint`` (the
reference the speed PI uses, after the drive's ramp generator) and, on a test bench with a
torque flange, ``Tload``. The hydraulic actuator's: ``x``, ``p``, ``A_valve``, ``F_load``,
``x_ref``.

Run ``python benchmarks/heldout/plants.py`` for each plant's sanity check (steady state, the
loop reaching its set-points, the hydraulic pressure).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from scipy.integrate import RK45, solve_ivp

Array = npt.NDArray[np.float64]

#: The logger's sample period [s] (every plant).
SAMPLE_PERIOD = 0.01
#: Relative and absolute tolerances of ``solve_ivp``.
RTOL = 1e-8
ATOL = 1e-10
#: Speed [rad/s] over which Coulomb friction changes sign (tanh regularisation: a friction
#: torque that is continuous through standstill, as a lubricated contact is).
COULOMB_EPS = 0.05
#: Drive updates integrated in one chunk of precomputed parameter trajectories.
_CHUNK = 2000


# -- what changes over time -------------------------------------------------------------------

@dataclass(frozen=True)
class Change:
    """A quantity of the plant that changes from ``onset``: its shape over time is
    :meth:`level` (0 before the onset, 1 at full size) times ``size``.

    Attributes:
        target: what changes: a motor parameter (``Ra``, ``La``, ``J``, ``Ke``: the magnet,
            which moves ``Kt`` with it, ``D``), relative (``size`` -0.06 is -6 %); ``Tc`` (a
            Coulomb friction torque [N m]), ``supply`` (the motor receives (1 + size) times the
            commanded voltage: -0.08 is a sag to 0.92), ``load_step`` (an extra load torque
            [N m]), ``load_osc`` (a load torque of amplitude ``size`` [N m] at ``frequency``
            [Hz]), ``dead_zone`` (the power stage delivers nothing below ``size`` volts and
            ``size`` volts less above it); hydraulic: ``D``, ``q_pump``, ``k_spring``
            (relative), ``leak`` (the pressure is (1 + size) times the force balance's, paper
            Eq. 18), ``F_resist`` (an extra force on the rod [N]), ``F_osc`` (a force of
            amplitude ``size`` [N] at ``frequency``).
        size: the full-size change.
        onset: plant time it starts [s].
        ramp: seconds from 0 to full size (0: a step).
        end: plant time it is repaired (None: never).
        period, duty: intermittent: on for ``duty*period`` of every ``period`` seconds from
            the onset (None: always on).
        frequency: ``load_osc`` and ``F_osc`` only [Hz].
    """

    target: str
    size: float
    onset: float
    ramp: float = 0.0
    end: float | None = None
    period: float | None = None
    duty: float = 0.5
    frequency: float = 0.0

    def level(self, t: Array | float) -> Array:
        """The change's shape at ``t`` (0..1), vectorised over ``t``."""
        t = np.asarray(t, dtype=np.float64)
        if self.ramp > 0.0:
            g = np.clip((t - self.onset) / self.ramp, 0.0, 1.0)
        else:
            g = (t >= self.onset).astype(np.float64)
        if self.end is not None:
            g = np.where(t >= self.end, 0.0, g)
        if self.period is not None:
            phase = np.mod(t - self.onset, self.period)
            g = g * (phase < self.duty * self.period)
        return g


@dataclass(frozen=True)
class SensorFault:
    """A reading that is wrong from ``onset``: ``gain`` (reading = g x value, g moving from 1
    to ``value`` over ``ramp`` s), ``offset`` (reading = value + offset) or ``frozen`` (the
    reading repeats its last value before the onset, noise and all).

    Attributes:
        channel: the logged channel (``ia``, ``omega``, ``x``, ``p``, ...).
        kind: ``gain``, ``offset`` or ``frozen``.
        value: the gain or the offset (unused when frozen).
        onset: plant time [s].
        ramp: seconds to full size (gain and offset).
    """

    channel: str
    kind: str
    value: float = 0.0
    onset: float = 0.0
    ramp: float = 0.0

    def _level(self, t: Array | float) -> Array:
        return Change(self.channel, 1.0, self.onset, self.ramp).level(t)

    def distort(self, t: Array | float, x: Array | float) -> Array:
        """The reading of the true ``x`` at ``t`` (gain and offset; frozen: unchanged)."""
        g = self._level(t)
        if self.kind == "gain":
            return np.asarray(x) * (1.0 + (self.value - 1.0) * g)
        if self.kind == "offset":
            return np.asarray(x) + self.value * g
        return np.asarray(x, dtype=np.float64)


@dataclass(frozen=True)
class Scenario:
    """What happens to the plant: its changes and the faults of the readings its controller
    uses. Hashable: the key of a simulated trajectory (sensor faults of readings the
    controller does not use are left out: they do not change the plant)."""

    changes: tuple[Change, ...] = ()
    loop_sensors: tuple[SensorFault, ...] = ()


# -- DC motor plants ----------------------------------------------------------------------------

@dataclass(frozen=True)
class DCMotor:
    """A permanent-magnet DC motor's true parameters (SI): armature resistance [ohm] and
    inductance [H], rotor inertia [kg m^2], back-EMF [V s/rad] and torque [N m/A] constants,
    viscous friction [N m s/rad]."""

    Ra: float
    La: float
    J: float
    Ke: float
    Kt: float
    D: float

    @property
    def tau_e(self) -> float:
        """Electrical time constant La/Ra [s]."""
        return self.La / self.Ra

    def as_dict(self) -> dict[str, float]:
        """The parameters by the dc_motor twin's names."""
        return {"Ra": self.Ra, "La": self.La, "J": self.J, "Ke": self.Ke, "Kt": self.Kt,
                "D": self.D}


@dataclass(frozen=True)
class SpeedDrive:
    """A speed PI on the armature voltage, as a drive's firmware runs it.

    Every ``period`` s: the reference moves towards the set-point by at most ``accel*period``
    (the ramp generator; None: steps), ``e = r - speed reading``, the integrator adds
    ``ki*period*e`` first and the output is ``kp*e + I`` (backward Euler: MATLAB's Discrete PID
    with that integrator method), clamped to ``[v_min, v_max]``; a clamped update whose error
    pushes further into the limit adds nothing to the integrator (clamping anti-windup). The
    output is held until the next update.
    """

    period: float
    kp: float
    ki: float
    v_min: float
    v_max: float
    accel: float | None = None


@dataclass(frozen=True)
class PWMStage:
    """A switching H-bridge between the drive and the motor: center-aligned PWM at
    ``frequency`` [Hz] from ``supply`` [V]; duty = command/supply (signed, clipped to 1); the
    off time freewheels through the low-side switches (the terminal voltage is 0, the current
    may reverse). The drive updates its command every ``periods_per_update`` PWM periods."""

    frequency: float
    supply: float
    periods_per_update: int


@dataclass(frozen=True)
class Schedule:
    """The operating profile: set-points held for dwells drawn uniformly in ``dwell`` [s]
    from ``levels`` (and, with a torque flange, load torques from ``loads`` [N m], 0 while the
    set-point is 0), drawn by a generator seeded with ``seed`` (the plant's own profile: every
    case of a plant runs it). Changes fall on the sample grid."""

    levels: tuple[float, ...]
    dwell: tuple[float, float]
    seed: int
    loads: tuple[float, ...] = ()
    load_ramp: float = 0.5

    def table(self, duration: float) -> tuple[Array, Array, Array]:
        """Change times [s], set-points and load levels up to ``duration``."""
        rng = np.random.default_rng(self.seed)
        times, sps, loads = [0.0], [0.0], [0.0]
        t = 3.0  # the machine starts at rest
        while t < duration:
            sp = float(rng.choice(self.levels))
            while sp == sps[-1]:
                sp = float(rng.choice(self.levels))
            load = float(rng.choice(self.loads)) if self.loads and sp != 0.0 else 0.0
            times.append(round(t / SAMPLE_PERIOD) * SAMPLE_PERIOD)
            sps.append(sp)
            loads.append(load)
            t += float(rng.uniform(*self.dwell))
        return np.array(times), np.array(sps), np.array(loads)


@dataclass(frozen=True)
class DCPlant:
    """A DC motor, its drive and its load.

    Attributes:
        name: the plant's short name (case names start with it).
        motor: the true parameters.
        drive: the speed PI.
        schedule: the operating profile.
        load: ``viscous_held`` (Tload = ``load_coefficient``*omega, computed at each drive
            update and held until the next: the paper's motor as an independent library
            simulates it), ``viscous`` (the same, continuous), ``flange`` (a load machine
            applies the schedule's torques, ramped over ``schedule.load_ramp`` s, measured by a
            torque flange: channel ``Tload``).
        load_coefficient: [N m s/rad].
        pwm: the H-bridge, or None (a linear power stage: the motor receives the command).
        resolution: the logger's resolution per channel (readings are rounded to it: a settled
            drive repeats its readings to the last digit).
        description: one line for the reader.
    """

    name: str
    motor: DCMotor
    drive: SpeedDrive
    schedule: Schedule
    load: str = "viscous"
    load_coefficient: float = 0.0
    pwm: PWMStage | None = None
    resolution: Mapping[str, float] = field(default_factory=dict)
    description: str = ""

    @property
    def channels(self) -> tuple[str, ...]:
        """The logged channels."""
        return ("Va", "ia", "omega", "setpoint") + (("Tload",) if self.load == "flange" else ())


def _setpoint_fn(plant: DCPlant, duration: float) -> tuple[Callable[[float], float],
                                                              Callable[[Array], Array]]:
    """The set-point at a time (scalar) and the flange's load torque (vectorised)."""
    times, sps, loads = plant.schedule.table(duration + 1.0)
    ramp = plant.schedule.load_ramp

    def setpoint(t: float) -> float:
        return float(sps[np.searchsorted(times, t + 1e-9, side="right") - 1])

    def flange(t: Array) -> Array:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros_like(t)
        for k in range(1, len(times)):  # each change ramps from the previous level
            out += (loads[k] - loads[k - 1]) * np.clip((t - times[k]) / ramp, 0.0, 1.0)
        return out

    return setpoint, flange


_RELATIVE = ("Ra", "La", "J", "Ke", "D")
_ABSOLUTE = ("Tc", "load_step", "load_osc", "dead_zone", "supply")


class _Batch:
    """The scenarios' parameter trajectories on a grid of times, as (times, scenarios)
    arrays."""

    def __init__(self, motor: DCMotor, scenarios: Sequence[Scenario]) -> None:
        self.motor = motor
        self.scenarios = list(scenarios)
        self.n = len(scenarios)
        freq = np.zeros(self.n)
        for s, sc in enumerate(self.scenarios):
            for c in sc.changes:
                if c.target not in _RELATIVE + _ABSOLUTE:
                    raise ValueError(f"a DC plant cannot change {c.target!r}")
                if c.target == "load_osc":
                    freq[s] = c.frequency
        self.osc_omega = 2.0 * math.pi * freq
        self.any = {t: any(c.target == t for sc in self.scenarios for c in sc.changes)
                    for t in _RELATIVE + _ABSOLUTE}

    def values(self, target: str, t: Array) -> Array:
        """(len(t), n): the target's value (relative targets: the parameter; ``supply``: the
        ratio; the others: their size) at the times ``t``."""
        out = np.zeros((len(t), self.n))
        if self.any[target]:
            for s, sc in enumerate(self.scenarios):
                for c in sc.changes:
                    if c.target == target:
                        out[:, s] += c.size * c.level(t)
        if target in _RELATIVE:
            base = getattr(self.motor, target)
            return base * (1.0 + out)
        if target == "supply":
            return 1.0 + out
        return out

    def sensor(self, t: Array) -> tuple[Array, Array] | None:
        """(len(t), n) gain and offset of the speed reading the drive sees at the times
        ``t`` (the loop's sensor faults), or None when no scenario has one."""
        faults = [(s, f) for s, sc in enumerate(self.scenarios) for f in sc.loop_sensors
                  if f.channel == "omega"]
        if not faults:
            return None
        gain, offset = np.ones((len(t), self.n)), np.zeros((len(t), self.n))
        for s, f in faults:
            if f.kind == "gain":
                gain[:, s] *= f.distort(t, np.ones(len(t)))
            elif f.kind == "offset":
                offset[:, s] += f.distort(t, np.zeros(len(t)))
            else:
                raise ValueError("a frozen reading in the speed loop is not simulated")
        return gain, offset

    def reading(self, t: float, w: Array) -> Array:
        """The speed reading the drive sees at ``t`` (the loop's sensor faults)."""
        gs = self.sensor(np.array([t]))
        return w if gs is None else gs[0][0] * w + gs[1][0]


class _PI:
    """The drive's speed PI over a batch (see :class:`SpeedDrive`)."""

    def __init__(self, drive: SpeedDrive, n: int) -> None:
        self.d = drive
        self.integ = np.zeros(n)
        self.ref = np.zeros(n)

    def update(self, setpoint: float, reading: Array) -> Array:
        """One update from the set-point and the speed reading: the new voltage command."""
        d = self.d
        if d.accel is None:
            self.ref[:] = setpoint
        else:
            step = d.accel * d.period
            self.ref += np.minimum(np.maximum(setpoint - self.ref, -step), step)
        e = self.ref - reading
        trial = self.integ + d.ki * d.period * e
        u = d.kp * e + trial
        pushing = ((u > d.v_max) & (e > 0)) | ((u < d.v_min) & (e < 0))
        if pushing.any():
            trial = np.where(pushing, self.integ, trial)
            u = d.kp * e + trial
        self.integ = trial
        return np.minimum(np.maximum(u, d.v_min), d.v_max)


class _Stepper:
    """scipy's RK45 (Dormand-Prince 5(4), the method of ``solve_ivp``) carried across the
    drive's updates with error control at :data:`RTOL`, :data:`ATOL`. The input jumps at an
    update, so at each one the solver restarts from the state it reached: its end time set to
    the next update, its first-same-as-last derivative evaluated afresh with the new input,
    its step size kept (what ``solve_ivp(..., first_step=h)`` does per interval, without
    building the solver again: a third of the cost)."""

    def __init__(self, rhs: Callable[[float, Array], Array], t0: float, y: Array) -> None:
        self.rhs = rhs
        self.solver: RK45 | None = None
        self.t0 = t0
        self.y0 = y

    def advance(self, t1: float) -> Array:
        """The state at ``t1`` (the next update) from the current one."""
        s = self.solver
        if s is None:
            s = self.solver = RK45(self.rhs, self.t0, self.y0, t1, rtol=RTOL, atol=ATOL,
                                   first_step=t1 - self.t0)
        else:
            s.t_bound = t1
            s.status = "running"
            s.f = s.fun(s.t, s.y)
        while s.status == "running":
            s.step()
        if s.status != "finished" or s.t != t1:
            raise RuntimeError(f"RK45 failed at {s.t} s")
        return s.y


def _dead_zone(v: Array, width: Array) -> Array:
    return np.sign(v) * np.maximum(np.abs(v) - width, 0.0)


def simulate_dc(plant: DCPlant, scenarios: Sequence[Scenario],
                durations: Sequence[float]) -> list[dict[str, Array]]:
    """Simulate ``scenarios`` of ``plant`` together (each for its duration [s]); return per
    scenario the noise-free log at every sample: ``t`` and :attr:`DCPlant.channels`, and the
    voltage the motor received (``Vm``, the sample's update's) for the checks.

    Within a drive interval the voltage, the held load and the parameters (evaluated at the
    interval's middle: a drift moves them by less than 1e-5 of its size within it) are
    constant; a Coulomb friction (``tanh(omega/COULOMB_EPS)``) and an oscillating load torque
    act continuously. The finished scenarios leave the batch (a nominal run is longer)."""
    if plant.pwm is not None:
        return _simulate_pwm(plant, scenarios, durations)
    drive = plant.drive
    per_sample = SAMPLE_PERIOD / drive.period
    if abs(per_sample - round(per_sample)) > 1e-9:
        raise ValueError(f"{plant.name}: the drive period must divide {SAMPLE_PERIOD} s")
    per_sample = int(round(per_sample))
    m = plant.motor
    n_all = len(scenarios)
    durations = [float(d) for d in durations]
    setpoint, flange = _setpoint_fn(plant, max(durations))
    logs: list[dict[str, list[Array]]] = [
        {k: [] for k in ("t", *plant.channels, "Vm")} for _ in range(n_all)]
    alive = list(range(n_all))
    state = np.zeros(2 * n_all)  # ia then omega of every scenario
    pi = _PI(drive, n_all)
    j = 0
    while alive:
        end_j = int(round(min(durations[s] for s in alive) / drive.period))
        idx = np.array(alive)
        n = len(alive)
        batch = _Batch(m, [scenarios[s] for s in alive])
        pi_sub = _PI(drive, n)
        pi_sub.integ, pi_sub.ref = pi.integ[idx].copy(), pi.ref[idx].copy()
        y = np.concatenate([state[idx], state[n_all + idx]])
        swap = np.concatenate([np.arange(n, 2 * n), np.arange(n)])
        # dx/dt = P*x + Q*x[swap] + R (+ the continuous torques / J on omega)
        coef: list[Array] = [np.zeros(2 * n)] * 5
        nonlinear = batch.any["Tc"] or batch.any["load_osc"]

        def rhs(t: float, x: Array, coef: list[Array] = coef, swap: Array = swap,
                n: int = n, batch: _Batch = batch, nonlinear: bool = nonlinear) -> Array:
            dx = coef[0] * x + coef[1] * x[swap] + coef[2]
            if nonlinear:
                w = x[n:]
                dx[n:] -= (coef[3] * np.tanh(w / COULOMB_EPS)
                           + coef[4] * np.sin(batch.osc_omega * t))
            return dx

        sample_rows: list[tuple[float, Array, Array, Array, Array, float]] = []
        stepper: _Stepper | None = None
        while j < end_j:
            j1 = min(j + _CHUNK, end_j)
            mids = (np.arange(j, j1) + 0.5) * drive.period
            traj = {tg: batch.values(tg, mids) for tg in _RELATIVE + _ABSOLUTE}
            fl = (flange(np.arange(j, j1) * drive.period) if plant.load == "flange"
                  else np.zeros(j1 - j))
            sensor = batch.sensor(np.arange(j, j1) * drive.period)
            visc = plant.load_coefficient if plant.load == "viscous" else 0.0
            held = plant.load_coefficient if plant.load == "viscous_held" else 0.0
            ratio = m.Kt / m.Ke
            # the coefficients of the chunk's intervals, (intervals, 2n) each
            ra, la, jm, ke, d = (traj[tg] for tg in _RELATIVE)
            c0 = np.concatenate((-ra / la, -(d + visc) / jm), axis=1)
            c1 = np.concatenate((-ke / la, ratio * ke / jm), axis=1)
            inv_la, inv_j = 1.0 / la, 1.0 / jm
            tc_j, osc_j = traj["Tc"] / jm, traj["load_osc"] / jm
            supply, load_step = traj["supply"], traj["load_step"]
            for jj in range(j, j1):
                r = jj - j
                t0 = jj * drive.period
                w = y[n:]
                cmd = pi_sub.update(setpoint(t0), w if sensor is None
                                    else sensor[0][r] * w + sensor[1][r])
                vm = cmd * supply[r]
                if batch.any["dead_zone"]:
                    vm = _dead_zone(vm, traj["dead_zone"][r])
                tl = load_step[r] + held * w + fl[r]
                coef[0] = c0[r]
                coef[1] = c1[r]
                coef[2] = np.concatenate((vm * inv_la[r], -tl * inv_j[r]))
                if nonlinear:
                    coef[3] = tc_j[r]
                    coef[4] = osc_j[r]
                if jj % per_sample == 0:
                    sample_rows.append((t0, cmd, y.copy(), pi_sub.ref.copy(), vm, fl[r]))
                if stepper is None:
                    stepper = _Stepper(rhs, t0, y)
                y = stepper.advance((jj + 1) * drive.period)
            j = j1
        for t0, cmd, yy, ref, vm, flv in sample_rows:
            for k, s in enumerate(alive):
                lg = logs[s]
                lg["t"].append(round(t0, 9))
                lg["Va"].append(cmd[k])
                lg["ia"].append(yy[k])
                lg["omega"].append(yy[n + k])
                lg["setpoint"].append(ref[k])
                lg["Vm"].append(vm[k])
                if plant.load == "flange":
                    lg["Tload"].append(flv)
        # write back, drop the finished scenarios
        state[idx], state[n_all + idx] = y[:n], y[n:]
        pi.integ[idx], pi.ref[idx] = pi_sub.integ, pi_sub.ref
        alive = [s for s in alive if durations[s] > end_j * drive.period + 1e-9]
    return [{k: np.asarray(v, dtype=np.float64) for k, v in lg.items()} for lg in logs]


# -- the PWM drive: exact per switching interval -------------------------------------------------

def _modes(a11: Array, a12: Array, a21: Array,
           a22: Array) -> tuple[Array, tuple[Array, ...], tuple[Array, ...]]:
    """The eigenvalues (2, n) of the 2x2 matrices A (an overdamped motor: real and
    distinct), the eigenvectors' matrix V = [[a12, a12], [l1 - a11, l2 - a11]] and its
    inverse, each as its four entries (v11, v12, v21, v22)."""
    s = 0.5 * (a11 + a22)
    disc = s * s - (a11 * a22 - a12 * a21)
    if np.any(disc <= 0.0):
        raise ValueError("the PWM plant's motor must be overdamped (real modes)")
    r = np.sqrt(disc)
    lam = np.array([s + r, s - r])
    v = (a12, a12, lam[0] - a11, lam[1] - a11)
    det = v[0] * v[3] - v[1] * v[2]
    vinv = (v[3] / det, -v[1] / det, -v[2] / det, v[0] / det)
    return lam, v, vinv


def _apply(m: tuple[Array, ...], x: Array) -> Array:
    """A 2x2 matrix (its four entries, each (n,)) times (2, n) vectors."""
    return np.array([m[0] * x[0] + m[1] * x[1], m[2] * x[0] + m[3] * x[1]])


def _pwm_modal(z: Array, lam: Array, tau: float, b_tl: Array, b_v: Array,
               on: Sequence[tuple[Array, Array]]) -> Array:
    """The modal state after ``tau`` s from ``z``: each mode dz/dt = lam z + b_tl + b_v*[on],
    solved exactly: e^{lam tau} z + (e^{lam tau} - 1)/lam b_tl + sum over the on intervals
    [s1, s2] (clipped to [0, tau]) of (e^{lam (tau - s1)} - e^{lam (tau - s2)})/lam b_v."""
    e = np.exp(lam * tau)
    acc = 0.0
    for s1, s2 in on:
        acc = acc + np.exp(lam * (tau - np.minimum(s1, tau))) - np.exp(
            lam * (tau - np.minimum(s2, tau)))
    return e * z + ((e - 1.0) * b_tl + acc * b_v) / lam


def _simulate_pwm(plant: DCPlant, scenarios: Sequence[Scenario],
                  durations: Sequence[float]) -> list[dict[str, Array]]:
    """:func:`simulate_dc` for a plant on an H-bridge. Between two drive updates the motor is
    linear and its voltage piecewise constant (on: the supply, off: 0), so the state at any
    instant is the exact solution in the motor's modal coordinates (:func:`_pwm_modal`),
    summed over the on intervals of the center-aligned PWM: per switching interval, no
    integrator. Parameters are held over each sample period (evaluated at its middle: a drift
    moves them by less than 1e-4 of its size within it)."""
    pwm = plant.pwm
    assert pwm is not None
    if plant.load not in ("viscous", "flange"):
        raise ValueError(f"{plant.name}: a PWM plant takes a viscous or flange load")
    n = len(scenarios)
    batch = _Batch(plant.motor, scenarios)
    for tg in ("Tc", "load_osc", "dead_zone"):
        if batch.any[tg]:
            raise ValueError(f"{plant.name}: the exact PWM plant is linear: no {tg}")
    tp = 1.0 / pwm.frequency
    period = tp * pwm.periods_per_update
    setpoint, flange = _setpoint_fn(plant, max(durations))
    n_samples = [int(round(d / SAMPLE_PERIOD)) for d in durations]
    total = max(n_samples)
    out = {k: np.zeros((total, n)) for k in ("Va", "ia", "omega", "setpoint", "Vm", "Tload")}
    pi = _PI(replace(plant.drive, period=period), n)
    x = np.zeros((2, n))
    c = plant.load_coefficient
    ratio = plant.motor.Kt / plant.motor.Ke
    mids = (np.arange(total) + 0.5) * SAMPLE_PERIOD
    traj = {tg: batch.values(tg, mids) for tg in _RELATIVE + ("load_step", "supply")}
    fl = flange(np.arange(total) * SAMPLE_PERIOD) if plant.load == "flange" else None
    k_next = 0   # the next sample to log
    jj = 0       # the drive update
    cache: tuple[int, tuple[Array, tuple[Array, ...], tuple[Array, ...]]] | None = None
    while k_next < total:
        t0 = jj * period
        kp = min(int(t0 / SAMPLE_PERIOD + 1e-9), total - 1)  # the sample period it starts in
        if cache is None or cache[0] != kp:
            ra, la, jm, ke, d = (traj[tg][kp] for tg in _RELATIVE)
            cache = (kp, _modes(-ra / la, -ke / la, ratio * ke / jm, -(d + c) / jm))
        lam, v, vinv = cache[1]
        ra, la, jm, ke, d = (traj[tg][kp] for tg in _RELATIVE)
        cmd = pi.update(setpoint(t0), batch.reading(t0, x[1]))
        duty = np.clip(cmd / pwm.supply, -1.0, 1.0)
        von = np.sign(duty) * pwm.supply * traj["supply"][kp]
        tl = traj["load_step"][kp] + (fl[kp] if fl is not None else 0.0)
        b_tl = np.array([vinv[1], vinv[3]]) * (-tl / jm)
        b_v = np.array([vinv[0], vinv[2]]) * (von / la)
        h_on = np.abs(duty) * tp
        h_off = 0.5 * (tp - h_on)
        on = [(k * tp + h_off, k * tp + h_off + h_on) for k in range(pwm.periods_per_update)]
        z = _apply(vinv, x)
        t_end = t0 + period
        while k_next < total and k_next * SAMPLE_PERIOD < t_end - 1e-12:
            tau = k_next * SAMPLE_PERIOD - t0
            xs = _apply(v, _pwm_modal(z, lam, tau, b_tl, b_v, on))
            out["Va"][k_next] = duty * pwm.supply
            out["ia"][k_next] = xs[0]
            out["omega"][k_next] = xs[1]
            out["setpoint"][k_next] = pi.ref
            out["Vm"][k_next] = von * np.abs(duty)
            out["Tload"][k_next] = fl[k_next] if fl is not None else 0.0
            k_next += 1
        x = _apply(v, _pwm_modal(z, lam, period, b_tl, b_v, on))
        jj += 1
    logs = []
    for s in range(n):
        m = n_samples[s]
        lg = {"t": np.round(np.arange(m) * SAMPLE_PERIOD, 9)}
        for ch in (*plant.channels, "Vm"):
            lg[ch] = out[ch][:m, s].copy()
        logs.append(lg)
    return logs


# -- the hydraulic actuator --------------------------------------------------------------------

@dataclass(frozen=True)
class HydraulicPlant:
    """The paper's hydraulic actuator (NOTES.md: Eq. 6-10, 14-18, Table 4) as a
    continuous-time system (see the module docstring).

    Attributes:
        k_spring, D, q_pump, A_max, A_piston, F_resist: the true parameters (SI).
        mass: the load [kg] (its weight is F_load).
        kp, ki, kd, n_filter: the valve PID (paper Eq. 17's gains), on e = x - x_ref
            (opening the valve lowers the piston), clamped to [0, A_max].
        reference: (offset [m], [(amplitude [m], frequency [Hz], phase [rad]), ...]): the
            position reference, a sum of sinusoids (this set's own, not the paper's).
        resolution: the logger's resolution per channel.
    """

    name: str = "hyd"
    k_spring: float = 200.0
    D: float = 100.0
    q_pump: float = 0.02
    A_max: float = 1e-4
    A_piston: float = 0.196349375
    F_resist: float = 0.0
    mass: float = 1000.0
    kp: float = 0.000346
    ki: float = 3.513406
    kd: float = 0.000119
    n_filter: float = 2.076743
    reference: tuple[float, tuple[tuple[float, float, float], ...]] = (
        0.5, ((0.33, 0.0041, 0.0), (0.07, 0.0237, 1.1)))
    resolution: Mapping[str, float] = field(default_factory=dict)
    description: str = ""

    channels = ("x", "p", "A_valve", "F_load", "x_ref")

    def as_dict(self) -> dict[str, float]:
        """The parameters by the hydraulic_actuator twin's names."""
        return {"k_spring": self.k_spring, "D": self.D, "q_pump": self.q_pump,
                "A_max": self.A_max, "A_piston": self.A_piston, "F_resist": self.F_resist}

    def x_ref(self, t: Array | float) -> Array:
        """The position reference [m]."""
        t = np.asarray(t, dtype=np.float64)
        off, parts = self.reference
        out = np.full_like(t, off)
        for amp, f, ph in parts:
            out = out + amp * np.sin(2.0 * math.pi * f * t + ph)
        return out

    def x_ref_dot(self, t: float) -> float:
        """Its time derivative [m/s]."""
        _, parts = self.reference
        return float(sum(amp * 2.0 * math.pi * f * math.cos(2.0 * math.pi * f * t + ph)
                         for amp, f, ph in parts))


_HYD_TARGETS = ("D", "q_pump", "k_spring", "leak", "F_resist", "F_osc")


def _hyd_value(plant: HydraulicPlant, sc: Scenario, target: str, t: float) -> float:
    """A hydraulic quantity at ``t`` under ``sc``."""
    total = 0.0
    for c in sc.changes:
        if c.target not in _HYD_TARGETS:
            raise ValueError(f"the hydraulic plant cannot change {c.target!r}")
        if c.target == target:
            lv = float(c.level(t))
            total += c.size * lv * (math.sin(2.0 * math.pi * c.frequency * t)
                                    if target == "F_osc" else 1.0)
    if target in ("D", "q_pump", "k_spring"):
        return getattr(plant, target) * (1.0 + total)
    if target == "F_resist":
        return plant.F_resist + total
    return total


def hydraulic_pressure(plant: HydraulicPlant, x: float, area: float, *, D: float,
                       q_pump: float, k_spring: float, leak: float, force: float) -> float:
    """The pressure [Pa] that balances the forces with the valve's flow: with s = sqrt(p),
    v = (q - A_v sqrt(2) s)/A_p and A_p s^2/(1 + C) = F + k x + D v + F_r, a quadratic in s
    (its positive root)."""
    ap = plant.A_piston
    a = ap / (1.0 + leak)
    b = D * area * math.sqrt(2.0) / ap
    c = force + k_spring * x + D * q_pump / ap
    s = (-b + math.sqrt(b * b + 4.0 * a * c)) / (2.0 * a)
    return s * s


def simulate_hydraulic(plant: HydraulicPlant, scenario: Scenario,
                       duration: float) -> dict[str, Array]:
    """Simulate the actuator under ``scenario`` for ``duration`` s; return the noise-free log
    (``t`` and :attr:`HydraulicPlant.channels`)."""
    g = 9.81
    f_load = plant.mass * g
    pos_faults = [f for f in scenario.loop_sensors if f.channel == "x"]

    def quantities(t: float) -> dict[str, float]:
        return {tg: _hyd_value(plant, scenario, tg, t) for tg in _HYD_TARGETS}

    def x_read(t: float, x: float) -> float:
        for f in pos_faults:
            x = float(f.distort(t, x))
        return x

    def area_of(t: float, y: Array) -> tuple[float, float, float]:
        x, integ, z = y
        e = x_read(t, x) - float(plant.x_ref(t))
        u = plant.kp * e + integ + plant.kd * plant.n_filter * (e - z)
        return min(max(u, 0.0), plant.A_max), u, e

    def rhs(t: float, y: Array) -> list[float]:
        x = y[0]
        z = y[2]
        area, u, e = area_of(t, y)
        q = quantities(t)
        force = f_load + q["F_resist"] + q["F_osc"]
        p = hydraulic_pressure(plant, x, area, D=q["D"], q_pump=q["q_pump"],
                               k_spring=q["k_spring"], leak=q["leak"], force=force)
        v = (q["q_pump"] - area * math.sqrt(2.0 * p)) / plant.A_piston
        pushing = (u > plant.A_max and e > 0) or (u < 0.0 and e < 0)
        di = 0.0 if pushing else plant.ki * e
        return [v, di, plant.n_filter * (e - z)]

    n = int(round(duration / SAMPLE_PERIOD))
    t_eval = np.arange(n) * SAMPLE_PERIOD
    # start on the reference, at rest in the loop: the integrator holds the valve's flow
    x0 = float(plant.x_ref(0.0))
    q0 = quantities(0.0)
    v0 = plant.x_ref_dot(0.0)
    p0 = (f_load + q0["k_spring"] * x0 + q0["D"] * v0) / plant.A_piston
    a0 = (q0["q_pump"] - plant.A_piston * v0) / math.sqrt(2.0 * p0)
    y0 = np.array([x0, a0, 0.0])
    sol = solve_ivp(rhs, (0.0, t_eval[-1]), y0, method="LSODA", t_eval=t_eval, rtol=RTOL,
                    atol=1e-13, max_step=0.005)
    if not sol.success:
        raise RuntimeError(f"{plant.name}: solve_ivp failed: {sol.message}")
    log: dict[str, list[float]] = {k: [] for k in plant.channels}
    for k, t in enumerate(sol.t):
        y = sol.y[:, k]
        area, _, _ = area_of(float(t), y)
        q = quantities(float(t))
        force = f_load + q["F_resist"] + q["F_osc"]
        p = hydraulic_pressure(plant, float(y[0]), area, D=q["D"], q_pump=q["q_pump"],
                               k_spring=q["k_spring"], leak=q["leak"], force=force)
        log["x"].append(float(y[0]))
        log["p"].append(p)
        log["A_valve"].append(area)
        log["F_load"].append(f_load)
        log["x_ref"].append(float(plant.x_ref(float(t))))
    out = {k: np.asarray(v) for k, v in log.items()}
    out["t"] = np.round(t_eval, 9)
    return out


# -- the log: sensor faults, noise, resolution -------------------------------------------------

def log_channels(clean: Mapping[str, Array], channels: Iterable[str],
                 noisy: Iterable[str], noise_pct: float, seed: int,
                 sensors: Sequence[SensorFault] = (),
                 resolution: Mapping[str, float] | None = None) -> dict[str, Array]:
    """The logged channels from a noise-free trajectory: each sensor fault's gain or offset
    (those the controller saw are already in ``clean``: pass only the others), then white
    Gaussian noise of ``noise_pct`` % of the channel's RMS on the measured channels
    (``noisy``; commands and references are exact), then a frozen reading repeats its last
    value before the onset, then the logger's resolution. Deterministic from ``seed``."""
    rng = np.random.default_rng(seed)
    t = np.asarray(clean["t"])
    out: dict[str, Array] = {"t": t.copy()}
    noisy = tuple(noisy)
    for ch in channels:
        x = np.asarray(clean[ch], dtype=np.float64).copy()
        for f in sensors:
            if f.channel == ch and f.kind in ("gain", "offset"):
                x = f.distort(t, x)
        if ch in noisy and noise_pct > 0.0:
            rms = float(np.sqrt(np.mean(np.asarray(clean[ch]) ** 2)))
            x = x + rng.normal(0.0, noise_pct / 100.0 * rms, size=x.shape)
        for f in sensors:
            if f.channel == ch and f.kind == "frozen":
                k0 = int(np.searchsorted(t, f.onset - 1e-9))
                if k0 > 0:
                    x[k0:] = x[k0 - 1]
        res = (resolution or {}).get(ch)
        if res:
            x = np.round(x / res) * res
        out[ch] = x
    return out


# -- the plants of the set -----------------------------------------------------------------------

#: (a) the paper's DC motor (NOTES.md, Table 3), its load held over the drive's 1 ms updates.
PAPER = DCPlant(
    name="pm",
    motor=DCMotor(Ra=6.5, La=0.673, J=0.001171, Ke=0.038, Kt=0.038, D=0.00143),
    drive=SpeedDrive(period=0.001, kp=0.3, ki=0.1, v_min=-48.0, v_max=48.0),
    schedule=Schedule(levels=(0.0, 3.0, 6.5, 9.0, 11.0, 15.5, 18.0, 20.0), dwell=(35.0, 70.0),
                      seed=5501),
    load="viscous_held", load_coefficient=0.006,
    resolution={"Va": 1e-4, "ia": 1e-5, "omega": 1e-4},
    description="the paper's motor (Ra 6.5 ohm, La 0.673 H, tau_e 104 ms), PI 0.3/0.1 every "
                "1 ms, load 0.006*omega held over 1 ms")

#: (b) an industrial 60 V permanent-magnet motor on a test bench (a load machine, its torque
#: measured by a flange): tau_e = 1 ms, a tenth of the sample period.
INDUSTRIAL = DCPlant(
    name="ind",
    motor=DCMotor(Ra=0.040, La=40e-6, J=0.010, Ke=0.17, Kt=0.17, D=0.0020),
    drive=SpeedDrive(period=0.001, kp=0.5, ki=5.0, v_min=-60.0, v_max=60.0, accel=150.0),
    schedule=Schedule(levels=(0.0, 60.0, 110.0, 160.0, 210.0, 260.0, 300.0),
                      dwell=(8.0, 22.0), seed=5502, loads=(1.0, 2.5, 4.0, 6.0, 8.0)),
    load="flange",
    resolution={"Va": 1e-3, "ia": 1e-3, "omega": 1e-3, "Tload": 1e-3},
    description="60 V PM motor, Ra 40 mohm, La 40 uH (tau_e 1 ms), Ke 0.17, J 0.01; PI at "
                "1 kHz clamped at +-60 V, set-point ramp 150 rad/s^2; load machine 1-8 N m")

#: (c) a small servo motor: tau_e = 2 ms, a fifth of the sample period; reverses and stops.
SERVO_SMALL = DCPlant(
    name="srvS",
    motor=DCMotor(Ra=1.10, La=2.2e-3, J=1.6e-5, Ke=0.026, Kt=0.026, D=1.2e-5),
    drive=SpeedDrive(period=0.0005, kp=0.02, ki=0.5, v_min=-24.0, v_max=24.0, accel=2500.0),
    schedule=Schedule(levels=(-500.0, -250.0, 0.0, 0.0, 150.0, 300.0, 450.0, 600.0),
                      dwell=(4.0, 12.0), seed=5503),
    load="viscous", load_coefficient=1.5e-5,
    resolution={"Va": 1e-3, "ia": 1e-4, "omega": 1e-3},
    description="24 V servo, Ra 1.1 ohm, La 2.2 mH (tau_e 2 ms), Ke 0.026, J 1.6e-5; PI at "
                "2 kHz, +-24 V, ramp 2500 rad/s^2; reverses and stops")

#: (d) a mid servo motor: tau_e = 10 ms, the sample period.
SERVO_MID = DCPlant(
    name="srvM",
    motor=DCMotor(Ra=0.60, La=6.0e-3, J=6.0e-4, Ke=0.11, Kt=0.11, D=2.0e-4),
    drive=SpeedDrive(period=0.001, kp=0.15, ki=2.0, v_min=-48.0, v_max=48.0, accel=1200.0),
    schedule=Schedule(levels=(0.0, 80.0, 140.0, 200.0, 260.0, 320.0), dwell=(5.0, 15.0),
                      seed=5504),
    load="viscous", load_coefficient=8e-4,
    resolution={"Va": 1e-3, "ia": 1e-4, "omega": 1e-3},
    description="48 V servo, Ra 0.6 ohm, La 6 mH (tau_e 10 ms), Ke 0.11, J 6e-4; PI at 1 kHz, "
                "+-48 V, ramp 1200 rad/s^2; viscous load 8e-4")

#: (e) a DC motor on a switching H-bridge (3906.25 Hz = 16 MHz/4096, center-aligned), the
#: drive's PI every 4 PWM periods (1.024 ms, not a divisor of the sample period: the logger's
#: clock is not the drive's), Va logged as duty x supply, the current sampled instantly.
PWM_DRIVE = DCPlant(
    name="pwm",
    motor=DCMotor(Ra=1.6, La=24e-3, J=3.0e-4, Ke=0.05, Kt=0.05, D=5.0e-5),
    drive=SpeedDrive(period=4 / 3906.25, kp=0.08, ki=1.2, v_min=-24.0, v_max=24.0,
                     accel=600.0),
    schedule=Schedule(levels=(0.0, 50.0, 100.0, 150.0, 200.0, 250.0), dwell=(6.0, 16.0),
                      seed=5505),
    load="viscous", load_coefficient=1.0e-3,
    pwm=PWMStage(frequency=3906.25, supply=24.0, periods_per_update=4),
    resolution={"Va": 1e-3, "ia": 1e-4, "omega": 1e-3},
    description="24 V motor, Ra 1.6 ohm, La 24 mH (tau_e 15 ms), Ke 0.05, J 3e-4, on a "
                "3.9 kHz H-bridge; PI every 1.024 ms; current sampled with its ripple")

#: (f) the paper's hydraulic actuator (NOTES.md), continuous time.
HYDRAULIC = HydraulicPlant(
    resolution={"x": 1e-7, "p": 1e-3, "A_valve": 1e-12, "F_load": 1e-3, "x_ref": 1e-7},
    description="the paper's actuator, 1000 kg, its PID in continuous time, incompressible "
                "(the pressure solved exactly), reference 0.5 + 0.33 sin + 0.07 sin")

PLANTS: dict[str, DCPlant | HydraulicPlant] = {
    p.name: p for p in (PAPER, INDUSTRIAL, SERVO_SMALL, SERVO_MID, PWM_DRIVE, HYDRAULIC)}


# -- sanity checks -----------------------------------------------------------------------------

def check_dc(plant: DCPlant, duration: float = 120.0) -> dict[str, float]:
    """A healthy run's checks: in the quasi-steady samples (the inductance's voltage
    La*dia/dt below 1e-4 of the voltage and the inertia's torque J*domega/dt below 1e-4 of
    the motor's torque, central differences; on a PWM drive the current averaged over 16
    samples, a whole cycle of the ripple's sampled phase), the voltage balance
    Va = Ra*ia + Ke*omega (the voltage the motor received) and the torque balance
    Kt*ia = (D + c)*omega + Tload, relative to their largest terms (both about 1e-4 by that
    choice); the same balances with the derivative terms (La*dia/dt, J*domega/dt) in every
    sample, their median (the ODE itself, to the central differences' error: the paper's
    slow loop is never quasi-steady to 1e-4); the speed's distance to the set-point at the end
    of each dwell; the largest speed, current and voltage."""
    lg = simulate_dc(plant, [Scenario()], [duration])[0]
    m = plant.motor
    w, i, vm = lg["omega"], lg["ia"], lg["Vm"]
    if plant.pwm is not None:
        i = np.convolve(i, np.ones(16) / 16, mode="same")
    ldi = m.La * np.gradient(i, SAMPLE_PERIOD)
    jdw = m.J * np.gradient(w, SAMPLE_PERIOD)
    steady = ((np.abs(ldi) < 1e-4 * np.abs(vm)) & (np.abs(jdw) < 1e-4 * np.abs(m.Kt * i))
              & (np.abs(w) > 1.0))
    steady[:16] = steady[-16:] = False
    vbal = (vm - m.Ra * i - m.Ke * w) / np.max(np.abs(vm))
    load = plant.load_coefficient * w if plant.load != "flange" else lg["Tload"]
    tbal = (m.Kt * i - m.D * w - load) / np.max(np.abs(m.Kt * i))
    vode = np.abs(vbal - ldi / np.max(np.abs(vm)))[16:-16]
    tode = np.abs(tbal - jdw / np.max(np.abs(m.Kt * i)))[16:-16]
    times, sps, _ = plant.schedule.table(duration)
    ends = zip(times[2:], sps[1:-1], strict=True)  # each dwell's end and its set-point
    err = [abs(w[int(round(t / SAMPLE_PERIOD)) - 1] - sp) for t, sp in ends if t < duration]
    return {"tau_e_ms": 1e3 * m.tau_e, "steady_samples": float(np.sum(steady)),
            "V_balance_rel_max": float(np.max(np.abs(vbal[steady]))) if np.any(steady) else -1,
            "T_balance_rel_max": float(np.max(np.abs(tbal[steady]))) if np.any(steady) else -1,
            "V_ode_rel_median": float(np.median(vode)), "T_ode_rel_median": float(np.median(tode)),
            "sp_err_end_dwell_max": float(max(err)) if err else -1.0,
            "sp_err_end_dwell_median": float(np.median(err)) if err else -1.0,
            "speed_max": float(np.max(np.abs(w))), "current_max": float(np.max(np.abs(i))),
            "va_max": float(np.max(np.abs(lg["Va"])))}


def check_hydraulic(plant: HydraulicPlant = HYDRAULIC,
                    duration: float = 300.0) -> dict[str, float]:
    """A healthy run's checks: pressure range, tracking error, valve area range."""
    lg = simulate_hydraulic(plant, Scenario(), duration)
    return {"p_min": float(lg["p"].min()), "p_max": float(lg["p"].max()),
            "track_err_max": float(np.max(np.abs(lg["x"] - lg["x_ref"]))),
            "area_min": float(lg["A_valve"].min()), "area_max": float(lg["A_valve"].max()),
            "x_min": float(lg["x"].min()), "x_max": float(lg["x"].max())}


if __name__ == "__main__":  # pragma: no cover - a manual check
    import time

    for name, plant in PLANTS.items():
        t0 = time.process_time()
        res = (check_hydraulic(plant) if isinstance(plant, HydraulicPlant)
               else check_dc(plant))
        print(f"{name:5} {time.process_time() - t0:6.1f} s CPU  " +
              "  ".join(f"{k} {v:.4g}" for k, v in res.items()))
