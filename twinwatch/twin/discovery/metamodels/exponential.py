"""Exponential meta-model ``a*b^z`` (paper Table 1: current leaking, deterioration, wear and
tear, corrosion)."""

from __future__ import annotations

import math

import numpy as np

from twinwatch.twin.discovery.metamodels.base import ScaledShape, fmt
from twinwatch.twin.model import FloatArray


class Exponential(ScaledShape):
    """``U(z) = a*b^z`` (b > 0); nonlinear in the base ``b``."""

    kind = "exponential"
    equation = "a*b^z"
    conditions = "current leaking, deterioration, wear and tear, corrosion"
    simplifies_to_constant = True
    b_bounds = (math.exp(-3.0), math.exp(3.0))

    @staticmethod
    def shape(z: FloatArray, b: FloatArray) -> FloatArray:
        """``b^z`` (of ``|b|``: a negative base is its magnitude's)."""
        return np.exp(z * np.log(np.abs(b)))

    def to_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        q = np.array(p, dtype=float, copy=True)
        q[..., 1] = np.abs(q[..., 1]) ** (1.0 / z_ref)
        return q

    def from_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        q = np.array(p, dtype=float, copy=True)
        q[..., 1] = np.abs(q[..., 1]) ** z_ref
        return q

    def move_origin(self, p: FloatArray, d: float) -> FloatArray | None:
        """``a b^z = (a b^d) b^(z - d)``."""
        q = np.array(p, dtype=float, copy=True)
        with np.errstate(all="ignore"):
            q[0] = q[0] * abs(q[1]) ** d
        return q if np.all(np.isfinite(q)) else None

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        return f"{fmt(float(p[0]), precision)}*{fmt(float(p[1]), max(precision, 4))}^{z}"
