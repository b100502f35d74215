"""Where things are: the repository (``ROOT``) and the shared data beside it."""

from __future__ import annotations

from pathlib import Path

import pytest

from harness import ROOT, SHARED

__all__ = ["ROOT", "SHARED", "shared_path"]


def shared_path(*parts: str) -> Path:
    """Path under ../shared, or skip the test with a clear reason if it is absent."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"{p} not present: the shared data directory is not beside the repository")
    return p
