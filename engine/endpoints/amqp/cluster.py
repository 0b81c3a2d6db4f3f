"""AMQP on a RabbitMQ cluster: failover between nodes, replicated (quorum) queues.

aio-pika's robust connection reconnects to the one URL it was given, so a connection
that lists several nodes (``amqp: {urls: [...]}``) uses :class:`FailoverConnection`: the
same robust connection (its channels re-declare their exchanges, queues, bindings and
consumers on every reconnect), but each connection attempt after the first goes to the
next node of the list. Queues the engine declares follow the connection's default
``queue_type`` unless a source names its own; quorum queues are replicated by Raft, so a
node lost with -9 loses no acknowledged message.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Iterator, Sequence
from urllib.parse import urlsplit

import aio_pika
import aio_pika.abc
from aio_pika.robust_connection import RobustConnection
from yarl import URL

from engine.common.redaction import reveal
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error
from engine.endpoints.amqp.options import AmqpConnectionOptions, AmqpSourceOptions

log = logging.getLogger("engine.amqp")

QUORUM_REFUSED_ARGUMENTS = {
    "x-max-priority": "quorum queues have no priorities",
    "x-queue-mode": "quorum queues keep messages on disk anyway (no lazy mode)",
    "x-queue-master-locator": "use x-queue-leader-locator for quorum queues",
    "x-queue-version": "applies to classic queues only",
    "x-max-age": "applies to streams only",
    "x-stream-max-segment-size-bytes": "applies to streams only",
}
"""Arguments RabbitMQ 3.10 refuses on a quorum queue (measured: PRECONDITION_FAILED
'invalid arg'); besides these, a quorum queue cannot be non-durable, exclusive or auto-delete."""


class FailoverConnection(RobustConnection):
    """A robust connection over several nodes: each (re)connection attempt after the first
    goes to the next URL of the list, round robin, so losing the node in use moves the
    connection (and every channel's topology) to a node that is up.

    aio-pika's reconnect loop resets ``transport`` to None right before every attempt and
    then connects to ``self.url``; that moment is where the next URL is chosen.
    """

    def __init__(self, urls: Sequence[str], first: int = 0, **kwargs: Any) -> None:
        self._urls = [URL(url) for url in urls]
        self._index = first % len(self._urls)
        self._attempts = 0
        super().__init__(self._urls[self._index], **kwargs)

    @property
    def transport(self) -> Any:
        return self.__dict__.get("_transport")

    @transport.setter
    def transport(self, value: Any) -> None:
        if value is None and "_transport" in self.__dict__ and len(self._urls) > 1:
            self._attempts += 1
            if self._attempts > 1:  # the first attempt uses the URL we were given
                self._index = (self._index + 1) % len(self._urls)
                self.url = self._urls[self._index]
        self.__dict__["_transport"] = value

    @property
    def endpoint(self) -> str:
        """``host:port`` of the node this connection uses (or is trying)."""
        return f"{self.url.host}:{self.url.port}"


async def connect_failover(urls: Sequence[str], **kwargs: Any) -> FailoverConnection:
    """Connect to the first node of ``urls`` that answers; raise the last error if none does."""
    error: BaseException | None = None
    timeout = kwargs.pop("timeout", None)
    for index in range(len(urls)):
        connection = FailoverConnection(urls, first=index, **kwargs)
        try:
            await connection.connect(timeout)
            return connection
        except LIBRARY_ERRORS as exc:
            error = exc
            await connection.close()
    assert error is not None
    raise error


def connection_urls(settings: AmqpConnectionOptions) -> list[str]:
    """Every node of a connection: ``urls`` (a cluster) or the single ``url``."""
    if settings.urls:
        return [str(reveal(url)) for url in settings.urls]
    return [str(reveal(settings.url))]


def check_urls(settings: AmqpConnectionOptions, redact: Any) -> Iterator[tuple[str | None, str]]:
    """Static checks of a connection's URLs; passwords never appear in a problem."""
    if settings.url is not None and settings.urls is not None:
        yield "urls", "give either url or urls, not both"
        return
    if settings.url is None and settings.urls is None:
        yield None, "an amqp connection needs url (one node) or urls (the nodes of a cluster)"
        return
    urls = settings.urls if settings.urls is not None else (settings.url,)
    seen: set[tuple[str, int | None, str]] = set()
    for index, url in enumerate(urls):
        where = "urls" if settings.urls is not None else None
        try:
            parts = urlsplit(str(reveal(url)))
            port = parts.port
        except ValueError as exc:
            yield where, f"URL {index + 1}: {redact(str(url))!r} is not a valid URL ({exc})"
            continue
        if parts.scheme not in ("amqp", "amqps") or not parts.hostname:
            label = f"URL {index + 1}: " if where else ""
            yield where, f"{label}not an amqp:// URL: {redact(str(url))!r}"
            continue
        key = (parts.hostname, port, parts.path or "/")
        if key in seen:
            yield where, f"URL {index + 1}: {redact(str(url))!r} names the same node twice"
        seen.add(key)


def queue_type(options: AmqpSourceOptions, default: str | None) -> str | None:
    """The queue type a source declares: its own ``queue_type``, an explicit
    ``x-queue-type`` argument, or the connection's default."""
    arguments = options.queue_arguments or {}
    return options.queue_type or arguments.get("x-queue-type") or default


def queue_arguments(
    options: AmqpSourceOptions, default_type: str | None, single_active: bool = False
) -> dict[str, Any] | None:
    """The ``queue.declare`` arguments of a source's queue."""
    arguments = dict(options.queue_arguments or {})
    kind = queue_type(options, default_type)
    if kind and kind != "classic":
        arguments["x-queue-type"] = kind
    if single_active:
        arguments["x-single-active-consumer"] = True
    return arguments or None


def check_queue(options: AmqpSourceOptions) -> Iterator[tuple[str | None, str]]:
    """What a quorum queue refuses, said before RabbitMQ says PRECONDITION_FAILED."""
    arguments = options.queue_arguments or {}
    declared = arguments.get("x-queue-type")
    if declared is not None and options.queue_type and declared != options.queue_type:
        yield "queue_arguments", f"x-queue-type {declared!r} contradicts queue_type {options.queue_type!r}"
    if queue_type(options, None) != "quorum":
        return
    if not options.durable:
        yield "durable", "a quorum queue is always durable (durable: false is refused)"
    for argument, why in QUORUM_REFUSED_ARGUMENTS.items():
        if argument in arguments:
            yield "queue_arguments", f"quorum queues refuse {argument} ({why})"


LEASE_QUEUE_PREFIX = "rabbitros.lease."
LEASE_EXPIRY_BEATS = 3
"""An active holder that has seen no heartbeat for this many periods steps down."""


class AmqpLease:
    """Which engine instance forwards an ``active_standby`` route, decided by the broker.

    Every instance consumes the lease queue with single active consumer (SAC) and publishes
    a heartbeat to it every ``heartbeat`` seconds. RabbitMQ delivers the queue's messages
    to one consumer only, so the instance that receives heartbeats is the one the broker
    made active; the others receive nothing and stay standby. When the active instance
    dies its connection closes, the broker activates the next consumer, and that one
    receives the next heartbeat (its own, at the latest one period later): the takeover is
    bounded by the heartbeat period plus the time the broker needs to notice the death
    (immediately for a killed process, whose socket the kernel closes; the AMQP heartbeat
    timeout for a machine that vanishes). An active instance that loses its connection, or
    sees no heartbeat for :data:`LEASE_EXPIRY_BEATS` periods, steps down at once.
    """

    def __init__(self, connection: Any, name: str, instance: str, heartbeat: float, queue_type: str | None) -> None:
        self.connection = connection
        self.name = name
        self.instance = instance
        self.heartbeat = heartbeat
        self.queue = LEASE_QUEUE_PREFIX + name
        self._queue_type = queue_type
        self.active = False
        self.changes = 0
        """How many times the role changed (acquired or lost)."""
        self.holder: str | None = None
        """The instance whose heartbeat reached us last while we were active (ourselves)."""
        self.peers: dict[str, float] = {}
        self._last_beat = 0.0
        self._channel: aio_pika.abc.AbstractChannel | None = None
        self._task: asyncio.Task[None] | None = None
        self.users = 0

    @property
    def role(self) -> str:
        return "active" if self.active else "standby"

    async def start(self) -> None:
        raw = self.connection.channel_factory()
        raw.close_callbacks.add(self._connection_lost)
        arguments = queue_arguments(AmqpSourceOptions(queue_arguments={"x-max-length": 16, "x-message-ttl": 10_000}),
                                    self._queue_type, single_active=True)
        try:
            self._channel = await raw.channel(publisher_confirms=False)
            queue = await self._channel.declare_queue(self.queue, durable=True, arguments=arguments)
            await queue.consume(self._on_heartbeat, no_ack=True)
        except LIBRARY_ERRORS as exc:
            raise edge_error(exc, f"lease {self.name!r} on amqp connection {self.connection.name!r}") from exc
        self._task = asyncio.create_task(self._beat(), name=f"lease {self.name}")

    def _connection_lost(self, *_: Any) -> None:
        self._set(False, "connection lost")

    async def _on_heartbeat(self, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        self._last_beat = time.monotonic()
        sender = message.body.decode(errors="replace")
        self.peers[sender] = time.time()
        self._set(True, "the broker made this instance the lease queue's active consumer")

    def _set(self, active: bool, why: str) -> None:
        if active == self.active:
            return
        self.active = active
        self.changes += 1
        log.warning("lease %s", "acquired" if active else "lost",
                    extra={"lease": self.name, "instance": self.instance, "reason": why})

    async def _beat(self) -> None:
        while True:
            try:
                assert self._channel is not None
                await self._channel.default_exchange.publish(
                    aio_pika.Message(self.instance.encode(), delivery_mode=aio_pika.DeliveryMode.NOT_PERSISTENT),
                    self.queue,
                )
            except Exception:  # the connection is failing over: no lease without a broker
                self._set(False, "cannot reach the broker")
            if self.active and time.monotonic() - self._last_beat > LEASE_EXPIRY_BEATS * self.heartbeat:
                self._set(False, f"no heartbeat for {LEASE_EXPIRY_BEATS} periods")
            await asyncio.sleep(self.heartbeat)

    async def stop(self) -> None:
        """Give the lease up: cancelling our consumer makes the broker activate another."""
        self._set(False, "stopped")
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        try:
            self.connection.channel_factory().close_callbacks.discard(self._connection_lost)
        except Exception:
            pass
        if self._channel is not None:
            try:
                await self._channel.close()
            except Exception:
                pass
