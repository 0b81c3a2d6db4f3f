"""An AMQP sink: each message published to its exchange with a routing key rendered from it.

Sinks publish on the connection's channel with publisher confirms (configurable), every
route's batch of a loop turn in one shared round (one write, one confirm wait:
engine/endpoints/amqp/publisher.py), each route answered per message, so "accepted" means the
broker took responsibility. A message that asks for a reply is a call (calls.py)."""

from __future__ import annotations

import asyncio
from typing import Any, Sequence

from aiormq import spec

from engine.common.placeholders import MappingError, compile_template
from engine.common.schemas import SchemaError, canonical_bytes
from engine.endpoints.amqp.calls import AmqpCaller
from engine.endpoints.amqp.link import AmqpLink
from engine.endpoints.amqp.options import AmqpSinkOptions
from engine.endpoints.base import EndpointError, MessageRejected, Outbound, Sink

MAX_ROUTING_KEY = 255
"""Bytes in a routing key (an AMQP short string): a longer one can never be published."""



class PublishProperties(spec.Basic.Properties):
    """The properties of a message a sink publishes. All but ``message_id`` are the same for
    every message of a route generation (content type, delivery mode, the route's headers), so
    they are validated and encoded once (:meth:`fixed`); pamqp would re-encode the headers
    table of every message, a tenth of the publish cost. ``message_id`` comes last on the wire."""

    def __init__(self, fixed: tuple[spec.Basic.Properties, bytes, bytes], message_id: str | None) -> None:
        template, self._with_id, self._without_id = fixed
        self.content_type, self.headers, self.delivery_mode = template.content_type, template.headers, template.delivery_mode
        self.content_encoding = self.priority = self.correlation_id = self.reply_to = self.expiration = None
        self.timestamp = self.message_type = self.user_id = self.app_id = None
        self.cluster_id = ""
        self.message_id = message_id

    @staticmethod
    def fixed(content_type: str, delivery_mode: int, headers: dict[str, Any]) -> tuple[spec.Basic.Properties, bytes, bytes]:
        """(template, encoding up to a message id, encoding without one), from pamqp itself."""
        template = spec.Basic.Properties(content_type=content_type, delivery_mode=delivery_mode, headers=headers)
        with_id = spec.Basic.Properties(content_type=content_type, delivery_mode=delivery_mode, headers=headers,
                                        message_id="x").marshal()[:-2]  # less the short string "x"
        return template, with_id, template.marshal()

    def marshal(self) -> bytes:
        message_id = self.message_id
        if not message_id:
            return self._without_id
        encoded = message_id.encode()
        return self._with_id + len(encoded).to_bytes(1, "big") + encoded


class AmqpSink(Sink):
    """Publishes without the mandatory flag: as in AMQP itself, an exchange with no matching
    binding drops the message (RabbitMQ's alternate exchanges are the way to keep those)."""

    def __init__(self, connection: AmqpLink, route: str, options: AmqpSinkOptions) -> None:
        self._connection = connection
        self._exchange = options.exchange
        self._kind = options.exchange_type
        self._durable = options.durable
        self._routing_key = compile_template(options.routing_key)
        self._content_type = options.content_type
        self._delivery_mode = 2 if options.persistent else 1
        self._properties: dict[tuple[str, int], tuple[spec.Basic.Properties, bytes, bytes]] = {}
        self._caller = None if options.timeout is None else AmqpCaller(
            connection, f"route {route!r}: amqp sink", options.timeout)
        """Calls: messages that ask for a reply are requests (engine/endpoints/amqp/calls.py)."""

    async def send(self, message: Outbound) -> None:
        error = (await self.send_batch((message,)))[0]
        if error is not None:
            raise error

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        if self._caller is not None and any(message.meta.get("reply_to") for message in messages):
            return list(await asyncio.gather(*(self._call(message) if message.meta.get("reply_to")
                                               else self._publish_one(message) for message in messages)))
        return await self._publish(messages)

    async def _publish_one(self, message: Outbound) -> BaseException | None:
        return (await self._publish((message,)))[0]

    async def _call(self, message: Outbound) -> BaseException | None:
        """A request and its answer, the call's reply."""
        assert self._caller is not None
        try:
            routing_key = self._routing_key(message.template_data)
            body = message.body if message.fields is message.canonical else canonical_bytes(message.fields)
            answer = await self._caller.call(self._exchange, self._kind, self._durable, routing_key, body,
                                             self._content_type, message.message_id,
                                             message.reply.late if message.reply is not None else None)
        except (MappingError, SchemaError) as exc:
            return MessageRejected(str(exc))
        except EndpointError as exc:
            return exc
        if message.reply is not None:
            await message.reply("result", answer)
        return None

    async def close(self) -> None:
        if self._caller is not None:
            await self._caller.close()

    async def _publish(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        results: list[BaseException | None] = [None] * len(messages)
        publishable: list[int] = []
        batch: list[tuple[str, bytes, spec.Basic.Properties]] = []
        for index, message in enumerate(messages):
            try:
                routing_key = self._routing_key(message.template_data)
                body = message.body if message.fields is message.canonical else canonical_bytes(message.fields)  # sink.mapping
            except (MappingError, SchemaError) as exc:  # a field the key needs is missing: no retry can help
                results[index] = MessageRejected(str(exc))
                continue
            if len(routing_key) > 85 and len(routing_key.encode()) > MAX_ROUTING_KEY:  # (85: 3 bytes a character at most)
                results[index] = MessageRejected(f"routing key {routing_key[:60]!r}... is {len(routing_key.encode())} bytes; "
                                                 f"AMQP allows {MAX_ROUTING_KEY}")
                continue
            meta = message.meta
            key = (meta["route"], meta["generation"])
            fixed = self._properties.get(key)
            if fixed is None:
                fixed = self._properties[key] = PublishProperties.fixed(
                    self._content_type, self._delivery_mode,
                    {"x-rabbitros-route": key[0], "x-rabbitros-generation": key[1]})
            publishable.append(index)
            batch.append((routing_key, body, PublishProperties(fixed, message.message_id)))
        if batch:
            for index, error in zip(publishable, await self._connection.publish_batch(self._exchange, batch, self._kind, self._durable)):
                results[index] = error
        return results
