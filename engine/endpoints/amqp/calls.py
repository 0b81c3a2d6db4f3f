"""The AMQP sink as a caller: a message that asks for a reply (a call to a ROS 2 service the
engine offers, engine.endpoints.ros2.calls.py) is published as an AMQP request and its worker's
answer is the call's reply.

The request carries ``reply_to: amq.rabbitmq.reply-to`` (RabbitMQ's direct reply-to: no reply
queue, and the reply must be consumed on the channel that published the request, so the sink
has a channel of its own for calls) and a fresh ``correlation_id``; the first reply with that
id, as JSON, is the answer. None within the sink's ``timeout``: the call fails for good
(:class:`MessageRejected`: the caller has given up), and a reply up to ``late_window`` later
(engine/endpoints/base.py) is dropped and counted (the route's ``replies.late``); after that it is only counted here
(``stray``), like a reply naming no call of this sink.

The calls channel is a plain channel (engine/endpoints/amqp/channels.py), opened again at the
next call once the broker (a request to an exchange deleted meanwhile: 404) or a lost
connection closed it: on a robust one aio-pika's restore got there first and no reply came on
it again (tests/endpoints/amqp/test_amqp_publish_channel.py). A direct reply can only come on the channel
that published the request, so the calls waiting on a channel that closed fail at once with
:class:`EndpointError` (retried: the request may never have reached a worker), not at their
timeout as if the worker had not answered.
"""

from __future__ import annotations

import asyncio
import uuid
from typing import Any, Callable, Protocol

import aio_pika
import aio_pika.abc
import orjson

from engine.endpoints.amqp.channels import open_plain_channel
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error, ignored
from engine.endpoints.base import EndpointError, MessageRejected, late_window


class Channels(Protocol):
    """What the caller needs of its connection (engine/endpoints/amqp/link.py's AmqpLink)."""

    def channel_factory(self) -> aio_pika.abc.AbstractRobustConnection: ...

DIRECT_REPLY_TO = "amq.rabbitmq.reply-to"


class AmqpCaller:
    def __init__(self, connection: Channels, where: str, timeout: float) -> None:
        self._connection = connection
        self._where = where
        self._timeout = timeout
        self._channel: aio_pika.abc.AbstractChannel | None = None
        self._exchanges: dict[str, aio_pika.abc.AbstractExchange] = {}
        self._pending: dict[str, tuple[asyncio.Future[bytes], aio_pika.abc.AbstractChannel]] = {}
        """Calls waiting for their answer, by correlation id, with the channel they were published on."""
        self._opening = asyncio.Lock()
        self._timed_out: dict[str, Callable[[], None]] = {}
        """Correlation ids of calls that timed out, for one more ``timeout``: their late reply's counter."""
        self.stray = 0

    async def _ready(self) -> aio_pika.abc.AbstractChannel:
        async with self._opening:
            if self._channel is None or self._channel.is_closed:
                channel = await open_plain_channel(self._connection.channel_factory(), publisher_confirms=False)
                try:
                    queue = await channel.get_queue(DIRECT_REPLY_TO, ensure=False)
                    await queue.consume(self._on_reply, no_ack=True)
                except BaseException:
                    with ignored():
                        await channel.close()
                    raise
                channel.close_callbacks.add(self._on_channel_close)
                self._channel, self._exchanges = channel, {}
            return self._channel

    def _on_channel_close(self, channel: Any, error: BaseException | None = None) -> None:
        """The calls published on ``channel`` can get no answer any more: they fail now."""
        for answered, published_on in self._pending.values():
            if published_on is channel and not answered.done():
                answered.set_exception(EndpointError(
                    f"{self._where}: the calls channel closed before the answer came ({error or 'closed'})"))

    async def _exchange(self, channel: aio_pika.abc.AbstractChannel, name: str, kind: str,
                        durable: bool) -> aio_pika.abc.AbstractExchange:
        exchange = self._exchanges.get(name)
        if exchange is None:
            exchange = channel.default_exchange if name == "" else await channel.declare_exchange(
                name, aio_pika.ExchangeType(kind), durable=durable)
            if channel is self._channel:  # not one that closed meanwhile
                self._exchanges[name] = exchange
        return exchange

    async def _on_reply(self, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        correlation_id = message.correlation_id or ""
        answered, _ = self._pending.get(correlation_id, (None, None))
        if answered is None or answered.done():
            late = self._timed_out.pop(correlation_id, None)
            if late is not None:
                late()
            else:
                self.stray += 1
            return
        answered.set_result(message.body)

    async def call(self, exchange: str, kind: str, durable: bool, routing_key: str, body: bytes,
                   content_type: str, message_id: str | None, late: Callable[[], None] | None = None) -> Any:
        """Publish the request; the answer as JSON data. ``late`` counts an answer that comes
        after the timeout."""
        try:
            channel = await self._ready()
            target = await self._exchange(channel, exchange, kind, durable)
        except Exception as exc:
            raise EndpointError(f"{self._where}: cannot open the calls channel: {exc}") from exc
        correlation_id = uuid.uuid4().hex
        answered: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        self._pending[correlation_id] = (answered, channel)
        try:
            try:
                await target.publish(aio_pika.Message(body, content_type=content_type, correlation_id=correlation_id,
                                                      reply_to=DIRECT_REPLY_TO, message_id=message_id), routing_key)
            except LIBRARY_ERRORS as exc:  # the channel closed between its opening and this request
                raise edge_error(exc, f"{self._where}: cannot publish the request") from exc
            try:
                answer = await asyncio.wait_for(answered, self._timeout)
            except asyncio.TimeoutError:
                if late is not None:
                    self._timed_out[correlation_id] = late
                    asyncio.get_running_loop().call_later(late_window(self._timeout), self._timed_out.pop, correlation_id, None)
                raise MessageRejected(f"{self._where}: no answer within {self._timeout:g} s") from None
        finally:
            del self._pending[correlation_id]
        try:
            return orjson.loads(answer)
        except orjson.JSONDecodeError as exc:
            raise MessageRejected(f"{self._where}: the answer is not JSON: {exc}") from None

    async def close(self) -> None:
        if self._channel is not None:
            try:
                await self._channel.close()
            except Exception:
                pass
            self._channel = None
