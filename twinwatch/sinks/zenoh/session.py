"""A zenoh session as the daemon opens it: the configuration (explicit endpoints only, no
scouting), opening it with a readable error, the key a process shares a session by, and the
advanced publishers with their cache.
"""

from __future__ import annotations

import json
import logging

from twinwatch.errors import PublisherError
from twinwatch.sinks.zenoh.config import RUST_LOCATION_RE, ZenohConfig, zenoh, zenoh_ext

logger = logging.getLogger(__package__)


def to_zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """Build the :class:`zenoh.Config` for ``cfg``.

    Multicast and gossip scouting are always off: the session only uses the endpoints given.

    Raises:
        PublisherError: zenoh rejected a value (should not happen for a validated ``cfg``).
    """
    conf = zenoh.Config()
    listen = [] if cfg.mode == "client" else list(cfg.listen)
    try:
        conf.insert_json5("mode", json.dumps(cfg.mode))
        conf.insert_json5("listen/endpoints", json.dumps(listen))
        conf.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
        if cfg.tls is not None:
            for key, value in cfg.tls.model_dump(exclude_none=True).items():
                conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
        if cfg.auth is not None:
            for key, value in cfg.auth.model_dump(exclude_none=True).items():
                conf.insert_json5(f"transport/auth/usrpwd/{key}", json.dumps(value))
        if cfg.access_control is not None:
            conf.insert_json5("access_control", json.dumps(cfg.access_control))
    except zenoh.ZError as exc:
        # never echo the config: it may hold secrets
        raise PublisherError(f"invalid zenoh configuration (mode={cfg.mode}): "
                             f"{RUST_LOCATION_RE.sub('', str(exc)).strip()}") from exc
    return conf


def open_session(cfg: ZenohConfig) -> zenoh.Session:
    """Open a zenoh session for ``cfg``; the caller owns it and must ``close()`` it.

    Raises:
        PublisherError: the session could not open; the message says which endpoint failed
            and what to change.
    """
    for key, path in cfg.input_files().items():
        try:
            with open(path, "rb"):
                pass
        except OSError as exc:
            raise PublisherError(f"cannot read zenoh.{key} = {path}: {exc.strerror or exc}; fix "
                                 f"the path in [zenoh.tls]/[zenoh.auth] or the file's "
                                 f"permissions (the service user must read it)") from exc
    conf = to_zenoh_config(cfg)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        raise PublisherError(explain_open_failure(cfg, str(exc))) from exc
    logger.debug("zenoh session %s open (mode=%s, listen=%s, connect=%s)", session.zid(),
                 cfg.mode, cfg.listen if cfg.mode != "client" else [], cfg.connect)
    return session


SESSION_FIELDS_NOT_SHARED = frozenset({"key_prefix", "enabled", "retry_max", "cache",
                                       "heartbeat", "summary_interval", "box", "presence"})
"""``[zenoh]`` keys that do not make the session (each machine's publisher has its own), so
machines that differ only in them share one session in a gateway."""


def session_key(cfg: ZenohConfig) -> str:
    """What makes a session, as one string: in a gateway, machines whose ``[zenoh]`` gives the
    same key share one session (:class:`~twinwatch.sinks.base.SharedResources`)."""
    data = cfg.model_dump(mode="json", exclude=set(SESSION_FIELDS_NOT_SHARED))
    return "zenoh:" + json.dumps(data, sort_keys=True, default=str)


def declare_publisher(session: zenoh.Session, key: str, cfg: ZenohConfig
                      ) -> zenoh.Publisher | zenoh_ext.AdvancedPublisher:
    """Declare the publisher of one topic (``P/health``, ``P/alarm``) on ``session``: with
    ``cfg.cache`` > 0 a ``zenoh.ext`` advanced publisher (cache, sample-miss detection with a
    sporadic heartbeat, publisher detection so an earlier subscriber asks for its cache);
    else a plain publisher. JSON encoding either way.

    Raises:
        zenoh.ZError: the declaration failed (the session closed).
    """
    encoding = zenoh.Encoding.APPLICATION_JSON
    if cfg.cache == 0:
        return session.declare_publisher(key, encoding=encoding)
    heartbeat = cfg.heartbeat if cfg.heartbeat > 0 else None
    return zenoh_ext.declare_advanced_publisher(
        session, key, encoding=encoding, cache=zenoh_ext.CacheConfig(cfg.cache),
        sample_miss_detection=zenoh_ext.MissDetectionConfig(heartbeat=None,
                                                            sporadic_heartbeat=heartbeat),
        publisher_detection=True)


def explain_open_failure(cfg: ZenohConfig, message: str) -> str:
    message = RUST_LOCATION_RE.sub("", message).strip()
    lowered = message.lower()
    if "address already in use" in lowered:
        endpoint = next((e for e in cfg.listen if e in message), None) or ", ".join(cfg.listen)
        host_port = endpoint.split("/", 1)[-1]
        host, _, port = host_port.rpartition(":")
        return (f"cannot listen on {endpoint}: port {port} already in use on {host}: another "
                "twinwatch or zenoh peer is listening; set [zenoh].listen to another port "
                f"(zenoh: {message})")
    if "unable to connect" in lowered:
        return (f"cannot connect to {', '.join(cfg.connect)}: nothing answers there; start "
                f"the zenoh router/peer first or fix [zenoh].connect (zenoh: {message})")
    if "lookup address" in lowered or "name or service not known" in lowered:
        return (f"cannot resolve a host in listen={cfg.listen} connect={cfg.connect}: "
                f"fix the endpoint host in [zenoh] (zenoh: {message})")
    return (f"cannot open zenoh session (mode={cfg.mode}, listen={cfg.listen}, "
            f"connect={cfg.connect}): {message}")
