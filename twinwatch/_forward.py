"""A read-only attribute that forwards to a part of its object: :class:`Forward`."""

from __future__ import annotations

import operator
from typing import Any, Generic, NoReturn, Self, TypeVar, overload

__all__ = ["Forward"]

T = TypeVar("T")


class Forward(Generic[T]):
    """A read-only attribute that reads an attribute of one of its object's parts, as a
    property that only returns ``self.<path>`` would: ``overruns: Forward[int] =
    Forward("worker.overruns", "Windows dropped...")`` on a class reads
    ``self.worker.overruns`` (the owner shows its parts' state under its own names).

    Args:
        path: the dotted attribute path from the object (``"pipeline.adapter.estimator"``).
    """

    def __init__(self, path: str, doc: str) -> None:
        self.path = path
        self.__doc__ = doc
        self._get = operator.attrgetter(path)
        self._name = path

    def __set_name__(self, owner: type[Any], name: str) -> None:
        self._name = name

    @overload
    def __get__(self, obj: None, owner: type[Any] | None = None) -> Self: ...

    @overload
    def __get__(self, obj: object, owner: type[Any] | None = None) -> T: ...

    def __get__(self, obj: object | None, owner: type[Any] | None = None) -> Self | T:
        if obj is None:
            return self
        value: T = self._get(obj)
        return value

    def __set__(self, obj: object, value: object) -> NoReturn:
        raise AttributeError(f"property {self._name!r} of {type(obj).__name__!r} object has "
                             "no setter")
