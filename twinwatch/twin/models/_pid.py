"""The twin's drive-loop update, shared by the closed-loop twins (compiled).

The simulated plants have their own (:mod:`twinwatch.plant._pid`) on purpose: a twin that shared
the plant's code would reproduce the plant's mistakes and the tests could not see them.
"""

from __future__ import annotations

from numba import njit

from twinwatch.twin.model import FloatArray


@njit(cache=True, nogil=True)
def pid_update(loop: FloatArray, i_s: float, f_s: float, r: float, y: float, period: float,
               hi: float) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """One update of a drive loop (:mod:`twinwatch.io.drive`): P/PI/PID with the derivative
    filter N, the output clamped to [loop[4], hi] with the loop's anti-windup, the integrator
    and the filter discretised by their methods (MATLAB's Discrete PID Controller).

    Args:
        loop: the packed loop (:meth:`twinwatch.io.drive.LoopConfig.pack`): kp, ki, kd, N,
            output_min, output_max, anti-windup (0 none, 1 clamping, 2 back-calculation),
            tracking time, feed-forward gain, sign, the integrator's and the derivative
            filter's share of this tick's input (0 forward Euler, 1 backward Euler, 1/2
            trapezoidal).
        i_s, f_s: the integrator and the derivative filter's state before the update.
        r, y: reference and feedback.
        period: the loop's update period [s].
        hi: the upper output limit (loop[5], or a limit the model resolves itself).

    Returns:
        (u, I, f): the held output until the next update, the integrator and the filter state
        after it.
    """
    kp, ki, kd, nf = loop[0], loop[1], loop[2], loop[3]
    lo, aw, tt, kff, sgn = loop[4], loop[6], loop[7], loop[8], loop[9]
    ci, cd = loop[10], loop[11]
    e = sgn * (r - y)
    d = nf * (kd * e - f_s) / (1.0 + cd * nf * period) if kd != 0.0 else 0.0
    u_pid = kp * e + (i_s + ci * ki * period * e) + d + kff * r
    u = min(max(u_pid, lo), hi)
    if aw == 1.0:
        if not ((u_pid > hi and ki * e > 0.0) or (u_pid < lo and ki * e < 0.0)):
            i_s += ki * period * e
    elif aw == 2.0:
        i_s += ki * period * e + (period / tt) * (u - u_pid)
    else:
        i_s += ki * period * e
    return u, i_s, f_s + period * d
