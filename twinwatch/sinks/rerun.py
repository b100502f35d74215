"""Recording every acquisition window to a Rerun ``.rrd`` file.

One :class:`RerunRecorder` per monitored machine, each with its own
:class:`rerun.RecordingStream` (never the global one, so several recorders coexist in one
process). Entity paths, with ``M`` the machine name and ``plant_time`` the timeline [s]:

* ``M/outputs/<output>/measured`` and ``M/outputs/<output>/twin``: the window's measured and
  twin-simulated output samples (:class:`rerun.Scalars`, one ``send_columns`` per series and
  window), styled once by a static :class:`rerun.SeriesLines`;
* ``M/parameters/<name>``: each parameter estimate, one point at the window's last time stamp;
* ``M/health``: the window's health document (:class:`rerun.TextDocument`, markdown with the
  JSON in a code block);
* ``M/log``: one :class:`rerun.TextLog` line per window;
* ``M/residual/<output>``: the twin's residual (measured - twin) over the window, and
  ``M/residual_rmse/<output>/dt_prime`` and ``.../dt_second``: per window, the RMSE of the twin
  without and with its meta-model terms (from the health message's ``residual``);
* ``M/model``: the twin's discovered structure DT'' as plain-text equations
  (:class:`rerun.TextDocument`), logged at the start and whenever a term is added or dropped;
* ``M/health/<param>/trend/...``: each estimated parameter's trend (:func:`log_trends`): its
  level and 2-sigma band (``level``, ``band/low``, ``band/high``), and, with an alarm rule, the
  remaining useful life to its alarm threshold (``rul/median``, ``rul/low``, ``rul/high`` [s])
  and the projection to that threshold with its band (``projection``: line strips in the
  plane of plant time and value, the latest per window).

The file also carries a default blueprint: one time-series view per output, a grid with one
view per parameter (their scales differ by orders of magnitude), the health document and log.

Durability: the recording is flushed to the file after every window, so the data of every
completed window is on disk whatever happens next. The RRD *footer* (chunk manifest) is written
by :meth:`RerunRecorder.close`, and also by the Rerun SDK when the interpreter exits normally
(end of ``main``, ``KeyboardInterrupt``, ``SystemExit`` raised by a SIGTERM handler). A hard
stop (SIGKILL, ``os._exit``, SIGTERM with its default action, power loss) leaves a file without
footer: the viewer opens it and ``rerun rrd verify --check-footers false FILE`` accepts it,
plain ``rerun rrd verify`` reports "Missing RRD footer"; ``rerun rrd optimize FILE -o OUT``
writes a complete copy. The daemon must therefore turn SIGTERM into a normal shutdown.

Faults: the file is locked (``flock``) before it is truncated, so a second twinwatch in the same
directory fails at start instead of destroying the file of the one running. The disk must keep
``RerunRecorder.min_free`` bytes free (64 MiB): below that the recording pauses (logged once,
the windows counted in :attr:`RerunRecorder.lost`) and resumes when there is room again, so a
slowly filling disk leaves its last space to the state database and never kills the Rerun
file writer. When the writer dies anyway (the disk filled at once, "File-writer thread shut
down prematurely" or a flush that times out), the recorder says so (an ERROR, and
:attr:`RerunRecorder.problem` until it recovers), keeps the broken file under a rotated name
(its windows are readable; ``rerun rrd optimize`` adds the footer), counts the windows it
cannot record, and opens a new file at ``path`` on a *new* recording stream after
``reopen_after`` seconds (doubling while it keeps failing). The dead stream is never touched
again: with the Rerun SDK 0.41 a flush, a new file or a disconnect on it, and its exit hook,
wait forever, so its helpers are disabled and Rerun's exit hook is unregistered (the recorder
closes its own stream).

Memory and rotation: to write the footer, the Rerun SDK (0.41) keeps every chunk's manifest
entry in memory for the life of the file (``rerun.save(..., write_footer=True)``): about
13 kB per window here (some 20 chunks per window: one per entity and flush), 13-23 MiB per 1000
windows, so a service writing one file for months would grow without bound. The recorder
therefore rotates: after ``[recording] rotate_windows`` windows (default 1800, one hour of 2 s
windows) it renames the file to ``<stem>.<UTC time>.<n>.rrd`` beside it and points the same
recording stream at a new ``path`` (the renamed file is finalised: footer written, manifest
freed); ``keep_files`` rotated files are kept (oldest deleted first). ``path`` is always the
file being written; ``<stem>.rbl`` holds the viewer layout for the rotated files.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
import uuid
from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self

import numpy as np
from pydantic import Field, field_validator

from twinwatch._lazy import lazy_module
from twinwatch.errors import RecorderError
from twinwatch.io.encoding import to_json
from twinwatch.sinks.base import ProcessedWindow, Role, Sink, SinkConfig, SinkContext, _frozen
from twinwatch.sinks.locks import FileLock, LockedError

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb

    from twinwatch.twin.health import HealthMessage
else:  # imported when a recording opens: loading a configuration does not load rerun
    rr = lazy_module("rerun")
    rrb = lazy_module("rerun.blueprint")

logger = logging.getLogger(__name__)

__all__ = ["RecorderError", "RecordingConfig", "RerunRecorder"]

TIMELINE = "plant_time"
"""Name of the Rerun timeline carrying plant time [s] (a duration timeline)."""

_MEASURED_COLOR = (31, 119, 180)
_TWIN_COLOR = (255, 127, 14)
_PARAMETER_COLORS = (
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)
_PROBLEM_STATUSES = frozenset({"warning", "alarm", "fault", "degraded", "error", "critical"})
_SUMMARY_MAX_CHARS = 240


class RecordingConfig(SinkConfig):
    """The ``[recording]`` section of a machine configuration.

    Attributes:
        path: the ``.rrd`` file to write (``~`` expanded); overwritten if it exists.
        enabled: when false, :class:`RerunRecorder` writes nothing and logging is a no-op.
        application_id: Rerun application id; the viewer groups recordings by it.

        rotate_windows: windows per file before it is closed and renamed (0: one file).
        keep_files: rotated files kept (0: all).

    Unknown keys are an error (``extra="forbid"``).
    """

    path: str = "twinwatch.rrd"
    enabled: bool = True
    application_id: str = "twinwatch"
    rotate_windows: int = Field(1800, ge=0, description="start a new file after this many "
                                "windows (0: never; Rerun keeps each chunk's footer entry "
                                "in memory until its file is closed)")
    keep_files: int = Field(48, ge=0, description="rotated files kept beside path (0: all)")

    @field_validator("path", "application_id")
    @classmethod
    def _not_blank(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be empty")
        return value

    def output_files(self, cwd: Path) -> dict[str, Path]:
        """The recording file (its directory must exist and be writable)."""
        path = Path(self.path).expanduser()
        return {"path": path if path.is_absolute() else cwd / path}


def _entity(*parts: str) -> str:
    """An entity path from raw parts, each escaped (a '/' in a name stays inside its part)."""
    return "/".join(rr.escape_entity_path_part(p) for p in parts)


def _check_writable(path: Path) -> FileLock:
    """Lock ``path`` (created empty if absent, not truncated) for this recorder.

    Raises:
        RecorderError: ``path`` cannot be created or written, or another process holds it.
    """
    parent = path.parent
    if path.is_dir():
        raise RecorderError(
            f"recording path {path} is a directory: set [recording].path to a file name"
        )
    if not parent.exists():
        raise RecorderError(
            f"cannot record to {path}: directory {parent} does not exist; create it or set "
            "[recording].path"
        )
    if not parent.is_dir():
        raise RecorderError(f"cannot record to {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise RecorderError(
            f"cannot record to {path}: directory {parent} is not writable by this user; "
            "fix its permissions or set [recording].path"
        )
    try:
        return FileLock(path, "recording", "stop it, or set another [recording].path")
    except LockedError as exc:
        raise RecorderError(str(exc)) from None
    except OSError as exc:
        raise RecorderError(f"cannot record to {path}: {exc.strerror or exc}") from exc


class RerunRecorder(Sink):
    """Records measured vs twin outputs, parameter estimates and health to a ``.rrd`` file:
    the built-in output ``rerun`` (table ``[recording]``, a recorder: it gets every window).

    :meth:`log_window` may be called from a worker thread while :meth:`close` is called from
    another; calls after :meth:`close` are ignored. With ``config.enabled`` false nothing is
    written and :meth:`log_window` only validates its arguments.

    Args:
        config: the ``[recording]`` configuration.
        machine: machine name, first part of every entity path.
        outputs: names of the output channels compared between plant and twin, e.g.
            ``("ia", "omega")``.
        parameters: parameter name -> unit, e.g. ``{"Ra": "ohm", "J": "kg m^2"}``.

    Attributes:
        path: the resolved recording file.
        windows: number of windows recorded.
        errors: number of windows whose flush to disk failed.

    Raises:
        ValueError: empty ``machine``, empty or duplicate ``outputs``.
        RecorderError: the file cannot be created or written (missing or read-only directory,
            path is a directory), or Rerun refused to open it.
    """

    config_class: ClassVar[type[RecordingConfig]] = RecordingConfig
    role: ClassVar[Role] = "recorder"
    counter_prefix: ClassVar[str | None] = "recording"
    open_order: ClassVar[int] = 30  # after every lock: opening truncates the file

    flush_timeout: float = 10.0
    """Seconds a flush may take before the window is counted as an error [s]."""

    reopen_after: float = 30.0
    """Seconds before the file is reopened after the file writer died; doubles while it keeps
    dying, up to 30 min [s]."""

    min_free: int = 64 * 2**20
    """Bytes the disk must keep free for the recording to go on [B]."""

    def __init__(
        self,
        config: RecordingConfig,
        machine: str,
        *,
        outputs: Sequence[str],
        parameters: Mapping[str, str],
    ) -> None:
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
        self.path = Path(config.path).expanduser()
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
        self._file_lock: FileLock | None = None
        self.rotations = 0
        self._file_windows = 0
        if not config.enabled:
            logger.info("rerun recording disabled for %s", machine)
            return
        self._file_lock = _check_writable(self.path)
        self._recording_id = uuid.uuid4()  # every file of this recorder shares it
        try:
            self._rec = self._open_stream()
        except BaseException:
            self._file_lock.release()
            raise
        self._closed = False
        logger.info("recording %s to %s", machine, self.path)

    def _open_stream(self) -> rr.RecordingStream:
        """The recorder's one recording stream, saving to :attr:`path` with the default
        blueprint; the blueprint is also written once to :attr:`blueprint_path`."""
        rec = rr.RecordingStream(self.config.application_id, recording_id=self._recording_id)
        blueprint = self._blueprint()
        self._attach_file(rec, blueprint=blueprint)
        if not rr.is_enabled(rec):
            logger.warning("rerun logging is disabled (RERUN=off?): %s stays empty", self.path)
        try:
            blueprint.save(self.config.application_id, self.blueprint_path)
        except (OSError, RuntimeError, ValueError) as exc:
            logger.warning("cannot write the blueprint %s (%s): rotated files open with the "
                           "viewer's default layout", self.blueprint_path, exc)
        return rec

    def _attach_file(self, rec: rr.RecordingStream, *,
                     blueprint: rrb.Blueprint | None = None) -> None:
        """Point ``rec`` at a new file at :attr:`path` (the previous file sink, if any, is
        finalised: footer written) and send what each file needs on its own (recording name,
        series styles; the default blueprint when given)."""
        try:
            rec.save(self.path, default_blueprint=blueprint)
        except (OSError, RuntimeError, ValueError) as exc:
            raise RecorderError(f"rerun cannot write {self.path}: {exc}") from exc
        rec.send_recording_name(f"{self.machine} twin")
        self._log_styles(rec)

    @property
    def blueprint_path(self) -> Path:
        """``<stem>.rbl`` beside :attr:`path`: the viewer layout, for rotated files
        (``rerun twinwatch.*.rrd twinwatch.rbl``)."""
        return self.path.with_suffix(".rbl")

    def _rotate(self) -> None:
        """Rename the current file with the UTC time, point the recording stream at a new file
        at :attr:`path` (the renamed file's footer is written and its manifest memory freed),
        and delete rotated files beyond ``keep_files``. Called with the lock held. A failure
        stops the recording (logged once).

        The stream is kept, not replaced: the Rerun SDK (0.41) never frees a Python recording
        stream (rerun-io/rerun#2116: its batcher threads live on after ``disconnect``), so a new
        stream per file (and one per blueprint sent) leaked about 1 MiB and four threads per
        rotation. Every file of one run
        therefore shares one recording id: opened together, the viewer shows them as one
        recording. The blueprint is sent to the first file only (each send is a new stream);
        the others use :attr:`blueprint_path`."""
        rec = self._rec
        assert rec is not None
        if not self._flush(rec):
            return  # the writer died: the file was kept aside and a new one will be opened
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        aside = self.path.with_name(f"{self.path.stem}.{stamp}.{self.rotations:04d}"
                                    f"{self.path.suffix}")
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
        self._file_windows = 0
        logger.info("recording rotated: %s closed, now writing %s", aside, self.path)
        keep = self.config.keep_files
        if keep:
            rotated = sorted(self.path.parent.glob(f"{self.path.stem}.*{self.path.suffix}"))
            rotated = [p for p in rotated if p != self.path]
            for old in rotated[:-keep]:
                try:
                    old.unlink()
                except OSError as exc:
                    logger.warning("cannot delete old recording %s: %s", old, exc)

    def _relock(self) -> None:
        """Lock the file now at :attr:`path` (after a rename) and release the old one."""
        old = self._file_lock
        self._file_lock = _check_writable(self.path)
        if old is not None:
            old.release()

    def _release(self) -> None:
        lock, self._file_lock = self._file_lock, None
        if lock is not None:
            lock.release()

    # -- the sink contract ---------------------------------------------------------------------
    @classmethod
    def from_config(cls, config: RecordingConfig, context: SinkContext) -> Self:
        """Record the twin's outputs and parameters to ``[recording] path`` (relative to the
        working directory).

        Raises:
            RecorderError: the file cannot be created, written or locked.
        """
        rec = config.model_copy()
        rec.path = str(config.output_files(context.cwd)["path"])
        return cls(rec, context.machine, outputs=context.outputs,
                   parameters=dict(context.parameters))

    @classmethod
    def reload_key(cls, config: RecordingConfig, context: SinkContext) -> Hashable:
        """The machine, the entities it declares (the twin's outputs and parameters) and the
        table."""
        return (context.machine, tuple(context.outputs), _frozen(dict(context.parameters)),
                _frozen(config.model_dump()))

    def counters(self) -> dict[str, int]:
        """``lost``: windows not recorded."""
        return {"lost": int(self.lost)}

    def summary(self) -> list[str]:
        """Where the recording is, and the windows it could not record."""
        cwd = self.context.cwd if self.context is not None else Path.cwd()
        shown = self.path.relative_to(cwd) if self.path.is_relative_to(cwd) else self.path
        lines = [f"recording: {self.path.resolve()} (open with: rerun {shown})"]
        if self.lost:
            lines.append(f"recording: {self.lost} windows could not be recorded (the Rerun "
                         "file writer failed: see the log)")
        return lines

    @property
    def problem(self) -> str | None:
        """Why windows are not being recorded right now (None while recording works)."""
        if self._broken is not None:
            return f"{self._broken}; {self.lost} windows not recorded"
        if self._paused is not None:
            return f"{self._paused}; {self.lost} windows not recorded"
        if self._dead_since is None:
            return None
        return (f"recording to {self.path} stopped (the file writer died: disk full?); "
                f"{self.lost} windows not recorded")

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

    def _writer_died(self, rec: rr.RecordingStream, exc: BaseException) -> None:
        """The file sink is gone: abandon the stream (see the module docstring), keep the
        broken file under a rotated name, and schedule a new file. Called with the lock held."""
        now = time.monotonic()
        _bury(rec)
        self._rec = None
        if self._dead_since is None:
            self._dead_since = now
            logger.error("recording to %s stopped: %s (disk full?); the windows recorded so "
                         "far are kept, the next ones are counted as not recorded until a new "
                         "file is opened (in %g s)", self.path, exc, self._reopen_delay)
        else:
            self._reopen_delay = min(2 * self._reopen_delay, 1800.0)
            logger.debug("recording to %s failed again: %s", self.path, exc)
        if self._file_windows:
            stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
            aside = self.path.with_name(f"{self.path.stem}.{stamp}.{self.rotations:04d}"
                                        f"{self.path.suffix}")
            try:
                self.path.rename(aside)
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
    def closed(self) -> bool:
        """True once :meth:`close` has run (or when recording is disabled)."""
        return self._closed

    @property
    def recording(self) -> rr.RecordingStream | None:
        """The underlying Rerun recording stream (``None`` when disabled)."""
        return self._rec

    def _blueprint(self) -> rrb.Blueprint:
        m = self.machine
        output_views = [
            rrb.TimeSeriesView(origin="/" + _entity(m, "outputs", o), name=o) for o in self.outputs
        ]
        parameter_views = [
            rrb.TimeSeriesView(origin="/" + _entity(m, "parameters", p), name=f"{p} [{u}]")
            for p, u in self.parameters.items()
        ]
        right: list[rrb.Container | rrb.View] = []
        if parameter_views:
            right.append(rrb.Grid(*parameter_views, name="parameters"))
        right.append(rrb.TimeSeriesView(origin="/" + _entity(m, "residual"), name="residual"))
        right.append(rrb.TimeSeriesView(origin="/" + _entity(m, "residual_rmse"),
                                        name="residual RMSE: DT' vs DT''"))
        right.append(rrb.Tabs(
            rrb.TextDocumentView(origin="/" + _entity(m, "model"), name="model (DT'')"),
            rrb.TextDocumentView(origin="/" + _entity(m, "health"), name="health"),
        ))
        right.append(rrb.TextLogView(origin="/" + _entity(m, "log"), name="log"))
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(*output_views, name="outputs"),
                rrb.Vertical(*right),
            ),
            collapse_panels=True,
        )

    def _log_styles(self, rec: rr.RecordingStream) -> None:
        for o in self.outputs:
            rec.log(
                _entity(self.machine, "outputs", o, "measured"),
                rr.SeriesLines(names=f"{o} measured", colors=_MEASURED_COLOR),
                static=True,
            )
            rec.log(
                _entity(self.machine, "outputs", o, "twin"),
                rr.SeriesLines(names=f"{o} twin", colors=_TWIN_COLOR),
                static=True,
            )
        for i, (p, unit) in enumerate(self.parameters.items()):
            rec.log(
                _entity(self.machine, "parameters", p),
                rr.SeriesLines(
                    names=f"{p} [{unit}]", colors=_PARAMETER_COLORS[i % len(_PARAMETER_COLORS)]
                ),
                static=True,
            )

    def _validate(
        self,
        t: np.ndarray,
        measured: Mapping[str, np.ndarray],
        simulated: Mapping[str, np.ndarray],
        parameters: Mapping[str, float],
    ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray], dict[str, float]]:
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
                    raise ValueError(
                        f"{label} channel {name!r} is not a declared output {list(self.outputs)}"
                    )
                array = np.asarray(values, dtype=np.float64)
                if array.shape != times.shape:
                    raise ValueError(
                        f"{label}[{name!r}] has shape {array.shape}, expected {times.shape}"
                    )
                arrays[name] = array
            series.append(arrays)
        unknown = set(parameters) - set(self.parameters)
        if unknown:
            raise ValueError(
                f"parameters {sorted(unknown)} are not declared {list(self.parameters)}"
            )
        estimates = {name: float(value) for name, value in parameters.items()}
        return times, series[0], series[1], estimates

    def log_window(
        self,
        *,
        t: np.ndarray,
        measured: Mapping[str, np.ndarray],
        simulated: Mapping[str, np.ndarray],
        parameters: Mapping[str, float],
        health: HealthMessage | Mapping[str, Any],
        terms_changed: bool = False,
        health_json: str | None = None,
    ) -> None:
        """Record one acquisition window, then flush it to the file.

        Args:
            t: shape (N,), sample times [s] on the plant clock, finite.
            measured: output name -> shape (N,) measured samples (SI units of the twin).
                Every key must be one of ``outputs``; an output may be absent.
            simulated: output name -> shape (N,) twin-simulated samples, same rules.
            parameters: parameter name -> estimate at ``t[-1]`` (unit as declared); every key
                must be one of the declared ``parameters``.
            health: the window's health message (typed), or any JSON-serialisable health
                document (see :func:`twinwatch.io.encoding.to_json`).
            terms_changed: the twin's meta-model terms changed in this window: log the model
                document (the message's ``terms``) again. The first window always logs it.
            health_json: ``health`` already encoded (the pipeline's one encoding), shown in
                the health document; None: encoded here.

        Raises:
            ValueError: a shape, name or value that does not fit the above (nothing recorded).
            TypeError: ``health`` is not JSON-serialisable (nothing recorded).

        A flush that fails or times out means the file writer died (a full disk): it is
        logged once, counted in :attr:`errors`, never raised; the windows that follow are
        counted in :attr:`lost` until the file is reopened (see the module docstring).
        """
        times, meas, sim, estimates = self._validate(t, measured, simulated, parameters)
        if health_json is None:
            health_json = (to_json(health) if isinstance(health, Mapping)
                           else health.to_json())
        pretty = json.dumps(json.loads(health_json), indent=2)
        if not self.config.enabled:
            return
        m = self.machine
        t_end = float(times[-1])
        with self._lock:
            rec = self._rec
            if self._closed:
                if self._broken is not None:
                    self.lost += 1
                logger.debug("recorder of %s closed, dropping window at t=%.3f s", m, t_end)
                return
            if not self._room() or (rec is None and not self._reopen()):
                self.lost += 1
                return
            rec = self._rec
            assert rec is not None
            index = [rr.TimeColumn(TIMELINE, duration=times)]
            for kind, channels in (("measured", meas), ("twin", sim)):
                for name, values in channels.items():
                    rec.send_columns(
                        _entity(m, "outputs", name, kind),
                        indexes=index,
                        columns=rr.Scalars.columns(scalars=values),
                    )
            for name in meas.keys() & sim.keys():
                rec.send_columns(
                    _entity(m, "residual", name),
                    indexes=index,
                    columns=rr.Scalars.columns(scalars=meas[name] - sim[name]),
                )
            rec.set_time(TIMELINE, duration=t_end)
            for variant, rmse in _residual_rmse(health).items():
                for name, value in rmse.items():
                    if value is not None:
                        rec.log(_entity(m, "residual_rmse", name, variant), rr.Scalars(value))
            if terms_changed or self._file_windows == 0:
                rec.log(_entity(m, "model"), rr.TextDocument(
                    _model_document(m, t_end, health), media_type=rr.MediaType.MARKDOWN))
            for name, value in estimates.items():
                rec.log(_entity(m, "parameters", name), rr.Scalars(value))
            document = f"## {m}: health at t = {t_end:.3f} s\n\n```json\n{pretty}\n```\n"
            rec.log(
                _entity(m, "health"), rr.TextDocument(document, media_type=rr.MediaType.MARKDOWN)
            )
            if not isinstance(health, Mapping):
                log_trends(rec, m, t_end, health)
            level = rr.TextLogLevel.WARN if _is_problem(health) else rr.TextLogLevel.INFO
            rec.log(
                _entity(m, "log"),
                rr.TextLog(_summary(float(times[0]), t_end, health), level=level),
            )
            if not self._flush(rec):
                self.lost += 1
                return
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
        """The window pipeline's sink call: :meth:`log_window` with the window's measured and
        twin outputs, estimates and its typed health message (and that message's one
        encoding)."""
        est = out.result.estimate
        self.log_window(
            t=out.window.t,
            measured={o: out.window[o] for o in self.outputs},
            simulated={o: est.simulated[:, j] for j, o in enumerate(self.outputs)},
            parameters=est.values,
            health=out.health,
            terms_changed=out.result.changed,
            health_json=out.health_json,
        )

    def _flush(self, rec: rr.RecordingStream) -> bool:
        """Flush to the file; False (logged once, counted) if it failed. A file writer that
        died is detected here (:meth:`_writer_died`)."""
        try:
            rec.flush(timeout_sec=self.flush_timeout)
        except Exception as exc:  # noqa: BLE001 - rerun raises plain exceptions on timeout
            # "File-writer thread shut down prematurely", or, when it died during this
            # flush, "Flush timed out": either way the file sink is gone (flushing it again
            # would block every window for flush_timeout)
            self.errors += 1
            self._writer_died(rec, exc)
            return False
        return True

    def close(self) -> None:
        """Flush, write the footer and close the file. Idempotent; the file is then complete."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            rec, self._rec = self._rec, None
            if rec is None:  # never opened, or its file writer died (abandoned)
                self._release()
                return
            if self._flush(rec):
                rec.disconnect()
            self._release()
        logger.info(
            "recording of %s closed: %d windows in %s", self.machine, self.windows, self.path
        )

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return (
            f"RerunRecorder({str(self.path)!r}, {self.machine!r}, {state}, windows={self.windows})"
        )


_GRAVEYARD: list[Any] = []
"""Recording streams whose file writer died: kept referenced so that nothing frees them."""


def _growth_curve(t0: float, y0: float, t1: float, y1: float, r: float | None,
                  n: int = 32) -> np.ndarray:
    """(n, 2) points of ``y0 + a (exp(r (t - t0)) - 1)/r`` from ``(t0, y0)`` through
    ``(t1, y1)`` (a line for r None or 0): the trend's shape, scaled to pass the threshold at
    a crossing time."""
    t = np.linspace(t0, t1, n)
    if r is None or abs(r) * (t1 - t0) < 1e-9:
        g, g1 = t - t0, t1 - t0
    else:
        g, g1 = np.expm1(r * (t - t0)) / r, np.expm1(r * (t1 - t0)) / r
    a = (y1 - y0) / g1 if g1 else 0.0
    return np.column_stack([t, y0 + a * g])


def log_trends(rec: rr.RecordingStream, machine: str, t_end: float,
               health: HealthMessage) -> None:
    """Log each parameter's trend and, with an alarm rule, its RUL and its projection to the
    alarm threshold (entity paths ``<machine>/health/<param>/trend/...``, module docstring),
    at the current time (``t_end`` on the plant-time timeline, set by the caller)."""
    for name, p in health.parameters.items():
        t = p.trend
        if t is None or t.level is None:
            continue
        base = (machine, "health", name, "trend")
        rec.log(_entity(*base, "level"), rr.Scalars(t.level))
        if t.level_std is not None:
            rec.log(_entity(*base, "band", "low"), rr.Scalars(t.level - 2.0 * t.level_std))
            rec.log(_entity(*base, "band", "high"), rr.Scalars(t.level + 2.0 * t.level_std))
        c = p.rul.alarm if p.rul is not None else None
        if c is None or c.status != "predicted" or c.t is None or c.threshold is None:
            continue
        for key, value in (("median", c.rul_s), ("low", c.low_s), ("high", c.high_s)):
            if value is not None:
                rec.log(_entity(*base, "rul", key), rr.Scalars(value))
        ends = [x for x in (c.t, c.t_low, c.t_high) if x is not None]
        strips = [_growth_curve(t_end, t.level, x, c.threshold, t.growth) for x in ends]
        strips.append(np.array([[t_end, c.threshold], [max(ends), c.threshold]]))
        rec.log(_entity(*base, "projection"), rr.LineStrips2D(
            strips, labels=["median", *(["band"] * (len(ends) - 1)), "alarm threshold"]))


def _bury(rec: rr.RecordingStream) -> None:
    """Abandon a stream whose file writer died. With the Rerun SDK 0.41 every later flush,
    disconnect or new file on it, its ``__del__`` (a sweep of orphaned recordings) and the
    SDK's exit hook wait forever for the dead writer: disable the instance's helpers, keep it
    referenced for the life of the process, and unregister the exit hook (each recorder
    disconnects its own stream in :meth:`RerunRecorder.close`)."""
    rec._flush = lambda *args, **kwargs: None  # type: ignore[method-assign]
    rec._disconnect_orphaned_recordings = lambda *args, **kwargs: None
    _GRAVEYARD.append((rec, getattr(rec, "inner", None)))
    rr.unregister_shutdown()


def _residual_rmse(health: HealthMessage | Mapping[str, Any]
                   ) -> dict[str, Mapping[str, float | None]]:
    """``residual.<dt_prime|dt_second>.rmse``: output -> RMSE of the twin without and with its
    terms (empty for a variant the message does not hold)."""
    if isinstance(health, Mapping):
        residual = health.get("residual") or {}
        return {v: (residual.get(v) or {}).get("rmse") or {} for v in ("dt_prime", "dt_second")}
    r = health.residual
    return {"dt_prime": r.dt_prime.rmse,
            "dt_second": r.dt_second.rmse if r.dt_second is not None else {}}


def _model_document(machine: str, t: float, health: HealthMessage | Mapping[str, Any]) -> str:
    """The twin's structure as markdown: DT plus each kept meta-model term with its meaning."""
    terms = ([(term.get("equation"), term.get("meaning")) for term in health.get("terms") or []]
             if isinstance(health, Mapping)
             else [(term.equation, term.meaning) for term in health.terms])
    lines = [f"## {machine}: twin structure at t = {t:.3f} s", ""]
    if not terms:
        lines.append("DT'' = DT: no meta-model term (the physical model explains the data).")
    else:
        lines.append("DT'' = DT + the terms below (paper Eq. 3):")
        lines.append("")
        for equation, meaning in terms:
            lines.append(f"* `{equation}`  \n  {meaning}")
    return "\n".join(lines) + "\n"


def _is_problem(health: HealthMessage | Mapping[str, Any]) -> bool:
    """True if the health document flags a change of the twin's structure, an alarm
    (``alarm`` truthy) or a problem ``status``."""
    if not isinstance(health, Mapping):
        return health.discovery.changed
    status = health.get("status")
    if (health.get("discovery") or {}).get("changed"):
        return True
    return bool(health.get("alarm")) or (
        isinstance(status, str) and status.lower() in _PROBLEM_STATUSES
    )


def _scalars(health: HealthMessage | Mapping[str, Any]) -> list[tuple[str, Any]]:
    """The health document's top-level (key, value) pairs, as a subscriber names them."""
    if isinstance(health, Mapping):
        return list(health.items())
    return [(info.alias or name, getattr(health, name))
            for name, info in type(health).model_fields.items()]


def _summary(t_start: float, t_end: float, health: HealthMessage | Mapping[str, Any]) -> str:
    """One line: the window's time span and the health document's top-level scalars."""
    items = []
    for key, value in _scalars(health):
        if isinstance(value, bool | str | None):
            items.append(f"{key}={value}")
        elif isinstance(value, int | float | np.integer | np.floating):
            items.append(f"{key}={float(value):.4g}")
    line = f"window {t_start:.2f}-{t_end:.2f} s: " + (", ".join(items) or "health recorded")
    if len(line) > _SUMMARY_MAX_CHARS:
        line = line[: _SUMMARY_MAX_CHARS - 3] + "..."
    return line
