"""A module imported on first use, so commands that never touch a backend never load it.

``twinwatch --help`` and loading a configuration must not pay for zenoh, rerun and the like
(``benchmarks/bench_startup.py``). A module that needs a backend only inside its functions
binds the backend's name to :func:`lazy_module` instead of importing it::

    if TYPE_CHECKING:
        import zenoh
    else:
        zenoh = lazy_module("zenoh")

The first use (``zenoh.Config()``, ``except zenoh.ZError``) imports it.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["lazy_module"]


class _LazyModule:
    """Stands for the module ``name``; any attribute imports it and returns its attribute."""

    __slots__ = ("_name",)

    def __init__(self, name: str) -> None:
        object.__setattr__(self, "_name", name)

    def __getattr__(self, attr: str) -> Any:
        return getattr(importlib.import_module(self._name), attr)

    def __setattr__(self, attr: str, value: Any) -> None:
        raise AttributeError(f"cannot set {attr!r} on the lazy module {self._name!r}")

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


def lazy_module(name: str) -> Any:
    """A stand-in for ``import name`` that imports the module on first attribute access."""
    return _LazyModule(name)
