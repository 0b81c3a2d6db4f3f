"""Plain aio-pika clients used by tests to publish and collect, independent of the engine."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import uuid
from typing import Any, AsyncIterator, Protocol, Self

import aio_pika


class SeqRecorder(Protocol):
    def record(self, seq: int) -> None: ...


class Collector:
    """A queue bound to a topic exchange that records every message it receives, and when: the
    one collector of the tests (what a source delivers to an engine-less test is
    tests/support/collecting_deliver.py).

    By default an exclusive, auto-named queue consumed without acknowledgements: a test's window
    on a route's output. ``queue=NAME``: a durable queue of that name, which outlives a broker
    restart (``quorum``: a quorum queue, which outlives the node that dies in a cluster test);
    ``ack``: each message acknowledged once recorded, so a broker killed mid-delivery redelivers
    it (a duplicate) instead of losing it; ``tally``: each message's JSON ``seq`` recorded there;
    ``prefetch``: the channel's prefetch. :meth:`consume`: on a queue the test declared itself.
    A test that keeps its own view of the stream (arrival times, seqs) overrides :meth:`received`."""

    def __init__(self, ack: bool = False, tally: SeqRecorder | None = None) -> None:
        self.messages: list[aio_pika.abc.AbstractIncomingMessage] = []
        self.ack = ack
        self.tally = tally
        self._arrived = asyncio.Event()

    @classmethod
    async def bind(cls, channel: Any, exchange: str, binding_key: str = "#", *, queue: str | None = None,
                   quorum: bool = False, ack: bool = False, tally: SeqRecorder | None = None,
                   prefetch: int | None = None) -> Self:
        collector = cls(ack, tally)
        if prefetch is not None:
            await channel.set_qos(prefetch_count=prefetch)
        target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
        if queue is None:
            declared = await channel.declare_queue(f"test-{uuid.uuid4().hex[:8]}", exclusive=True)
        else:
            declared = await channel.declare_queue(queue, durable=True,
                                                   arguments={"x-queue-type": "quorum"} if quorum else None)
        await declared.bind(target, binding_key)
        await declared.consume(collector._on_message, no_ack=not ack)
        return collector

    @classmethod
    async def consume(cls, queue: Any, *, ack: bool = False, tally: SeqRecorder | None = None) -> Self:
        """A collector on a queue the test declared and bound itself (an alternate exchange's
        fanout queue, a queue bound to several exchanges)."""
        collector = cls(ack, tally)
        await queue.consume(collector._on_message, no_ack=not ack)
        return collector

    async def _on_message(self, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        self.received(time.monotonic(), message)
        self.messages.append(message)
        self._arrived.set()
        if self.tally is not None:
            self.tally.record(json.loads(message.body)["seq"])
        if self.ack:
            try:
                await message.ack()
            except Exception:
                pass  # the broker is gone: it redelivers what was not acked

    def received(self, at: float, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        """Called with each message and its arrival (monotonic) before it is recorded: for a
        subclass that keeps its own view of the stream."""

    async def wait_for(self, count: int, timeout: float = 20.0) -> list[aio_pika.abc.AbstractIncomingMessage]:
        """Wait until ``count`` messages arrived; fail naming how many did once none arrived for
        ``timeout`` seconds (or ten times that passed in all): a stream that keeps coming is
        waited for however slowly it flows (on a machine loaded by parallel test workers, 3,000
        messages took more than 20 s), a stalled one is not waited for longer than before."""
        loop = asyncio.get_running_loop()
        began = loop.time()
        overall = began + 10 * timeout
        while len(self.messages) < count:
            self._arrived.clear()
            stall = min(timeout, overall - loop.time())
            try:
                if stall <= 0:
                    raise asyncio.TimeoutError
                await asyncio.wait_for(self._arrived.wait(), stall)
            except asyncio.TimeoutError:
                why = f"the last more than {stall:g} s ago" if stall > 0 else f"the overall bound of {10 * timeout:g} s reached"
                raise AssertionError(f"timed out after {loop.time() - began:.1f} s waiting for {count} messages: "
                                     f"{len(self.messages)} arrived, {why}") from None
        return self.messages


async def publish(channel: Any, exchange: str, routing_key: str, bodies: list[bytes]) -> None:
    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
    for index, body in enumerate(bodies):
        await target.publish(
            aio_pika.Message(body, content_type="application/json", message_id=f"m{index}"), routing_key
        )


async def publish_burst(channel: Any, queue: str, bodies: list[bytes]) -> None:
    """Publish ``bodies`` to ``queue`` through the default exchange, pipelined (all in flight
    at once, as a burst reaches the broker), in order."""
    await asyncio.gather(*(channel.default_exchange.publish(aio_pika.Message(body), queue) for body in bodies))


def amqp_to_ros2_routes(name: str, queue: str, domain: int, tag: str, prefetch: int | None = None) -> str:
    """A routes file of one raw_json route ``name`` from AMQP ``queue`` to the ROS 2 topic
    ``/{tag}/{name}`` (std_msgs/String), on its own node in ``domain``."""
    source = f"queue: {queue}" + (f", prefetch: {prefetch}" if prefetch is not None else "")
    return f"""
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: {name}
    source: {{amqp: {{{source}}}}}
    schema: raw_json
    sink: {{ros2: {{topic: /{tag}/{name}}}}}
"""


@contextlib.asynccontextmanager
async def started_with_client(engine: Any, amqp_url: str) -> AsyncIterator[aio_pika.abc.AbstractConnection]:
    """Start ``engine`` (an engine.running.runtime.Engine) and open a plain aio-pika connection beside
    it; on the way out close the connection, then stop the engine."""
    await engine.start()
    try:
        connection = await aio_pika.connect(amqp_url)
        try:
            yield connection
        finally:
            await connection.close()
    finally:
        await engine.stop()


DIRECT_REPLY_TO = "amq.rabbitmq.reply-to"


class Caller:
    """An AMQP RPC client on RabbitMQ's direct reply-to: consumes ``amq.rabbitmq.reply-to``
    (no_ack, on the channel it publishes from) and files every reply by its correlation id."""

    def __init__(self, channel: Any) -> None:
        self.channel = channel
        self.replies: dict[str, list[aio_pika.abc.AbstractIncomingMessage]] = {}
        self._arrived = asyncio.Event()

    @classmethod
    async def open(cls, channel: Any) -> "Caller":
        caller = cls(channel)
        queue = await channel.get_queue(DIRECT_REPLY_TO, ensure=False)
        await queue.consume(caller._on_reply, no_ack=True)
        return caller

    async def _on_reply(self, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        self.replies.setdefault(message.correlation_id or "", []).append(message)
        self._arrived.set()

    async def call(self, exchange: str, routing_key: str, body: bytes, correlation_id: str | None = None,
                   reply_to: str | None = DIRECT_REPLY_TO, headers: dict[str, Any] | None = None) -> str:
        """Publish a request; returns its correlation id."""
        correlation_id = correlation_id or uuid.uuid4().hex
        target = self.channel.default_exchange if exchange == "" else await self.channel.get_exchange(exchange, ensure=False)
        await target.publish(aio_pika.Message(body, content_type="application/json", correlation_id=correlation_id,
                                              reply_to=reply_to, headers=headers or {}), routing_key)
        return correlation_id

    async def wait(self, condition: Any, timeout: float, what: str) -> None:
        """Until ``condition(self.replies)`` holds; fails naming ``what`` after ``timeout`` s."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not condition(self.replies):
            remaining = deadline - loop.time()
            assert remaining > 0, f"timed out waiting for {what}; replies: {self.summary()}"
            self._arrived.clear()
            try:
                await asyncio.wait_for(self._arrived.wait(), remaining)
            except asyncio.TimeoutError:
                pass

    def summary(self) -> dict[str, list[tuple[Any, bytes]]]:
        return {key: [(m.headers.get("x-rabbitros-reply"), m.body[:200]) for m in messages]
                for key, messages in list(self.replies.items())[:5]}


def message_count(queue: aio_pika.abc.AbstractQueue) -> int:
    """The ready-message count the broker gave when ``queue`` was declared (aiormq types it
    optional; a declare, passive or not, always answers with it)."""
    count = queue.declaration_result.message_count
    assert count is not None, f"the declare of {queue.name} answered without a message count"
    return count


def header_text(message: aio_pika.abc.AbstractMessage, name: str) -> str:
    """Header ``name`` of ``message``, a string as the engine writes it (an AMQP table value
    may be any of a dozen types; the test reads this one as text)."""
    value = message.headers[name]
    assert isinstance(value, str), f"header {name} is not text: {value!r}"
    return value


def consumer_count(queue: aio_pika.abc.AbstractQueue) -> int:
    """The consumer count the broker gave when ``queue`` was declared (optional in aiormq's
    types, always in a declare's answer)."""
    count = queue.declaration_result.consumer_count
    assert count is not None, f"the declare of {queue.name} answered without a consumer count"
    return count
