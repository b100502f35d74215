"""``[recording]``: the recording's table (:class:`RecordingConfig`)."""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path

from pydantic import Field, StrictFloat, StrictInt, field_validator

from twinwatch.sinks.base import SinkConfig

__all__ = ["RUN_STAMP", "RecordingConfig"]

RUN_STAMP = "%Y%m%dT%H%M%SZ"
"""A run's UTC start as it leads a run id and names files (``20261122T101530Z``)."""


class RecordingConfig(SinkConfig):
    """The ``[recording]`` section of a machine configuration.

    Attributes:
        path: the recording's stable name (``~`` expanded): a symbolic link to the file of
            the run being written, ``<stem>-<run id>.rrd`` beside it.
        enabled: when false, :class:`RerunRecorder` writes nothing and logging is a no-op.
        application_id: Rerun application id; the viewer groups recordings by it.
        server_memory_limit: as its field says; ``256MiB``, ``2GB`` or ``10%`` of the RAM.

    The other keys are described by their fields. Unknown keys are an error (``extra="forbid"``).
    """

    path: str = "twinwatch.rrd"
    enabled: bool = True
    application_id: str = "twinwatch"
    rotate_windows: StrictInt = Field(1800, ge=0, description="start a new file after this many "
                                      "windows (0: never; Rerun keeps each chunk's footer entry "
                                      "in memory until its file is closed)")
    keep_files: StrictInt = Field(
        48, ge=0, description="older files of path kept (rotated ones and "
        "earlier runs'; 0: all), the oldest deleted when a file rotates")
    recent_s: StrictFloat = Field(10.0, gt=0.0, le=86400.0, description="plant time before the "
                                  "cursor shown by the outputs' and residuals' views [s]")
    serve: bool = Field(False, description="also serve the recording live (Rerun gRPC "
                        "server): rerun rerun+http://<serve_bind>:<serve_port>/proxy")
    serve_bind: str = Field("127.0.0.1", description="address the live server listens on")
    serve_port: StrictInt = Field(9876, ge=1, le=65535, description="TCP port of the live server")
    server_memory_limit: str = Field("256MiB", description="history the live server keeps "
                                     "for viewers that connect late (oldest dropped first)")

    @field_validator("path", "application_id")
    @classmethod
    def _not_blank(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be empty")
        return value

    @field_validator("serve_bind")
    @classmethod
    def _address(cls, value: str) -> str:
        try:
            ipaddress.ip_address(value)
        except ValueError:
            raise ValueError(f"{value!r} is not an IP address (127.0.0.1: this machine "
                             "only)") from None
        return value

    @field_validator("server_memory_limit")
    @classmethod
    def _memory(cls, value: str) -> str:
        if not re.fullmatch(r"\s*\d+(\.\d+)?\s*(B|kB|KB|KiB|MB|MiB|GB|GiB|TB|TiB|%)\s*", value):
            raise ValueError(f"{value!r} is not an amount of memory (e.g. '256MiB', '2GB', "
                             "'10%')")
        return value.strip()

    def output_files(self, cwd: Path) -> dict[str, Path]:
        """The recording's link (its directory must exist and be writable)."""
        path = Path(self.path).expanduser()
        return {"path": path if path.is_absolute() else cwd / path}

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The recording (its link and the run's file it names) and, when serving, the live
        server's endpoint."""
        link = self.output_files(cwd)["path"]
        held = {str(link.absolute()), str(link.resolve())}
        if self.serve:
            held.add(f"tcp/{self.serve_bind}:{self.serve_port}")
        return held
