"""Recording every window to a Rerun ``.rrd`` file, and serving it live: the built-in output
``rerun`` (table ``[recording]``). Its parts:

* :mod:`~twinwatch.sinks.rerun.config`: ``[recording]``;
* :mod:`~twinwatch.sinks.rerun.live`: the live view, Rerun's gRPC server on a second stream;
* :mod:`~twinwatch.sinks.rerun.recorder`: :class:`RerunRecorder`, the files and their faults;
* what it draws: :mod:`~twinwatch.sinks.rerun.views` (the entities and the default
  blueprint), :mod:`~twinwatch.sinks.rerun.style`, :mod:`~twinwatch.sinks.rerun.projection`,
  :mod:`~twinwatch.sinks.rerun.texts`.
"""

from __future__ import annotations

from twinwatch.errors import RecorderError
from twinwatch.sinks.rerun.config import RecordingConfig
from twinwatch.sinks.rerun.recorder import RerunRecorder

__all__ = ["RecorderError", "RecordingConfig", "RerunRecorder"]
