"""asyncua, imported when the output opens: loading a configuration does not load it.

The modules of this package hold ``asyncua`` and ``ua`` as module globals, lazy modules until
:func:`bind` (called when a server opens) rebinds them to the real ones (:func:`rebinds`):
every ``ua.X`` through the lazy module costs an import-system lookup. Typed Any: asyncua
annotates its protocol types as NewTypes, which every literal would have to be wrapped in.
"""

from __future__ import annotations

import logging
from typing import Any

from twinwatch._lazy import lazy_module

__all__ = ["asyncua", "bind", "rebinds", "ua"]

asyncua: Any = lazy_module("asyncua")
ua: Any = lazy_module("asyncua.ua")

_USERS: list[dict[str, Any]] = []
"""The globals of the modules that use ``asyncua`` / ``ua`` (:func:`rebinds`)."""
_BOUND = False


class _QuietStart(logging.Filter):
    """asyncua's start logs a traceback when the port is taken (twinwatch says it in one line:
    :class:`OpcUaServer`) and two warnings about identity tokens on an endpoint without
    security (the default here: anonymous clients only, nothing to verify)."""

    DROPPED = ("%s error starting server", "No signing policy available",
               "No encrypting policy available")

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.DROPPED)


_QUIET = _QuietStart()


def rebinds(namespace: dict[str, Any]) -> None:
    """Have :func:`bind` rebind ``asyncua`` and ``ua`` in ``namespace`` (a module's
    ``globals()``); at once if it has run already."""
    _USERS.append(namespace)
    if _BOUND:
        namespace.update(asyncua=asyncua, ua=ua)


def bind() -> None:
    """Bind the real modules once a server opens, here and in every module that
    :func:`rebinds`; quiet asyncua's start (:class:`_QuietStart`)."""
    global asyncua, ua, _BOUND
    import asyncua as real
    from asyncua import ua as real_ua

    asyncua, ua = real, real_ua
    _BOUND = True
    for namespace in _USERS:
        namespace.update(asyncua=real, ua=real_ua)
    quiet = logging.getLogger("asyncua.server.server")
    if _QUIET not in quiet.filters:
        quiet.addFilter(_QUIET)
