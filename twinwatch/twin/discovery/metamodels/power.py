"""Power meta-model ``a*z^b`` (paper Table 1: hard stops, overloading, mechanical shock)."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import ScaledShape, fmt
from twinwatch.twin.model import FloatArray


class Power(ScaledShape):
    """``U(z) = a*z^b`` for ``z > 0``; nonlinear in the exponent ``b``."""

    kind = "power"
    equation = "a*z^b"
    conditions = "hard stops, overloading, mechanical shock"
    positive_input = True
    simplifies_to_constant = True
    b_bounds = (0.0, 3.0)

    @staticmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """``z^b``, nan where ``z <= 0``."""
        return np.where(z > 0, z, np.nan) ** b

    def to_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        q = np.array(p, dtype=float, copy=True)
        q[..., 0] = q[..., 0] / z_ref ** q[..., 1]
        return q

    def from_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        q = np.array(p, dtype=float, copy=True)
        q[..., 0] = q[..., 0] * z_ref ** q[..., 1]
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*{z}^{fmt(float(p[1]), precision)}"
