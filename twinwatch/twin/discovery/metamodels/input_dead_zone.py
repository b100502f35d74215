"""Input dead-zone meta-model ``a*clip(z, b)``: a dead zone of an input the twin already uses
(a drive's power stage that applies nothing while ``|Va| <= b``). Not in paper Table 1."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import fmt
from twinwatch.twin.discovery.metamodels.dead_zone import DeadZone
from twinwatch.twin.model import FloatArray

#: The band ``b`` is searched between these quantiles of the input's magnitude: samples on
#: both sides of it (below the lower one, every sample is beyond the band and ``clip(z, b)``
#: is ``b*sign(z)``, which a Coulomb term or a constant states; above the upper one it is a
#: line).
BAND_QUANTILES = (0.02, 0.95)
#: A window whose input magnitude spans less (lower quantile above this fraction of the upper
#: one) cannot tell the knee from a line or a constant.
MIN_SPAN = 0.7


def clip(z: FloatArray, b: FloatArray) -> FloatArray:
    """``clip(z, b)``: ``z`` limited to ``[-|b|, |b|]`` (broadcasts)."""
    b = np.abs(b)
    return np.clip(z, -b, b)


class InputDeadZone(DeadZone):
    """``U(z) = a*clip(z, b)``: the part of an input within ``+-b``, scaled.

    The dead zone of an actuator (Tao and Kokotovic, *Adaptive Control of Systems with
    Actuator and Sensor Nonlinearities*, Wiley 1996) passes ``dz(v, b) = v - clip(v, b)`` of
    the commanded ``v``. Where the twin already drives an equation with ``v`` (the DC motor's
    ``d(ia)/dt = (Va - Ra*ia - Ke*omega)/La``), the component it lacks is
    ``-clip(Va, b)/La``: this kind with ``a = -1/La`` and ``b`` the dead zone [V], an exact
    and interpretable term ("the drive applies no voltage while |Va| <= b"), where the
    ``dead_zone`` kind would have to cancel the twin's own ``Va/La`` and the smooth
    ``saturation`` only approximates the knee. With ``a > 0`` it is a hard limit of the
    input's effect.

    Separable: ``b`` the only nonlinear parameter, searched within :data:`BAND_QUANTILES` of
    ``|z|``; a window whose input magnitude hardly varies is skipped (:meth:`identifiable`).
    """

    kind = "input_dead_zone"
    equation = "a*clip(z, b)"
    conditions = ("a dead zone of an input the twin already uses: its part within +-b does "
                  "not act (on d(ia)/dt of Va with a = -1/La: the drive applies no voltage "
                  "while |Va| <= b, a worn or miscalibrated power stage)")
    # params, z_powers, nonlinear, evaluate, basis, bounds and canonical: DeadZone's, with
    # clip as the band's function

    @staticmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """:func:`clip`."""
        return clip(z, b)

    def data_range(self, u: FloatArray) -> tuple[float, float] | None:
        lo, hi = (float(q) for q in np.quantile(np.abs(u), BAND_QUANTILES))
        return (lo, hi) if hi > lo else None

    def identifiable(self, u: FloatArray) -> bool:
        lo, hi = (float(q) for q in np.quantile(np.abs(u), BAND_QUANTILES))
        return hi > 0 and lo < MIN_SPAN * hi

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*clip({z}, {fmt(float(p[1]), precision)})"
