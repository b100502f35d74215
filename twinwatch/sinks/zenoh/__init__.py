"""Publishing machine health over zenoh.

One :class:`HealthPublisher` per monitored machine. It owns one zenoh session and declares,
with ``P = {key_prefix}/{machine}``:

* a publisher on ``P/health``: one JSON document per acquisition window
  (encoding ``application/json``), see :meth:`HealthPublisher.publish`;
* publishers on ``P/<suffix>`` created on first use by :meth:`HealthPublisher.publish_json`
  (``P/alarm``, ...);
* every publisher is a ``zenoh.ext`` *advanced* publisher (:func:`declare_publisher`) with a
  cache of its last ``[zenoh] cache`` samples (30 windows: a minute), sequence numbers and a
  heartbeat for sample-miss detection, and publisher detection: an ``AdvancedSubscriber`` that
  joins late gets each machine's recent windows from the cache (through a router too), one that
  lost samples (a router outage, a dropped link) gets them again from the cache or is told how
  many it missed (its sample-miss listener) and asks ``P/history`` for them (``twinwatch
  watch``/``tail`` do). Its cache and heartbeat live under ``P/health/@adv/...``, which the
  queryable below and ``P/**`` never match (``@`` chunks are verbatim in zenoh);
* the machine's fleet summary on ``P/summary`` (:mod:`twinwatch.twin.summary`: state, alarm
  levels, top fault, RUL, deviations in a few hundred bytes), when it changed and at least
  every ``[zenoh] summary_interval`` seconds (:meth:`HealthPublisher.publish_summary`), a plain
  publisher: late joiners get the latest from the queryable below. Its matching listener sends
  the latest summary again whenever a subscriber becomes reachable (the router's session
  failed over to another router, a restarted router is back, the first subscriber came): a
  watcher holds it without asking, as soon as routes exist again (``summaries_resent``);
* a liveliness token ``P/alive``, present while the publisher is open: a remote process sees the
  machine appear and disappear with ``session.liveliness().declare_subscriber(...)`` or polls it
  with ``session.liveliness().get(...)``. With ``[zenoh] presence = "box"`` the machines of a
  gateway's shared session declare none: one token per box, ``<key_prefix>/@box/<box>/<zid>``,
  stands for them all, and a get on that key answers their names (:class:`QueryDispatch`);
* one queryable on ``P/**`` (in a gateway, one on ``<key_prefix>/**`` for every machine sharing
  the session: :class:`QueryDispatch`) that answers a ``session.get(selector)`` with the
  *latest* payload of every topic above whose key intersects the selector:
  ``get("twinwatch/m1/health")`` returns the last health document, ``get("twinwatch/m1/**")``
  the last health and the last alarm. Topics not published yet are not answered (the get
  ends with no reply).

* handlers added with :meth:`HealthPublisher.add_query_handler` answer their own key under the
  same queryable; opened as the daemon's output (:meth:`HealthPublisher.from_config`) it serves
  ``P/history?t_from=..;t_to=..;by=wall;limit=..;run=..`` from the state database this way,
  asking the gate through its :class:`~twinwatch.sinks.base.SinkContext`
  (:func:`history_parameters`).

Every session is configured by :func:`to_zenoh_config`: explicit endpoints only, multicast and
gossip scouting off, so the daemon never talks to anything it was not told to. TLS/mTLS
(``[zenoh.tls]``), user/password authentication (``[zenoh.auth]``) and zenoh's access control
(``[zenoh.access_control]``, zenoh's own table, passed through verbatim and validated by zenoh
at load time) come from the configuration.

With ``retry_connect=True`` (the daemon) a session whose router cannot be reached at start is
opened in the background, with a delay that doubles up to ``[zenoh].retry_max`` seconds:
publishing is a counted no-op until then (the state database keeps every window, and the
history queryable serves them once the router is there). A connection lost later is restored
by zenoh itself.

An external process subscribes with (``pip install eclipse-zenoh``)::

    import json, zenoh
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", '["tcp/127.0.0.1:7447"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    with zenoh.open(conf) as session:
        for reply in session.get("twinwatch/motor1/health", timeout=2.0):
            if reply.ok is not None:
                print("latest:", json.loads(reply.ok.payload.to_string()))
        with session.declare_subscriber("twinwatch/*/health") as sub:
            for sample in sub:
                print(sample.key_expr, json.loads(sample.payload.to_string()))
"""

from twinwatch.errors import PublisherError
from twinwatch.io.encoding import to_json
from twinwatch.sinks.zenoh.config import ZenohAuthConfig, ZenohConfig, ZenohTlsConfig
from twinwatch.sinks.zenoh.publisher import UNRULED_THRESHOLD_PCT, HealthPublisher, worst_parameter
from twinwatch.sinks.zenoh.queries import HISTORY_LIMIT, QueryDispatch, history_parameters
from twinwatch.sinks.zenoh.session import (
    declare_publisher,
    open_session,
    session_key,
    to_zenoh_config,
)

__all__ = [
    "HISTORY_LIMIT",
    "UNRULED_THRESHOLD_PCT",
    "worst_parameter",
    "HealthPublisher",
    "PublisherError",
    "QueryDispatch",
    "ZenohAuthConfig",
    "ZenohConfig",
    "ZenohTlsConfig",
    "declare_publisher",
    "history_parameters",
    "open_session",
    "session_key",
    "to_json",
    "to_zenoh_config",
]
