"""Data quality: a sensor that is frozen or saturated, named by its channel.

A measured output that repeats one value exactly for many samples is not measuring: a live
sensor's reading carries noise or at least moves by its quantisation step as the machine moves.
Where the twin's own output moves materially over the same stretch, the stretch is a sensor
fault, *saturated* or *frozen* (:func:`sensor_faults` gives the rules); a drive output that
sits at its limit is neither (the twin clamps it too). The window's estimates are then not
measurements of the machine: the estimator publishes them ``suspect``
(:mod:`~twinwatch.twin.estimation.publish`), does not trust or fuse them, and the health
message names each fault (``sensors``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from twinwatch.twin.estimation.fit import WindowFit
from twinwatch.twin.estimation.statistics import mean
from twinwatch.twin.model import FloatArray

__all__ = ["SensorFault", "live_outputs", "sensor_faults"]

#: The twin's output must move by more than this share of the output's scale over the stuck
#: stretch (and by more than four quantisation steps of the reading) for it to be a fault.
MATERIAL = 0.01


@dataclass(frozen=True)
class SensorFault:
    """One stuck stretch of a measured output.

    Attributes:
        channel: the output's channel.
        kind: ``frozen`` or ``saturated``.
        value: the stuck reading [the channel's unit].
        t_start: time of its first sample [s].
        duration_s: how long it stayed [s] (to the last stuck sample).
        samples: stuck samples in the window.
    """

    channel: str
    kind: Literal["frozen", "saturated"]
    value: float
    t_start: float
    duration_s: float
    samples: int

    def describe(self, unit: str = "") -> str:
        """For a person: ``sensor ia frozen at 1.2 A for 2.00 s from t = 180.00 s``."""
        u = f" {unit}" if unit else ""
        return (f"sensor {self.channel} {self.kind} at {self.value:.6g}{u} for "
                f"{self.duration_s:.2f} s from t = {self.t_start:.2f} s")


def live_outputs(fit: WindowFit, min_run: int) -> dict[str, bool]:
    """Per output, whether its readings are live noise in this window: no value repeats for
    even a fifth of ``min_run`` samples, its second differences are larger than its first ones
    (white noise: sqrt(3) times; a smooth, noise-free signal such as a drive's own output: far
    smaller), and its noise is more than three of its quantisation steps (an encoder's count
    toggles by one step at a steady speed and may repeat for seconds)."""
    out = {}
    for j, name in enumerate(fit.names):
        meas = fit.meas[:, j]
        d1 = meas[1:] - meas[:-1]  # np.diff's subtraction without its dispatch
        d2 = d1[1:] - d1[:-1]
        if d2.size == 0:
            out[name] = False
            continue
        rms1 = float(np.sqrt(mean(d1 * d1)))
        if not float(np.sqrt(mean(d2 * d2))) > rms1:  # smooth: no quantum needed
            out[name] = False
            continue
        steps = np.abs(d1[d1 != 0])
        quantum = float(steps.min()) if steps.size else math.inf
        out[name] = (rms1 / math.sqrt(2.0) > 3.0 * quantum
                     and fit.longest_runs[j][1] < max(min_run // 5, 2))
    return out


def sensor_faults(fit: WindowFit, y: FloatArray, min_run: int,
                  live: dict[str, bool] | None = None,
                  clips: dict[str, float] | None = None) -> list[SensorFault]:
    """The window's frozen and saturated sensors (module docstring).

    A stuck stretch (one reading repeated exactly for at least ``min_run`` samples) is

    * saturated where its value is the window's largest (smallest) reading and the twin goes
      beyond it by more than :data:`MATERIAL` of the output's scale on average there, or where
      it is the level the sensor was found saturated at before (``clips``: once the twin has
      been fitted to a clipped reading it no longer goes beyond it);
    * frozen where the twin moves by more than :data:`MATERIAL` of the output's scale and four
      quantisation steps of the reading over it, or where the output was ``live`` in a sound
      window before (a reading that carried noise and now repeats itself exactly has stopped
      updating, even where the machine is steady);
    * not a fault where the twin itself holds the same value over most of the stretch (a drive
      output at its modelled limit, even while the drive chatters there), nor where none of
      the above holds (a quantised reading of a steady machine).

    Args:
        fit: the window's fit (measured outputs ``fit.meas`` (N, n_out), their scales).
        y: the twin's outputs at the estimate (N, n_out).
        min_run: a stuck stretch shorter than this many samples is not a fault (0: off).
        live: output -> its readings were live in a sound window before (:func:`live_outputs`);
            None: unknown.
        clips: output -> the level it was found saturated at before.

    Returns:
        At most one fault per output.
    """
    if min_run <= 0:
        return []
    t = fit.window.t
    out: list[SensorFault] = []
    for j, name in enumerate(fit.names):
        meas = fit.meas[:, j]
        k0, length = fit.longest_runs[j]
        if length < min_run:
            continue
        twin = y[k0:k0 + length, j]
        if not np.isfinite(twin).all():
            continue
        value = float(meas[k0])
        if np.mean(np.abs(twin - value) <= 1e-9 * max(abs(value), 1.0)) > 0.5:
            continue  # the twin holds it too: a drive output at its modelled limit
        tol = 1e-12 * max(abs(value), 1.0)
        margin = MATERIAL * float(fit.scale[j])
        top = value >= float(meas.max()) - tol and float(np.mean(twin)) > value + margin
        bottom = value <= float(meas.min()) + tol and float(np.mean(twin)) < value - margin
        known = (clips or {}).get(name)
        at_clip = known is not None and abs(value - known) <= tol
        steps = np.abs(meas[1:] - meas[:-1])
        steps = steps[steps > 0]
        quantum = float(steps.min()) if steps.size else 0.0
        moves = float(np.ptp(twin)) > max(margin, 4.0 * quantum)
        kind: Literal["frozen", "saturated"]
        if top or bottom or at_clip:
            kind = "saturated"
        elif moves or (live or {}).get(name, False):
            kind = "frozen"
        else:
            continue
        out.append(SensorFault(name, kind, value, float(t[k0]),
                               float(t[k0 + length - 1] - t[k0]), length))
    return out
