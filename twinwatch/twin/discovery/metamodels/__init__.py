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
import importlib
import logging
from collections.abc import Mapping
from importlib.metadata import entry_points

from twinwatch.twin.discovery.metamodels.base import MetaModel

logger = logging.getLogger(__name__)

#: Entry-point group through which other packages add meta-models.
ENTRY_POINT_GROUP = "twinwatch.metamodels"

#: Built-in kinds: kind -> (module, class). The first six are paper Table 1, in its order; the
#: others are the non-smooth terms real drives need (issue 9), candidates only where listed.
BUILTIN_META_MODELS: Mapping[str, tuple[str, str]] = {
    "linear": ("twinwatch.twin.discovery.metamodels.linear", "Linear"),
    "exponential": ("twinwatch.twin.discovery.metamodels.exponential", "Exponential"),
    "negative_exponential": ("twinwatch.twin.discovery.metamodels.negative_exponential",
                             "NegativeExponential"),
    "power": ("twinwatch.twin.discovery.metamodels.power", "Power"),
    "logarithmic": ("twinwatch.twin.discovery.metamodels.logarithmic", "Logarithmic"),
    "periodic": ("twinwatch.twin.discovery.metamodels.periodic", "Periodic"),
    "rectifier": ("twinwatch.twin.discovery.metamodels.rectifier", "Rectifier"),
    "dead_zone": ("twinwatch.twin.discovery.metamodels.dead_zone", "DeadZone"),
    "coulomb": ("twinwatch.twin.discovery.metamodels.coulomb", "Coulomb"),
    "saturation": ("twinwatch.twin.discovery.metamodels.saturation", "Saturation"),
}

#: The kinds of paper Table 1 (a candidate's default ``kinds``).
TABLE_1 = ("linear", "exponential", "negative_exponential", "power", "logarithmic",
           "periodic")


@functools.cache
def meta_model_table() -> Mapping[str, tuple[str, str]]:
    """Every known kind -> (module, class): the built-ins plus the entry points (read once; a
    plug-in cannot replace a built-in kind)."""
    table = dict(BUILTIN_META_MODELS)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in BUILTIN_META_MODELS:
            logger.warning("entry point %s = %r ignored: %r is a built-in meta-model",
                           ep.name, ep.value, ep.name)
            continue
        module, _, attr = ep.value.partition(":")
        table[ep.name] = (module.strip(), attr.strip())
    return table


@functools.cache
def get_meta_model(kind: str) -> MetaModel:
    """The meta-model of a kind (one shared instance: meta-models hold no state).

    Raises:
        ValueError: an unknown kind (the message lists the known ones), or a plug-in that
            cannot be imported or is not a :class:`MetaModel`.
    """
    table = meta_model_table()
    try:
        module, cls_name = table[kind]
    except KeyError:
        raise ValueError(f"unknown meta-model {kind!r}; choose from {sorted(table)}") from None
    try:
        cls = getattr(importlib.import_module(module), cls_name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"meta-model {kind!r} not available: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, MetaModel)) or cls.kind != kind:
        raise ValueError(f"meta-model {kind!r}: {module}.{cls_name} is not a MetaModel of "
                         f"kind {kind!r}")
    return cls()


def available_kinds() -> list[str]:
    """Every kind a configuration may name."""
    return list(meta_model_table())


class _Library(Mapping[str, MetaModel]):
    """The library by kind, loaded on access (``META_MODELS["periodic"]``)."""

    def __getitem__(self, kind: str) -> MetaModel:
        if kind not in meta_model_table():
            raise KeyError(kind)
        return get_meta_model(kind)

    def __iter__(self):  # type: ignore[no-untyped-def]
        return iter(meta_model_table())

    def __len__(self) -> int:
        return len(meta_model_table())


#: Every meta-model, by kind.
META_MODELS: Mapping[str, MetaModel] = _Library()


def working_conditions() -> dict[str, str]:
    """Kind -> its working conditions (paper Table 1 for the first six)."""
    return {k: get_meta_model(k).meaning for k in meta_model_table()}


__all__ = [
    "BUILTIN_META_MODELS",
    "ENTRY_POINT_GROUP",
    "META_MODELS",
    "TABLE_1",
    "MetaModel",
    "available_kinds",
    "get_meta_model",
    "working_conditions",
]
