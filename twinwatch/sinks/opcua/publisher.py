"""The OPC UA output as a sink (:class:`OpcUaPublisher`): one machine's share of its
endpoint's server; each stored window handed to the server's loop, never waiting for a
client."""

from __future__ import annotations

import json
from collections.abc import Hashable
from typing import ClassVar, Self

from twinwatch.errors import PublisherError
from twinwatch.sinks.base import ProcessedWindow, SharedResources, Sink, SinkContext
from twinwatch.sinks.opcua.config import OpcUaConfig
from twinwatch.sinks.opcua.server import OpcUaServer

__all__ = ["OpcUaPublisher"]


class OpcUaPublisher(Sink):
    """The OPC UA output (the module docstring): the built-in ``opcua``, ``[outputs.opcua]``.

    Args:
        config: the validated table.
        context: the daemon's context (``shared``: the process's shared servers).

    Raises:
        PublisherError: the port is taken, a certificate or key cannot be loaded, the machine
            is already served, another machine serves the endpoint with other settings.
    """

    config_class: ClassVar[type[OpcUaConfig]] = OpcUaConfig
    counter_prefix: ClassVar[str | None] = "opcua"
    open_order: ClassVar[int] = 15   # a port: before the file locks (20, 30)

    def __init__(self, config: OpcUaConfig, context: SinkContext) -> None:
        self._closed = True  # until fully open
        self.config = config
        self.machine = context.machine
        self.windows = 0
        self.events = 0
        shared, key = context.shared, config.server_key()
        if shared is not None and [k for k in shared.keys() if k.startswith("opcua:") and k != key
                                   and json.loads(k[6:]).get("endpoint") == config.endpoint]:
            raise PublisherError(
                f"outputs.opcua: {config.endpoint} is served by another machine of this "
                f"process with other server settings; give the machines of one endpoint "
                f"the same [outputs.opcua] table (stale_after aside)")
        self.server: OpcUaServer
        self.server, self._release = SharedResources.hold(
            shared, key, lambda: OpcUaServer(config), OpcUaServer.close)
        try:
            self.server.add_machine(context, config.stale_after)
        except BaseException:
            self._release()
            raise
        self._closed = False

    @classmethod
    def from_config(cls, config: OpcUaConfig, context: SinkContext) -> Self:
        """Open the output: the server (or this process's shared one) and the machine's
        object."""
        return cls(config, context)

    @classmethod
    def reload_key(cls, config: OpcUaConfig, context: SinkContext) -> Hashable:
        """The table, and what the machine's nodes are made of: a reload that changes them
        makes the object anew."""
        bands = tuple(sorted((k, (b.warning_high, b.warning_low, b.alarm_high, b.alarm_low))
                             for k, b in context.alarm_bands.items()))
        return (super().reload_key(config, context), context.model,
                tuple(context.parameters.items()), tuple(sorted(context.nominal.items())), bands)

    def write(self, out: ProcessedWindow) -> None:
        """Hand the window's values and alarm events to the server's loop."""
        if self._closed:
            return
        self.server.publish(self.machine, out.health, list(out.events))
        self.windows += 1
        self.events += len(out.events)

    def counters(self) -> dict[str, int]:
        """``windows`` (written), ``events`` (alarm events raised), ``errors`` (writes that
        failed, the whole server's)."""
        return {"windows": int(self.windows), "events": int(self.events),
                "errors": int(self.server.errors)}

    @property
    def status(self) -> str:
        return f"OPC UA on {self.config.endpoint}"

    def summary(self) -> list[str]:
        return [f"health was served over OPC UA on {self.config.endpoint} "
                f"({self.windows} windows, {self.events} alarm events)"]

    def close(self) -> None:
        """Remove the machine's object; the last machine of the server stops it."""
        if self._closed:
            return
        self._closed = True
        self.server.remove_machine(self.machine)
        self._release()
