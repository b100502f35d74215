"""Strict numbers in the configuration: a boolean is never a number (issue 26 item 3).

The models are walked, not listed: every pydantic table reachable from the configuration file
(the file's own tables, every registered driver's, every registered output's, the twin's tables
and what they nest) and every twin model's options. A key whose type is a number (``int`` or
``float``, alone, optional, or inside a list, tuple or table of them) is given ``true`` and must
be refused at its own location; ``7`` must still pass where a float is expected.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, get_args, get_origin

import pytest
from pydantic import BaseModel, ValidationError

from twinwatch.config.loader import load_config
from twinwatch.config.schema import TwinwatchConfig
from twinwatch.drivers import DRIVERS, get_driver_class
from twinwatch.errors import ConfigError
from twinwatch.sinks import SINKS, sink_class
from twinwatch.twin.models import MODELS, create_model, get_model_class

_NUMBERS = (int, float)


def _twin_tables() -> list[type[BaseModel]]:
    """The classes behind the schema's lazily imported tables (typed ``Any`` in the schema)."""
    from twinwatch.config import schema

    return [schema._estimation_config(), schema._discovery_config(), schema._identify_config(),
            schema._prognostics_config(), schema._adaptive_config()]


def _roots() -> list[type[BaseModel]]:
    roots: list[type[BaseModel]] = [TwinwatchConfig, *_twin_tables()]
    roots += [get_driver_class(name).config_class for name in DRIVERS.names()]
    roots += [sink_class(name).config_class for name in SINKS.names()]
    return roots


def _members(annotation: Any) -> list[Any]:
    """The types an annotation is made of (unions, Annotated, containers unwrapped)."""
    origin = get_origin(annotation)
    if origin is typing.Annotated:
        return _members(get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType) or origin is not None:
        return [m for a in get_args(annotation) if a is not Ellipsis for m in _members(a)]
    return [annotation]


def _models(root: type[BaseModel], seen: set[type]) -> None:
    if root in seen:
        return
    seen.add(root)
    for field in root.model_fields.values():
        for member in _members(field.annotation):
            if isinstance(member, type) and issubclass(member, BaseModel):
                _models(member, seen)


def all_models() -> list[type[BaseModel]]:
    seen: set[type] = set()
    for root in _roots():
        _models(root, seen)
    return sorted(seen, key=lambda c: f"{c.__module__}.{c.__qualname__}")


def _bool_input(annotation: Any) -> Any | None:
    """A value that puts a ``True`` where this annotation expects a number, or None when the
    annotation takes no number or takes a boolean as such."""
    members = _members(annotation)
    if bool in members or not any(m in _NUMBERS for m in members):
        return None
    # the innermost container decides where the boolean goes
    def build(ann: Any) -> Any | None:
        origin = get_origin(ann)
        if origin is typing.Annotated:
            return build(get_args(ann)[0])
        if origin in (typing.Union, types.UnionType):
            for a in get_args(ann):
                v = build(a)
                if v is not None:
                    return v
            return None
        if ann in _NUMBERS:
            return True
        if origin is dict:
            v = build(get_args(ann)[1])
            return None if v is None else {"x": v}
        if origin in (list, tuple, set, frozenset, typing.Sequence):
            args = [a for a in get_args(ann) if a is not Ellipsis]
            vs = [build(a) for a in args]
            if any(v is not None for v in vs):
                if origin is tuple and len(args) > 1 and Ellipsis not in get_args(ann):
                    return [v if v is not None else 0 for v in vs]
                return [next(v for v in vs if v is not None)]
        return None
    return build(annotation)


def numeric_keys() -> list[tuple[type[BaseModel], str, Any]]:
    keys = []
    for model in all_models():
        for name, field in model.model_fields.items():
            value = _bool_input(field.annotation)
            if value is not None:
                keys.append((model, field.alias or name, value))
    return keys


def test_the_walk_finds_the_tables_and_their_numbers():
    names = {m.__name__ for m in all_models()}
    assert {"AcquisitionConfig", "PrognosticsConfig", "StateConfig", "AlarmRule",
            "EstimationConfig", "FileDriverConfig", "DCMotorPlantConfig"} <= names
    keys = {(m.__name__, k) for m, k, _ in numeric_keys()}
    assert {("StateConfig", "keep_days"), ("PrognosticsConfig", "horizon"),
            ("AcquisitionConfig", "window"), ("MachineConfig", "parameters")} <= keys
    assert len(keys) > 100


@pytest.mark.parametrize(("model", "key", "value"), numeric_keys(),
                         ids=lambda p: p.__name__ if isinstance(p, type) else
                         p if isinstance(p, str) else "")
def test_a_boolean_is_not_a_number(model, key, value):
    with pytest.raises(ValidationError) as info:
        model.model_validate({key: value})
    locs = [e["loc"] for e in info.value.errors(include_url=False)
            if e["type"] != "missing"]
    assert any(loc[:1] == (key,) for loc in locs), (
        f"{model.__name__}.{key} = {value!r} accepted: {info.value}")


def _twin_option_keys() -> list[tuple[str, str]]:
    keys = []
    for name in MODELS.names():
        cls = get_model_class(name)
        if not dataclasses.is_dataclass(cls):
            continue
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if f.init and _bool_input(hints[f.name]) is True:
                keys.append((name, f.name))
    return keys


def test_twin_model_options_walked():
    assert ("dc_motor", "kp") in _twin_option_keys()


@pytest.mark.parametrize(("model", "option"), _twin_option_keys())
def test_a_boolean_is_not_a_model_option_number(model, option):
    with pytest.raises(ValueError, match=option):
        create_model(model, {option: True})


def test_ints_still_pass_where_floats_are_expected():
    from twinwatch.config.schema import AcquisitionConfig
    from twinwatch.sinks.store import StateConfig

    assert StateConfig.model_validate({"keep_days": 7}).keep_days == 7
    assert AcquisitionConfig.model_validate({"stall_timeout": 5}).stall_timeout == 5.0
    assert create_model("dc_motor", {"kp": 1}).kp == 1


_BASE = """
[machine]
name = "m1"
[driver]
type = "simulated"
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "m1.toml"
    path.write_text(_BASE + text)
    return path


@pytest.mark.parametrize(("text", "key"), [
    ("[state]\nkeep_days = true\n", "state.keep_days"),
    ("[prognostics]\nhorizon = true\n", "prognostics.horizon"),
    ("[outputs.mqtt]\nrate = true\n", "outputs.mqtt.rate"),
    ("[alarms]\n[alarms.parameters.Ra]\nrul_alarm = true\n", "alarms.parameters.Ra.rul_alarm"),
])
def test_the_issues_booleans_are_refused_naming_the_key(tmp_path, text, key):
    with pytest.raises(ConfigError, match=rf"\b{key}: .*not true: a boolean is not a number"):
        load_config(_write(tmp_path, text))


def test_every_error_of_a_file_is_named_at_once(tmp_path):
    path = _write(tmp_path, "[acquisition]\nstall_timeout = nan\nqueue = true\n"
                  "[state]\nkeep_days = true\n[prognostics]\nhorizon = -1\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text = str(info.value)
    for key in ("acquisition.stall_timeout", "acquisition.queue", "state.keep_days",
                "prognostics.horizon"):
        assert f"  {key}:" in text, text
    assert text.count("acquisition.stall_timeout") == 1, text
