"""The sink contract: what every output receives for each processed window.

:class:`ProcessedWindow` is everything a sink needs about one window (the window, what the
adaptation did, the typed health message and its one encoding, the alarm events, the twin to
persist); :class:`WindowSink` is what the window pipeline calls.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from twinwatch.twin.adaptation import AdaptationResult
from twinwatch.twin.health import HealthMessage
from twinwatch.twin.model import WindowData

__all__ = ["ProcessedWindow", "WindowSink"]


@dataclass(frozen=True)
class ProcessedWindow:
    """Everything the sinks need about one processed window.

    Attributes:
        window: the acquisition window (times, channels, index).
        result: what adaptation did (estimate, terms, residuals, discovery).
        health: the window's health message (README "The health message"), with ``alarms``.
        health_json: ``health`` encoded, once, by the one encoder: what every sink writes.
        message: ``health_json`` decoded: the message as a subscriber reads it.
        events: alarm-state changes this window caused (published on ``<machine>/alarm``).
        twin_state: the accepted twin to persist (``TwinAdapter.state()``) when this window
            was trusted, else None (the stored twin is kept).
    """

    window: WindowData
    result: AdaptationResult
    health: HealthMessage
    health_json: str
    message: dict[str, Any]
    events: list[dict[str, Any]]
    twin_state: dict[str, Any] | None


class WindowSink(Protocol):
    """Where processed windows go: the state store, the Zenoh publisher, the Rerun recorder.

    A sink with a true ``publishes`` attribute makes the window visible to others (Zenoh): it
    gets only the windows the pipeline's gate (the state store) has stored."""

    def write(self, out: ProcessedWindow) -> Any:
        """Take one processed window (called from the adaptation worker); the gate returns
        False when it could not take it."""

    def close(self) -> None:
        """Release the sink; idempotent."""
