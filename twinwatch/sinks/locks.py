"""Exclusive locks on the files one daemon owns (the state database, the recording).

A second ``twinwatch run`` in the same working directory must fail before it touches a file the
first one writes. Each owner takes an advisory ``flock(2)`` on the file itself, opened without
truncating it, before anything else, and holds it until it closes; a crash releases it.

Closing any descriptor of a file drops the process's POSIX locks on it (SQLite's): the store
therefore releases its lock only after its SQLite connections are closed.

The lock's descriptor also tells whether the path still names the file being written
(:meth:`FileLock.changed`).
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from twinwatch.errors import LockedError

__all__ = ["FileLock", "LockedError"]


def _holder(fd: int) -> int | None:
    """The pid holding a FLOCK on the file open as ``fd`` (from /proc/locks), if known."""
    try:
        st = os.fstat(fd)
        with open("/proc/locks", encoding="ascii") as f:
            lines = f.readlines()
    except OSError:
        return None
    want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    for line in lines:
        parts = line.split()
        # "1: FLOCK  ADVISORY  WRITE 1234 08:01:5678 0 EOF" ("->" marks a waiter)
        if "->" in parts or len(parts) < 6 or parts[1] != "FLOCK":
            continue
        if parts[5] == want:
            try:
                return int(parts[4])
            except ValueError:
                return None
    return None


class FileLock:
    """An exclusive ``flock`` on ``path``, taken at once or not at all.

    Args:
        path: the file (created empty, with the process umask, if it does not exist; never
            truncated).
        what: what the file is, for the error message (``"state database"``).
        fix: what to do about a clash, for the error message.

    Raises:
        LockedError: another process holds it.
        OSError: the file cannot be opened (a missing directory, permissions).
    """

    def __init__(self, path: str | os.PathLike[str], what: str, fix: str) -> None:
        self.path = Path(path)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _holder(fd)
            os.close(fd)
            who = f"process {pid}" if pid is not None else "another process"
            raise LockedError(f"{what} {self.path} is in use by {who} (another twinwatch on "
                              f"the same files?): {fix}") from None
        except OSError:
            os.close(fd)
            raise
        self._fd: int | None = fd

    def changed(self) -> str | None:
        """Whether :attr:`path` still names the locked file (one ``fstat`` and one ``stat``).

        Returns:
            None while it does (or once released); ``"deleted"``: nothing at the path and the
            locked file has no name left (its content goes when it is closed);
            ``"replaced"``: another file at the path, the locked one has no name left;
            ``"moved"``: the locked file still exists under another name (renamed or
            hard-linked away), the path names another file or nothing.
        """
        if self._fd is None:
            return None
        held = os.fstat(self._fd)
        try:
            now: os.stat_result | None = os.stat(self.path)
        except (FileNotFoundError, NotADirectoryError):
            now = None
        except OSError:  # cannot tell (e.g. the directory is no longer searchable)
            return None
        if now is not None and (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino):
            return None
        if held.st_nlink > 0:
            return "moved"
        return "deleted" if now is None else "replaced"

    def release(self) -> None:
        """Release the lock (close the descriptor). Idempotent."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    def __repr__(self) -> str:
        return f"FileLock({str(self.path)!r}, {'held' if self._fd is not None else 'released'})"
