"""The meta-model library (paper Section 3.3, Table 1): one class per kind, one file each.

=========================  ====================  =================================================
kind                       U(z)                  working conditions (paper Table 1)
=========================  ====================  =================================================
``linear``                 m*z + b               friction, misalignment, backlash
``exponential``            a*b^z                 current leaking, deterioration, wear and tear,
                                                 corrosion
``negative_exponential``   a*exp(-b*z)           ageing, degradation, fatigue, crack growth
``power``                  a*z^b                 hard stops, overloading, mechanical shock
``logarithmic``            a*ln(z) + b           saturation, memory effects, hysteresis
``periodic``               a*sin(b*z + c) + d    unbalanced shaft, shaft misalignment, machine
                                                 unsteadiness
=========================  ====================  =================================================

Beyond Table 1 (the non-smooth effects of real drives; never a default candidate, a
configuration lists them by kind):

=========================  ====================  =================================================
kind                       U(z)                  working conditions
=========================  ====================  =================================================
``rectifier``              a*max(0, z - b) + c   a power stage that conducts one way only
                                                 (unidirectional chopper, diode), a one-sided
                                                 load or stop
``dead_zone``              a*dz(z, b)            backlash, a voltage the stage needs before
                                                 current flows, a stiction band
``coulomb``                a*sign(z) + c         dry (Coulomb) friction on a speed input
``saturation``             a*tanh(z/b)           a limit: current limiting, a clamped actuator,
                                                 magnetic saturation
``input_dead_zone``        a*clip(z, b)          a dead zone of an input the twin already uses:
                                                 on d(ia)/dt of Va with a = -1/La, the drive
                                                 applies no voltage while |Va| <= b
=========================  ====================  =================================================

Each has at most one nonlinear parameter (the knee, the band, the scale; none for Coulomb), so
the discovery's separable search fits it as it fits Table 1's.

A new meta-model is one :class:`~twinwatch.twin.discovery.metamodels.base.MetaModel` subclass in one
file plus one line in :data:`BUILTIN_META_MODELS`, or, from another package, an entry in the
``twinwatch.metamodels`` entry-point group (``kind = "package.module:Class"``). Modules are
imported when a kind is first used.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Iterator, Mapping

from twinwatch.plugins import Registry
from twinwatch.twin.discovery.metamodels.base import MetaModel

logger = logging.getLogger(__name__)

#: Entry-point group through which other packages add meta-models.
ENTRY_POINT_GROUP = "twinwatch.metamodels"

#: Built-in kinds: kind -> "module:Class". The first six are paper Table 1, in its order; the
#: others are the non-smooth terms real drives need, candidates only where listed.
BUILTIN_META_MODELS: Mapping[str, str] = {
    "linear": "twinwatch.twin.discovery.metamodels.linear:Linear",
    "exponential": "twinwatch.twin.discovery.metamodels.exponential:Exponential",
    "negative_exponential":
        "twinwatch.twin.discovery.metamodels.negative_exponential:NegativeExponential",
    "power": "twinwatch.twin.discovery.metamodels.power:Power",
    "logarithmic": "twinwatch.twin.discovery.metamodels.logarithmic:Logarithmic",
    "periodic": "twinwatch.twin.discovery.metamodels.periodic:Periodic",
    "rectifier": "twinwatch.twin.discovery.metamodels.rectifier:Rectifier",
    "dead_zone": "twinwatch.twin.discovery.metamodels.dead_zone:DeadZone",
    "coulomb": "twinwatch.twin.discovery.metamodels.coulomb:Coulomb",
    "saturation": "twinwatch.twin.discovery.metamodels.saturation:Saturation",
    "input_dead_zone": "twinwatch.twin.discovery.metamodels.input_dead_zone:InputDeadZone",
}

#: The kinds of paper Table 1 (a candidate's default ``kinds``).
TABLE_1 = ("linear", "exponential", "negative_exponential", "power", "logarithmic",
           "periodic")


#: The meta-model registry (:class:`twinwatch.plugins.Registry`).
REGISTRY: Registry[MetaModel] = Registry("meta-model", ENTRY_POINT_GROUP, BUILTIN_META_MODELS,
                                         base=lambda: MetaModel)


@functools.cache
def get_meta_model(kind: str) -> MetaModel:
    """The meta-model of a kind (one shared instance: meta-models hold no state).

    Raises:
        ValueError: an unknown kind (:class:`~twinwatch.errors.PluginError`, the message lists
            the known ones), or a plug-in that cannot be imported or is not a
            :class:`MetaModel` of that kind.
    """
    cls = REGISTRY.load(kind)
    if cls.kind != kind:
        raise ValueError(f"meta-model {kind!r}: {cls.__module__}.{cls.__name__} is a "
                         f"MetaModel of kind {cls.kind!r}, not {kind!r}")
    return cls()


class _Library(Mapping[str, MetaModel]):
    """The library by kind, loaded on access (``META_MODELS["periodic"]``)."""

    def __getitem__(self, kind: str) -> MetaModel:
        if kind not in REGISTRY.table():
            raise KeyError(kind)
        return get_meta_model(kind)

    def __iter__(self) -> Iterator[str]:
        return iter(REGISTRY.table())

    def __len__(self) -> int:
        return len(REGISTRY.table())


#: Every meta-model, by kind.
META_MODELS: Mapping[str, MetaModel] = _Library()


def working_conditions() -> dict[str, str]:
    """Kind -> its working conditions (paper Table 1 for the first six)."""
    return {k: get_meta_model(k).meaning for k in REGISTRY.table()}


__all__ = [
    "BUILTIN_META_MODELS",
    "ENTRY_POINT_GROUP",
    "META_MODELS",
    "REGISTRY",
    "TABLE_1",
    "MetaModel",
    "get_meta_model",
    "working_conditions",
]
