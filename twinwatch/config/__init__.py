"""Configuration: schema (:mod:`twinwatch.config.schema`) and loading."""

from twinwatch.config.loader import ConfigError, default_config, load_config

__all__ = ["ConfigError", "default_config", "load_config"]
