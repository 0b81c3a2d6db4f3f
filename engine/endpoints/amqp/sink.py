"""An AMQP sink: each message published to its exchange with a routing key rendered from it.

Sinks publish on the connection's channel with publisher confirms (configurable), every
route's batch of a loop turn in one shared round (one write, one confirm wait:
engine/endpoints/amqp/publisher.py), each route answered per message, so "accepted" means the
broker took responsibility. A message that asks for a reply is a call (calls.py)."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Sequence

from aiormq import spec

from engine.common.placeholders import MappingError, compile_template
from engine.common.schemas import SchemaError, canonical_bytes
from engine.endpoints.amqp.calls import AmqpCaller
from engine.endpoints.amqp.link import AmqpLink
from engine.endpoints.amqp.options import AmqpSinkOptions
from engine.common.backoff import Backoff
from engine.endpoints.base import EndpointError, MessageRejected, Outbound, Sink, Unroutable, UnroutableRejected

log = logging.getLogger("engine.amqp")

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
    """Publishes ``mandatory`` (unless ``mandatory: false``): nothing is delivered to nobody.

    An exchange with no queue bound for a message's routing key drops it unless it was
    published mandatory: a sink on such an exchange counted 10 messages delivered, the source
    acknowledged them, and all 10 were gone. Published mandatory, the broker returns it
    (``basic.return``, before its confirm: publisher.py matches the two) and it is the sink's
    refusal (:class:`~engine.endpoints.base.Unroutable`): never counted delivered, never
    acknowledged at the source, counted ``unroutable``. Then, by ``unroutable``:

    * ``hold`` (the default): the sink is not :attr:`ready` and the route holds its messages
      as a ROS 2 sink does until a subscriber matched (``require_subscriber``): nothing
      acknowledged (AMQP keeps them queued; a buffered route's buffer holds them), no delivery
      attempt spent, the reason in the status (``sink_not_ready``); they are published again
      after the engine's backoff (0.05-0.1 s doubling to 2.5-5 s), so a queue bound meanwhile
      gets them within 5 s, in order. The default because a missing queue is most often one
      not declared *yet* (its consumer starts after the engine, or is being re-declared: the
      source's own queue is, resume.py) and the messages are wanted once it is; dead-lettering
      them would ask the operator to replay them by hand. Like a ROS 2 templated topic, one
      routing key nobody is bound for holds the route's other messages too;
    * ``dead_letter``: each returned message is dead-lettered at once, naming the exchange and
      routing key, for exchanges where nobody listening is a fault to look at later.

    ``mandatory: false`` is for fire-and-forget exchanges (telemetry nobody may be listening
    to): the broker drops what no queue is bound for. Mandatory costs nothing while messages
    route: the flag is one bit of the publish frame, and only a returned message is matched.
    It needs publisher confirms (the return is matched to its confirm): without them the flag
    is not set. Calls (a sink's request/reply) are not published mandatory: their timeout
    answers a missing worker."""

    def __init__(self, connection: AmqpLink, route: str, options: AmqpSinkOptions) -> None:
        self._connection = connection
        self._where = f"route {route!r}: amqp sink"
        self._mandatory = options.mandatory and connection.settings.publisher_confirms
        self._dead_letter_unroutable = options.unroutable == "dead_letter"
        self._holding: str | None = None
        """Why the route's messages are held (an unroutable message, ``unroutable: hold``)."""
        self._retry_at = 0.0
        """Monotonic time from which the held messages are published again (0: not holding)."""
        self._backoff = Backoff(0.05, 5.0)
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

    @property
    def ready(self) -> bool:
        retry_at = self._retry_at
        return not retry_at or time.monotonic() >= retry_at

    def not_ready_reason(self) -> str | None:
        """While it holds unroutable messages, between attempts and during them."""
        return self._holding

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
            outcomes = await self._connection.publish_batch(self._exchange, batch, self._kind, self._durable, self._mandatory)
            unroutable = None
            for index, error in zip(publishable, outcomes):
                if error is not None and isinstance(error, Unroutable):
                    unroutable = error
                    if self._dead_letter_unroutable:
                        error = UnroutableRejected(f"{error} (mandatory; unroutable: dead_letter)")
                results[index] = error
            if unroutable is not None and not self._dead_letter_unroutable:
                self._hold(unroutable)
            elif self._holding is not None:
                self._routed(outcomes)
        return results

    def _hold(self, error: Unroutable) -> None:
        """Hold the route's messages (not :attr:`ready`) for the backoff's next wait."""
        self._retry_at = time.monotonic() + self._backoff.next()
        if self._holding is None:
            log.warning("%s: %s; holding the route's messages until a queue is bound", self._where, error)
        self._holding = f"{error} (mandatory; unroutable: hold)"

    def _routed(self, outcomes: list[BaseException | None]) -> None:
        if None in outcomes:
            log.info("%s: messages route again; publishing", self._where)
            self._holding = None
            self._retry_at = 0.0
            self._backoff.reset()
