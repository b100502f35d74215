"""The DC motor twin (paper Section 4.1 and 5.2, Eq. 4-5 and 11-12).

Electrical (Eq. 4):   Va = Ra*ia + La*dia/dt + Ke*omega
Mechanical (Eq. 12):  J*domega/dt = Kt*ia - Tload - D*omega

(Eq. 5 as printed has the torque signs swapped; Eq. 12 is the physical one, see NOTES.md.)

The paper integrates these with the explicit scheme of Eq. 11-12 at a sub-step of 1e-4 s:

    i[j+1]     = i[j] + dt*(Va - Ra*i[j] - Ke*omega[j])/La                 (11)
    omega[j+1] = omega[j] + dt*(Kt*i[j+1] - Tload - D*omega[j])/J          (12)

The twin keeps exactly that scheme but never loops over the sub-steps: with the inputs held over
a sample, one sample is the linear map composed ``n_sub`` times, which :func:`composite_zoh`
evaluates exactly by repeated squaring (to rounding, ~1e-13 relative). The whole swarm is
simulated at once.

Two structures are offered (option ``structure``):

* ``closed_loop`` (default for the simulated plant): the twin contains the drive's PI speed
  controller (Kp, Ki known from the drive's configuration) updated every sub-step, driven by the
  measured set-point, and the armature voltage Va becomes an *output*. This is exact for a drive
  whose controller runs faster than the acquisition, where holding the sampled Va over a sample
  biases Ra by more than the estimation's target. The integrator state at the window start is
  recovered from the measured Va.
* ``open_loop``: the measured Va drives the twin, held over each sample. Exact when the voltage
  really is held between samples (e.g. a commanded, piecewise-constant voltage as in the
  MotoShield recording) and the only choice when the controller is unknown.

Option ``current_filter`` models a first-order low-pass on the current measurement (time
constant ``tau_i`` [s], an extra parameter): ``ia_meas' = (ia - ia_meas)/tau_i``. Drives and
evaluation boards often report a filtered current (the MotoShield's ``ifltr``); fitting a filtered
current with an unfiltered model drives J to zero, because only a rotor without inertia avoids the
start-up current spike that the filter hides.

The load torque is either ``viscous`` (Tload = c_load*omega, the paper's 0.006*omega, folded into
the dynamics) or ``measured`` (the Tload channel drives the twin, held over each sample).

Meta-model terms (discovery, paper Eq. 3 and 13) attach additively to the state equations:
``d(omega)/dt`` [rad/s^2] (an unknown torque per inertia: an unbalanced shaft adds a periodic
one) and ``d(ia)/dt`` [A/s]. Each enters the sub-step recursion as an extra input held over the
sample, so the composed twin stays one exact linear map per sample for the whole swarm.

**The drive as it runs** (option ``drive``, :class:`~twinwatch.io.drive.DriveConfig`): a real
drive updates its controller every ``period`` and holds the output in between, clamps it, and may
run an inner current loop. With a ``drive`` that is not the ideal PI above (a period, limits, a
derivative, a current loop) the closed-loop twin runs the drive's updates exactly as the drive
does, between them the motor's sub-step map composed exactly over each stretch of constant
voltage (one matrix product per stretch); the window starts from the measured state, the
integrator recovered from the measured voltage (see :mod:`twinwatch.io.drive`).

**Elements real drives have** (options): ``power_stage = "unidirectional"`` (one switch and a
freewheeling diode: the current cannot reverse), ``coulomb_friction`` (a parameter ``Tc`` [N m],
torque ``Tc*sign(omega)``), ``speed_filter`` (a parameter ``tau_w`` [s], a first-order low-pass
filter on the measured speed, as ``current_filter``), ``speed_measurement = "average"`` (the
speed is an encoder count over the last sample period: the twin outputs the mean speed over the
sample period; the count's quantisation stays noise). The nonlinear elements are stepped sub-step
by sub-step in a compiled kernel with the plant's own scheme (no exact composite map exists).

**Open loop** states how the voltage behaved between samples (``input_hold``): ``zoh`` (held:
exact for a commanded, piecewise-constant voltage) or ``linear`` (interpolated between samples).
An open-loop twin driven by the *sampled* voltage of a drive whose controller updates within the
sample is biased (the voltage moved between samples); use ``closed_loop`` with the drive
described.

Identifiability (docs/architecture.md): with a viscous load, J, Kt and D cannot be
told apart unless Kt is tied to Ke; in windows without a transient Ra and Ke trade off. The
estimator decides per window which parameters the data determine.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numba import njit

from twinwatch.io.drive import DriveConfig, LoopConfig
from twinwatch.twin.model import (
    AttachPoint,
    BoolArray,
    EstimationDefaults,
    FloatArray,
    IntArray,
    OutputSpec,
    ParameterSpec,
    SubStepTwin,
    WindowData,
    _zoh_propagate_kernel,
    as_rows,
    composite_zoh,
    readonly,
    term_array,
)
from twinwatch.twin.models._pid import pid_update

DC_MOTOR_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("Ra", "ohm", 6.5, "armature resistance",
                  "winding temperature, shorted turns (falls) or degraded connections (rises)"),
    ParameterSpec("La", "H", 0.673, "armature inductance", "winding insulation or core faults"),
    ParameterSpec("J", "kg m^2", 0.001171, "rotor and load moment of inertia",
                  "change of the coupled load or of the rotor"),
    ParameterSpec("Ke", "V s/rad", 0.038, "back-EMF constant",
                  "field weakening, magnet ageing, commutator faults"),
    ParameterSpec("Kt", "N m/A", 0.038, "torque constant",
                  "field weakening, magnet ageing"),
    ParameterSpec("D", "N m s/rad", 0.00143, "viscous damping (friction) coefficient",
                  "bearing wear, lubrication loss, misalignment"),
)


#: Length -> the (1, N) zeros that stand for no meta-model term, no initial offset or no load
#: (read-only, shared).
_ZEROS: dict[int, FloatArray] = {}


def _zeros(n: int) -> FloatArray:
    """The shared read-only zeros (1, n)."""
    zero = _ZEROS.get(n)
    if zero is None:
        zero = np.zeros((1, n))
        zero.flags.writeable = False
        _ZEROS[n] = zero
    return zero

_TAU_I = ParameterSpec("tau_i", "s", 0.05,
                       "time constant of the current measurement's low-pass filter",
                       "a change of the current sensor or its filtering")
_TAU_W = ParameterSpec("tau_w", "s", 0.01,
                       "time constant of the speed measurement's low-pass filter",
                       "a change of the speed sensor or its filtering")
_TC = ParameterSpec("Tc", "N m", 1e-3, "Coulomb (dry) friction torque",
                    "bearing or brush wear, contamination, misalignment (rises)")


@njit(cache=True, nogil=True)
def _step_kernel(theta: FloatArray, dt: float, c: float, kp: float, ki: float, closed: bool,
                 pos: IntArray, a: FloatArray, b: FloatArray) -> None:  # pragma: no cover
    """:meth:`DCMotorTwin.step_matrices` into zeroed ``a`` (P, n, n), ``b`` (P, n, 4):
    ``pos`` = positions of [z, fi, fw, angle, v] (-1: absent), then the columns of tau_i
    and tau_w in ``theta`` (-1: absent)."""
    n = a.shape[1]
    pz, pv = pos[0], pos[4]
    for q in range(theta.shape[0]):
        ra, la, j, ke, kt, d = (theta[q, 0], theta[q, 1], theta[q, 2], theta[q, 3],
                                theta[q, 4], theta[q, 5])
        a_el = dt / la
        g = dt * kt / j
        a[q, 0, 0] = 1.0 - a_el * ra
        if closed:
            # i' = i + dt/La*(Kp*(sp - w) + Ki*z - Ra*i - Ke*w); z' = z + dt*(sp - w)
            a[q, 0, 1] = -a_el * (kp + ke)
            a[q, 0, pz] = a_el * ki
            b[q, 0, 0] = a_el * kp
            a[q, pz, 1] = -dt
            a[q, pz, pz] = 1.0
            b[q, pz, 0] = dt
        else:
            a[q, 0, 1] = -a_el * ke
            if pv >= 0:  # the voltage is a state that ramps by u[0] per sub-step
                a[q, 0, pv] = a_el
                a[q, pv, pv] = 1.0
                b[q, pv, 0] = 1.0
            else:
                b[q, 0, 0] = a_el
        b[q, 0, 3] = dt  # i' += dt*f_ia
        # w' = w + dt/J*(Kt*i' - c*w - D*w - Tload) + dt*f_omega (semi-implicit: the new i)
        for col in range(n):
            a[q, 1, col] = g * a[q, 0, col]
        a[q, 1, 1] += 1.0 - dt * (d + c) / j
        for col in range(4):
            b[q, 1, col] = g * b[q, 0, col]
        b[q, 1, 1] += -dt / j
        b[q, 1, 2] += dt
        # the filtered current and speed, then the angle: f' = f + dt/tau*(x' - f)
        for which in range(3):
            r = pos[1 + which]
            if r < 0:
                continue
            src = 0 if which == 0 else 1
            if which < 2:
                gain = dt / theta[q, pos[5 + which]]
            else:
                gain = dt
            for col in range(n):
                a[q, r, col] = gain * a[q, src, col]
            for col in range(4):
                b[q, r, col] = gain * b[q, src, col]
            a[q, r, r] += 1.0 if which == 2 else 1.0 - gain


@njit(cache=True, nogil=True, error_model="numpy")
def _fast_kernel(a: FloatArray, b: FloatArray, n_sub: int, ia: FloatArray, omega: FloatArray,
                 va: FloatArray, drive: FloatArray, tl: FloatArray, f_w: FloatArray,
                 f_i: FloatArray, off: FloatArray, pos: IntArray, kp: float, ki: float,
                 average: bool, ts: float, y: FloatArray) -> None:  # pragma: no cover
    """:meth:`DCMotorTwin._simulate_fast` after the step matrices ``a``, ``b`` (P, n, ...):
    each particle's state at the first sample (the measurements plus the offsets ``off``
    (1 or P, 2) on ia and omega; a filtered or averaged measurement stands in for the state
    it filters; the ideal PI's integrator recovered from the measured Va), the exact map per
    sample (:func:`~twinwatch.twin.model.zoh_propagate`), then the outputs ``y`` (P, N,
    n_out): the (filtered) current, the (filtered or averaged) speed and, closed loop, the
    PI's voltage ``kp*(set-point - omega) + ki*z``. ``pos``: :meth:`step_matrices`'s."""
    p, nk, n_out = y.shape
    pz, pfi, pfw, pang, pv = pos[0], pos[1], pos[2], pos[3], pos[4]
    x = np.zeros((p, nk, a.shape[1]))
    w0 = 0.5 * (omega[0] + omega[1]) if average and nk > 1 else omega[0]
    for q in range(p):
        o = 0 if off.shape[0] == 1 else q
        x[q, 0, 0] = ia[0] + off[o, 0]
        x[q, 0, 1] = w0 + off[o, 1]
        if pfi >= 0:
            x[q, 0, pfi] = ia[0] + off[o, 0]
        if pfw >= 0:
            x[q, 0, pfw] = omega[0] + off[o, 1]
        if pv >= 0:
            x[q, 0, pv] = va[0]
        if pz >= 0:
            x[q, 0, pz] = (va[0] - kp * (drive[0] - x[q, 0, 1])) / ki
    _zoh_propagate_kernel(a, b, n_sub, x, drive, tl, f_w, f_i)
    ci = pfi if pfi >= 0 else 0
    cw = pfw if pfw >= 0 else 1
    for q in range(p):
        for k in range(nk):
            y[q, k, 0] = x[q, k, ci]
            if pang < 0:
                y[q, k, 1] = x[q, k, cw]
            elif k == 0:
                y[q, k, 1] = omega[0]
            else:
                y[q, k, 1] = (x[q, k, pang] - x[q, k - 1, pang]) / ts
            if n_out == 3:
                y[q, k, 2] = kp * (drive[k] - x[q, k, 1]) + ki * x[q, k, pz]


@njit(cache=True, nogil=True)
def _drive_kernel(phis: FloatArray, gams: FloatArray, seg_len: IntArray, seg_type: IntArray,
                  ev_sample: IntArray, ev_sub: IntArray, ev_tick_s: BoolArray,
                  ev_tick_c: BoolArray, x0: FloatArray, ctrl0: FloatArray, hold0: FloatArray,
                  mode: int, sp: FloatArray, va_meas: FloatArray, iref_meas: FloatArray,
                  tl: FloatArray, f_w: FloatArray, f_i: FloatArray, speed: FloatArray,
                  current: FloatArray, has_current: bool, t_s: float, t_c: float,
                  explicit: bool, prm: FloatArray, dt: float, stage: int, n_sub: int,
                  lin_hold: bool, idx: IntArray, ts: float,
                  y: FloatArray) -> None:  # pragma: no cover - compiled
    """Simulate a swarm through the window's events (samples and drive updates).

    Between events the inputs are constant: the motor advances by the composed sub-step map of
    the stretch (``phis``/``gams`` (P, n_types, n, n|4), by ``seg_type``), or, with
    ``explicit``, sub-step by sub-step with the plant's scheme and its nonlinear elements
    (``prm`` (P, 10): Ra, La, J, Ke, Kt, D, c_load, tau_i, tau_w, Tc; ``stage`` 1:
    unidirectional). At an event the drive updates (``ev_tick_s``/``ev_tick_c``) before the
    sample (``ev_sample`` >= 0) is recorded: a sample reports the voltage applied from it on.
    ``mode``: 0 the measured voltage drives the motor (open loop), 1 the current loop runs on
    the measured current reference (the speed loop at its limit), 2 the whole drive runs.
    ``idx`` = [ia output state, omega output state, angle state or -1, current filter state or
    -1, speed filter state or -1]. ``x0`` (P, n) and ``ctrl0`` (P, 4) [I_s, f_s, I_c, f_c]:
    each particle's initial state. ``y`` (P, N, 3): ia, omega, Va.
    """
    n_p = y.shape[0]
    n_ev = ev_sample.shape[0]
    n = x0.shape[1]
    shared_f = f_w.shape[0] == 1
    i_out, w_out, ang, i_fi, i_fw = idx[0], idx[1], idx[2], idx[3], idx[4]
    x = np.empty(n)
    xn = np.empty(n)
    u = np.empty(4)
    for q in range(n_p):
        qf = 0 if shared_f else q
        for j in range(n):
            x[j] = x0[q, j]
        i_s, f_s, i_c, f_c = ctrl0[q, 0], ctrl0[q, 1], ctrl0[q, 2], ctrl0[q, 3]
        va, iref = hold0[0], hold0[1]
        prev_angle = 0.0
        kc = 0
        ok = True
        ra, la, jj, ke, kt, d = prm[q, 0], prm[q, 1], prm[q, 2], prm[q, 3], prm[q, 4], prm[q, 5]
        cl, tau_i, tau_w, tc = prm[q, 6], prm[q, 7], prm[q, 8], prm[q, 9]
        for e in range(n_ev):
            k = ev_sample[e]
            if k >= 0:
                kc = k
                if mode == 0:
                    va = va_meas[kc]
                elif mode == 1:
                    iref = iref_meas[kc]
            if mode > 0 and ok:
                if mode == 2 and ev_tick_s[e]:
                    out, i_s, f_s = pid_update(speed, i_s, f_s, sp[kc], x[1], t_s, speed[5])
                    if has_current:
                        iref = out
                    else:
                        va = out
                if has_current and ev_tick_c[e]:
                    va, i_c, f_c = pid_update(current, i_c, f_c, iref, x[0], t_c, current[5])
            if k >= 0:
                if not ok:
                    y[q, k, 0] = np.nan
                    y[q, k, 1] = np.nan
                    y[q, k, 2] = np.nan
                else:
                    y[q, k, 0] = x[i_out]
                    if ang >= 0:
                        y[q, k, 1] = (x[ang] - prev_angle) / ts
                        prev_angle = x[ang]
                    else:
                        y[q, k, 1] = x[w_out]
                    y[q, k, 2] = va
            if e == n_ev - 1 or not ok:
                continue
            t_type = seg_type[e]
            if explicit:
                for s in range(seg_len[t_type]):
                    v = va
                    if lin_hold and mode == 0 and kc + 1 < va_meas.shape[0]:
                        v = va + (va_meas[kc + 1] - va) * (ev_sub[e] + s) / n_sub
                    ia = x[0] + dt * (v - ra * x[0] - ke * x[1]) / la + dt * f_i[qf, kc]
                    if stage == 1 and ia < 0.0:
                        ia = 0.0
                    w = x[1]
                    fric = 0.0
                    if tc > 0.0:
                        fric = tc if w > 0.0 else (-tc if w < 0.0 else 0.0)
                    w_new = (w + dt * (kt * ia - (cl + d) * w - tl[kc] - fric) / jj
                             + dt * f_w[qf, kc])
                    x[0] = ia
                    x[1] = w_new
                    if ang >= 0:
                        x[ang] += dt * w_new
                    if i_fi >= 0:
                        x[i_fi] += dt / tau_i * (ia - x[i_fi])
                    if i_fw >= 0:
                        x[i_fw] += dt / tau_w * (w_new - x[i_fw])
            else:
                u[0] = va
                u[1] = tl[kc]
                u[2] = f_w[qf, kc]
                u[3] = f_i[qf, kc]
                for i in range(n):
                    acc = 0.0
                    for j in range(n):
                        acc += phis[q, t_type, i, j] * x[j]
                    for j in range(4):
                        acc += gams[q, t_type, i, j] * u[j]
                    xn[i] = acc
                for i in range(n):
                    x[i] = xn[i]
            for i in range(n):
                if not np.isfinite(x[i]):
                    ok = False


@dataclass
class DCMotorTwin(SubStepTwin):
    """DC motor twin; see the module docstring for the equations.

    Args:
        structure: ``closed_loop`` (the drive's controller inside the twin, driven by
            ``setpoint``; outputs ia, omega, Va) or ``open_loop`` (driven by ``Va``; outputs
            ia, omega).
        load: ``viscous`` (Tload = load_coefficient*omega) or ``measured`` (channel Tload).
        load_coefficient: c_load [N m s/rad] for the viscous load (paper: 0.006).
        kp: PI proportional gain [V s/rad] (paper: 0.3), closed loop without ``drive``.
        ki: PI integral gain [V/rad] (paper: 0.1), closed loop without ``drive``.
        drive: the drive as it runs (:class:`~twinwatch.io.drive.DriveConfig` or its table:
            update period, phase, speed loop with limits, anti-windup and feed-forward, current
            loop); replaces ``kp``/``ki``. Closed loop only.
        sub_step: integration sub-step [s] (paper: 1e-4); the sample period (and the drive's
            periods) must be whole multiples of it (to 1e-6 relative).
        input_hold: open loop: ``zoh`` (the voltage held between samples) or ``linear``
            (interpolated between samples).
        current_scale, speed_scale, voltage_scale: residual normalisation floors [A, rad/s, V].
        current_filter: the measured current is low-pass filtered with time constant tau_i
            (adds the parameter ``tau_i`` [s]); the twin's ia output is the filtered current.
        speed_filter: the same for the speed (parameter ``tau_w`` [s]).
        speed_measurement: ``instant`` (the speed at the sample) or ``average`` (an encoder
            count over the last sample period: the mean speed over it).
        power_stage: ``bidirectional`` or ``unidirectional`` (the current cannot reverse).
        coulomb_friction: add the Coulomb friction torque ``Tc`` [N m] (a parameter).

    Raises:
        ValueError: an option that cannot work (named).
    """

    structure: Literal["closed_loop", "open_loop"] = "closed_loop"
    load: Literal["viscous", "measured"] = "viscous"
    load_coefficient: float = 0.006
    kp: float = 0.3
    ki: float = 0.1
    drive: DriveConfig | dict[str, Any] | None = None
    sub_step: float = 1e-4
    input_hold: Literal["zoh", "linear"] = "zoh"
    current_scale: float = 0.1
    speed_scale: float = 1.0
    voltage_scale: float = 1.0
    current_filter: bool = False
    speed_filter: bool = False
    speed_measurement: Literal["instant", "average"] = "instant"
    power_stage: Literal["bidirectional", "unidirectional"] = "bidirectional"
    coulomb_friction: bool = False

    def __post_init__(self) -> None:
        self._check_choices()
        if not self.sub_step > 0:
            raise ValueError("sub_step must be > 0")
        if isinstance(self.drive, Mapping):
            self.drive = DriveConfig.model_validate(self.drive)
        if self.drive is not None and self.structure != "closed_loop":
            raise ValueError("drive: describes the controller of a closed-loop twin; an open "
                             "loop twin is driven by the measured voltage")
        closed = self.structure == "closed_loop"
        if self.drive is None:
            if closed and self.ki == 0:
                raise ValueError("closed_loop structure needs a non-zero integral gain ki")
            self._drive = DriveConfig(speed=LoopConfig(kp=self.kp, ki=self.ki))
        else:
            if (self.kp, self.ki) != (0.3, 0.1):
                raise ValueError("kp, ki: with a drive table set the gains there "
                                 "(drive.speed.kp, drive.speed.ki)")
            self._drive = self.drive
            self._drive.ticks(self.sub_step)  # a period that is not whole sub-steps fails now
        extra = []
        if self.current_filter:
            extra.append(_TAU_I)
        if self.speed_filter:
            extra.append(_TAU_W)
        if self.coulomb_friction:
            extra.append(_TC)
        self.parameters = (*DC_MOTOR_PARAMETERS, *extra)
        inputs = ["setpoint"] if closed else ["Va"]
        if self.load == "measured":
            inputs.append("Tload")
        outputs = [
            OutputSpec("ia", "A", self.current_scale),
            OutputSpec("omega", "rad/s", self.speed_scale),
        ]
        if closed:
            # Va is an input of the closed-loop twin's *initial state* (the integrator)
            # and an output compared with the measurement.
            inputs.append("Va")
            outputs.append(OutputSpec("Va", "V", self.voltage_scale))
            if self._drive.current is not None:
                inputs.append("current_reference")
        self.inputs = tuple(inputs)
        self.outputs = tuple(outputs)
        self.exogenous = tuple(c for c in inputs if c in ("setpoint", "Tload")
                               or (c == "Va" and not closed))
        self.initial_states = ("ia", "omega")
        self.attach_points = (
            AttachPoint("d(omega)/dt", "additive", "rad/s^2", "shaft speed", scale=50.0),
            AttachPoint("d(ia)/dt", "additive", "A/s", "armature current", scale=50.0),
        )
        # The exact linear map per sample (fast path) serves the ideal drive and every linear
        # element; the others go through the event kernel.
        self._nonlinear = self.power_stage == "unidirectional" or self.coulomb_friction
        self._plans: dict[tuple[float, int, int, int], tuple[np.ndarray, ...]] = {}
        self._fast = not self._nonlinear and (not closed or self._drive.ideal)
        # fixed from here on: the state layouts (and the step kernel's positions) with and
        # without the ideal PI in the map, and the effective PI: the ideal drive's PI as the
        # sub-step map applies it, ``Va = kp_eff*e + ki*z`` with ``z`` the integral of the
        # error up to the previous sub-step; an integrator that includes this sub-step's error
        # (backward Euler, trapezoidal: ``c_i`` of :mod:`twinwatch.io.drive`) adds
        # ``c_i*ki*dt`` to the proportional gain
        self._layouts = {cp: self._make_layout(cp) for cp in (False, True)}
        names = self.parameter_names
        self._positions = {cp: np.array(
            [pos.get(k, -1) for k in ("z", "fi", "fw", "angle", "v")]
            + [names.index(t) if t in names else -1 for t in ("tau_i", "tau_w")],
            dtype=np.int64) for cp, pos in self._layouts.items()}
        sp = self._drive.speed
        self._pi = (sp.kp + sp.pack()[10] * sp.ki * self.sub_step, sp.ki)
        #: the last window's kernel inputs (:meth:`_window_inputs`)
        self._last_inputs: tuple[Any, ...] | None = None

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        """Ra, D, Ke, La, J in that priority (then the options' parameters), Kt tied to Ke:
        with a viscous load (J, Kt, D) -> (sJ, sKt, s(D+c)-c) leaves the outputs unchanged, so
        Kt cannot be estimated beside them; in SI units Kt [N m/A] = Ke [V s/rad]. D comes
        before Ke: with c_load >> D a Ke error is amplified five times in D."""
        extra = tuple(p.name for p in self.parameters[len(DC_MOTOR_PARAMETERS):])
        return EstimationDefaults(("Ra", "D", "Ke", "La", "J", *extra), {"Kt": "Ke"})

    def time_constants(self, values: Mapping[str, float]) -> dict[str, tuple[float, str]]:
        """La's: the armature's electrical time constant ``tau_e = La/Ra``
        (:meth:`TwinModel.time_constants`)."""
        ra, la = float(values.get("Ra", 0.0)), float(values.get("La", 0.0))
        return {"La": (la / ra, "tau_e = La/Ra")} if ra > 0 and la > 0 else {}

    # -- the linear sub-step map ------------------------------------------------------------
    def _layout(self, closed_pi: bool) -> dict[str, int]:
        """State positions: ia, omega, [z], [ia filtered], [omega filtered], [angle], [v]
        (built once; the callers read it)."""
        return self._layouts[bool(closed_pi)]

    def _make_layout(self, closed_pi: bool) -> dict[str, int]:
        pos = {"ia": 0, "omega": 1}
        for name, on in (("z", closed_pi), ("fi", self.current_filter),
                         ("fw", self.speed_filter),
                         ("angle", self.speed_measurement == "average"),
                         ("v", self.structure == "open_loop" and self.input_hold == "linear"
                          and closed_pi is False and self._fast)):
            if on:
                pos[name] = len(pos)
        return pos

    def step_matrices(self, theta: FloatArray, dt: float, *, closed_pi: bool | None = None
                      ) -> tuple[FloatArray, FloatArray]:
        """One sub-step of Eq. 11-12 (plus the ideal PI loop) as ``x' = A x + B u``.

        Args:
            theta: (P, n_params) parameters in :attr:`parameters` order (Ra, La, J, Ke, Kt, D,
                then the options' parameters).
            dt: sub-step [s].
            closed_pi: include the ideal PI (updated every sub-step) in the map; default: the
                closed-loop structure with the ideal drive.

        Returns:
            A of shape (P, n, n), B of shape (P, n, 4), with the states of :meth:`_layout`
            (ia [A], omega [rad/s], then z [rad] the PI integrator, the filtered current and
            speed, the shaft angle [rad], the interpolated voltage [V]) and u = [setpoint or
            Va (or its per-sub-step increment with ``input_hold = "linear"``), Tload_measured,
            f_omega, f_ia]. ``f_omega`` [rad/s^2] and ``f_ia`` [A/s] are the meta-model terms
            added to d(omega)/dt and d(ia)/dt.
        """
        if closed_pi is None:
            closed_pi = self.structure == "closed_loop" and self._fast
        pos = self._layout(closed_pi)
        theta = np.ascontiguousarray(theta, dtype=float)
        p = theta.shape[0]
        n = len(pos)
        a = np.zeros((p, n, n))
        b = np.zeros((p, n, 4))
        c = self.load_coefficient if self.load == "viscous" else 0.0
        kp, ki = self._pi
        _step_kernel(theta, float(dt), float(c), float(kp), float(ki), bool(closed_pi),
                     self._positions[bool(closed_pi)], a, b)
        return a, b

    # -- simulation -------------------------------------------------------------------------
    def simulate(self, theta: FloatArray, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 initial: FloatArray | None = None) -> FloatArray:
        """Simulate the window for a swarm; see :meth:`TwinModel.simulate`.

        Args:
            theta: (P, n_params) parameters in :attr:`parameters` order.
            window: needs ``ia``, ``omega`` and the inputs of the structure.
            terms: ``d(omega)/dt`` [rad/s^2] and/or ``d(ia)/dt`` [A/s] -> values (N,) or
                (P, N), added to that state equation and held over each sample.
            initial: offsets [A, rad/s] (2,) or (P, 2) added to the measured ia and omega of
                the first sample (the estimator's initial-state estimate); None: 0.

        Returns:
            (P, N, n_outputs): ia [A], omega [rad/s] and, closed loop, Va [V].
        """
        theta = as_rows(theta)
        n = window.n
        p = theta.shape[0]
        f_w, f_i = self._terms(terms, p, n)
        rows = max(p, f_w.shape[0])
        if rows > p:
            theta = np.repeat(theta[:1], rows, axis=0)
        off = _zeros(2) if initial is None else as_rows(initial)
        if off.shape[0] not in (1, rows) or off.shape[1:] != (2,):
            raise ValueError(f"initial: shape {off.shape}, expected (2,) or ({rows}, 2)")
        if self._fast:
            return self._simulate_fast(theta, window, f_w, f_i, off)
        off = np.broadcast_to(off, (rows, 2))
        if self.structure != "closed_loop":
            return self._simulate_events(theta, window, f_w, f_i, 0, 0, off)[:, :, :2]
        # A drive at a limit hides its integrator: the window is cut where the limits are left
        # and each part restarts from the measured state there (module notes), in the mode the
        # measurements allow: the measured voltage drives the motor while it sits at its limit;
        # the current loop runs on the measured reference while the speed loop sits at its.
        y = np.empty((rows, n, len(self.outputs)))
        for k0, stop, mode in self._segments(window):
            y[:, k0:stop] = self._simulate_events(theta, window, f_w, f_i, k0, mode,
                                                  off if k0 == 0 else None, stop=stop)
        return y

    def _segments(self, window: WindowData) -> list[tuple[int, int, int]]:
        """(first sample, end, mode) of each part of a closed-loop window; parts overlap by one
        sample (the next part's start, overwritten by it)."""
        n = window.n
        dr = self._drive
        va_free = self._inside(dr.current or dr.speed, window["Va"])
        ref_free = (self._inside(dr.speed, window["current_reference"])
                    if dr.current is not None else np.ones(n, dtype=bool))
        parts: list[tuple[int, int, int]] = []
        k = 0
        while k < n:
            if va_free[k] and ref_free[k]:
                mode, free = 2, None
            elif va_free[k]:
                mode, free = 1, ref_free
            else:
                mode, free = 0, va_free
            nxt = n
            if free is not None:
                later = np.flatnonzero(free[k + 1:])
                nxt = k + 1 + int(later[0]) if later.size else n
            if mode == 2:
                nxt = n
            parts.append((k, min(nxt + 1, n), mode))
            k = nxt
        return parts

    @staticmethod
    def _inside(loop: LoopConfig, u: FloatArray) -> FloatArray:
        """Samples whose drive output is strictly inside the loop's limits."""
        ok = np.ones(u.shape, dtype=bool)
        for lim in (loop.output_min, loop.output_max):
            if lim is not None:
                ok &= np.abs(u - lim) > 1e-9 * max(1.0, abs(lim))
        return ok

    @staticmethod
    def _terms(terms: Mapping[str, FloatArray] | None, p: int, n: int
               ) -> tuple[FloatArray, FloatArray]:
        """The meta-model terms as C-contiguous (1 or P, N) arrays: d(omega)/dt, d(ia)/dt."""
        if terms:
            unknown = set(terms) - {"d(omega)/dt", "d(ia)/dt"}
            if unknown:
                raise KeyError(f"unknown attach point(s) {sorted(unknown)}; the DC motor "
                               "twin offers d(omega)/dt and d(ia)/dt")
        if not terms:  # no meta-model: the same zeros every call
            return _zeros(n), _zeros(n)
        out = []
        for name in ("d(omega)/dt", "d(ia)/dt"):
            out.append(term_array((terms or {}).get(name), p, n, name))
        rows = max(a.shape[0] for a in out)
        f_w, f_i = (np.ascontiguousarray(np.broadcast_to(a, (rows, n))) if a.shape[0] != rows
                    else a for a in out)
        return f_w, f_i

    def _initial_state(self, window: WindowData, k: int, pos: Mapping[str, int],
                       off: FloatArray) -> FloatArray:
        """Each particle's motor state (P, n) at sample ``k`` from the measurements plus the
        offsets ``off`` (P, 2) on ia and omega (a filtered or averaged measurement stands in
        for the state it filters)."""
        p = off.shape[0]
        x0 = np.zeros((p, len(pos)))
        ia, omega = window["ia"], window["omega"]
        w0 = omega[k]
        if self.speed_measurement == "average" and k + 1 < window.n:
            w0 = 0.5 * (omega[k] + omega[k + 1])  # the means over the periods either side
        x0[:, 0] = ia[k] + off[:, 0]
        x0[:, 1] = w0 + off[:, 1]
        if "fi" in pos:
            x0[:, pos["fi"]] = ia[k] + off[:, 0]
        if "fw" in pos:
            x0[:, pos["fw"]] = omega[k] + off[:, 1]
        if "v" in pos:
            x0[:, pos["v"]] = window["Va"][k]
        return x0

    def _simulate_fast(self, theta: FloatArray, window: WindowData, f_w: FloatArray,
                       f_i: FloatArray, off: FloatArray) -> FloatArray:
        """The exact linear map per sample, composed by matrix squaring (ideal drive), in one
        compiled call (:func:`_fast_kernel`); ``off``: (1 or P, 2)."""
        closed = self.structure == "closed_loop"
        n_sub, ts, ia, omega, va, drive, tl = self._window_inputs(window, closed)
        a, b = self.step_matrices(theta, self.sub_step, closed_pi=closed)
        kp, ki = self._pi
        y = np.empty((a.shape[0], ia.size, 3 if closed else 2))
        _fast_kernel(a, b, n_sub, ia, omega, va, drive, tl, readonly(f_w), readonly(f_i),
                     readonly(off), self._positions[closed], kp, ki,
                     self.speed_measurement == "average", ts, y)
        return y

    def _window_inputs(self, window: WindowData, closed: bool
                       ) -> tuple[int, float, FloatArray, FloatArray, FloatArray, FloatArray,
                                  FloatArray]:
        """What :func:`_fast_kernel` reads of the window: (sub-steps per sample, sample period
        [s], then ia, omega, Va, the drive's input (the set-point closed loop; Va, or its
        per-sub-step increment with ``input_hold = "linear"``, open loop) and Tload, each (N,)
        and read-only: one compiled signature, numba compiling a kernel again for each mix of
        writable and read-only arrays). Made once per window: a fit simulates one window some
        thirty times; the last window's are kept while its arrays are the same objects."""
        ch = window.channels
        ia, omega, va = ch["ia"], ch["omega"], ch["Va"]
        src = ch["setpoint"] if closed else None
        load = ch["Tload"] if self.load == "measured" else None
        last = self._last_inputs
        if (last is not None and last[0] is window and last[1] is window.t and last[2] is ia
                and last[3] is omega and last[4] is va and last[5] is src and last[6] is load
                and last[7] is closed):
            kept: tuple[int, float, FloatArray, FloatArray, FloatArray, FloatArray,
                        FloatArray] = last[8]
            return kept
        ts = window.sample_period
        n_sub = self.n_sub(ts)
        if closed:
            drive = ch["setpoint"]
        elif "v" in self._layout(False):
            drive = np.append(np.diff(va), 0.0) / n_sub
        else:
            drive = va
        tl = load if load is not None else _zeros(ia.size)[0]
        out = (n_sub, ts, readonly(ia), readonly(omega), readonly(va), readonly(drive),
               readonly(tl))
        self._last_inputs = (window, window.t, ia, omega, va, src, load, closed, out)
        return out

    def _controller_state(self, window: WindowData, k: int, t_s: float, t_c: float,
                          ticked_s: bool, ticked_c: bool, omega0: FloatArray, ia0: FloatArray
                          ) -> tuple[FloatArray, FloatArray]:
        """The drive's states [I_s, f_s, I_c, f_c] and held outputs [Va, iref] at sample ``k``,
        recovered from the measured outputs (module :mod:`twinwatch.io.drive`), for each
        particle's initial speed and current ``omega0``, ``ia0`` (P,): (P, 4) and (2,). When no
        update falls on the sample, the last one is taken to have seen the sample's error."""
        dr = self._drive
        r = float(window["setpoint"][k])
        sp = dr.speed
        sign = 1.0 if sp.action == "reverse" else -1.0
        omega = window["omega"]
        e = sign * (r - omega0)
        # The derivative filter's state: the derivative term taken as kd times the error's
        # slope over the next sample (the set-point held), f = kd*e - d/N.
        packed = sp.pack()
        c_i, c_d = packed[10], packed[11]
        d0 = 0.0
        f0: FloatArray | float = 0.0
        if sp.kd != 0 and sp.n_filter:
            slope = -sign * (float(omega[k + 1]) - float(omega[k])) / window.sample_period \
                if k + 1 < window.n else 0.0
            d0 = sp.kd * slope
            # d = N*(kd*e - f)/(1 + c_d*N*T)  =>  f = kd*e - d*(1 + c_d*N*T)/N
            f0 = sp.kd * e - d0 * (1.0 + c_d * sp.n_filter * t_s) / sp.n_filter
        va = float(window["Va"][k])
        out = np.zeros((omega0.size, 4))
        # The update's output u = kp*e + I + c_i*ki*T*e + d + kff*r solved for the state I
        # before it; without an update on the sample, the state after one that saw this error.
        if dr.current is None:
            i_s = va - sp.kp * e - sp.feedforward * r - d0 - c_i * sp.ki * t_s * e
            if not ticked_s:
                i_s = i_s + sp.ki * t_s * e
            out[:, 0], out[:, 1] = i_s, f0
            return out, np.array([va, 0.0])
        iref = float(window["current_reference"][k])
        i_s = iref - sp.kp * e - sp.feedforward * r - d0 - c_i * sp.ki * t_s * e
        if not ticked_s:
            i_s = i_s + sp.ki * t_s * e
        cur = dr.current
        cur_packed = cur.pack()
        ec = cur_packed[9] * (iref - ia0)
        i_c = va - cur.kp * ec - cur.feedforward * iref - cur_packed[10] * cur.ki * t_c * ec
        if not ticked_c:
            i_c = i_c + cur.ki * t_c * ec
        out[:, 0], out[:, 1], out[:, 2], out[:, 3] = i_s, f0, i_c, cur.kd * ec
        return out, np.array([va, iref])

    def _event_plan(self, t0: float, count: int, n_sub: int, mode: int
                    ) -> tuple[np.ndarray, ...]:
        """The events of ``count`` samples from time ``t0`` on the sub-step grid: samples and,
        by ``mode``, the drive's updates (its clock is absolute: phase from t = 0). Returns
        (segment lengths by type, each segment's type, each event's sample or -1, its sub-step
        within the sample, speed-loop update, current-loop update). Kept for the window: an
        estimation simulates the same window a few hundred times."""
        key = (t0, count, n_sub, mode)
        cached = self._plans.get(key)
        if cached is not None:
            return cached
        dr = self._drive
        dt = self.sub_step
        m, mc, ph = dr.ticks(dt)
        j0 = int(round(t0 / dt))
        end = (count - 1) * n_sub
        samples = np.arange(count) * n_sub
        ev = [samples]
        tick_s = tick_c = np.zeros(0, dtype=np.int64)
        if mode == 2:
            tick_s = np.arange((ph - j0) % m, end + 1, m)
            ev.append(tick_s)
        if mode > 0 and dr.current is not None:
            tick_c = np.arange((ph - j0) % mc, end + 1, mc)
            ev.append(tick_c)
        events = np.unique(np.concatenate(ev))
        lengths = np.diff(events)
        types, seg_type = np.unique(lengths, return_inverse=True) if lengths.size else (
            np.array([1]), np.zeros(0, dtype=np.int64))
        ev_sample = np.full(events.size, -1, dtype=np.int64)
        ev_sample[np.searchsorted(events, samples)] = np.arange(count)
        ev_sub = events - samples[np.searchsorted(samples, events, side="right") - 1]
        plan = (types.astype(np.int64), seg_type.astype(np.int64), ev_sample,
                ev_sub.astype(np.int64), np.isin(events, tick_s), np.isin(events, tick_c))
        if len(self._plans) > 8:
            self._plans.clear()
        self._plans[key] = plan
        return plan

    def _simulate_events(self, theta: FloatArray, window: WindowData, f_w: FloatArray,
                         f_i: FloatArray, k0: int, mode: int, off: FloatArray | None = None,
                         *, stop: int | None = None) -> FloatArray:
        """Samples ``k0 .. stop-1`` through the event kernel (drive updates, nonlinear
        elements), starting from the measured state at ``k0``; ``mode`` 0: the measured voltage
        drives the motor, 1: the current loop runs on the measured current reference, 2: the
        whole drive runs. Returns (P, stop - k0, 3): ia, omega and the voltage."""
        closed = mode > 0
        stop = window.n if stop is None else stop
        ts = window.sample_period
        dt = self.sub_step
        n_sub = self.n_sub(ts)
        count = stop - k0
        p = theta.shape[0]
        pos = self._layout(False)
        dr = self._drive
        m, mc, ph = dr.ticks(dt)
        plan = self._event_plan(float(window.t[k0]), count, n_sub, mode)
        types, seg_type, ev_sample, ev_sub, ev_tick_s, ev_tick_c = plan
        explicit = self._nonlinear
        n_state = len(pos)
        if explicit:
            phis = np.zeros((p, 1, n_state, n_state))
            gams = np.zeros((p, 1, n_state, 4))
        else:
            a, b = self.step_matrices(theta, dt, closed_pi=False)
            phis = np.empty((p, types.size, n_state, n_state))
            gams = np.empty((p, types.size, n_state, 4))
            with np.errstate(over="ignore", invalid="ignore"):
                for i, length in enumerate(types):
                    phis[:, i], gams[:, i] = composite_zoh(a, b, int(length))
        names = self.parameter_names
        prm = np.zeros((p, 10))
        prm[:, :6] = theta[:, :6]
        prm[:, 6] = self.load_coefficient if self.load == "viscous" else 0.0
        for col, name in ((7, "tau_i"), (8, "tau_w"), (9, "Tc")):
            if name in names:
                prm[:, col] = theta[:, names.index(name)]
        x0 = self._initial_state(window, k0, pos, np.zeros((p, 2)) if off is None else off)
        ctrl0, hold0 = np.zeros((p, 4)), np.zeros(2)
        if closed:
            ctrl0, hold0 = self._controller_state(window, k0, m * dt, mc * dt,
                                                  bool(ev_tick_s[0]), bool(ev_tick_c[0]),
                                                  x0[:, 1], x0[:, 0])
        sl = slice(k0, stop)
        tl = window["Tload"][sl] if self.load == "measured" else np.zeros(count)
        sp = window["setpoint"][sl] if closed else np.zeros(count)
        va = np.ascontiguousarray(window["Va"][sl], dtype=float)
        iref = (np.ascontiguousarray(window["current_reference"][sl], dtype=float)
                if dr.current is not None else np.zeros(count))
        idx = np.array([pos.get("fi", 0), pos.get("fw", 1), pos.get("angle", -1),
                        pos.get("fi", -1), pos.get("fw", -1)], dtype=np.int64)
        y = np.empty((p, count, 3))
        _drive_kernel(np.ascontiguousarray(phis), np.ascontiguousarray(gams),
                      types, seg_type, ev_sample, ev_sub, ev_tick_s, ev_tick_c,
                      np.ascontiguousarray(x0), np.ascontiguousarray(ctrl0), hold0, mode,
                      np.ascontiguousarray(sp, dtype=float), va, iref,
                      np.ascontiguousarray(tl, dtype=float),
                      np.ascontiguousarray(f_w[:, sl]), np.ascontiguousarray(f_i[:, sl]),
                      dr.speed.pack(), (dr.current or LoopConfig()).pack(),
                      dr.current is not None, m * dt, mc * dt, explicit, prm, dt,
                      1 if self.power_stage == "unidirectional" else 0, n_sub,
                      self.input_hold == "linear", idx, ts, y)
        y[:, 0, 1] = window["omega"][k0]  # a mean over the period before the window: measured
        return y
