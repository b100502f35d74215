"""Publishing machine health over zenoh: one :class:`HealthPublisher` per monitored machine.

With ``P = {key_prefix}/{machine}`` it publishes ``P/health`` (one JSON document per window),
``P/alarm`` and other suffixes through ``zenoh.ext`` advanced publishers
(:func:`declare_publisher`), the fleet summary on ``P/summary``, the liveliness token
``P/alive`` (or one per box, :class:`QueryDispatch`), and one queryable on ``P/**`` answering
the latest payload of each topic and ``P/history`` from the state database. Every key, its
payload and how to subscribe: docs/fleet.md and docs/outputs.md.

Every session uses explicit endpoints only, scouting off (:func:`to_zenoh_config`). With
``retry_connect=True`` (the daemon) an unreachable router is retried in the background:
publishing is a counted no-op until then.
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
