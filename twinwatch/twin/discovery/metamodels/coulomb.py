"""Coulomb (dry) friction meta-model ``a*sign(z) + c`` on a speed input: brush, seal or bearing
friction that opposes motion with a force independent of the speed. Not in paper Table 1."""

from __future__ import annotations

import numpy as np

from twinwatch.twin.discovery.metamodels.base import MetaModel, fmt, plus
from twinwatch.twin.model import FloatArray

#: Fewest samples, as a fraction of the window, where ``sign(z)`` differs from its most common
#: value: below it, the sign is (nearly) a constant and says nothing a constant does not.
MINORITY_FRACTION = 0.02


def sampled_sign(z: FloatArray) -> FloatArray:
    """``sign(z)`` averaged over each sample interval of a sampled input, shape of ``z``.

    A twin holds a term's value over a sample interval, while the machine's friction switches
    where the speed crosses zero inside it. Taking the input linear between samples, the
    average of ``sign`` over an interval whose mid value is ``z_k`` and whose change is
    ``2 h_k`` is exactly ``clip(z_k / h_k, -1, 1)``: ``+-1`` away from zero, the fraction of
    time on each side at a crossing. ``h_k`` is half the input's change over one sample
    (``np.gradient`` along the last axis); where it is 0 this is ``sign(z)``. On a noisy speed
    near zero, ``h_k`` is about the noise: the sign is smoothed over what the data can tell.
    """
    z = np.asarray(z, dtype=float)
    if z.shape[-1] < 2:
        return np.sign(z)
    h = 0.5 * np.abs(np.gradient(z, axis=-1))
    with np.errstate(all="ignore"):
        return np.where(h > 0, np.clip(z / np.where(h > 0, h, 1.0), -1.0, 1.0), np.sign(z))


class Coulomb(MetaModel):
    """``U(z) = a*sign(z) + c`` (``sign(0) = 0``: no dry friction at rest); ``c`` optional.

    Linear in both parameters (``sign(z)`` of the measured input is a fixed basis column).
    The sign is averaged over each sample interval (:func:`sampled_sign`), else a speed
    reversal inside an interval biases ``a``. A window where the sign barely changes is not
    used (:meth:`identifiable`). As a term on ``d(omega)/dt`` it reads
    ``-Tc/J*sign(omega)``: ``a < 0``.
    """

    kind = "coulomb"
    equation = "a*sign(z) + c"
    conditions = "dry (Coulomb) friction on a speed input: brushes, seals, bearings"
    params = ("a", "c")
    optional = ("c",)

    def evaluate(self, p: FloatArray, z: FloatArray) -> FloatArray:
        p = np.atleast_2d(np.asarray(p, dtype=float))
        z = np.asarray(z, dtype=float)[None, :]
        with np.errstate(all="ignore"):
            return p[:, 0, None] * sampled_sign(z) + p[:, 1, None]

    def basis(self, nl: FloatArray, u: FloatArray) -> FloatArray:
        n_p = np.atleast_2d(nl).shape[0]
        s = np.repeat(sampled_sign(np.asarray(u, dtype=float))[None, :], n_p, axis=0)
        return np.stack([s, np.ones_like(s)], axis=1)

    def identifiable(self, u: FloatArray) -> bool:
        s = np.sign(np.asarray(u, dtype=float))
        counts = [int(np.sum(s == v)) for v in (-1.0, 0.0, 1.0)]
        n = int(s.size)
        return n - max(counts) >= max(3, MINORITY_FRACTION * n)

    def render(self, p: FloatArray, z: str, precision: int = 2) -> str:
        out = f"{fmt(float(p[0]), precision)}*sign({z})"
        return out + plus(float(p[1]), precision) if p[1] != 0 else out
