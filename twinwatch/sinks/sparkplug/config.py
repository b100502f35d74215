"""``[outputs.sparkplug]``: the Sparkplug B output's table, and which of its keys the machines
sharing one edge node (one MQTT session) must set alike.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from twinwatch.sinks.mqtt.config import MqttConnectionConfig

__all__ = ["NAMESPACE", "NODE_KEYS", "SparkplugConfig", "check_id", "key_clash", "node_clashes",
           "node_key"]

NAMESPACE = "spBv1.0"

NODE_KEYS = ("host", "port", "client_id", "username", "password_file", "password", "tls",
             "keepalive", "qos", "reconnect_min", "reconnect_max", "connect_timeout",
             "primary_host_id")
"""The keys of the edge node's one MQTT session: every machine that is a device of one edge
node must set them alike (the others are the device's own)."""


def check_id(value: str, what: str) -> str:
    """A Sparkplug id (group, edge node, device, host): one MQTT topic level, UTF-8, without
    ``/``, ``+``, ``#`` (Sparkplug 3.0, 1.4.1.8: the MQTT topic rules).

    Raises:
        ValueError: naming what is wrong.
    """
    bad = [c for c in ("/", "+", "#", "\x00") if c in value]
    if not value or bad:
        raise ValueError(f"{what} {value!r} must be one non-empty topic level: no "
                         f"{', '.join(repr(c) for c in bad) or 'empty value'} (Sparkplug ids "
                         f"are MQTT topic levels without '/', '+', '#')")
    if len(value.encode("utf-8")) > 1000:
        raise ValueError(f"{what} is longer than 1000 bytes")
    return value


class SparkplugConfig(MqttConnectionConfig):
    """``[outputs.sparkplug]``: the Sparkplug B output (docs/sparkplug.md)."""

    client_id: str | None = Field(None, min_length=1, max_length=128,
                                  description="unique per broker; unset: "
                                  "twinwatch-sparkplug-<group_id>-<edge_node_id>")
    qos: Literal[0, 1] = Field(  # type: ignore[assignment]  # Sparkplug allows 0, not 2
        1, description="1: each window acknowledged (the outbox's delivery); 0: as Sparkplug "
        "3.0 says for births and data")
    group_id: str = Field("twinwatch", description="the Sparkplug group id (a topic level)")
    edge_node_id: str | None = Field(None, description="the edge node id: the machines of one "
                                     "process naming the same one are its devices, over one "
                                     "MQTT session; unset: the machine name (an edge node per "
                                     "machine)")
    device_id: str | None = Field(None, description="the machine's device id; unset: the "
                                  "machine name")
    primary_host_id: str | None = Field(None, description="wait for this primary host "
                                        "application's STATE online before publishing; unset: "
                                        "do not wait")

    @field_validator("group_id", "edge_node_id", "device_id", "primary_host_id")
    @classmethod
    def _ids(cls, value: str | None) -> str | None:
        return None if value is None else check_id(value, "the id")

    def exclusive_resources(self, cwd: Path) -> set[str]:
        """The client id and the edge node at the broker (a second session of one edge node
        would take its births and deaths over)."""
        return {f"mqtt://{self.host}:{self.port}/{self.client_id or ''}",
                f"sparkplug://{self.host}:{self.port}/{self.group_id}/"
                f"{self.edge_node_id or ''}"}


def node_key(config: SparkplugConfig, machine: str) -> str:
    """The edge node a machine's table names (the key its session is shared by):
    ``sparkplug://<host>:<port>/<group_id>/<edge_node_id or machine>``."""
    return (f"sparkplug://{config.host}:{config.port}/{config.group_id}/"
            f"{config.edge_node_id or machine}")


def key_clash(key: str, machine: str, where: str, first: str) -> str:
    """Why ``machine``'s ``key`` (one of :data:`NODE_KEYS`) is refused: the edge node ``where``
    has it otherwise from its first machine (``first``, as the message names it)."""
    return (f"outputs.sparkplug.{key}: machine {machine!r} is a device of {where} with machine "
            f"{first}, whose {key} differs (one edge node is one MQTT session); set {key} alike "
            f"or give {machine!r} its own edge_node_id")


def node_clashes(tables: list[tuple[str, str, SparkplugConfig]]) -> list[str]:
    """What a gateway's machines' ``[outputs.sparkplug]`` tables would be refused for when the
    gateway starts them (:meth:`~twinwatch.sinks.sparkplug.node.EdgeNode.join`), for
    ``check-config`` on a directory.

    Args:
        tables: (file name, machine name, its validated table) of each machine in the order
            the gateway reads them.

    Returns:
        One line per clash, naming the file, the key and the fix; empty if none.
    """
    first: dict[str, tuple[str, str, SparkplugConfig]] = {}
    devices: dict[tuple[str, str], str] = {}
    out = []
    for source, machine, cfg in tables:
        key = node_key(cfg, machine)
        head = first.setdefault(key, (source, machine, cfg))
        where = f"edge node {cfg.group_id}/{cfg.edge_node_id or machine} on {cfg.host}:{cfg.port}"
        for name in NODE_KEYS:
            if getattr(cfg, name) != getattr(head[2], name):
                out.append(f"{source}: " + key_clash(name, machine, where,
                                                     f"{head[1]!r} ({head[0]})"))
        device = cfg.device_id or machine
        owner = devices.setdefault((key, device), source)
        if owner != source:
            out.append(f"{source}: outputs.sparkplug.device_id: {device!r} is already a device "
                       f"of {where} ({owner}); set device_id (unset: the machine name)")
    return out
