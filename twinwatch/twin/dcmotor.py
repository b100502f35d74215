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
  whose controller runs faster than the acquisition: holding the sampled Va over 10 ms while the
  plant's PI runs every 0.1 ms biases Ra by up to 1.7 % (measured), which would swamp the 0.2 %
  target. The integrator state at the window start is recovered from the measured Va.
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

Identifiability (measured, see docs/architecture.md): with a viscous load, J, Kt and D cannot be
told apart unless Kt is tied to Ke; in windows without a transient Ra and Ke trade off. The
estimator decides per window which parameters the data determine.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from twinwatch.twin.model import (
    AttachPoint,
    EstimationDefaults,
    FloatArray,
    OutputSpec,
    ParameterSpec,
    TwinModel,
    WindowData,
    composite_zoh,
    propagate,
    sub_steps,
)

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


@dataclass
class DCMotorTwin(TwinModel):
    """DC motor twin; see the module docstring for the equations.

    Args:
        structure: ``closed_loop`` (PI controller inside the twin, driven by ``setpoint``;
            outputs ia, omega, Va) or ``open_loop`` (driven by ``Va``; outputs ia, omega).
        load: ``viscous`` (Tload = load_coefficient*omega) or ``measured`` (channel Tload).
        load_coefficient: c_load [N m s/rad] for the viscous load (paper: 0.006).
        kp: PI proportional gain [V s/rad] (paper: 0.3), closed loop only.
        ki: PI integral gain [V/rad] (paper: 0.1), closed loop only.
        sub_step: integration sub-step [s] (paper: 1e-4); the sample period must be a whole
            multiple of it (to 1e-6 relative).
        current_scale, speed_scale, voltage_scale: residual normalisation floors [A, rad/s, V].
        current_filter: the measured current is low-pass filtered with time constant tau_i
            (adds the parameter ``tau_i`` [s]); the twin's ia output is the filtered current.
    """

    structure: Literal["closed_loop", "open_loop"] = "closed_loop"
    load: Literal["viscous", "measured"] = "viscous"
    load_coefficient: float = 0.006
    kp: float = 0.3
    ki: float = 0.1
    sub_step: float = 1e-4
    current_scale: float = 0.1
    speed_scale: float = 1.0
    voltage_scale: float = 1.0
    current_filter: bool = False

    def __post_init__(self) -> None:
        self.parameters = DC_MOTOR_PARAMETERS
        if self.current_filter:
            self.parameters = (*DC_MOTOR_PARAMETERS, ParameterSpec(
                "tau_i", "s", 0.05, "time constant of the current measurement's low-pass filter",
                "a change of the current sensor or its filtering"))
        inputs = ["setpoint"] if self.structure == "closed_loop" else ["Va"]
        if self.load == "measured":
            inputs.append("Tload")
        outputs = [
            OutputSpec("ia", "A", self.current_scale),
            OutputSpec("omega", "rad/s", self.speed_scale),
        ]
        if self.structure == "closed_loop":
            # Va is an input of the closed-loop twin's *initial state* (the integrator)
            # and an output compared with the measurement.
            inputs.append("Va")
            outputs.append(OutputSpec("Va", "V", self.voltage_scale))
        self.inputs = tuple(inputs)
        self.outputs = tuple(outputs)
        self.attach_points = (
            AttachPoint("d(omega)/dt", "additive", "rad/s^2", "shaft speed", scale=50.0),
            AttachPoint("d(ia)/dt", "additive", "A/s", "armature current", scale=50.0),
        )
        if self.structure == "closed_loop" and self.ki == 0:
            raise ValueError("closed_loop structure needs a non-zero integral gain ki")

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        """Ra, D, Ke, La, J in that priority (then tau_i with the current filter), Kt tied to
        Ke: with a viscous load (J, Kt, D) -> (sJ, sKt, s(D+c)-c) leaves the outputs unchanged,
        so Kt cannot be estimated beside them; in SI units Kt [N m/A] = Ke [V s/rad]. D comes
        before Ke: with c_load >> D a Ke error is amplified five times in D."""
        extra = ("tau_i",) if self.current_filter else ()
        return EstimationDefaults(("Ra", "D", "Ke", "La", "J", *extra), {"Kt": "Ke"})

    def n_sub(self, sample_period: float) -> int:
        """Number of sub-steps per sample; raises ValueError if not a whole number."""
        return sub_steps(sample_period, self.sub_step)

    def check_sample_period(self, sample_period: float) -> None:
        """The sample period must be a whole number of sub-steps (ValueError otherwise)."""
        self.n_sub(sample_period)

    def step_matrices(self, theta: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
        """One sub-step of Eq. 11-12 (plus the PI loop) as ``x' = A x + B u``.

        Args:
            theta: (P, 6) parameters in the order Ra, La, J, Ke, Kt, D (then tau_i with
                ``current_filter``).
            dt: sub-step [s].

        Returns:
            A of shape (P, n, n), B of shape (P, n, 4). Closed loop: x = [ia, omega, z]
            (z the PI integrator state, rad), u = [setpoint, Tload_measured, f_omega, f_ia].
            Open loop: x = [ia, omega], u = [Va, Tload_measured, f_omega, f_ia]. ``f_omega``
            [rad/s^2] and ``f_ia`` [A/s] are the meta-model terms added to d(omega)/dt and
            d(ia)/dt.
        """
        ra, la, j, ke, kt, d = (theta[:, k] for k in range(6))
        c = self.load_coefficient if self.load == "viscous" else 0.0
        p = theta.shape[0]
        a_el = dt / la
        g = dt * kt / j
        if self.structure == "closed_loop":
            a = np.zeros((p, 3, 3))
            b = np.zeros((p, 3, 4))
            # i' = i + dt/La*(Kp*(sp - w) + Ki*z - Ra*i - Ke*w)
            a[:, 0, 0] = 1.0 - a_el * ra
            a[:, 0, 1] = -a_el * (self.kp + ke)
            a[:, 0, 2] = a_el * self.ki
            b[:, 0, 0] = a_el * self.kp
            # z' = z + dt*(sp - w)
            a[:, 2, 1] = -dt
            a[:, 2, 2] = 1.0
            b[:, 2, 0] = dt
        else:
            a = np.zeros((p, 2, 2))
            b = np.zeros((p, 2, 4))
            a[:, 0, 0] = 1.0 - a_el * ra
            a[:, 0, 1] = -a_el * ke
            b[:, 0, 0] = a_el
        b[:, 0, 3] = dt  # i' += dt*f_ia
        # w' = w + dt/J*(Kt*i' - c*w - D*w - Tload)   (semi-implicit: uses the new current)
        a[:, 1, :] = g[:, None] * a[:, 0, :]
        a[:, 1, 1] += 1.0 - dt * (d + c) / j
        b[:, 1, :] = g[:, None] * b[:, 0, :]
        b[:, 1, 1] += -dt / j
        b[:, 1, 2] += dt  # w' += dt*f_omega
        if self.current_filter:
            # Filtered current, appended as the last state: f' = f + dt/tau*(i' - f).
            n = a.shape[1]
            g_f = dt / theta[:, 6]
            a2 = np.zeros((p, n + 1, n + 1))
            b2 = np.zeros((p, n + 1, b.shape[2]))
            a2[:, :n, :n] = a
            b2[:, :n] = b
            a2[:, n, :n] = g_f[:, None] * a[:, 0, :]
            a2[:, n, n] = 1.0 - g_f
            b2[:, n] = g_f[:, None] * b[:, 0, :]
            a, b = a2, b2
        return a, b

    def simulate(self, theta: FloatArray, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None) -> FloatArray:
        """Simulate the window for a swarm; see :meth:`TwinModel.simulate`.

        Args:
            theta: (P, 6) parameters (Ra, La, J, Ke, Kt, D).
            window: needs ``ia``, ``omega`` and the inputs of the structure.
            terms: ``d(omega)/dt`` [rad/s^2] and/or ``d(ia)/dt`` [A/s] -> values (N,) or
                (P, N), added to that state equation and held over each sample.

        Returns:
            (P, N, n_outputs): ia [A], omega [rad/s] and, closed loop, Va [V].
        """
        theta = np.asarray(theta, dtype=float)
        n_sub = self.n_sub(window.sample_period)
        a, b = self.step_matrices(theta, self.sub_step)
        with np.errstate(over="ignore", invalid="ignore"):
            phi, gamma = composite_zoh(a, b, n_sub)
        ia, omega = window["ia"], window["omega"]
        tl = window["Tload"] if self.load == "measured" else np.zeros_like(ia)
        p = theta.shape[0]
        if self.structure == "closed_loop":
            sp, va = window["setpoint"], window["Va"]
            z0 = (va[0] - self.kp * (sp[0] - omega[0])) / self.ki
            x0 = [ia[0], omega[0], z0]
            drive = sp
        else:
            x0 = [ia[0], omega[0]]
            drive = window["Va"]
        u = np.column_stack([drive, tl, np.zeros_like(tl), np.zeros_like(tl)])
        if terms:
            unknown = set(terms) - {"d(omega)/dt", "d(ia)/dt"}
            if unknown:
                raise KeyError(f"unknown attach point(s) {sorted(unknown)}; the DC motor "
                               "twin offers d(omega)/dt and d(ia)/dt")
            rows = max(np.ndim(v) == 2 and np.shape(v)[0] or 1 for v in terms.values())
            u3 = np.repeat(u[None], rows, axis=0)
            for col, name in ((2, "d(omega)/dt"), (3, "d(ia)/dt")):
                if name in terms:
                    u3[:, :, col] = terms[name]
            u = u3
        if self.current_filter:
            x0.append(ia[0])  # the true current at the start is taken as the filtered one
        x0_arr = np.array(x0)
        x = propagate(phi, gamma, np.broadcast_to(x0_arr, (p, x0_arr.size)), u)
        i_out = x[:, :, -1] if self.current_filter else x[:, :, 0]
        if self.structure == "closed_loop":
            va_sim = self.kp * (drive[None, :] - x[:, :, 1]) + self.ki * x[:, :, 2]
            return np.stack([i_out, x[:, :, 1], va_sim], axis=2)
        return np.stack([i_out, x[:, :, 1]], axis=2)
