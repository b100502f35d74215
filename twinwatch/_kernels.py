"""Where numba keeps the compiled kernels: a cache directory per version of their sources.

numba's ``cache=True`` keys a kernel's cache on the file that defines it (its modification
time and size), not on the files it calls into: a kernel in ``twin/models/dcmotor.py`` that
calls ``pid_update`` from ``twin/models/_pid.py`` keeps its compiled code after ``_pid.py``
changes, and the twin silently simulates the old drive.

:func:`configure` points numba's cache at ``<base>/<hash of every kernel source>``, so a
change to any of them compiles everything afresh. ``<base>`` is ``NUMBA_CACHE_DIR`` when the
user set it, else ``$XDG_CACHE_HOME/twinwatch/numba``; when neither can be written (a
read-only home under systemd's ``ProtectHome``), numba's own default is left alone.

numba compiles a kernel missing from its disk cache in every process that needs it before
another has saved it: the worker processes of a gateway (one per core and per 50 machines)
that reach a kernel together on a cold cache each compiled it (four processes started
together: 40.9 s of CPU, 15.0 s taking turns). :func:`share_compilation` makes the
processes on one cache directory take turns: while a process is inside numba's compiler
lock it holds a lock file there, so a kernel is compiled by one process while the others
wait, and they load it from the cache.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

logger = logging.getLogger(__name__)

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


#: The longest a process waits for another's compilation before compiling on its own [s]
#: (a process stopped while it holds the lock file must not stop the others' windows); after
#: one such wait it compiles without waiting for the rest of its life.
COMPILE_WAIT_S = 60.0
#: The lock file in the cache directory (:func:`share_compilation`).
LOCK_NAME = "compile.lock"

_shared: Any = None


def share_compilation() -> bool:
    """Make the processes compiling into this cache directory take turns (module docstring):
    a listener on numba's ``numba:compiler_lock`` event holds :data:`LOCK_NAME` (``flock``)
    from the outermost acquisition of numba's compiler lock to its release. A process that
    finds a kernel missing from the cache then waits for the one compiling it and loads it
    (numba looks in the cache under its compiler lock, before it compiles). Waiting longer
    than :data:`COMPILE_WAIT_S`, it compiles on its own, from then on without waiting (logged
    once). Idempotent; False (nothing done) without a writable cache directory of ours.
    Never raises."""
    global _shared
    if _shared is not None:
        return True
    cache = os.environ.get("NUMBA_CACHE_DIR")
    if not cache or not _writable(Path(cache)):
        return False
    try:
        from numba.core import event

        class _Turns(event.Listener):  # type: ignore[misc, unused-ignore]  # numba: untyped
            def __init__(self, path: Path) -> None:
                self.path = path
                self.depth = 0
                self.fd: int | None = None
                self.guard = threading.Lock()
                self.waits = True  # False after a wait ran out: compile without waiting

            def on_start(self, event: Any) -> None:
                with self.guard:
                    self.depth += 1
                    if self.depth > 1 or not self.waits:  # held already, or given up
                        return
                try:
                    fd = _lock_file(self.path)
                except TimeoutError:
                    fd = None
                    logger.warning(
                        "numba kernel cache %s: waited %.0f s for another process compiling "
                        "into it (%s held); this process compiles its kernels without "
                        "waiting from now on", self.path.parent, COMPILE_WAIT_S,
                        self.path.name)
                with self.guard:
                    self.fd = fd
                    if fd is None:  # the wait ran out, or the file cannot be opened
                        self.waits = False

            def on_end(self, event: Any) -> None:
                with self.guard:
                    self.depth -= 1
                    if self.depth > 0:
                        return
                    fd, self.fd = self.fd, None
                if fd is not None:
                    os.close(fd)  # closing the descriptor releases the flock

        listener = _Turns(Path(cache) / LOCK_NAME)
        register = cast(Callable[[str, Any], None], event.register)  # numba is untyped
        register("numba:compiler_lock", listener)
    except (ImportError, AttributeError, TypeError):  # another numba's event API: no turns
        return False
    _shared = listener
    return True


def _lock_file(path: Path) -> int | None:
    """``path`` opened and locked exclusively (``flock``), waiting up to
    :data:`COMPILE_WAIT_S`: the descriptor (closing it releases the lock); None when it cannot
    be opened or locked.

    Raises:
        TimeoutError: another process held the lock all that time.
    """
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError:
        return None
    deadline = time.monotonic() + COMPILE_WAIT_S
    pause = 0.005
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
        except BlockingIOError:
            if time.monotonic() >= deadline:
                os.close(fd)
                raise TimeoutError(f"{path} held for {COMPILE_WAIT_S:g} s") from None
            time.sleep(pause)
            pause = min(pause * 2.0, 0.1)
        except OSError:
            os.close(fd)
            return None
