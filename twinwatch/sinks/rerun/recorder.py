"""Recording every acquisition window to a Rerun ``.rrd`` file, and serving it live.

One :class:`RerunRecorder` per monitored machine, each with its own
:class:`rerun.RecordingStream` (never the global one, so several recorders coexist in one
process). What it logs is :class:`~twinwatch.sinks.rerun.views.RecordingViews`; this module
keeps the files, the live server and the faults (operator's side: docs/operating.md,
docs/runtime.md).

Durability: the recording is flushed after every window. The RRD *footer* is written by
:meth:`RerunRecorder.close` or at a normal interpreter exit; a hard stop leaves a file without
footer, so the daemon turns SIGTERM into a normal shutdown.

Faults: the run's file is locked (``flock``) while it is written. Below ``RerunRecorder.min_free``
bytes free the recording pauses. A dead file writer (a full disk, a flush that times out) is
reported, its file kept under a rotated name, and a new file opened on a *new* stream after
``reopen_after`` seconds (doubling); the dead stream is never touched again (in the Rerun SDK
0.41 a flush, a new file or a disconnect on it, and its exit hook, wait forever). The run's file
deleted, replaced or moved away is noticed before the next window and the same stream goes on
in a new file of the same name.

Rotation: the SDK keeps every chunk's manifest entry in memory for the life of a file, so after
``[recording] rotate_windows`` windows the run's file is renamed to
``<run file stem>.<UTC time>.<n>.rrd`` (finalised) and the same stream goes on in a new file of
the run's name; the newest ``keep_files`` older files of ``path`` are kept.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
import uuid
from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self

import numpy as np

from twinwatch.errors import RecorderError
from twinwatch.io.encoding import to_json
from twinwatch.sinks.base import AlarmBands, ProcessedWindow, Role, Sink, SinkContext, _frozen
from twinwatch.sinks.locks import FileLock, LockedError
from twinwatch.sinks.rerun.config import RUN_STAMP, RecordingConfig
from twinwatch.sinks.rerun.live import LiveServer, bury
from twinwatch.sinks.rerun.style import rr, rrb
from twinwatch.sinks.rerun.views import RecordingViews, emit

if TYPE_CHECKING:
    from twinwatch.twin.health import HealthMessage

logger = logging.getLogger(__package__)  # the log lines name the package

__all__ = ["RerunRecorder"]


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


class RerunRecorder(Sink):
    """Records measured vs twin outputs, parameter health and data quality to a ``.rrd`` file
    of its own per run (and serves them live when configured): the built-in output ``rerun``
    (table ``[recording]``, a recorder: it gets every window).

    Thread-safe against :meth:`close`; calls after it are ignored. With ``config.enabled``
    false nothing is written and :meth:`log_window` only validates its arguments.

    Args:
        config: the ``[recording]`` configuration.
        machine, outputs, parameters, output_units, nominal, estimated, alarm_bands: as
            :class:`~twinwatch.sinks.rerun.views.RecordingViews` (default ``estimated``: every
            parameter).
        run: the run's id (``20261122T101530Z-3f9a2c``), the file's name after ``<stem>-``
            (default: the UTC start time; an id that does not start with one follows it).

    Attributes:
        link: the configured ``path``: a symbolic link to the run's file.
        path: the run's file being written.
        windows: number of windows recorded.
        errors: number of windows whose flush to disk failed.

    Raises:
        ValueError: empty ``machine``, empty or duplicate ``outputs``.
        RecorderError: the file cannot be created or written, the recording at ``path`` is in
            use by another process, the live server's port is taken, or Rerun refused to open
            the file.
    """

    config_class: ClassVar[type[RecordingConfig]] = RecordingConfig
    role: ClassVar[Role] = "recorder"
    counter_prefix: ClassVar[str | None] = "recording"
    open_order: ClassVar[int] = 30  # after every lock

    flush_timeout: float = 10.0
    """Seconds a flush may take before the window is counted as an error [s]."""

    reopen_after: float = 30.0
    """Seconds before the file is reopened after the file writer died; doubles while it keeps
    dying, up to :attr:`reopen_max` [s]."""

    reopen_max: float = 1800.0
    """The longest wait between two attempts to reopen the file [s]."""

    serve_timeout: float = 5.0
    """Seconds the live server may take to listen before opening fails [s]."""

    min_free: int = 64 * 2**20
    """Bytes the disk must keep free for the recording to go on [B]."""

    def __init__(self, config: RecordingConfig, machine: str, *, outputs: Sequence[str],
                 parameters: Mapping[str, str], output_units: Mapping[str, str] | None = None,
                 nominal: Mapping[str, float] | None = None,
                 estimated: Sequence[str] | None = None,
                 alarm_bands: Mapping[str, AlarmBands] | None = None,
                 run: str | None = None) -> None:
        self._closed = True  # until fully open, so __del__ and close() are safe
        if not machine:
            raise ValueError("machine must not be empty")
        if isinstance(outputs, str):
            raise ValueError("outputs must be a sequence of names, not a string")
        if not outputs or len(set(outputs)) != len(outputs):
            raise ValueError(f"outputs must be non-empty and unique, got {list(outputs)}")
        self.config = config
        self.machine = machine
        self.outputs: tuple[str, ...] = tuple(outputs)
        self.parameters: dict[str, str] = dict(parameters)
        self.views = RecordingViews(machine, self.outputs, self.parameters,
                                    output_units=output_units, nominal=nominal,
                                    estimated=estimated, alarm_bands=alarm_bands,
                                    recent_s=config.recent_s)
        self.link = Path(config.path).expanduser()
        self.path = self.link
        self.windows = 0
        self.errors = 0
        self.lost = 0
        self._dead_since: float | None = None  # monotonic time the file writer died
        self._broken: str | None = None  # why recording stopped for good
        self._paused: str | None = None  # why recording waits for disk space
        self._reopen_at = 0.0
        self._reopen_delay = self.reopen_after
        self._lock = threading.Lock()
        self._rec: rr.RecordingStream | None = None
        self._live: LiveServer | None = None  # the live view, with ``serve``
        self._file_lock: FileLock | None = None
        self.rotations = 0
        self._file_windows = 0
        self._rotated: dict[Path, int] = {}  # files kept aside -> windows recorded in each
        self._kept_aside: Path | None = None  # a regular file found at the link, renamed
        self._file_gone: str | None = None  # what happened to the file, until a new one
        self._file_gone_lost = 0
        self._no_new_file: str | None = None  # why no new file could be started yet
        self._link_problem: str | None = None  # why the link cannot name the run's file
        if not config.enabled:
            logger.info("rerun recording disabled for %s", machine)
            return
        self._recording_id = uuid.uuid4()  # every file of this recorder shares it
        if config.serve:
            self._live = LiveServer(machine, config.serve_bind, config.serve_port,
                                    config.server_memory_limit)
            self._live.probe()  # before any file is touched
        self._file_lock = self._claim(run)
        try:
            self._rec = self._open_stream()
            if self._live is not None:
                self._live.open(config.application_id, self._recording_id,
                                self.views.blueprint(), self._log_static, self.serve_timeout)
        except BaseException:
            if self._rec is not None:
                self._rec.disconnect()
                self._rec = None
            self._file_lock.release()
            raise
        self._closed = False
        logger.info("recording %s to %s (%s)", machine, self.path, self.link)

    def _open_stream(self) -> rr.RecordingStream:
        """A recording stream saving to :attr:`path`; the blueprint also goes to
        :attr:`blueprint_path`."""
        rec = rr.RecordingStream(self.config.application_id, recording_id=self._recording_id)
        blueprint = self.views.blueprint()
        self._attach_file(rec, blueprint=blueprint)
        if not rr.is_enabled(rec):
            logger.warning("rerun logging is disabled (RERUN=off?): %s stays empty", self.path)
        self._save_blueprint(blueprint)
        return rec

    def _save_blueprint(self, blueprint: rrb.Blueprint | None = None) -> None:
        try:
            (blueprint or self.views.blueprint()).save(self.config.application_id,
                                                 self.blueprint_path)
        except (OSError, RuntimeError, ValueError) as exc:
            logger.warning("cannot write the blueprint %s (%s): rotated files open with the "
                           "viewer's default layout", self.blueprint_path, exc)

    def _attach_file(self, rec: rr.RecordingStream, *,
                     blueprint: rrb.Blueprint | None = None) -> None:
        """Point ``rec`` at a new file at :attr:`path` (the previous one is finalised) and send
        what each file needs on its own."""
        try:
            rec.save(self.path, default_blueprint=blueprint)
        except (OSError, RuntimeError, ValueError) as exc:
            raise RecorderError(f"rerun cannot write {self.path}: {exc}") from exc
        self._log_static(rec)

    def _log_static(self, rec: rr.RecordingStream) -> None:
        """What every file and the live stream need once (name, key, series styles)."""
        rec.send_recording_name(f"{self.machine} twin")
        emit(rec, self.views.static_ops())

    @property
    def live_url(self) -> str | None:
        """Where a viewer connects (``rerun+http://127.0.0.1:9876/proxy``), None when not
        serving."""
        live = self._live
        return live.url if live is not None and live.stream is not None else None

    # -- the sink contract ---------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: RecordingConfig, context: SinkContext) -> Self:
        """Record to a new file beside ``[recording] path``, which links to it.

        Raises:
            RecorderError: the file cannot be created, written or locked, or the live server
                cannot listen.
        """
        rec = config.model_copy()
        rec.path = str(config.output_files(context.cwd)["path"])
        return cls(rec, context.machine, outputs=context.outputs,
                   parameters=dict(context.parameters), output_units=context.output_units,
                   nominal=context.nominal,
                   estimated=context.estimated or tuple(context.parameters),
                   alarm_bands=context.alarm_bands, run=context.run or None)

    @classmethod
    def reload_key(cls, config: RecordingConfig, context: SinkContext) -> Hashable:
        """The machine, the entities and views it declares and the table; not the alarm
        thresholds (a reload that changes them keeps the file, :meth:`attach`)."""
        return (context.machine, tuple(context.outputs), _frozen(dict(context.parameters)),
                _frozen(dict(context.output_units)), _frozen(dict(context.nominal)),
                tuple(context.estimated), _frozen(config.model_dump()))

    def attach(self, context: SinkContext) -> None:
        """A reload hands the recorder over: draw its alarm thresholds from the next window."""
        super().attach(context)
        with self._lock:
            ops = self.views.set_alarm_bands(context.alarm_bands)
            if ops and self._rec is not None:
                emit(self._rec, ops)
            if ops and self._live is not None:
                self._live.emit(ops)

    def counters(self) -> dict[str, int]:
        """``lost``: windows not recorded."""
        return {"lost": int(self.lost)}

    def summary(self) -> list[str]:
        """Where the run's recording is, how to open it, and the windows it could not record."""
        cwd = self.context.cwd if self.context is not None else Path.cwd()

        def shown(p: Path) -> Path:
            return p.relative_to(cwd) if p.is_relative_to(cwd) else p

        if self._link_problem is None and self.link != self.path:
            opened = f"{shown(self.link)}, the link to it"
        else:
            opened = str(shown(self.path))
        lines = [f"recording: {self.path.absolute()} (open with: rerun {opened})"]
        if self.rotations:
            lines.append(f"recording: this run's {self.rotations} earlier files are beside it: "
                         f"rerun {shown(self.path.parent)}/{self.path.stem}*{self.path.suffix} "
                         f"{shown(self.blueprint_path)}")
        if self._kept_aside is not None:
            lines.append(f"recording: the file found at {shown(self.link)} was kept as "
                         f"{shown(self._kept_aside)}")
        if self.lost:
            lines.append(f"recording: {self.lost} windows could not be recorded or were lost "
                         "with a deleted file (see the log)")
        return lines

    @property
    def status(self) -> str | None:
        """The live view's address while serving."""
        url = self.live_url
        return f"live view on {url}" if url is not None else None

    @property
    def problem(self) -> str | None:
        """Why windows are not being recorded right now, or how many were not."""
        if self._broken is not None:
            return f"{self._broken}; {self.lost} windows not recorded"
        if self._no_new_file is not None:
            return f"{self._no_new_file}; {self.lost} windows not recorded"
        if self._paused is not None:
            return f"{self._paused}; {self.lost} windows not recorded"
        if self._dead_since is not None:
            return (f"recording to {self.path} stopped (the file writer died: disk full?); "
                    f"{self.lost} windows not recorded")
        if self.lost:
            return f"recording: {self.lost} windows not recorded"
        return self._live.problem if self._live is not None else None

    def _writer_died(self, rec: rr.RecordingStream, exc: BaseException) -> None:
        """The file sink is gone: abandon the stream, keep the broken file under a rotated
        name, and schedule a new file. Called with the lock held."""
        now = time.monotonic()
        bury(rec)
        self._rec = None
        if self._dead_since is None:
            self._dead_since = now
            logger.error("recording to %s stopped: %s (disk full?); the windows recorded so "
                         "far are kept, the next ones are counted as not recorded until a new "
                         "file is opened (in %g s)", self.path, exc, self._reopen_delay)
        else:
            self._reopen_delay = min(2 * self._reopen_delay, self.reopen_max)
            logger.debug("recording to %s failed again: %s", self.path, exc)
        if self._file_windows:
            aside = self._aside_name()
            try:
                self.path.rename(aside)
                self._rotated[aside] = self._file_windows
                self.rotations += 1
                logger.error("the recording up to the failure is %s (no footer: "
                             "`rerun rrd optimize` completes it)", aside)
            except OSError as err:
                logger.error("cannot keep the broken recording %s aside (%s): it will be "
                             "overwritten when recording resumes", self.path, err)
        self._reopen_at = now + self._reopen_delay
        self._file_windows = 0

    def _reopen(self) -> bool:
        """A new stream and file at :attr:`path` once ``_reopen_at`` has passed. Called with
        the lock held. Returns True if recording can go on."""
        if time.monotonic() < self._reopen_at:
            return False
        self._reopen_at = time.monotonic() + self._reopen_delay
        try:
            self._relock()
            self._rec = self._open_stream()
        except (OSError, RecorderError) as exc:
            logger.debug("reopening the recording %s failed: %s", self.path, exc)
            return False
        logger.warning("recording to %s reopened (a new file) after %.0f s", self.path,
                       time.monotonic() - (self._dead_since or 0.0))
        return True

    @property
    def recording(self) -> rr.RecordingStream | None:
        """The underlying Rerun recording stream (``None`` when disabled)."""
        return self._rec

    # -- the files (with the lock held, but _claim at open) -----------------------------------
    def _claim(self, run: str | None) -> FileLock:
        """Make sure no other process records at :attr:`link`, keep aside a regular file found
        there, create and lock this run's file, and point the link at it.

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
        """``<stem>.rbl`` beside :attr:`link`: the viewer layout for files opened together
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
        the run's name, and delete the older files of the link beyond ``keep_files``. Called
        with the lock held. A failure stops the recording.

        The stream is kept, not replaced (the Rerun SDK 0.41 never frees a Python recording
        stream: rerun-io/rerun#2116), so every file of one run shares one recording id. The
        blueprint is sent to the first file only; the others use :attr:`blueprint_path`."""
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
        """``<run file stem>.<UTC time>.<n>.rrd``: the run's file rotated or kept aside."""
        stamp = time.strftime(RUN_STAMP, time.gmtime())
        return self.path.with_name(f"{self.path.stem}.{stamp}.{self.rotations:04d}"
                                   f"{self.path.suffix}")

    def _check_file(self, window: Any) -> bool:
        """If the file at :attr:`path` was deleted, replaced or moved away, count the windows
        lost with it and go on in a new file at the path (its directory created again, one
        level). Called with the lock held, before each window. Returns False while no new
        file can be started."""
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
        old = self._file_lock
        self._file_lock = check_writable(self.path)
        if old is not None:
            old.release()

    def _release(self) -> None:
        lock, self._file_lock = self._file_lock, None
        if lock is not None:
            lock.release()

    def _free(self) -> int | None:
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

    # -- one window ----------------------------------------------------------------------------
    def _validate(self, t: np.ndarray, measured: Mapping[str, np.ndarray],
                  simulated: Mapping[str, np.ndarray], parameters: Mapping[str, float]
                  ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray],
                             dict[str, float]]:
        times = np.asarray(t, dtype=np.float64)
        if times.ndim != 1 or times.size == 0:
            raise ValueError(f"t must have shape (N,) with N >= 1, got {times.shape}")
        if not np.all(np.isfinite(times)):
            raise ValueError("t must be finite")
        series: list[dict[str, np.ndarray]] = []
        for label, channels in (("measured", measured), ("simulated", simulated)):
            arrays: dict[str, np.ndarray] = {}
            for name, values in channels.items():
                if name not in self.outputs:
                    raise ValueError(f"{label} channel {name!r} is not a declared output "
                                     f"{list(self.outputs)}")
                array = np.asarray(values, dtype=np.float64)
                if array.shape != times.shape:
                    raise ValueError(f"{label}[{name!r}] has shape {array.shape}, expected "
                                     f"{times.shape}")
                arrays[name] = array
            series.append(arrays)
        unknown = set(parameters) - set(self.parameters)
        if unknown:
            raise ValueError(f"parameters {sorted(unknown)} are not declared "
                             f"{list(self.parameters)}")
        estimates = {name: float(value) for name, value in parameters.items()}
        return times, series[0], series[1], estimates

    def log_window(self, *, t: np.ndarray, measured: Mapping[str, np.ndarray],
                   simulated: Mapping[str, np.ndarray], parameters: Mapping[str, float],
                   health: HealthMessage | Mapping[str, Any], terms_changed: bool = False,
                   health_json: str | None = None,
                   events: Sequence[Mapping[str, Any]] = ()) -> None:
        """Record one acquisition window, flush it, and send it to the live server if serving.

        Args:
            t: shape (N,), sample times [s] on the plant clock, finite.
            measured: output name -> shape (N,) measured samples (SI units of the twin).
                Every key must be one of ``outputs``; an output may be absent.
            simulated: output name -> shape (N,) twin-simulated samples, same rules.
            parameters: parameter name -> estimate at ``t[-1]`` (unit as declared); every key
                must be one of the declared ``parameters``.
            health: the window's health message (typed), or any JSON-serialisable health
                document; the fields it holds are drawn.
            terms_changed: the twin's meta-model terms changed in this window.
            health_json: ``health`` already encoded; None: encoded here.
            events: the alarm changes of this window (:meth:`AlarmEvaluator.update
                <twinwatch.daemon.alarms.AlarmEvaluator.update>`): each a log row and a marker
                on the parameter's view.

        Raises:
            ValueError: a shape, name or value that does not fit the above (nothing recorded).
            TypeError: ``health`` is not JSON-serialisable (nothing recorded).

        A failed flush is never raised: it is counted in :attr:`errors`, and the windows that
        follow in :attr:`lost` until the file is reopened.
        """
        from twinwatch.twin.health import read_health

        times, meas, sim, estimates = self._validate(t, measured, simulated, parameters)
        if health_json is None:
            health_json = (to_json(health) if isinstance(health, Mapping)
                           else health.to_json())
        try:
            doc = read_health(health_json)  # the one typed reading of the message
        except ValueError as exc:
            raise TypeError(f"health must encode to a JSON object: {exc}") from exc
        if not self.config.enabled:
            return
        m = self.machine
        t_end = float(times[-1])
        with self._lock:
            if self._closed:
                if self._broken is not None:
                    self.lost += 1
                logger.debug("recorder of %s closed, dropping window at t=%.3f s", m, t_end)
                return
            ops = self.views.window_ops(times, meas, sim, estimates, doc, health_json,
                                   terms_changed, list(events))
            if self._live is not None:
                self._live.emit(ops)
            window = doc.window
            if (not self._check_file(window) or not self._room()
                    or (self._rec is None and not self._reopen())):
                self.lost += 1
                return
            rec = self._rec
            assert rec is not None
            emit(rec, ops)
            if not self._flush(rec):
                self.lost += 1
                return
            self._recorded()

    def _recorded(self) -> None:
        """A window is in the file: count it, note a dead writer back, rotate when due."""
        if self._dead_since is not None:
            logger.warning("recording to %s works again after %.0f s: %d windows were "
                           "not recorded", self.path, time.monotonic() - self._dead_since,
                           self.lost)
            self._dead_since = None
            self._reopen_delay = self.reopen_after
        self.windows += 1
        self._file_windows += 1
        if self.config.rotate_windows and self._file_windows >= self.config.rotate_windows:
            self._rotate()

    def write(self, out: ProcessedWindow) -> None:
        """:meth:`log_window` with the processed window."""
        est = out.result.estimate
        self.log_window(t=out.window.t, measured={o: out.window[o] for o in self.outputs},
                        simulated={o: est.simulated[:, j] for j, o in enumerate(self.outputs)},
                        parameters=est.values, health=out.health,
                        terms_changed=out.result.changed, health_json=out.health_json,
                        events=out.events)

    def _flush(self, rec: rr.RecordingStream) -> bool:
        """Flush to the file; False if it failed (the writer died: :meth:`_writer_died`)."""
        try:
            rec.flush(timeout_sec=self.flush_timeout)
        except Exception as exc:  # noqa: BLE001 - rerun raises plain exceptions on timeout
            # the file sink is gone: flushing it again would block every window
            self.errors += 1
            self._writer_died(rec, exc)
            return False
        return True

    def close(self) -> None:
        """Flush, write the footer and close the file; the live server is kept for the next
        recorder on its address. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._live is not None:  # kept for a later recorder on its address
                self._live.park(self.flush_timeout)
            rec, self._rec = self._rec, None
            if rec is None:  # never opened, or its file writer died (abandoned)
                self._release()
                kept = [p for p in self._rotated if p.exists()]
                if not self.path.exists() and kept:  # the link names the last file kept
                    self._point_link(max(kept, key=lambda p: p.name))
                return
            why = self._file_lock.changed() if self._file_lock is not None else None
            if why in ("deleted", "replaced") and self._file_windows:
                self.lost += self._file_windows
                logger.error("recording %s was %s before it was closed: %d windows recorded in "
                             "it are lost", self.path, why, self._file_windows)
            if self._flush(rec):
                rec.disconnect()
            self._release()
        logger.info("recording of %s closed: %d windows in %s", self.machine, self.windows,
                    self.path)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return (f"RerunRecorder({str(self.path)!r}, {self.machine!r}, {state}, "
                f"windows={self.windows})")
