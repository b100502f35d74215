"""Logarithmic meta-model ``a*ln(z) + b`` (paper Table 1: saturation, memory effects,
hysteresis)."""

from __future__ import annotations

import math

import numpy as np

from twinwatch.twin.discovery.metamodels.base import MetaModel, fmt, plus
from twinwatch.twin.model import FloatArray


class Logarithmic(MetaModel):
    """``U(z) = a*ln(z) + b`` for ``z > 0``; the offset ``b`` is optional."""

    kind = "logarithmic"
    equation = "a*ln(z) + b"
    conditions = "saturation, memory effects, hysteresis"
    params = ("a", "b")
    optional = ("b",)
    positive_input = True

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * np.log(np.where(z > 0, z, np.nan)) + p[:, 1, None]

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        n_p = np.atleast_2d(nl).shape[0]
        u = np.asarray(u, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            log = np.repeat(np.log(np.where(u > 0, u, np.nan)), n_p, axis=0)
        return np.stack([log, np.ones((n_p, u.shape[1]))], axis=1)

    def to_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        q = np.array(p, dtype=float, copy=True)
        q[..., 1] = q[..., 1] - q[..., 0] * math.log(z_ref)
        return q

    def from_raw(self, p: FloatArray, z_ref: float) -> FloatArray:
        q = np.array(p, dtype=float, copy=True)
        q[..., 1] = q[..., 1] + q[..., 0] * math.log(z_ref)
        return q

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        out = f"{fmt(float(p[0]), precision)}*ln({z})"
        return out + plus(float(p[1]), precision) if p[1] != 0 else out
