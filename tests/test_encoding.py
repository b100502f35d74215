"""The one JSON encoder (twinwatch/io/encoding.py): strict JSON of everything the daemon sends or
stores, the same values whichever of its two paths (orjson, or the standard library after
``to_jsonable``) writes them."""

from __future__ import annotations

import enum
import json
import math
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel

from twinwatch.io.encoding import to_json, to_jsonable


class _Level(enum.Enum):
    WARNING = "warning"


class _Reading(BaseModel):
    value: float
    unit: str = "ohm"


def _reference(payload: object) -> object:
    """What the standard library writes after to_jsonable, read back."""
    return json.loads(json.dumps(to_jsonable(payload), allow_nan=False))


def test_nan_and_infinities_are_null_everywhere() -> None:
    payload = {"x": math.nan, "y": [1.0, -math.inf], "z": np.array([np.nan, 2.0]),
               "w": np.float64(np.inf)}
    text = to_json(payload)
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"x": None, "y": [1.0, None], "z": [None, 2.0], "w": None}


def test_the_same_values_as_the_standard_library(monkeypatch: pytest.MonkeyPatch) -> None:
    grid = np.arange(12.0).reshape(3, 4)
    payload = {
        "floats": [1e-05, 1e16, 0.1, 6.5, -0.0, 2.0 ** -1074],
        "numpy": {"scalar": np.float64(0.25), "int": np.int64(7), "flag": np.bool_(True),
                  "matrix": grid, "strided": grid[:, ::2], "bools": np.array([True, False])},
        "model": _Reading(value=6.5),
        "enum": _Level.WARNING,
        "when": datetime(2026, 11, 28, 10, 0, 0, 123456, tzinfo=UTC),
        "path": Path("/var/lib/twinwatch/state.sqlite"),
        "tuple": (1, 2),
        "set": {3},
        "unicode": "Ra = 6.5 Ω ± 0.1 %",
        4: "an int key",
    }
    expected = _reference(payload)
    import twinwatch.io.encoding as encoding

    def refuse(*args: object, **kwargs: object) -> str:
        raise AssertionError("orjson should have encoded it all, not the standard library")

    monkeypatch.setattr(encoding.json, "dumps", refuse)
    text = to_json(payload)
    monkeypatch.undo()
    assert json.loads(text) == expected
    assert " " not in to_json({"a": [1, 2]})  # compact


def test_what_orjson_refuses_takes_the_standard_library_path() -> None:
    assert to_json({"n": 2 ** 70}) == '{"n":1180591620717411303424}'
    assert json.loads(to_json({"b": b"\x01\x02", "x": math.nan})) == {"b": [1, 2], "x": None}


def test_a_type_json_cannot_hold_is_a_type_error() -> None:
    with pytest.raises(TypeError, match="object"):
        to_json({"x": object()})
