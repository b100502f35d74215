"""Recording every window to a Rerun ``.rrd`` file, and serving it live: the built-in output
``rerun`` (table ``[recording]``). Its parts:

* :mod:`~twinwatch.sinks.rerun.config`: ``[recording]`` (:class:`RecordingConfig`);
* :mod:`~twinwatch.sinks.rerun.live`: the live view, Rerun's gRPC server on a second stream
  (:class:`~twinwatch.sinks.rerun.live.LiveServer`);
* :mod:`~twinwatch.sinks.rerun.recorder`: :class:`RerunRecorder`, the recording stream, one
  window's way to it, the writer's failures (the durability and the faults: its docstring);
  the run's file and its lock, the link, the rotation, a file deleted or replaced while
  written, the disk's free space;
* what it draws: :mod:`~twinwatch.sinks.rerun.views` (the entities and the default blueprint,
  :class:`~twinwatch.sinks.rerun.views.RecordingViews`), :mod:`~twinwatch.sinks.rerun.style`
  (the timeline, colours, markers, numbers for a person), :mod:`~twinwatch.sinks.rerun.
  projection` (a parameter's trend to its alarm threshold), :mod:`~twinwatch.sinks.rerun.texts`
  (the documents and rows in words).
"""

from __future__ import annotations

from twinwatch.errors import RecorderError
from twinwatch.sinks.rerun.config import RecordingConfig
from twinwatch.sinks.rerun.recorder import RerunRecorder

__all__ = ["RecorderError", "RecordingConfig", "RerunRecorder"]
