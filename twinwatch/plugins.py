"""One registry pattern for everything a configuration names: drivers, models, meta-models, sinks.

Modelled on python-can's ``can/interfaces/__init__.py``: a table maps a name (the ``type`` of a
``[driver]`` table, the ``model`` of ``[machine]``, a meta-model ``kind``, an output's table
name) to ``"module:Class"``. The table is extended by an entry-point group
(``name = "package.module:Class"`` in another package's metadata, read once), and a module is
imported only when its name is first used, so a missing optional dependency only matters to the
configurations that need it.

Rules, the same for every registry:

* a plug-in cannot replace a built-in: the clash is logged once and the entry point ignored;
* an unknown name raises :class:`~twinwatch.errors.PluginError` listing the known ones;
* a module that cannot be imported raises :class:`~twinwatch.errors.PluginError` saying which
  package (and extra) to install;
* the loaded object must be a subclass of the registry's base class.

Each room keeps its own registry next to its base class (:data:`twinwatch.drivers.DRIVERS`,
:data:`twinwatch.twin.models.MODELS`, :data:`twinwatch.twin.discovery.metamodels.META_MODELS`,
:data:`twinwatch.sinks.SINKS`); the built-in tables are plain literals, so
``tests/test_layering.py`` reads them as imports.
"""

from __future__ import annotations

import importlib
import logging
import threading
from collections.abc import Callable, Iterator, Mapping
from importlib.metadata import entry_points
from typing import Generic, TypeVar

from twinwatch.errors import PluginError

__all__ = ["Registry"]

logger = logging.getLogger(__name__)

T = TypeVar("T")

#: Third-party modules whose absence an extra of twinwatch's pyproject.toml would mend.
_EXTRAS: Mapping[str, str] = {"paho": "mqtt", "rich": "watch"}


class Registry(Generic[T]):
    """Name -> class, from built-in ``"module:Class"`` paths and an entry-point group.

    Args:
        kind: what the registry holds, for messages (``"driver"``, ``"model"``, ...).
        group: the entry-point group other packages register in (``"twinwatch.drivers"``).
        builtins: name -> ``"module:Class"`` of the built-in classes.
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
        once; a plug-in that clashes with a built-in is logged and ignored)."""
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


def _install_hint(exc: ImportError, module_name: str) -> str:
    """What to install so that ``module_name`` imports."""
    missing = (getattr(exc, "name", None) or "").split(".")[0]
    if missing in _EXTRAS:
        return f"Install it with: pip install 'twinwatch[{_EXTRAS[missing]}]'"
    if missing and not module_name.startswith(missing):
        return f"Install the package that provides {missing!r} (pip install {missing})"
    return (f"Is the package that provides {module_name} installed, with its extras? "
            f"(pip show it, or pip install it)")
