"""AMQP 0-9-1 (RabbitMQ) endpoint on aio-pika.

Sources consume with manual acknowledgement and ack only after ``deliver`` settled the
message, so a crash or a reload redelivers instead of losing. Sinks publish persistent
messages on a channel with publisher confirms (configurable), so "accepted" means the
broker took responsibility. One robust connection per named connection is shared by all
routes; each source has its own channel so its prefetch and its stop are its own.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any, Iterable, Mapping
from urllib.parse import urlsplit

import aio_pika
import aio_pika.abc
import aiormq.exceptions
from aio_pika.exceptions import AMQPError

from engine.endpoints.base import (
    CheckResult,
    Connection,
    Deliver,
    EndpointError,
    Inbound,
    MessageRejected,
    Outbound,
    Sink,
    Source,
    Transport,
)
from engine.mapping import MappingError, compile_template
from engine.schemas import SchemaError, canonical_bytes

_ERRORS = (AMQPError, aiormq.exceptions.AMQPError, ConnectionError, OSError, asyncio.TimeoutError)
DEAD_LETTER_EXCHANGE = "rabbitros.dead-letter"


def redact(url: str) -> str:
    """The URL with its password hidden, for logs and errors."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return parts._replace(netloc=netloc).geturl()


class AmqpConnection(Connection):
    keeps_dead_letters = True

    def __init__(self, name: str, settings: Mapping[str, Any]) -> None:
        super().__init__(name, settings)
        self._connection: aio_pika.abc.AbstractRobustConnection | None = None
        self._publish_channel: aio_pika.abc.AbstractChannel | None = None
        self._exchanges: dict[str, aio_pika.abc.AbstractExchange] = {}
        self._declare_lock = asyncio.Lock()

    @property
    def url(self) -> str:
        return str(self.settings["url"])

    @property
    def healthy(self) -> bool:
        """Connected now: the robust connection is open and its AMQP transport too (it is
        dropped while aio-pika reconnects)."""
        connection = self._connection
        underlay = getattr(connection, "transport", None)
        return (connection is not None and not connection.is_closed and underlay is not None
                and not underlay.connection.is_closed)

    async def open(self) -> None:
        try:
            self._connection = await aio_pika.connect_robust(
                self.url,
                client_properties={"connection_name": f"rabbitros-engine/{self.name}"},
                heartbeat=self.settings.get("heartbeat", 30),
            )
            self._publish_channel = await self._connection.channel(
                publisher_confirms=self.settings.get("publisher_confirms", True)
            )
            exchange = await self.exchange(DEAD_LETTER_EXCHANGE)
            queue = await self._publish_channel.declare_queue(DEAD_LETTER_EXCHANGE, durable=True)
            await queue.bind(exchange, "#")
        except _ERRORS as exc:
            raise EndpointError(f"amqp connection {self.name!r} ({redact(self.url)}): {exc}") from exc

    def channel_factory(self) -> aio_pika.abc.AbstractRobustConnection:
        if self._connection is None:
            raise EndpointError(f"amqp connection {self.name!r} is not open")
        return self._connection

    async def exchange(self, name: str, kind: str = "topic", durable: bool = True) -> aio_pika.abc.AbstractExchange:
        """The publish channel's exchange, declared once (durable topic unless told)."""
        exchange = self._exchanges.get(name)
        if exchange is not None:
            return exchange
        assert self._publish_channel is not None
        async with self._declare_lock:
            if name not in self._exchanges:
                if name == "":
                    self._exchanges[name] = self._publish_channel.default_exchange
                else:
                    self._exchanges[name] = await self._publish_channel.declare_exchange(
                        name, aio_pika.ExchangeType(kind), durable=durable
                    )
        return self._exchanges[name]

    async def publish(
        self,
        exchange_name: str,
        routing_key: str,
        message: aio_pika.Message,
        kind: str = "topic",
        durable: bool = True,
    ) -> None:
        try:
            exchange = await self.exchange(exchange_name, kind, durable)
            await exchange.publish(message, routing_key, mandatory=False)
        except _ERRORS as exc:
            raise EndpointError(f"amqp publish to {exchange_name!r}/{routing_key!r} on {self.name!r}: {exc}") from exc

    async def dead_letter(self, route: str, body: bytes, headers: Mapping[str, Any]) -> None:
        """Dead letters go to a durable exchange and queue declared at open, so they are kept
        even when nobody listens yet; the routing key is the route name."""
        message = aio_pika.Message(body, headers=dict(headers), delivery_mode=aio_pika.DeliveryMode.PERSISTENT)
        await self.publish(DEAD_LETTER_EXCHANGE, route, message)

    def source(self, route: str, options: Mapping[str, Any]) -> Source:
        return AmqpSource(self, route, options)

    def sink(self, route: str, options: Mapping[str, Any]) -> Sink:
        return AmqpSink(self, route, options)

    async def close(self) -> None:
        if self._connection is not None:
            try:
                await self._connection.close()
            except _ERRORS:
                pass
            self._connection = None


class AmqpSource(Source):
    def __init__(self, connection: AmqpConnection, route: str, options: Mapping[str, Any]) -> None:
        self._connection = connection
        self._route = route
        self._options = options
        self._channel: aio_pika.abc.AbstractChannel | None = None
        self._queue: aio_pika.abc.AbstractQueue | None = None
        self._consumer_tag: str | None = None
        self._in_flight: set[asyncio.Task[Any]] = set()
        self._deliver: Deliver | None = None

    @property
    def queue_name(self) -> str:
        return self._options.get("queue") or f"rabbitros.{self._route}"

    async def start(self, deliver: Deliver) -> None:
        self._deliver = deliver
        options = self._options
        try:
            self._channel = await self._connection.channel_factory().channel()
            await self._channel.set_qos(prefetch_count=options.get("prefetch", 256))
            self._queue = await self._channel.declare_queue(
                self.queue_name,
                durable=options.get("durable", True),
                arguments=options.get("queue_arguments"),
            )
            if "exchange" in options and options["exchange"] != "":
                exchange = await self._channel.declare_exchange(
                    options["exchange"],
                    aio_pika.ExchangeType(options.get("exchange_type", "topic")),
                    durable=options.get("durable", True),
                )
                await self._queue.bind(exchange, options.get("binding_key", "#"))
            self._consumer_tag = await self._queue.consume(self._on_message, no_ack=False)
        except _ERRORS as exc:
            raise EndpointError(f"route {self._route!r}: amqp source queue {self.queue_name!r}: {exc}") from exc

    async def _on_message(self, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        task = asyncio.current_task()
        assert task is not None and self._deliver is not None
        self._in_flight.add(task)
        try:
            inbound = Inbound(
                body=message.body,
                meta={
                    "routing_key": message.routing_key,
                    "exchange": message.exchange,
                    "message_id": message.message_id,
                    "headers": message.headers,
                    "content_type": message.content_type,
                    "redelivered": message.redelivered,
                },
                received_ns=time.monotonic_ns(),
            )
            try:
                await self._deliver(inbound)
            except Exception:
                await message.nack(requeue=True)
                return
            await message.ack()
        except _ERRORS:
            pass  # the channel is gone: the broker requeues whatever was not acked
        finally:
            self._in_flight.discard(task)

    async def stop(self) -> None:
        """Cancel the consumer, let in-flight messages settle, then close the channel so
        anything the broker sent but we did not take is requeued."""
        if self._queue is not None and self._consumer_tag is not None:
            try:
                await self._queue.cancel(self._consumer_tag)
            except _ERRORS:
                pass
        if self._in_flight:
            await asyncio.wait(set(self._in_flight))
        if self._channel is not None:
            try:
                await self._channel.close()
            except _ERRORS:
                pass


class AmqpSink(Sink):
    """Publishes without the mandatory flag: as in AMQP itself, an exchange with no matching
    binding drops the message (RabbitMQ's alternate exchanges are the way to keep those)."""

    def __init__(self, connection: AmqpConnection, route: str, options: Mapping[str, Any]) -> None:
        self._connection = connection
        self._exchange = options.get("exchange", "")
        self._kind = options.get("exchange_type", "topic")
        self._durable = options.get("durable", True)
        self._routing_key = compile_template(options.get("routing_key", ""))
        self._content_type = options.get("content_type", "application/json")
        self._delivery_mode = (
            aio_pika.DeliveryMode.PERSISTENT if options.get("persistent", True) else aio_pika.DeliveryMode.NOT_PERSISTENT
        )

    async def send(self, message: Outbound) -> None:
        try:
            routing_key = self._routing_key(message.canonical)
            body = message.body if message.fields is message.canonical else canonical_bytes(message.fields)  # sink.mapping
        except (MappingError, SchemaError) as exc:  # a field the key needs is missing: no retry can help
            raise MessageRejected(str(exc)) from None
        meta = message.meta
        await self._connection.publish(
            self._exchange,
            routing_key,
            aio_pika.Message(
                body,
                content_type=self._content_type,
                delivery_mode=self._delivery_mode,
                message_id=message.message_id,
                headers={"x-rabbitros-route": meta["route"], "x-rabbitros-generation": meta["generation"]},
            ),
            self._kind,
            self._durable,
        )


class AmqpTransport(Transport):
    name = "amqp"
    default_settings = {"url": "amqp://guest:guest@localhost:5672/"}

    def check_connection(self, settings: Mapping[str, Any]) -> CheckResult:
        parts = urlsplit(str(settings.get("url", "")))
        if parts.scheme not in ("amqp", "amqps") or not parts.hostname:
            yield None, f"not an amqp:// URL: {redact(str(settings.get('url', '')))!r}"

    def check_source(self, options: Mapping[str, Any], mapping: str | None) -> CheckResult:
        if "queue" not in options and "exchange" not in options:
            yield None, "an amqp source needs a queue, an exchange, or both"
        if "binding_key" in options and not options.get("exchange"):
            yield "binding_key", "binding_key needs an exchange to bind to"
        if "exchange_type" in options and not options.get("exchange"):
            yield "exchange_type", "exchange_type is not used without an exchange to declare"

    def check_sink(self, options: Mapping[str, Any], mapping: str | None) -> CheckResult:
        if "exchange" not in options and "routing_key" not in options:
            yield None, "an amqp sink needs an exchange and/or a routing_key"
        for key in ("exchange_type", "durable"):
            if key in options and not options.get("exchange"):
                yield key, f"{key} is not used: the default exchange is never declared (name an exchange)"

    async def source_retired(
        self, connection: Connection, route: str, options: Mapping[str, Any],
        remaining: Iterable[tuple[str, Mapping[str, Any]]],
    ) -> None:
        from engine.endpoints.amqp_topology import retire_source

        await retire_source(connection, route, options, remaining)

    def competing_consumers(self, route: str, options: Mapping[str, Any]) -> str | None:
        queue = options.get("queue")
        return f"queue {queue!r}" if queue else None

    def connect(self, name: str, settings: Mapping[str, Any]) -> Connection:
        return AmqpConnection(name, settings)


TRANSPORT = AmqpTransport()
