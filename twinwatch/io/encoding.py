"""The one JSON encoder of everything twinwatch sends or stores: the health message (Zenoh, the
state store, the Rerun recording), alarm events, history replies, the saved twin.

Strict JSON: NaN and infinities become ``null`` (JSON has no NaN, and a bare ``NaN`` token
breaks most readers); numpy scalars and arrays become numbers and lists, pydantic models their
fields, enums their value, dates ISO 8601 strings, paths strings. Compact (no spaces), UTF-8
text (no ``\\u`` escapes). Encoded by orjson (the saved twin, ~380 kB once the diagnosis
holds 150 windows of evidence, in under 1 ms of CPU); a value orjson refuses (an integer
beyond 64 bits, bytes) goes through :func:`to_jsonable` and the standard library's encoder.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from datetime import date, datetime
from enum import Enum
from pathlib import PurePath
from typing import Any

import numpy as np
import orjson
from pydantic import BaseModel

__all__ = ["to_json", "to_jsonable"]


def to_jsonable(value: Any) -> Any:
    """``value`` as plain JSON types (dict, list, str, int, float, bool, None); NaN and
    infinities become None.

    Raises:
        TypeError: a value of another type.
    """
    if value is None or isinstance(value, bool | str | int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, BaseModel):
        return to_jsonable(value.model_dump())
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        # numbers all finite (the saved twin's covariance, every window): ``tolist`` suffices
        if value.dtype.kind in "biu" or (value.dtype.kind == "f"
                                         and bool(np.isfinite(value).all())):
            return value.tolist()
        return [to_jsonable(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, Enum):
        return to_jsonable(value.value)
    if isinstance(value, datetime | date):
        return value.isoformat()
    if isinstance(value, PurePath):
        return str(value)
    if isinstance(value, Sequence | set | frozenset):
        return [to_jsonable(v) for v in value]
    raise TypeError(f"cannot serialise {type(value).__name__} to JSON")


#: orjson's options: numpy arrays and scalars as numbers and lists, keys that are not strings
#: (an int, an enum) as their text.
_OPTIONS = orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS


def to_json(payload: Mapping[str, Any] | BaseModel) -> str:
    """Serialise ``payload`` to compact, strictly valid JSON (see the module docstring).

    Raises:
        TypeError: a value of a type JSON cannot hold.
    """
    try:  # what orjson does not encode itself (a pydantic model, a path) goes to to_jsonable
        return orjson.dumps(payload, default=to_jsonable, option=_OPTIONS).decode()
    except orjson.JSONEncodeError:  # an integer beyond 64 bits, or a type JSON cannot hold
        return json.dumps(to_jsonable(payload), separators=(",", ":"), allow_nan=False,
                          ensure_ascii=False)
