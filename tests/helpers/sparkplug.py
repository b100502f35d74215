"""A Sparkplug B host application's view of a real broker: every ``spBv1.0/#`` message decoded
with Eclipse Tahu's protobuf, in order."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from twinwatch.sinks.sparkplug_pb import payload_class

from .mqtt import Subscriber
from .net import free_port

Payload = payload_class()


@dataclass
class Decoded:
    topic: str
    kind: str          # NBIRTH, DBIRTH, DDATA, DDEATH, NDEATH, NCMD, STATE
    payload: Any       # the decoded Payload (STATE: the JSON)


@dataclass
class HostDecoder:
    """A Sparkplug host application's view: every ``spBv1.0/#`` message decoded, in order."""

    sub: Subscriber
    aliases: dict[int, str] = field(default_factory=dict)
    device_aliases: dict[tuple[str, str], dict[int, str]] = field(default_factory=dict)

    @classmethod
    def start(cls, port: int) -> HostDecoder:
        return cls(Subscriber(port, ["spBv1.0/#"], client_id=f"test-host-{free_port()}"))

    def messages(self) -> list[Decoded]:
        with self.sub.lock:
            raw = list(self.sub.messages)
        out = []
        seen: set[tuple[str, bytes]] = set()
        for m in raw:
            if m.dup and (m.topic, m.payload) in seen:
                continue  # the broker's QoS 1 redelivery to this subscriber (not a new message)
            seen.add((m.topic, m.payload))
            parts = m.topic.split("/")
            if parts[1] == "STATE":
                out.append(Decoded(m.topic, "STATE", json.loads(m.payload)))
            else:
                out.append(Decoded(m.topic, parts[2], Payload.FromString(m.payload)))
        return out

    def kinds(self) -> list[str]:
        return [d.kind for d in self.messages()]

    def wait(self, predicate: Any, timeout: float, what: str) -> None:
        self.sub.wait(lambda: predicate(self.messages()), timeout, what)

    def check_session(self) -> dict[str, int]:
        """The rules every message must keep (asserted): an NBIRTH has ``seq`` 0 and a
        ``bdSeq``; every later message of the node up to the next NBIRTH, whichever device it
        is about, has the next ``seq`` (mod 256), none missing; after each NBIRTH a DBIRTH
        comes before any DDATA of its device; a DDATA names no metric, carries only aliases its
        device's DBIRTH announced; an NDEATH with the ``bdSeq`` of the live NBIRTH ends the
        session (counted ``NDEATH``), another is ignored as a host ignores it (``stale
        NDEATH``). Returns counts by kind."""
        seqs: dict[str, int | None] = {}
        bd_seqs: dict[str, int] = {}
        borns: dict[tuple[str, str], set[int] | None] = {}
        counts: dict[str, int] = {}
        for d in self.messages():
            counts[d.kind] = counts.get(d.kind, 0) + 1
            if d.kind in ("STATE", "NCMD", "DCMD"):
                continue
            p = d.payload
            parts = d.topic.split("/")
            node = parts[3]
            device = (node, parts[4] if len(parts) > 4 else "")
            if d.kind == "NBIRTH":
                assert p.seq == 0, f"NBIRTH seq {p.seq}"
                (bd,) = [m.long_value for m in p.metrics if m.name == "bdSeq"]
                bd_seqs[node], seqs[node] = bd, 0
                for key in [k for k in borns if k[0] == node]:
                    borns[key] = None   # a new NBIRTH: every device is born again
                assert any(m.name == "Node Control/Rebirth" for m in p.metrics)
                continue
            if d.kind == "NDEATH":
                (bd,) = [m.long_value for m in p.metrics if m.name == "bdSeq"]
                assert not p.HasField("seq")
                if bd != bd_seqs.get(node) or seqs.get(node) is None:
                    # an older connection's will (the broker's, after a restart) or a second
                    # copy: a host ignores it, which bdSeq is for (Sparkplug 3.0)
                    counts["NDEATH"] -= 1
                    counts["stale NDEATH"] = counts.get("stale NDEATH", 0) + 1
                    continue
                seqs[node] = None
                continue
            seq = seqs.get(node)
            assert seq is not None, f"{d.kind} before any NBIRTH"
            assert p.seq == (seq + 1) % 256, f"{d.kind} of {device} seq {p.seq} after {seq}"
            seqs[node] = p.seq
            if d.kind == "DBIRTH":
                born = borns[device] = {m.alias for m in p.metrics}
                names = self.device_aliases.setdefault(device, {})
                for m in p.metrics:
                    assert m.name and m.alias and m.datatype
                    self.aliases[m.alias] = names[m.alias] = m.name
                assert len(born) == len(p.metrics), "aliases not unique"
            elif d.kind == "DDATA":
                born = borns.get(device)
                assert born is not None, f"DDATA of {device} before its DBIRTH"
                assert all(not m.name and m.alias in born for m in p.metrics)
            elif d.kind == "DDEATH":
                borns[device] = None
        return counts

    def windows(self, device: str | None = None) -> list[tuple[str, int, bool]]:
        """(run, window, historical) of every DDATA (of ``device`` only, if given), in the
        order received (after :meth:`check_session`: the aliases)."""
        out = []
        for d in self.messages():
            if d.kind != "DDATA":
                continue
            parts = d.topic.split("/")
            if device is not None and parts[4] != device:
                continue
            names = self.device_aliases.get((parts[3], parts[4]), self.aliases)
            v = {names[m.alias]: m for m in d.payload.metrics}
            out.append((v["Window/Run"].string_value, v["Window/Index"].long_value,
                        v["Window/Index"].is_historical))
        return out

    def close(self) -> None:
        self.sub.close()


def stored(db: Path) -> list[tuple[str, int]]:
    con = sqlite3.connect(db, timeout=10)
    try:
        return [(json.loads(d)["run"], json.loads(d)["window"])
                for (d,) in con.execute("SELECT doc FROM health ORDER BY id")]
    finally:
        con.close()
