"""The recording's views, by their earlier import path: they live in :mod:`twinwatch.sinks.rerun`
now (:mod:`~twinwatch.sinks.rerun.views`, :mod:`~twinwatch.sinks.rerun.style`,
:mod:`~twinwatch.sinks.rerun.projection`, :mod:`~twinwatch.sinks.rerun.texts`). Kept for the
names outside the recorder that import them from here.
"""

from twinwatch.sinks.rerun.style import TIMELINE
from twinwatch.sinks.rerun.texts import diagnosis_lines as _diagnosis_lines
from twinwatch.sinks.rerun.texts import model_document as _model_document
from twinwatch.sinks.rerun.views import RecordingViews, emit

__all__ = ["TIMELINE", "RecordingViews", "_diagnosis_lines", "_model_document", "emit"]
