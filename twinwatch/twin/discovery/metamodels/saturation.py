"""Saturation meta-model ``a*tanh(z/b)``: a limit (current limiting, a clamped actuator),
magnetic saturation. Not in paper Table 1."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import ScaledShape, fmt
from twinwatch.twin.model import FloatArray


class Saturation(ScaledShape):
    """``U(z) = a*tanh(z/b)`` (b > 0): slope ``a/b`` near zero, levelling off at ``+-a``.

    The smooth ``tanh`` rather than a hard clip: a cost smooth in ``b`` for the swarm and the
    polish, covering both a soft limit and, for small ``b``, a hard one. ``b`` is searched from
    0.02 to 3 times the input's largest magnitude (beyond, the term is a line).
    """

    kind = "saturation"
    equation = "a*tanh(z/b)"
    conditions = "a limit: current limiting, a clamped actuator, magnetic saturation"
    z_powers = (0, 1)
    b_bounds = (0.02, 3.0)

    @staticmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """``tanh(z/b)``."""
        return np.tanh(z / b)

    def canonical(self, p: FloatArray) -> FloatArray:
        """``b > 0`` (``a tanh(z/b) = -a tanh(-z/b)``)."""
        q = np.array(p, dtype=float, copy=True)
        if q[1] < 0:
            q[0], q[1] = -q[0], -q[1]
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*tanh({z}/{fmt(float(p[1]), precision)})"
