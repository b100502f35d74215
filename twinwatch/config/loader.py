"""Loading and validating configuration files (TOML, read with :mod:`tomllib`).

Secrets: a private key or password file an output names (``[zenoh.tls]``, ``[zenoh.auth]``,
an ``[outputs.<name>]`` table's: :meth:`~twinwatch.sinks.base.SinkConfig.secret_input_files`),
and a configuration file that holds a secret inline (``*_private_key_base64``, ``[zenoh.auth]
password``), are refused when others can read them (mode ``o+r``): install them
``0640 root:twinwatch`` (the unit's group). Certificate and key paths are relative to the
configuration file's directory.
"""

from __future__ import annotations

import math
import os
import re
import stat
import tomllib
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from twinwatch.config.schema import TwinwatchConfig
from twinwatch.errors import ConfigError

_KEY_FIRST = re.compile(r"^([A-Za-z_][\w.\[\]-]*(?: \([^)]*\))?): (.+)$", re.DOTALL)
"""A whole configuration's check naming its key first (``diagnosis.library (f.toml): ...``)."""


def _errors(exc: ValidationError) -> list[tuple[str, str]]:
    """Each error of a validation as (dotted key, message)."""
    found = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if not str(p).startswith("function-"))
        msg = str(err["msg"]).removeprefix("Value error, ")  # pydantic's, says nothing
        if not loc and (m := _KEY_FIRST.match(msg)):  # a cross-check names its key first
            loc, msg = m.group(1), m.group(2)
        if err["type"] == "extra_forbidden":
            msg = "unknown key (misspelt, or not valid in this table)"
        elif err["type"] == "missing":
            msg = "required key is missing"
        elif err["type"] in ("float_type", "int_type") and isinstance(err.get("input"), bool):
            msg = f"{msg}, not {str(err['input']).lower()}: a boolean is not a number"
        found.append((loc or "(top level)", msg))
    return found


def _format(errors: list[tuple[str, str]], source: str) -> str:
    return "\n".join([f"{source}: invalid configuration",
                      *(f"  {key}: {msg}" for key, msg in errors)])


def _non_finite(data: Any, path: str = "") -> list[tuple[str, str]]:
    """Keys holding ``nan`` or ``inf`` (TOML has both): no key of a configuration takes them."""
    if isinstance(data, float):
        return [] if math.isfinite(data) else [(path, f"must be a finite number, not {data}")]
    if isinstance(data, dict):
        return [e for k, v in data.items() for e in _non_finite(v, f"{path}.{k}" if path else k)]
    if isinstance(data, list):
        return [e for i, v in enumerate(data) for e in _non_finite(v, f"{path}.{i}")]
    return []


def validate_config(data: dict[str, Any], source: str = "<config>") -> TwinwatchConfig:
    """Validate a parsed configuration.

    Raises:
        ConfigError: naming each bad key and why (``nan`` and ``inf`` are refused anywhere).
    """
    bad = _non_finite(data)
    try:
        cfg = TwinwatchConfig.model_validate(data)
    except ValidationError as exc:
        # every error at once: the non-finite keys, then the others (a non-finite key named
        # once, even when its table's model refuses it too)
        named = {key for key, _ in bad}
        raise ConfigError(_format(bad + [e for e in _errors(exc) if e[0] not in named],
                                  source)) from None
    except (ArithmeticError, TypeError) as exc:  # a validator computing with a huge value
        if bad:
            raise ConfigError(_format(bad, source)) from None
        raise ConfigError(f"{source}: invalid configuration: a value is out of range "
                          f"({type(exc).__name__}: {exc})") from None
    if bad:
        raise ConfigError(_format(bad, source))
    return cfg


def load_config(path: str | Path) -> TwinwatchConfig:
    """Read and validate a TOML configuration file.

    Raises:
        ConfigError: the file cannot be read, is not UTF-8 text, is not TOML, or a key is
            invalid.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the configuration: {exc.strerror}") from None
    except UnicodeDecodeError as exc:  # a file in another encoding, or not text at all
        raise ConfigError(f"{p}: not UTF-8 text (byte {exc.start}: {exc.reason}): a "
                          "configuration is a TOML file in UTF-8") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    cfg = validate_config(data, str(p))
    for output in cfg.output_tables():
        output.config.resolve_paths(p.resolve().parent)
    check_secrets(cfg, p)
    return cfg


def _readable_by_others(path: Path) -> bool:
    return bool(os.stat(path).st_mode & stat.S_IROTH)


def check_secrets(cfg: TwinwatchConfig, path: Path) -> None:
    """Refuse secrets that other users can read (see the module docstring).

    Raises:
        ConfigError: naming the file, the key and the ``chmod`` that fixes it.
    """
    outputs = cfg.output_tables()
    inline = [f"{o.key}.{k}" for o in outputs for k in o.config.inline_secret_keys()]
    # a driver's secrets (the OPC UA driver's key and password), where its table names them
    driver_inline = getattr(cfg.driver, "inline_secret_keys", None)
    if driver_inline is not None:
        inline += [f"driver.{k}" for k in driver_inline()]
    if inline and _readable_by_others(path):
        raise ConfigError(
            f"{path}: holds secrets ({', '.join(inline)}) and is readable by other users "
            f"(mode {stat.filemode(os.stat(path).st_mode)}): run `chmod o-rwx {path}` (install "
            f"it 0640 root:twinwatch), or move the key to a file readable only by the service")
    secret_files = {f"{o.key}.{k}": v for o in outputs for k, v in
                    o.config.secret_input_files().items()}
    driver_files = getattr(cfg.driver, "secret_input_files", None)
    if driver_files is not None:
        secret_files.update({f"driver.{k}": str(v) for k, v in
                             driver_files(path.resolve().parent).items()})
    for key, file in secret_files.items():
        f = Path(file)
        try:
            bad = _readable_by_others(f)
        except OSError:
            continue  # a missing file is reported when the session opens, naming the key
        if bad:
            raise ConfigError(
                f"{path}: {key} = {f} is a secret readable by other users (mode "
                f"{stat.filemode(os.stat(f).st_mode)}): run `chmod o-rwx {f}` (install it "
                f"0640 root:twinwatch)")


DEFAULT_CONFIG_PATH = Path(__file__).with_name("default.toml")


def default_config() -> TwinwatchConfig:
    """The built-in default (``default.toml`` beside this module, also printed by
    ``twinwatch sample-config``): the simulated DC motor in the resistance-degradation
    scenario, as fast as possible, recording to ``twinwatch.rrd``, health published on
    tcp/127.0.0.1:7447."""
    return load_config(DEFAULT_CONFIG_PATH)
