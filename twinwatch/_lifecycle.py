"""One lifecycle for everything that holds a resource (drivers, publisher, recorder)."""

from __future__ import annotations

import warnings
from typing import Self


class Closeable:
    """Context manager whose :meth:`close` is idempotent; warns if never closed.

    Subclasses set ``self._closed = False`` once the resource is open and implement
    :meth:`close` (which sets ``_closed``).
    """

    _closed: bool = True

    def close(self) -> None:  # pragma: no cover - always overridden
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            warnings.warn(
                f"{self!r} was never closed; call close() or use it as a context manager",
                ResourceWarning,
                stacklevel=2,
            )
            self.close()
