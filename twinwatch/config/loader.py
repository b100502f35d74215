"""Loading and validating configuration files (TOML, read with :mod:`tomllib`)."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from twinwatch.config.schema import TwinwatchConfig


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the key and why."""


def _format(exc: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid configuration"]
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if not str(p).startswith("function-"))
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key (misspelt, or not valid in this table)"
        elif err["type"] == "missing":
            msg = "required key is missing"
        lines.append(f"  {loc or '(top level)'}: {msg}")
    return "\n".join(lines)


def validate_config(data: dict[str, Any], source: str = "<config>") -> TwinwatchConfig:
    """Validate a parsed configuration.

    Raises:
        ConfigError: naming each bad key and why.
    """
    try:
        return TwinwatchConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format(exc, source)) from None


def load_config(path: str | Path) -> TwinwatchConfig:
    """Read and validate a TOML configuration file.

    Raises:
        ConfigError: the file cannot be read, is not TOML, or a key is invalid.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the configuration: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return validate_config(data, str(p))


DEFAULT_CONFIG_PATH = Path(__file__).with_name("default.toml")


def default_config() -> TwinwatchConfig:
    """The built-in default (``default.toml`` beside this module, also printed by
    ``twinwatch sample-config``): the simulated DC motor in the resistance-degradation
    scenario, as fast as possible, recording to ``twinwatch.rrd``, health published on
    tcp/127.0.0.1:7447."""
    return load_config(DEFAULT_CONFIG_PATH)
