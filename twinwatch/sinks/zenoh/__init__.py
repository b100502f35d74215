"""Publishing machine health over zenoh: one :class:`HealthPublisher` per monitored machine.

With ``P = {key_prefix}/{machine}`` it publishes ``P/health`` (one JSON document per window,
:meth:`HealthPublisher.publish`), ``P/<suffix>`` (:meth:`HealthPublisher.publish_json`:
``P/alarm``, ...) through ``zenoh.ext`` advanced publishers (:func:`declare_publisher`: a cache
of the last ``[zenoh] cache`` samples, sequence numbers, heartbeat; under ``P/health/@adv/...``),
the fleet summary on ``P/summary`` (:meth:`HealthPublisher.publish_summary`), the liveliness
token ``P/alive`` (with ``[zenoh] presence = "box"``: one per box, :class:`QueryDispatch`), and
one queryable on ``P/**`` answering the latest payload of each topic and, through
:meth:`HealthPublisher.add_query_handler`, ``P/history`` from the state database
(:func:`history_parameters`). Every key, its payload and how to subscribe: docs/fleet.md and
docs/outputs.md ("Subscribing from another process").

Every session is configured by :func:`to_zenoh_config`: explicit endpoints only, multicast and
gossip scouting off; TLS (``[zenoh.tls]``), authentication (``[zenoh.auth]``) and access
control (``[zenoh.access_control]``, passed through verbatim) come from the configuration.
With ``retry_connect=True`` (the daemon) an unreachable router is retried in the background
(the delay doubling up to ``[zenoh].retry_max`` s): publishing is a counted no-op until then.
"""

from twinwatch.errors import PublisherError
from twinwatch.io.encoding import to_json
from twinwatch.sinks.zenoh.config import ZenohConfig
from twinwatch.sinks.zenoh.publisher import HealthPublisher, worst_parameter
from twinwatch.sinks.zenoh.queries import QueryDispatch, history_parameters
from twinwatch.sinks.zenoh.session import declare_publisher, open_session, to_zenoh_config

__all__ = [
    "HealthPublisher",
    "PublisherError",
    "QueryDispatch",
    "ZenohConfig",
    "declare_publisher",
    "history_parameters",
    "open_session",
    "to_json",
    "to_zenoh_config",
    "worst_parameter",
]
