"""The key layout the daemon's Zenoh publisher and the watchers share, with no dependency on
either: the boxes' liveliness tokens of ``[zenoh] presence = "box"`` (the sinks declare them,
``twinwatch watch`` follows them without importing the twin or the sinks)."""

from __future__ import annotations

import re

BOX_TOKENS = "@box"
"""The key chunk under a ``[zenoh] key_prefix`` holding the boxes' liveliness tokens with
``[zenoh] presence = "box"``: ``<key_prefix>/@box/<box chunk>/<session zid>``
(:func:`box_token_key`). A chunk starting with ``@`` is verbatim in Zenoh: ``*`` and ``**`` never
match it, so no machine's key expression (``<key_prefix>/*/alive``, ``<key_prefix>/**``) reaches
a box's token."""

_NOT_CHUNK_RE = re.compile(r"[^A-Za-z0-9_.\-]")


def box_chunk(box: str) -> str:
    """A box's name (a summary's ``box``, ``[zenoh] box`` or the host name) as one plain key
    chunk: every character other than letters, digits, ``_``, ``-``, ``.`` becomes ``_``."""
    return _NOT_CHUNK_RE.sub("_", box) or "_"


def box_token_key(prefix: str, box: str, zid: str) -> str:
    """The liveliness token of a box (a gateway's session) standing for its machines:
    ``<prefix>/@box/<box_chunk(box)>/<zid>`` (``zid``: the session's Zenoh id, which keeps two
    sessions of one box apart)."""
    return f"{prefix}/{BOX_TOKENS}/{box_chunk(box)}/{zid}"


__all__ = ["BOX_TOKENS", "box_chunk", "box_token_key"]
