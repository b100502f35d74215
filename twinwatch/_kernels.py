"""Where numba keeps the compiled kernels: a cache directory per version of their sources.

numba's ``cache=True`` keys a kernel's cache on the file that defines it (its modification
time and size), not on the files it calls into: a kernel in ``twin/models/dcmotor.py`` that
calls ``pid_update`` from ``twin/models/_pid.py`` keeps its compiled code after ``_pid.py``
changes, and the twin silently simulates the old drive.

:func:`configure` points numba's cache at ``<base>/<hash of every kernel source>``, so a
change to any of them compiles everything afresh. ``<base>`` is ``NUMBA_CACHE_DIR`` when the
user set it, else ``$XDG_CACHE_HOME/twinwatch/numba``; when neither can be written (a
read-only home under systemd's ``ProtectHome``), numba's own default is left alone.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

#: The packages whose modules define or call numba kernels.
_KERNEL_DIRS = ("twin", "twin/models", "twin/prognostics", "twin/estimation", "plant")


def sources_hash(root: Path | None = None) -> str:
    """16 hex digits of SHA-256 over every module in the kernel packages under ``root``
    (twinwatch's own by default)."""
    root = root or Path(__file__).resolve().parent
    h = hashlib.sha256()
    for sub in _KERNEL_DIRS:
        for path in sorted((root / sub).glob("*.py")):
            h.update(path.name.encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _writable(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)


def configure() -> Path | None:
    """Set numba's cache directory for twinwatch's kernels (module docstring); call before
    the kernel modules are imported. Returns the directory, or None when numba's default is
    kept. Never raises."""
    try:
        base_env = os.environ.get("TWINWATCH_NUMBA_BASE") or os.environ.get("NUMBA_CACHE_DIR")
        if base_env:
            base = Path(base_env)
        else:
            xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
            base = Path(xdg) / "twinwatch" / "numba"
        os.environ.setdefault("TWINWATCH_NUMBA_BASE", str(base))
        target = base / sources_hash()
        if not _writable(target):
            return None
    except (OSError, RuntimeError):
        return None
    os.environ["NUMBA_CACHE_DIR"] = str(target)
    numba = sys.modules.get("numba")
    if numba is not None:  # imported before twinwatch: its config was read already
        numba.config.CACHE_DIR = str(target)
    return target
