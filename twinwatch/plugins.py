"""One registry pattern for everything a configuration names: drivers, models, meta-models, sinks.

Modelled on python-can's ``can/interfaces/__init__.py``: a table maps a name (the ``type`` of a
``[driver]`` table, the ``model`` of ``[machine]``, a meta-model ``kind``, an output's table
name) to ``"module:Class"``. The table is extended by an entry-point group, and a module is
imported only when its name is first used, so a missing optional dependency only matters to the
configurations that need it. A plug-in cannot replace a built-in (the clash is logged once and
the entry point ignored).

Each room keeps its own registry next to its base class (:data:`twinwatch.drivers.DRIVERS`,
:data:`twinwatch.twin.models.MODELS`, :data:`twinwatch.twin.discovery.metamodels.META_MODELS`,
:data:`twinwatch.sinks.SINKS`); the built-in tables are plain literals, so
``tests/test_layering.py`` reads them as imports.
"""

from __future__ import annotations

import importlib
import json
import logging
import math
import re
import threading
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from importlib import metadata
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from twinwatch.errors import PluginError

__all__ = ["Registry", "commented_table", "toml_value"]

logger = logging.getLogger(__name__)

T = TypeVar("T")

#: twinwatch's own dependencies whose import name is not their distribution's name (a missing
#: one is a broken install).
_DISTRIBUTIONS: Mapping[str, str] = {"can": "python-can", "paho": "paho-mqtt",
                                     "zenoh": "eclipse-zenoh", "rerun": "rerun-sdk",
                                     "google": "protobuf"}


class Registry(Generic[T]):
    """Name -> class, from built-in ``"module:Class"`` paths and an entry-point group.

    Args:
        kind: what the registry holds, for messages (``"driver"``, ``"model"``, ...).
        group: the entry-point group other packages register in (``"twinwatch.drivers"``).
        base: returns the base class every entry must subclass (a callable, so that the
            registry can be declared before the base class's module is imported).
    """

    def __init__(self, kind: str, group: str, builtins: Mapping[str, str],
                 base: Callable[[], type[T]]) -> None:
        self.kind = kind
        self.group = group
        self.builtins: Mapping[str, str] = dict(builtins)
        self._base = base
        self._table: dict[str, str] | None = None
        self._loaded: dict[str, type[T]] = {}
        self._lock = threading.Lock()

    # -- the table ---------------------------------------------------------------------------
    def table(self) -> Mapping[str, str]:
        """Every known name -> ``"module:Class"``: the built-ins, then the entry points (read
        once)."""
        with self._lock:
            if self._table is None:
                table = dict(self.builtins)
                for ep in entry_points(group=self.group):
                    if ep.name in self.builtins:
                        logger.warning("entry point %s = %r ignored: %r is a built-in %s",
                                       ep.name, ep.value, ep.name, self.kind)
                        continue
                    table[ep.name] = ep.value.strip()
                self._table = table
            return self._table

    def names(self) -> list[str]:
        """The known names, built-ins first, in their declared order."""
        return list(self.table())

    def __contains__(self, name: object) -> bool:
        return name in self.table()

    def __iter__(self) -> Iterator[str]:
        return iter(self.table())

    def path(self, name: str) -> tuple[str, str]:
        """``(module, class)`` of ``name``.

        Raises:
            PluginError: an unknown name (the message lists the known ones).
        """
        try:
            module, _, attr = self.table()[name].partition(":")
        except KeyError:
            raise PluginError(f"unknown {self.kind} {name!r}; known: "
                              f"{', '.join(sorted(self.table()))}") from None
        return module.strip(), attr.strip()

    # -- loading -----------------------------------------------------------------------------
    def load(self, name: str) -> type[T]:
        """Import and return the class registered as ``name`` (cached).

        Raises:
            PluginError: an unknown name, a module that cannot be imported (the message says
                what to install), or an object that is not a subclass of the base class.
        """
        cls = self._loaded.get(name)
        if cls is not None:
            return cls
        module_name, class_name = self.path(name)
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise PluginError(f"{self.kind} {name!r} not available: {exc}. "
                              f"{_install_hint(exc, module_name)}") from exc
        obj = getattr(module, class_name, None)
        base = self._base()
        if not (isinstance(obj, type) and issubclass(obj, base)):
            raise PluginError(f"{self.kind} {name!r}: {module_name}.{class_name} is not a "
                              f"{base.__module__}.{base.__qualname__} subclass")
        self._loaded[name] = obj
        return obj

    def cache_clear(self) -> None:
        """Forget the table and the loaded classes (tests that install entry points)."""
        with self._lock:
            self._table = None
            self._loaded.clear()


def _dependencies() -> set[str]:
    """The distributions twinwatch's installed metadata requires, normalised, without the
    extras'."""
    try:
        requires = metadata.requires("twinwatch") or []
    except metadata.PackageNotFoundError:
        return set()
    return {re.split(r"[\s\[<>=!~;]", r, maxsplit=1)[0].lower().replace("_", "-")
            for r in requires if "extra ==" not in r}


def _install_hint(exc: ImportError, module_name: str) -> str:
    """What to install so that ``module_name`` imports."""
    missing = (getattr(exc, "name", None) or "").split(".")[0]
    dist = _DISTRIBUTIONS.get(missing, missing).lower().replace("_", "-")
    if missing and dist in _dependencies():
        return (f"{dist} is a dependency of twinwatch, missing from this environment: install "
                f"twinwatch again (pip install twinwatch) or pip install {dist}")
    if missing and not module_name.startswith(missing):
        return f"Install the package that provides {missing!r} (pip install {missing})"
    return (f"Is the package that provides {module_name} installed, with its extras? "
            f"(pip show it, or pip install it)")


# -- a plug-in's sample table ---------------------------------------------------------------------
def commented_table(model: Any, table: str, *, commented: bool = False,
                    fixed: Mapping[str, Any] | None = None) -> str:
    """The sample of a plug-in's configuration table, from its pydantic model: the table header,
    then every key with its default and description, optional keys commented out (what
    ``twinwatch sample-config`` prints for a plug-in that ships no sample of its own).

    Args:
        table: the table's dotted path (``"driver"``, ``"outputs.mqtt"``).
        commented: comment out everything, the header and required keys too (an output that
            stays off until its table is written).
        fixed: key -> value written as a live line (``{"type": "plant_direct"}``).

    Returns:
        TOML text: ``[table]``, its keys (``# key = default  # description``), then its
        sub-tables the same way.
    """
    lead = "# " if commented else ""
    lines = [f"{lead}[{table}]"]
    subtables: list[tuple[str, Any]] = []
    for name, info in model.model_fields.items():
        key = info.alias or name
        sub = _submodel(info.annotation)
        if sub is not None:
            subtables.append((key, sub))
            continue
        note = info.description or ""
        if fixed is not None and key in fixed:
            lines.append(_line(f"{lead}{key} = {toml_value(fixed[key])}", note))
        elif info.is_required():
            literal = _literal(info.annotation)
            if literal is not None:
                lines.append(_line(f"{lead}{key} = {toml_value(literal)}", note))
            else:
                lines.append(_line(f"# {key} = ...", f"required: {note}" if note
                                   else "required"))
        else:
            try:
                default = info.get_default(call_default_factory=True, validated_data={})
            except (TypeError, KeyError):  # a factory that needs the other fields
                default = None
            value = toml_value(default)
            lines.append(_line(f"# {key} = {value}" if value is not None else f"# {key} =",
                               note if value is not None else f"{note} (default: unset)"
                               .strip()))
    text = "\n".join(lines) + "\n"
    for key, sub in subtables:
        text += "\n" + commented_table(sub, f"{table}.{key}", commented=True)
    return text


def _line(code: str, note: str) -> str:
    return f"{code:<30} # {note}" if note else code


def _submodel(annotation: Any) -> Any:
    """The model class a field holds (also ``Model | None``), or None."""
    if isinstance(annotation, type) and hasattr(annotation, "model_fields"):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        found = [a for a in typing.get_args(annotation) if _submodel(a) is not None]
        return found[0] if len(found) == 1 else None
    return None


def _literal(annotation: Any) -> Any:
    """The value of a one-value ``Literal`` annotation, or None."""
    if typing.get_origin(annotation) is typing.Literal and len(typing.get_args(annotation)) == 1:
        return typing.get_args(annotation)[0]
    return None


def toml_value(value: Any) -> str | None:
    """``value`` as a TOML value, or None when TOML cannot write it (no null in TOML)."""
    if value is None:
        return None
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else None
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        items = [toml_value(v) for v in value]
        return None if None in items else "[" + ", ".join(typing.cast(list[str], items)) + "]"
    if isinstance(value, Mapping):
        pairs = [(k, toml_value(v)) for k, v in value.items()]
        return "{" + ", ".join(f"{k} = {v}" for k, v in pairs if v is not None) + "}"
    if hasattr(value, "model_dump"):
        return toml_value(value.model_dump())
    return toml_value(getattr(value, "value", None)) if hasattr(value, "value") else None
