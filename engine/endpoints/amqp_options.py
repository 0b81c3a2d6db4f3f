"""The AMQP endpoint's options, declared once (engine/options.py): connection, source, sink.

Apart from engine/endpoints/amqp.py so the cluster helpers (amqp_cluster.py, amqp_topology.py)
can use them without importing the endpoint itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from engine.endpoints.base import EndpointOptions
from engine.options import option

RECONNECT_INTERVAL = 1.0
"""Seconds between aio-pika's reconnection attempts after a lost connection (its default, 5 s,
is most of the time from a broker's restart to the first message delivered after it)."""


ExchangeType = Literal["topic", "direct", "fanout", "headers"]
QueueType = Literal["classic", "quorum"]


@dataclass(frozen=True, kw_only=True)
class AmqpConnectionOptions:
    """``connections.<name>.amqp``: one broker (``url``, also the string shorthand) or a cluster."""

    url: str | None = option(None, secret=True)
    publisher_confirms: bool = option(True)
    heartbeat: int = option(30, minimum=0, show_default=False)
    reconnect_interval: float = option(RECONNECT_INTERVAL, exclusive_minimum=0,
                                       description="seconds between reconnection attempts after the connection is lost")
    urls: tuple[str, ...] | None = option(None, min_items=1, secret=True,
                                          description="the nodes of a RabbitMQ cluster: connect to one, fail over to the next on loss")
    queue_type: QueueType | None = option(None, description="type of the queues this connection's routes (and its dead letters) declare unless a source says otherwise")


@dataclass(frozen=True, kw_only=True)
class AmqpSourceOptions(EndpointOptions):
    exchange: str | None = option(None, description="exchange name ('' is the default exchange)")
    exchange_type: ExchangeType = option("topic")
    durable: bool = option(True)
    queue: str | None = option(None, description="queue to consume; declared durable; default rabbitros.<route>")
    binding_key: str = option("#", show_default=False, description="binds the queue to the exchange; default '#'")
    prefetch: int = option(256, minimum=1, maximum=65535)
    queue_arguments: dict[str, Any] | None = option(None)
    queue_type: QueueType | None = option(None, description="quorum: replicated by Raft over the cluster; default: the connection's queue_type")
    ordered: bool = option(False, internal=True)
    """Set by the loader from the route's ``ordered: true`` (single active consumer)."""


@dataclass(frozen=True, kw_only=True)
class AmqpSinkOptions(EndpointOptions):
    exchange: str = option("", show_default=False, description="exchange name ('' is the default exchange)")
    exchange_type: ExchangeType = option("topic")
    durable: bool = option(True)
    routing_key: str = option("", show_default=False, description="may interpolate canonical fields: canonical.weeds.{agent_id}")
    content_type: str = option("application/json")
    persistent: bool = option(True)
