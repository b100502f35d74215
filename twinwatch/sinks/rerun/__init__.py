"""Recording every window to a Rerun ``.rrd`` file, and serving it live: the built-in output
``rerun`` (table ``[recording]``). Its parts:

* :mod:`~twinwatch.sinks.rerun.config`: ``[recording]`` (:class:`RecordingConfig`);
* :mod:`~twinwatch.sinks.rerun.files`: the run's file and its lock, the link, the rotation,
  a file deleted or replaced while written, the disk's free space (:class:`~twinwatch.sinks.
  rerun.files.RecordingFiles`);
* :mod:`~twinwatch.sinks.rerun.live`: the live view, Rerun's gRPC server on a second stream
  (:class:`~twinwatch.sinks.rerun.live.LiveServer`);
* :mod:`~twinwatch.sinks.rerun.recorder`: :class:`RerunRecorder`, the recording stream, one
  window's way to it, the writer's failures (the durability and the faults: its docstring);
* what it draws, the entities and the default blueprint: :mod:`twinwatch.sinks.rerun_views`.
"""

from __future__ import annotations

from twinwatch.errors import RecorderError
from twinwatch.sinks.rerun.config import RecordingConfig
from twinwatch.sinks.rerun.recorder import RerunRecorder
from twinwatch.sinks.rerun_views import TIMELINE

__all__ = ["TIMELINE", "RecorderError", "RecordingConfig", "RerunRecorder"]
