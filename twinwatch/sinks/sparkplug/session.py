"""An edge node's Sparkplug B session state and payloads, no I/O: its topics, ``seq`` (one
count for every message of the edge node, whichever device it is about), ``bdSeq`` (kept in a
small file across restarts), and each device's metrics, aliases and payloads.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from twinwatch.sinks.sparkplug.config import NAMESPACE
from twinwatch.sinks.sparkplug.metrics import MetricSpec, set_value
from twinwatch.sinks.sparkplug_pb import DATATYPE, payload_class

logger = logging.getLogger(__package__)

__all__ = ["BDSEQ", "DEVICE_REBIRTH", "REBIRTH", "BdSeqFile", "DeviceSession",
           "EdgeNodeSession", "now_ms"]

REBIRTH = "Node Control/Rebirth"
DEVICE_REBIRTH = "Device Control/Rebirth"
BDSEQ = "bdSeq"


def now_ms() -> int:
    """The wall clock in ms since the epoch (Sparkplug's timestamps)."""
    return int(time.time() * 1000)


class EdgeNodeSession:
    """An edge node: its topics, ``seq`` and ``bdSeq``, its NBIRTH and NDEATH payloads.

    Args:
        group_id, edge_node_id: the Sparkplug ids (checked topic levels).
        bd_seq: the last ``bdSeq`` used (the next connection takes the one after it, mod 256);
            None: the first connection is 0.
    """

    def __init__(self, group_id: str, edge_node_id: str, bd_seq: int | None = None) -> None:
        self.group_id = group_id
        self.edge_node_id = edge_node_id
        node = f"{NAMESPACE}/{group_id}/%s/{edge_node_id}"
        self.node_topic = node
        self.nbirth_topic = node % "NBIRTH"
        self.ndeath_topic = node % "NDEATH"
        self.ncmd_topic = node % "NCMD"
        self.dcmd_topics = f"{node % 'DCMD'}/+"
        self.bd_seq = -1 if bd_seq is None else bd_seq % 256
        self.seq = 0
        self._payload = payload_class()

    def new_connection(self) -> int:
        """A new MQTT CONNECT: the next ``bdSeq`` (0..255), for its will and NBIRTH."""
        self.bd_seq = (self.bd_seq + 1) % 256
        return self.bd_seq

    def next_seq(self) -> int:
        """The ``seq`` of the next message of the edge node (0..255, then round again)."""
        seq = self.seq
        self.seq = (self.seq + 1) % 256
        return seq

    def message(self, seq: int | None, now: int) -> Any:
        """An empty payload stamped ``now`` [ms] (with ``seq`` unless None)."""
        p = self._payload()
        p.timestamp = now
        if seq is not None:
            p.seq = seq
        return p

    def nbirth(self, now: int) -> bytes:
        """NBIRTH: ``seq`` 0 (the count starts again), ``bdSeq``, ``Node Control/Rebirth``."""
        self.seq = 0
        p = self.message(self.next_seq(), now)
        m = p.metrics.add(name=BDSEQ, timestamp=now, datatype=DATATYPE["Int64"])
        m.long_value = max(self.bd_seq, 0)
        m = p.metrics.add(name=REBIRTH, timestamp=now, datatype=DATATYPE["Boolean"])
        m.boolean_value = False
        return bytes(p.SerializeToString())

    def ndeath(self, now: int) -> bytes:
        """NDEATH (the will, and on a clean stop): ``bdSeq`` only, no ``seq``."""
        p = self.message(None, now)
        m = p.metrics.add(name=BDSEQ, timestamp=now, datatype=DATATYPE["Int64"])
        m.long_value = max(self.bd_seq, 0)
        return bytes(p.SerializeToString())


class DeviceSession:
    """One device of an edge node: its topics, metrics and aliases, its payloads (their
    ``seq`` taken from the node's one count).

    Args:
        node: the edge node.
        device_id: the device id (a checked topic level).

    Raises:
        ValueError: (:meth:`declare`) two metric names that differ only in case (a SCADA's tag
            paths, Ignition's among them, are case-insensitive).
    """

    def __init__(self, node: EdgeNodeSession, device_id: str) -> None:
        self.node = node
        self.device_id = device_id
        base = node.node_topic
        self.dbirth_topic = f"{base % 'DBIRTH'}/{device_id}"
        self.ddata_topic = f"{base % 'DDATA'}/{device_id}"
        self.ddeath_topic = f"{base % 'DDEATH'}/{device_id}"
        self.specs: dict[str, MetricSpec] = {}
        self.aliases: dict[str, int] = {}

    def declare(self, specs: list[MetricSpec]) -> bool:
        """Add ``specs`` to the device's metrics (never removes one: a birth announces them
        all); True when one is new (a birth is then due)."""
        new = False
        for spec in specs:
            if spec.name in self.specs:
                continue
            folded = spec.name.casefold()
            clash = next((n for n in self.specs if n.casefold() == folded), None)
            if clash is not None:
                raise ValueError(f"the metrics {clash!r} and {spec.name!r} differ only in case: "
                                 f"a SCADA's tag paths do not tell them apart")
            self.specs[spec.name] = spec
            self.aliases[spec.name] = len(self.aliases) + 1
            new = True
        return new

    def dbirth(self, values: Mapping[str, Any], now: int, ts_ms: int | None = None) -> bytes:
        """DBIRTH: every declared metric with name, alias, datatype, ``engUnit`` and its value
        in ``values`` (missing: null); the node's next ``seq``."""
        p = self.node.message(self.node.next_seq(), now)
        for name, spec in self.specs.items():
            m = p.metrics.add(name=name, alias=self.aliases[name], timestamp=ts_ms or now,
                              datatype=DATATYPE[spec.datatype])
            if spec.unit:
                m.properties.keys.append("engUnit")
                m.properties.values.add(type=DATATYPE["String"], string_value=spec.unit)
            set_value(m, spec.datatype, values.get(name))
        return bytes(p.SerializeToString())

    def ddata(self, values: Mapping[str, Any], now: int, ts_ms: int,
              historical: bool = False) -> bytes:
        """DDATA: the declared metrics of ``values`` by alias (a name not declared is left
        out: declare it and send a birth first); the node's next ``seq``."""
        p = self.node.message(self.node.next_seq(), now)
        specs, aliases = self.specs, self.aliases
        for name, value in values.items():
            spec = specs.get(name)
            if spec is None:
                continue
            m = p.metrics.add(alias=aliases[name], timestamp=ts_ms)
            if historical:
                m.is_historical = True
            set_value(m, spec.datatype, value)
        return bytes(p.SerializeToString())

    def ddeath(self, now: int) -> bytes:
        """DDEATH: the device is gone (the node's next ``seq`` only)."""
        return bytes(self.node.message(self.node.next_seq(), now).SerializeToString())


class BdSeqFile:
    """The last ``bdSeq`` an edge node used, kept across restarts (Sparkplug 3.0: the NBIRTH
    after a restart carries the next one): ``<directory>/sparkplug-<group>-<edge node>.bdseq``
    (a hash when that name is too long), one decimal number, replaced atomically.

    A file that cannot be read or written is said once (a warning naming the path) and the
    count goes on in memory.
    """

    def __init__(self, directory: Path, group_id: str, edge_node_id: str) -> None:
        name = f"sparkplug-{group_id}-{edge_node_id}.bdseq"
        if len(name.encode("utf-8")) > 200 or name.startswith("."):
            name = ("sparkplug-" + hashlib.sha256(f"{group_id}/{edge_node_id}".encode())
                    .hexdigest()[:32] + ".bdseq")
        self.path = directory / name
        self._warned = False

    def load(self) -> int | None:
        """The last ``bdSeq`` used (0..255), or None (no file: a first start)."""
        try:
            text = self.path.read_text(encoding="ascii").strip()
        except FileNotFoundError:
            return None
        except (OSError, UnicodeDecodeError) as exc:
            self._warn(f"cannot read {self.path} ({exc}): bdSeq starts at 0")
            return None
        try:
            value = int(text)
        except ValueError:
            self._warn(f"{self.path} holds {text[:20]!r}, not a bdSeq: it starts at 0")
            return None
        return value % 256

    def save(self, value: int) -> None:
        """Keep ``value`` (written before the connection that uses it)."""
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            with open(tmp, "w", encoding="ascii") as f:
                f.write(f"{value}\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except OSError as exc:
            self._warn(f"cannot write {self.path} ({exc.strerror or exc}): the next start's "
                       f"NBIRTH may repeat a bdSeq; make the directory writable")

    def _warn(self, line: str) -> None:
        if not self._warned:
            self._warned = True
            logger.warning("outputs.sparkplug: %s", line)
