"""The hydraulic actuator twin (paper Section 4.2 and 5.3, Eq. 6-10 and 14-18).

A constant-displacement pump feeds a piston cylinder; a controlled valve of cross-section
A_valve returns fluid to the reservoir; the load F_load sits on the piston. With Ts the
sub-step (the paper's integration step, 1e-4 s), one sub-step j -> j+1 reads::

    v_{j+1} = (q_pump - A_valve*sqrt(2*p_j)) / A_piston + f_x            (Eq. 7-8)
    x_{j+1} = x_j + Ts*v_{j+1}                                           (Eq. 14-15)
    p_{j+1} = (1 + U) * (F_load + k_spring*x_{j+1} + D*v_{j+1} + F_resist) / A_piston
                                                                         (Eq. 16, 18)

(density is left out of the valve flow, as in the paper; see NOTES.md). ``U`` and ``f_x`` are
the meta-model terms of discovery (paper Eq. 3), zero for the plain DT. ``U`` = C reproduces the
internal leak of Eq. 18 (the paper's discovery prints ``p_k = p'_k - 0.19999991*p'_k``, Eq. 20:
the same term with the sign of its own convention; ours is ``p = (1 + U)*p'``, U ~ +0.2).

The model is nonlinear (sqrt) and has no exact sample map, so one compiled kernel runs the
sub-steps for every particle of the swarm and every sample of the window; a window of 200
samples x 100 sub-steps costs about 0.5 ms per particle (7.6 ms for a swarm of 15, measured).

**Structure: open loop.** The measured valve area and load drive the twin; it starts each window
from the measured x and p of the window's first sample. The plant's Eq. 17 PID runs every
1e-4 s (with these gains it is unstable at 10 ms; see :mod:`twinwatch.plant.hydraulic`), so the
area moves within a sample. Option ``input_hold``:

* ``linear`` (default): the area (and load) is interpolated linearly between consecutive samples
  over the sub-steps (first-order hold). Measured against the plant at its true parameters:
  x within 2.3e-10 m and p within 5e-12 relative (nominal; leak with U = 0.2), p within
  4.3e-7 relative under fluid degradation (D drifts ~0.4 % within a 2 s window while the twin
  holds it constant): all far below D's share of the pressure (1.4e-4).
* ``zoh``: each sample's value is held until the next one: exact for a valve whose command is
  really held between samples; against this plant it errs by up to 4.4e-6 m in x (near a
  reversal) and 1.3e-7 relative in p.

The measured area is clipped to [0, A_max] (the valve cannot open further), so A_max matters
only when a reading exceeds it: a window never determines A_max.

**Meta-model terms** (attach points, :attr:`HydraulicActuatorTwin.attach_points`):

* ``p`` (multiplicative, dimensionless): ``U[k]`` multiplies the pressure equation on every
  sub-step of the step k-1 -> k, so the pressure at sample k is ``(1 + U[k])`` times the
  plain equation's value, and the next step's valve flow sees that pressure, exactly as in the
  plant's leak (Eq. 18). ``U[0]`` is unused: the window starts from the measured pressure.
* ``d(x)/dt`` (additive, m/s): ``f_x[k]`` is added to the piston velocity on every sub-step of
  the step k -> k+1 (value k drives step k -> k+1, as for the DC motor); it is a velocity of
  the piston, so it enters the damping force D*v as well. ``f_x[N-1]`` is unused.

**Sensitivity caveat.** The damping force D*v is at most ~1.4 N at nominal D (|v| <= 0.014
m/s), about 7 Pa of the 50 kPa pressure (a 1.4e-4 share). D is seen only through the pressure,
only in clean data, and not at all when the piston reverses (v ~ 0): the estimator holds it
there. The position fixes q_pump/A_piston and 1/A_piston; the pressure fixes
(F_load + F_resist)/A_piston, k_spring/A_piston and D/A_piston. Within one 2 s window, though,
x is nearly linear and v nearly constant, so D*v trades with the pressure level: measured
(tests/test_twin_hydraulic.py, relative standard errors at a 1e-7 residual floor) q_pump and D
together are determined (~1e-6 and ~1e-3), D with k_spring, A_piston or F_resist is not (a few
percent and more), and A_max never (the valve does not saturate). Estimate q_pump and D; keep
the others at nameplate.

Paper numbers (Table 4, Eq. 17): k_spring 200 N/m, D 100 N/(m/s), q_pump 0.02 m^3/s, A_max 1e-4
m^2, A_piston 0.196349375 m^2, load 1000 kg; PID Kp 0.000346, Ki 3.513406, Kd 0.000119, N
2.076743; reference 0.45 m at 0.005 Hz; fluid degradation D error below 3 %; leak C = 0.2.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit

from twinwatch.twin.model import (
    AttachPoint,
    EstimationDefaults,
    FloatArray,
    OutputSpec,
    ParameterSpec,
    TwinModel,
    WindowData,
    sub_steps,
)

logger = logging.getLogger(__name__)

HYDRAULIC_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("k_spring", "N/m", 200.0, "elastic constant of the system",
                  "change of the mounting's or the load's compliance"),
    ParameterSpec("D", "N/(m/s)", 100.0, "viscous damping coefficient",
                  "hydraulic fluid degradation (viscosity change: ageing, contamination, "
                  "temperature), seal friction"),
    ParameterSpec("q_pump", "m^3/s", 0.02, "flow of the constant-displacement pump",
                  "pump wear or an external leak on the supply side (falls)"),
    ParameterSpec("A_max", "m^2", 1e-4, "largest cross-section of the valve",
                  "valve clogging or erosion (only seen when the valve saturates)"),
    ParameterSpec("A_piston", "m^2", 0.196349375, "piston area",
                  "effective area change: seal damage, internal bypass"),
    ParameterSpec("F_resist", "N", 0.0, "internal resistance force (not defined by the paper)",
                  "seal or guide friction, mechanical binding"),
)

_ATTACH = ("p", "d(x)/dt")


@njit(cache=True, nogil=True)
def _simulate_kernel(theta, a_in, f_in, x0, p0, n_sub, dt, linear, u_p, f_x, y):
    # pragma: no cover - compiled
    """Sub-step Eq. 14-16 for every particle; fills ``y`` (P, N, 2) with x and p.

    ``theta`` (P, 6): k_spring, D, q_pump, A_max, A_piston, F_resist. ``a_in``, ``f_in`` (N,)
    measured area and load. ``x0``, ``p0`` (P,): each particle's initial state. ``u_p`` (1 or
    P, N): multiplicative pressure term, ``U[k]`` on the sub-steps of step k-1 -> k. ``f_x``
    (1 or P, N): additive velocity term, ``f_x[k]`` on the sub-steps of step k -> k+1. A
    particle whose state stops being finite gets nan from there.
    """
    n_p, n_k = y.shape[0], y.shape[1]
    shared_u = u_p.shape[0] == 1
    shared_f = f_x.shape[0] == 1
    inv = 1.0 / n_sub
    for q in range(n_p):
        ks, d, qp, a_max, ap, fr = (theta[q, 0], theta[q, 1], theta[q, 2], theta[q, 3],
                                    theta[q, 4], theta[q, 5])
        qu = 0 if shared_u else q
        qf = 0 if shared_f else q
        x, p = x0[q], p0[q]
        y[q, 0, 0] = x
        y[q, 0, 1] = p
        inv_ap = 1.0 / ap
        ok = True
        for k in range(n_k - 1):
            if not ok:
                y[q, k + 1, 0] = np.nan
                y[q, k + 1, 1] = np.nan
                continue
            a0, a1 = a_in[k], a_in[k + 1]
            l0, l1 = f_in[k], f_in[k + 1]
            gain = 1.0 + u_p[qu, k + 1]
            fx = f_x[qf, k]
            for s in range(n_sub):
                if linear:
                    w = s * inv
                    a = a0 + (a1 - a0) * w
                    fl = l0 + (l1 - l0) * w
                else:
                    a = a0
                    fl = l0
                if a < 0.0:
                    a = 0.0
                elif a > a_max:
                    a = a_max
                if p >= 0.0:
                    q_valve = a * math.sqrt(2.0 * p)
                else:
                    q_valve = np.nan  # cavitation: outside the model
                v = (qp - q_valve) * inv_ap + fx
                x = x + dt * v
                p = gain * (fl + ks * x + d * v + fr) * inv_ap
            if not (math.isfinite(x) and math.isfinite(p)):
                ok = False
                x, p = np.nan, np.nan
            y[q, k + 1, 0] = x
            y[q, k + 1, 1] = p


@dataclass
class HydraulicActuatorTwin(TwinModel):
    """Hydraulic actuator twin (open loop); see the module docstring for the equations.

    Inputs: ``A_valve`` [m^2] and ``F_load`` [N]. Outputs: ``x`` [m] and ``p`` [Pa].

    Args:
        sub_step: integration sub-step [s] (paper: 1e-4); the sample period must be a whole
            multiple of it (to 1e-6 relative).
        input_hold: ``linear`` (interpolate the inputs between samples; default) or ``zoh``
            (hold each sample's inputs until the next one).
        position_scale: residual normalisation floor for x [m].
        pressure_scale: residual normalisation floor for p [Pa].
        min_speed: D is held in a window whose RMS piston speed (from the measured x) is
            below this [m/s]: the damping force D*v is then a fraction of a pascal (the piston
            reversing; the paper's error spikes). 0.0015 m/s is about 10 % of the paper's
            largest speed; 0 disables the test.
    """

    sub_step: float = 1e-4
    input_hold: Literal["linear", "zoh"] = "linear"
    position_scale: float = 0.01
    pressure_scale: float = 1000.0
    min_speed: float = 0.0015

    def __post_init__(self) -> None:
        if self.sub_step <= 0:
            raise ValueError("sub_step must be > 0")
        if self.input_hold not in ("linear", "zoh"):
            raise ValueError(f"input_hold must be 'linear' or 'zoh', not {self.input_hold!r}")
        self.parameters = HYDRAULIC_PARAMETERS
        self.inputs = ("A_valve", "F_load")
        self.outputs = (
            OutputSpec("x", "m", self.position_scale),
            OutputSpec("p", "Pa", self.pressure_scale),
        )
        self.exogenous = ("A_valve", "F_load")
        # x is the state; p follows from it algebraically (Eq. 16) and enters only the first
        # sub-step's valve flow, so its offset would wander undetermined.
        self.initial_states = ("x",)
        self.attach_points = (
            AttachPoint("p", "multiplicative", "1", "pressure"),
            AttachPoint("d(x)/dt", "additive", "m/s", "piston position"),
        )

    def excitation(self, window: WindowData) -> dict[str, str]:
        """D is not excited while the piston nearly stands still (see ``min_speed``)."""
        if self.min_speed <= 0 or window.n < 2:
            return {}
        v = np.diff(window["x"]) / np.diff(window.t)
        rms = float(np.sqrt(np.mean(v * v)))
        if rms >= self.min_speed:
            return {}
        return {"D": f"too little excitation: the piston nearly stands still (RMS speed "
                     f"{rms:.2g} m/s < {self.min_speed:g} m/s, e.g. reversing)"}

    @property
    def estimation_defaults(self) -> EstimationDefaults:
        """q_pump then D (a reversal then holds D alone); k_spring, A_piston and F_resist trade
        off with D within one window and A_max is never excited: kept at nameplate."""
        return EstimationDefaults(("q_pump", "D"))

    def n_sub(self, sample_period: float) -> int:
        """Number of sub-steps per sample; raises ValueError if not a whole number."""
        return sub_steps(sample_period, self.sub_step)

    def check_sample_period(self, sample_period: float) -> None:
        """The sample period must be a whole number of sub-steps (ValueError otherwise)."""
        self.n_sub(sample_period)

    @staticmethod
    def _term(values: FloatArray | None, p: int, n: int, name: str) -> FloatArray:
        """A term's values as a C-contiguous (1, N) or (P, N) array (zeros if absent)."""
        if values is None:
            return np.zeros((1, n))
        arr = np.asarray(values, dtype=float)
        if arr.ndim == 0:
            arr = np.full((1, n), float(arr))
        elif arr.ndim == 1:
            arr = arr[None, :]
        if arr.ndim != 2 or arr.shape[1] != n or arr.shape[0] not in (1, p):
            raise ValueError(f"term {name!r} has shape {np.shape(values)}; expected ({n},) or "
                             f"({p}, {n})")
        return np.ascontiguousarray(arr)

    def simulate(self, theta: FloatArray, window: WindowData,
                 terms: Mapping[str, FloatArray] | None = None,
                 initial: FloatArray | None = None) -> FloatArray:
        """Simulate the window for a swarm; see :meth:`TwinModel.simulate`.

        Args:
            theta: (P, 6) parameters: k_spring [N/m], D [N/(m/s)], q_pump [m^3/s],
                A_max [m^2], A_piston [m^2], F_resist [N].
            window: needs ``A_valve``, ``F_load``, ``x`` and ``p`` (N samples); the twin starts
                from the measured x and p of the first sample.
            terms: ``p`` (dimensionless; ``U[k]`` multiplies the pressure equation on the
                sub-steps of step k-1 -> k, so sample k's pressure) and/or ``d(x)/dt`` [m/s]
                (``f_x[k]`` added to the piston velocity over step k -> k+1); values of shape
                (N,) or (P, N).
            initial: offsets [m] (1,) or (P, 1) added to the measured x of the first sample
                (the estimator's initial-state estimate); None: 0.

        Returns:
            (P, N, 2): x [m], p [Pa]. A particle that blows up (non-finite state, negative
            pressure) gives nan from that sample on; nothing raises.

        Raises:
            KeyError: an unknown attach point in ``terms``.
            ValueError: a sample period that is not a whole number of sub-steps, or a term of
                the wrong shape.
        """
        theta = np.ascontiguousarray(np.asarray(theta, dtype=float))
        if theta.ndim != 2 or theta.shape[1] != len(self.parameters):
            raise ValueError(f"theta must have shape (P, {len(self.parameters)}), "
                             f"got {theta.shape}")
        n_sub = self.n_sub(window.sample_period)
        n = window.n
        p = theta.shape[0]
        terms = terms or {}
        unknown = set(terms) - set(_ATTACH)
        if unknown:
            raise KeyError(f"unknown attach point(s) {sorted(unknown)}; the hydraulic "
                           f"actuator twin offers {list(_ATTACH)}")
        u_p = self._term(terms.get("p"), p, n, "p")
        f_x = self._term(terms.get("d(x)/dt"), p, n, "d(x)/dt")
        a_in = np.ascontiguousarray(window["A_valve"], dtype=float)
        f_in = np.ascontiguousarray(window["F_load"], dtype=float)
        off = np.zeros((p, 1)) if initial is None else np.broadcast_to(
            np.atleast_2d(np.asarray(initial, dtype=float)), (p, 1))
        x0 = np.ascontiguousarray(float(window["x"][0]) + off[:, 0])
        p0 = np.full(p, float(window["p"][0]))
        y = np.empty((p, n, 2))
        _simulate_kernel(theta, a_in, f_in, x0, p0, n_sub, self.sub_step,
                         self.input_hold == "linear", u_p, f_x, y)
        return y
