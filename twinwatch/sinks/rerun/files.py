"""The recording's files: the run's file and its lock, the link at ``[recording] path``, the
rotation, the file deleted, replaced or moved away while it is written, and the disk's free
space (see :mod:`twinwatch.sinks.rerun.recorder` for what happens when). :class:`RecordingFiles`
is the part of :class:`~twinwatch.sinks.rerun.recorder.RerunRecorder` that keeps them; the
recording stream it points at them is the recorder's.
"""

from __future__ import annotations

import logging
import os
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twinwatch.errors import RecorderError
from twinwatch.sinks.locks import FileLock, LockedError
from twinwatch.sinks.rerun.config import RUN_STAMP, RecordingConfig

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

logger = logging.getLogger(__package__)  # the log lines name the package

__all__ = ["FIX", "RecordingFiles", "check_directory", "check_writable", "free_name",
           "run_label"]


def check_directory(path: Path) -> None:
    """``path``'s directory exists and is writable, and ``path`` is no directory.

    Raises:
        RecorderError: saying what to change.
    """
    parent = path.parent
    if path.is_dir() and not path.is_symlink():
        raise RecorderError(f"recording path {path} is a directory: set [recording].path to a "
                            "file name")
    if not parent.exists():
        raise RecorderError(f"cannot record to {path}: directory {parent} does not exist; "
                            "create it or set [recording].path")
    if not parent.is_dir():
        raise RecorderError(f"cannot record to {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise RecorderError(f"cannot record to {path}: directory {parent} is not writable by "
                            "this user; fix its permissions or set [recording].path")


FIX = "stop it, or set another [recording].path"


def check_writable(path: Path) -> FileLock:
    """Lock ``path`` (created empty if absent, not truncated) for this recorder.

    Raises:
        RecorderError: ``path`` cannot be created or written, or another process holds it.
    """
    check_directory(path)
    try:
        return FileLock(path, "recording", FIX)
    except LockedError as exc:
        raise RecorderError(str(exc)) from None
    except OSError as exc:
        raise RecorderError(f"cannot record to {path}: {exc.strerror or exc}") from exc


def free_name(path: Path) -> Path:
    """``path``, or ``<stem>-2<suffix>``, ``-3``, ... : the first name nothing uses."""
    candidate, n = path, 1
    while candidate.exists() or candidate.is_symlink():
        n += 1
        candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
    return candidate


def run_label(run: str | None) -> str:
    """A run id as a file-name part (letters, digits, ``._-``; at most 40 characters)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", run or "")[:40].strip("._-")


class RecordingFiles:
    """The recorder's files (a part of :class:`~twinwatch.sinks.rerun.recorder.RerunRecorder`,
    which holds the state below and the recording stream). Its methods that take a window are
    called with the recorder's lock held.
    """

    min_free: int = 64 * 2**20
    """Bytes the disk must keep free for the recording to go on [B]."""

    config: RecordingConfig
    link: Path
    path: Path
    lost: int
    errors: int
    rotations: int
    _closed: bool
    _broken: str | None
    _paused: str | None
    _rec: rr.RecordingStream | None
    _file_lock: FileLock | None
    _file_windows: int
    _rotated: dict[Path, int]
    _kept_aside: Path | None
    _file_gone: str | None
    _file_gone_lost: int
    _no_new_file: str | None
    _link_problem: str | None

    if TYPE_CHECKING:  # the recorder's: the stream pointed at a file
        def _flush(self, rec: rr.RecordingStream) -> bool: ...

        def _attach_file(self, rec: rr.RecordingStream, *,
                         blueprint: rrb.Blueprint | None = None) -> None: ...

        def _save_blueprint(self, blueprint: rrb.Blueprint | None = None) -> None: ...

    def _claim(self, run: str | None) -> FileLock:
        """Make sure no other process records at :attr:`link`, keep a regular file found there
        (an earlier version's recording), create and lock this run's file, and point the link
        at it.

        Raises:
            RecorderError: the directory is missing or read-only, the link names a file another
                process writes, or the file cannot be created.
        """
        link = self.link
        check_directory(link)
        if link.is_symlink():
            if link.exists():  # the file of the run that wrote last: in use?
                try:
                    FileLock(link, "recording", FIX).release()
                except LockedError as exc:
                    raise RecorderError(str(exc)) from None
                except OSError:
                    pass  # cannot open it: not ours to check, the link is replaced
        elif link.exists():
            lock = check_writable(link)
            try:
                st = link.stat()
                if st.st_size:
                    stamp = time.strftime(RUN_STAMP, time.gmtime(st.st_mtime))
                    aside = free_name(link.with_name(f"{link.stem}-{stamp}{link.suffix}"))
                    link.rename(aside)
                    self._kept_aside = aside
                    logger.info("the recording found at %s (%d bytes) is kept as %s", link,
                                st.st_size, aside.name)
                else:
                    link.unlink()
            except OSError as exc:
                raise RecorderError(f"cannot keep the recording {link} aside: "
                                    f"{exc.strerror or exc}") from exc
            finally:
                lock.release()
        label = run_label(run)
        if not re.match(r"\d{8}T\d{6}Z", label):  # a run id starts with its UTC start
            label = time.strftime(RUN_STAMP, time.gmtime()) + (f"-{label}" if label else "")
        self.path = free_name(link.with_name(f"{link.stem}-{label}{link.suffix}"))
        lock = check_writable(self.path)
        self._point_link()
        return lock

    def _point_link(self, target: Path | None = None) -> None:
        """Make :attr:`link` a symbolic link to the run's file, or ``target`` beside it
        (atomically; logged once when the file system cannot)."""
        target = target or self.path
        if self.link == target:
            return
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        try:
            tmp.unlink(missing_ok=True)
            os.symlink(target.name, tmp)
            os.replace(tmp, self.link)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            if self._link_problem is None:
                self._link_problem = f"cannot link {self.link} to {target.name}: {exc}"
                logger.warning("%s; open %s itself", self._link_problem, self.path)
            return
        if self._link_problem is not None:
            logger.info("%s links to %s again", self.link, self.path.name)
            self._link_problem = None

    def _check_link(self) -> None:
        """Point the link again if something removed or changed it (one readlink a window)."""
        try:
            if os.readlink(self.link) == self.path.name:
                return
        except OSError:
            pass
        if self._link_problem is None:
            logger.warning("%s no longer named the run's recording %s: linked again",
                           self.link, self.path.name)
        self._point_link()

    @property
    def blueprint_path(self) -> Path:
        """``<stem>.rbl`` beside :attr:`link`: the viewer layout, for files opened together
        (``rerun twinwatch-*.rrd twinwatch.rbl``)."""
        return self.link.with_suffix(".rbl")

    def _family(self) -> list[Path]:
        """The older files of :attr:`link` (earlier runs', rotated ones), oldest first."""
        pattern = re.compile(re.escape(self.link.stem) + r"-\d{8}T\d{6}Z([-.][A-Za-z0-9._-]*)?"
                             + re.escape(self.link.suffix))
        found = []
        for p in self.link.parent.iterdir():
            if p != self.path and pattern.fullmatch(p.name) and not p.is_symlink():
                try:
                    found.append((p.stat().st_mtime, p.name, p))
                except OSError:
                    continue
        return [p for _, _, p in sorted(found)]

    def _rotate(self) -> None:
        """Rename the run's file with the UTC time, point the recording stream at a new file of
        the run's name (the renamed file's footer is written and its manifest memory freed),
        and delete the older files of the link beyond ``keep_files``. Called with the lock held.
        A failure stops the recording (logged once).

        The stream is kept, not replaced (the Rerun SDK 0.41 never frees a Python recording
        stream: rerun-io/rerun#2116, docs/runtime.md), so every file of one run shares one
        recording id (opened together: one recording). The blueprint is sent to the first
        file only (each send is a new stream); the others use :attr:`blueprint_path`."""
        rec = self._rec
        assert rec is not None
        if not self._flush(rec):
            return  # the writer died: the file was kept aside and a new one will be opened
        aside = self._aside_name()
        try:
            self.path.rename(aside)  # the open file sink keeps writing to the renamed file
            self._relock()
            self._attach_file(rec)
        except (OSError, RecorderError) as exc:
            self.errors += 1
            logger.error("cannot rotate the recording %s (%s): recording stops; fix the "
                         "directory's permissions or space and restart", self.path, exc)
            self._closed = True
            self._broken = f"recording stopped: cannot rotate {self.path} ({exc})"
            self._rec = None
            rec.disconnect()
            self._release()
            return
        self.rotations += 1
        self._rotated[aside] = self._file_windows
        self._file_windows = 0
        logger.info("recording rotated: %s closed, now writing %s", aside, self.path)
        keep = self.config.keep_files
        if keep:
            for old in self._family()[:-keep]:
                try:
                    old.unlink()
                    self._rotated.pop(old, None)
                    logger.info("old recording %s deleted ([recording] keep_files = %d)",
                                old.name, keep)
                except OSError as exc:
                    logger.warning("cannot delete old recording %s: %s", old, exc)

    def _aside_name(self) -> Path:
        """The name the run's file is rotated (or kept aside) to:
        ``<run file stem>.<UTC time>.<n>.rrd``."""
        stamp = time.strftime(RUN_STAMP, time.gmtime())
        return self.path.with_name(f"{self.path.stem}.{stamp}.{self.rotations:04d}"
                                   f"{self.path.suffix}")

    def _check_file(self, window: Any) -> bool:
        """The file at :attr:`path` is still the one being written (called with the lock held,
        before each window). Deleted, replaced or moved away: count the windows lost with it
        (and with the rotated files that went with its directory), and go on in a new file at
        the path, its directory created again (one level) if it was removed, the link made
        again. Returns False while no new file can be started (the window is then not
        recorded)."""
        rec = self._rec
        if rec is None:  # its file writer died: a new stream and file come with _reopen
            return True
        if self._file_gone is None:
            why = self._file_lock.changed() if self._file_lock is not None else None
            if why is None:
                self._check_link()
                return True
            gone = 0 if why == "moved" else self._file_windows
            with_it = ""
            for aside, n in list(self._rotated.items()):
                if not aside.exists():  # its directory was removed with it
                    gone += n
                    with_it = " and in the rotated files beside it"
                    del self._rotated[aside]
            self.lost += gone
            self._file_gone = (f"recording {self.path} was {why} while running (noticed at "
                               f"window {window}): {gone} windows recorded in it{with_it} "
                               f"are lost")
            self._file_gone_lost = gone
        try:
            if not self.path.parent.exists():
                self.path.parent.mkdir(mode=0o750)  # its parent must be there: one level only
                logger.warning("recording directory %s created again", self.path.parent)
            self._relock()
            self._attach_file(rec)  # the old file is finalised (footer) wherever it is now
        except (OSError, RecorderError) as exc:
            if self._no_new_file is None:
                self._no_new_file = f"{self._file_gone}; no new file can be started ({exc})"
                logger.error("%s: the windows are not recorded; tried again with each window",
                             self._no_new_file)
            return False
        self._point_link()
        self._save_blueprint()
        logger.log(logging.ERROR if self._file_gone_lost else logging.WARNING,
                   "%s; recording goes on in a new file %s", self._file_gone, self.path)
        self._file_windows = 0
        self._file_gone = self._no_new_file = None
        return True

    def _relock(self) -> None:
        """Lock the file now at :attr:`path` (after a rename) and release the old one."""
        old = self._file_lock
        self._file_lock = check_writable(self.path)
        if old is not None:
            old.release()

    def _release(self) -> None:
        lock, self._file_lock = self._file_lock, None
        if lock is not None:
            lock.release()

    def _free(self) -> int | None:
        """Free bytes on the recording's file system (None if unknown)."""
        try:
            st = os.statvfs(self.path.parent)
        except OSError:
            return None
        return st.f_bavail * st.f_frsize

    def _room(self) -> bool:
        """True if the disk has ``min_free`` bytes free; pauses and resumes (logged once)."""
        free = self._free()
        if free is None or free >= self.min_free:
            if self._paused is not None:
                logger.warning("recording to %s resumes: the disk has room again (%d windows "
                               "were not recorded)", self.path, self.lost)
                self._paused = None
            return True
        if self._paused is None:
            self._paused = (f"recording to {self.path} paused: {free / 2**20:.0f} MiB free on "
                            f"its disk, it keeps {self.min_free / 2**20:.0f} MiB for the state "
                            f"database")
            logger.error("%s; it resumes when there is room", self._paused)
        return False
