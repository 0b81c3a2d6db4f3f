"""The AMQP endpoint's options, declared once (engine/common/options.py): connection, source, sink.

Apart from the endpoint (link.py, source.py, sink.py) so the cluster helpers (cluster.py, topology.py)
can use them without importing the endpoint itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from engine.common.options import option
from engine.common.tls import TlsOptions
from engine.endpoints.base import EndpointOptions

RECONNECT_INTERVAL = 1.0
"""Seconds between aio-pika's reconnection attempts after a lost connection (its default, 5 s,
is most of the time from a broker's restart to the first message delivered after it)."""


ExchangeType = Literal["topic", "direct", "fanout", "headers"]
QueueType = Literal["classic", "quorum"]


@dataclass(frozen=True, kw_only=True)
class AmqpConnectionOptions:
    """``connections.<name>.amqp``: one broker (``url``, also the string shorthand) or a cluster."""

    __schema_description__ = "a RabbitMQ connection (aio-pika, reconnects by itself): url (one node) or urls (a cluster)"

    url: str | None = option(None, secret=True,
                             description="amqp://USER:PASSWORD@HOST:PORT/VHOST (amqps:// for TLS); `amqp: URL` is short for `amqp: {url: URL}`; the password is never logged")
    publisher_confirms: bool = option(True, description="a sink's send returns once the broker confirmed the message (at-least-once); false: once written to the socket")
    heartbeat: int = option(30, minimum=0, description="AMQP heartbeat timeout in seconds, negotiated with the broker (a silent peer is dropped after it); 0: none")
    reconnect_interval: float = option(RECONNECT_INTERVAL, exclusive_minimum=0,
                                       description="seconds between reconnection attempts after the connection is lost")
    urls: tuple[str, ...] | None = option(None, min_items=1, secret=True,
                                          description="the nodes of a RabbitMQ cluster: connect to one, fail over to the next on loss")
    queue_type: QueueType | None = option(None, description="type of the queues this connection's routes (and its dead letters) declare unless a source says otherwise")
    tls: TlsOptions | None = option(None)
    auth: Literal["plain", "external"] = option("plain", description="plain: the URL's user and password; external: the client "
                                                "certificate is the identity (RabbitMQ's EXTERNAL mechanism, plugin rabbitmq_auth_mechanism_ssl; needs tls.cert_file)")


@dataclass(frozen=True, kw_only=True)
class AmqpSourceOptions(EndpointOptions):
    __schema_description__ = "consume a queue; a message is acknowledged only once it is settled (route-language.md, Delivery semantics)"

    exchange: str | None = option(None, description="exchange to bind the queue to ('' is the default exchange); a source needs a queue, an exchange, or both")
    exchange_type: ExchangeType = option("topic", description="type the exchange is declared with")
    durable: bool = option(True, description="declare the queue and exchange durable (they survive a broker restart)")
    queue: str | None = option(None, description="queue to consume, declared (durable unless durable: false); default rabbitros.<route>")
    binding_key: str = option("#", description="binds the queue to the exchange ('#': every routing key of a topic exchange)")
    prefetch: int = option(256, minimum=1, maximum=65535, description="unacknowledged messages in flight from the broker")
    queue_arguments: dict[str, Any] | None = option(None, description="x- arguments the queue is declared with, e.g. {x-max-length: 10000}")
    queue_type: QueueType | None = option(None, description="quorum: replicated by Raft over the cluster; default: the connection's queue_type")
    ordered: bool = option(False, internal=True)
    """Set by the loader from the route's ``ordered: true`` (single active consumer)."""
    partitions: int = option(1, internal=True)
    """Set by the loader from the route's ``ordered: {partitions: N}`` (partitions.py)."""
    partition_key: str = option("routing_key", internal=True)
    """Set by the loader from the route's ``ordered.key``: ``routing_key`` or ``headers.NAME``."""


@dataclass(frozen=True, kw_only=True)
class AmqpSinkOptions(EndpointOptions):
    __schema_description__ = "publish to an exchange; accepted once the broker confirmed (publisher confirms)"

    exchange: str = option("", description="exchange to publish to ('' is the default exchange, which routes to the queue named by the routing key)")
    exchange_type: ExchangeType = option("topic", description="type the exchange is declared with")
    durable: bool = option(True, description="declare the exchange durable (it survives a broker restart)")
    routing_key: str = option("", description="may interpolate canonical fields: canonical.weeds.{agent_id}; a message lacking one is dead-lettered")
    content_type: str = option("application/json", description="content_type property of every message")
    persistent: bool = option(True, description="delivery mode 2: the broker writes the message to disk in durable queues")
    mandatory: bool = option(True, description="publish mandatory: a message the exchange routes to no queue is returned by the broker, "
                                               "never counted delivered nor acknowledged at the source, and counted unroutable (see unroutable); "
                                               "false: fire and forget, the broker drops what no queue is bound for (needs publisher_confirms to refuse)")
    unroutable: Literal["hold", "dead_letter"] = option(
        "hold", description="what a returned (unroutable) message does: hold (the route's messages wait, as for a ROS 2 sink's "
                            "require_subscriber, and are published again with the engine's backoff until a queue is bound) or "
                            "dead_letter (at once, naming the exchange and routing key)")
    timeout: float | None = option(None, exclusive_minimum=0,
                                   description="for a message that asks for a reply (a call to a ROS 2 service the engine offers): "
                                               "publish it as a request (direct reply-to) and wait this many seconds for the "
                                               "worker's answer; none: the call fails, and no response is sent")
