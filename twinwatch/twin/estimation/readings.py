"""The reading check: could one wrong reading on a healthy machine explain the window?

Fault detection and isolation tells a sensor fault from a process fault by their structure
(Isermann, *Fault-Diagnosis Systems*, 2006, ch. 10 and 17: structured residuals; Gertler,
*Fault Detection and Diagnosis in Engineering Systems*, 1998, ch. 6). A current sensor whose
gain drifts to 1.1 moves the estimated Ra down and D up; so do a shorted winding and worn
bearings together. The parameters alone cannot tell them apart (their relation depends on the
operating point: with a load torque TL the apparent D is ``k D + (k - 1) TL/omega``, not
``k D``), but the twin can test the sensor's hypothesis directly: simulate the machine at its
nameplate parameters (``nominal``: a healthy machine), correct one measured output by a gain or
an offset (fitted in closed form by least squares: ``y_meas = g y_nominal`` or ``y_meas =
y_nominal + o``), and compare the normalised RMSE with that of the window's process fit (the
estimate). A sensor fault leaves nothing once its reading is corrected; a process fault leaves
the other outputs (the speed's dynamics, the voltage the shorted winding needs) unexplained.

The correction is applied to the reported reading only: the machine's controller is the
twin's own (closed loop) or absent (open loop). A drive that closes its loop on the faulty
reading changes the process too; the check then explains less than all of it.

A reading the twin starts from (an initial state: the measured first sample) or is driven by
(an input: the closed-loop motor's measured Va sets its controller's integrator) is corrected
in the window itself: the healthy twin is run again on it once (a probe), the correction is
fitted by least squares over every output with the twin's response taken as linear in it, and
the fitted correction is simulated exactly (a 0.5 V offset on the closed-loop Va read 0.19 V
from the reading alone, its integrator starting 0.5 V off and settling within the window;
0.47 V so, at 1 % noise).

Cost: one simulation of the twin per window (the healthy twin); when it fits worse than the
estimate by :data:`EXPLAIN`, four more per output tested that it starts from or is driven by
(a gain and an offset, each probed, then simulated exactly at its fitted value). The daemon
tests the outputs its fault library's ``readings`` name (the default motor: ia), none without
one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from twinwatch.twin.estimation.fit import WindowFit
from twinwatch.twin.model import FloatArray

__all__ = ["ReadingCheck", "ReadingFit", "reading_check"]

#: The healthy twin's nRMSE must exceed the fit's (floored at :data:`NRMSE_FLOOR`) by this
#: factor for the readings to be corrected in the window and the twin run again: below it
#: there is nothing for a reading to explain, and a healthy machine costs one simulation.
EXPLAIN = 1.1
#: The fit's nRMSE below which the comparison does not resolve (a noise-free plant's fit
#: reaches 1e-6, 2e-4 in the windows of a growing fault: the growth within one window).
NRMSE_FLOOR = 2e-4
#: The smallest correction the twin's response to a corrected reading is probed with (a gain
#: of 1 + this; an offset of this share of the reading's RMS).
PROBE = 0.01


@dataclass(frozen=True)
class ReadingFit:
    """One output's reading corrected on the healthy twin.

    Attributes:
        gain: ``g`` of ``y_meas = g y_nominal`` (least squares; 1: no gain error).
        gain_nrmse: the normalised RMSE of the healthy twin with that reading's gain.
        offset: ``o`` of ``y_meas = y_nominal + o`` [the output's unit].
        offset_nrmse: the normalised RMSE with that reading's offset.
        mean: the healthy twin's mean of this output [its unit] (the sign a reading's
            offset reads "high" by).
    """

    gain: float
    gain_nrmse: float
    offset: float
    offset_nrmse: float
    mean: float

    def as_dict(self) -> dict[str, float]:
        return {"gain": self.gain, "gain_nrmse": self.gain_nrmse, "offset": self.offset,
                "offset_nrmse": self.offset_nrmse, "mean": self.mean}


@dataclass(frozen=True)
class ReadingCheck:
    """The window's reading check (see the module docstring).

    Attributes:
        nominal_nrmse: the normalised RMSE of the healthy twin (nameplate parameters, the
            window's meta-model terms), no reading corrected.
        fit_nrmse: that of the window's process fit (the estimate), for comparison.
        outputs: measured output -> its reading corrected (:class:`ReadingFit`).
    """

    nominal_nrmse: float
    fit_nrmse: float
    outputs: dict[str, ReadingFit] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return {"nominal_nrmse": self.nominal_nrmse, "fit_nrmse": self.fit_nrmse,
                "outputs": {k: v.as_dict() for k, v in self.outputs.items()}}


def reading_check(fit: WindowFit, nominal: FloatArray, fit_nrmse: float,
                  terms: Mapping[str, FloatArray] | None = None,
                  outputs: Sequence[str] | None = None) -> ReadingCheck | None:
    """Test, for each measured output, a wrong reading on a healthy machine.

    Args:
        fit: the window's fit problem (measured outputs, their normalisation, the window's
            initial-state offsets).
        nominal: the nameplate parameter vector (n_params,) [SI].
        fit_nrmse: the normalised RMSE of the window's process fit.
        terms: the meta-model terms in the twin (attach point -> values (N,)), as in the fit.
        outputs: the measured outputs whose reading is tested (None: every one; the daemon
            passes those its fault library's ``readings`` name).

    Returns:
        The check, or None when the healthy twin does not simulate the window (it blew up).
    """
    theta = np.asarray(nominal, dtype=float)[None, :]
    y0 = fit.simulate(theta, terms)[0]
    if not np.all(np.isfinite(y0)):
        return None
    base = fit.nrmse_of(y0)
    meas = fit.meas
    model, window = fit.model, fit.window
    # a reading the twin also starts from (an initial state) or is driven by (an input: the
    # closed-loop motor's Va sets its controller's integrator) is corrected in the window and
    # the healthy twin run again on it; the gain and offset are then read from that run
    rerun = set(model.initial_states) | set(model.inputs)
    explain = base > EXPLAIN * max(fit_nrmse, NRMSE_FLOOR)
    norm = fit.normalisation
    r0 = (meas[1:] - y0[1:]) * norm
    wanted = set(fit.names if outputs is None else outputs)
    checked: dict[str, ReadingFit] = {}
    for j, name in enumerate(fit.names):
        if name not in wanted:
            continue
        m = meas[1:, j]
        gain, offset = _gain(y0[1:, j], m), float(np.mean(m - y0[1:, j]))
        # the hypotheses' outputs, linear in the correction: y0 + x z (z: the reading's own
        # change, plus the twin's response to the corrected window where it is run again)
        z_g = np.zeros_like(y0)
        z_g[:, j] = y0[:, j]
        z_o = np.zeros_like(y0)
        z_o[:, j] = 1.0
        u = _lsq(r0, z_g[1:] * norm)
        o = _lsq(r0, z_o[1:] * norm)
        g_fit = (1.0 + u, fit.nrmse_of(y0 + u * z_g))
        o_fit = (o, fit.nrmse_of(y0 + o * z_o))
        if explain and name in rerun:
            scale = float(np.sqrt(np.mean(window[name] ** 2))) or 1.0
            u1 = gain - 1.0 if abs(gain - 1.0) > PROBE else PROBE
            o1 = offset if abs(offset) > PROBE * scale else PROBE * scale
            y_g = _rerun(fit, theta, terms, name, window[name] / (1.0 + u1))
            y_o = _rerun(fit, theta, terms, name, window[name] - o1)
            if y_g is not None and y_o is not None:
                # the twin's response to the correction, taken as linear from the probe
                z_g += (y_g - y0) / u1
                z_o += (y_o - y0) / o1
                u = _lsq(r0, z_g[1:] * norm)
                o = _lsq(r0, z_o[1:] * norm)
                # the fitted corrections simulated exactly (the linear step neglects the
                # u^2 terms: a current gain of 1.1 on a noise-free motor read 1.0998 and
                # left nRMSE 7e-4 so, against 3e-7 at 1.1)
                g_fit = _exact(fit, theta, terms, j, name, "gain", 1.0 + u, g_fit)
                o_fit = _exact(fit, theta, terms, j, name, "offset", o, o_fit)
        checked[name] = ReadingFit(g_fit[0], g_fit[1], o_fit[0], o_fit[1],
                                   float(np.mean(y0[1:, j])))
    return ReadingCheck(base, float(fit_nrmse), checked)


def _lsq(r: FloatArray, z: FloatArray) -> float:
    """Least-squares ``x`` of ``r = x z`` over every sample and output."""
    zz = float(np.sum(z * z))
    return float(np.sum(r * z)) / zz if zz > 0.0 else 0.0


def _exact(fit: WindowFit, theta: FloatArray, terms: Mapping[str, FloatArray] | None, j: int,
           channel: str, how: str, value: float, linear: tuple[float, float]
           ) -> tuple[float, float]:
    """The reading of output ``j`` (the window's ``channel``) corrected by a ``gain`` or an
    ``offset`` of ``value``, simulated exactly: (value, its nRMSE), or ``linear`` (the linear
    step's) when that fits better or the twin blew up."""
    raw = fit.window[channel]
    y = _rerun(fit, theta, terms, channel, raw / value if how == "gain" else raw - value)
    if y is None:
        return linear
    y[:, j] = y[:, j] * value if how == "gain" else y[:, j] + value
    n = fit.nrmse_of(y)
    return (value, n) if n <= linear[1] else linear


def _rerun(fit: WindowFit, theta: FloatArray, terms: Mapping[str, FloatArray] | None,
           channel: str, corrected: FloatArray) -> FloatArray | None:
    """The healthy twin on the window with ``channel`` replaced by ``corrected`` (None: it
    blew up)."""
    window = dataclasses.replace(fit.window, channels={**fit.window.channels,
                                                       channel: corrected})
    if fit.initial is not None and fit.model.initial_states:
        y = fit.model.simulate(theta, window, terms or None, initial=fit.initial)[0]
    else:
        y = fit.model.simulate(theta, window, terms or None)[0]
    return y if np.all(np.isfinite(y)) else None


def _gain(s: FloatArray, m: FloatArray) -> float:
    """Least-squares ``g`` of ``m = g s`` (1 when ``s`` is zero)."""
    ss = float(s @ s)
    return float(s @ m) / ss if ss > 0.0 else 1.0
