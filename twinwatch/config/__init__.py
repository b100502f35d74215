"""Configuration: schema (:mod:`twinwatch.config.schema`) and loading.

The names below are imported on first use (PEP 562), so that importing a light submodule such as
:mod:`twinwatch.config.samples` (the CLI does, for ``--help``) does not load the schema.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from twinwatch.config.loader import ConfigError, default_config, load_config

__all__ = ["ConfigError", "default_config", "load_config"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from twinwatch.config import loader

        return getattr(loader, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
