"""An AMQP source: a queue consumed on a channel of its own, handed to the route in batches.

Batch-shaped, as a plain aiormq pass-through would be: a source's consumer callback only
appends to a list (unless the message arrives alone while the source is idle: it is then
settled in the callback, see ``AmqpSource._on_message``); the engine's read loop
(engine/endpoints/pump.py) hands everything received (up to half the prefetch; a backlog arrives about
100 messages at a time, as the source's channel buffers :data:`FRAME_BUFFER` frames, not
aiormq's 10) to the route as one batch, then acknowledges with a single ``basic_ack(multiple=True)`` up to the
highest delivery tag whose whole prefix was settled (accepted by the sink or dead-lettered);
the rest of the batch is acked one by one or nacked with requeue. That ``multiple`` ack is
held across batches while a burst lasts (acks.py says when it goes out, and why). Batches are
acknowledged in order, so every earlier tag is already acked or nacked and at-least-once
holds: a crash redelivers instead of losing. They are settled one at a time unless the route's
sink declares it can send more meanwhile (``Sink.batches_in_flight``: the JSON tunnel over a
radio).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from typing import Any, Mapping, cast

import aio_pika.abc
import aiormq.abc
from aiormq import spec

from engine.endpoints.amqp.acks import HeldAcks
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error
from engine.endpoints.amqp.link import AmqpLink
from engine.endpoints.amqp.options import AmqpSourceOptions
from engine.endpoints.amqp.resume import Resumption, declare
from engine.endpoints.base import Deliver, Inbound, Inbox, Source
from engine.endpoints.pump import Pump, settle_batch

log = logging.getLogger("engine.amqp")

Delivered = tuple[aiormq.abc.DeliveredMessage, int]
"""A message as the consumer received it, with ``time.monotonic_ns()`` then."""

ALONE_GAP_NS = 1_000_000
"""A message received more than this after the previous one is taken to arrive alone (a
robot's pace: 100-200 msg/s is 5-10 ms apart) and, if the source is idle, settled in its
consumer callback (:meth:`AmqpSource._on_message`); closer together they are a burst, which
the batch loop takes in batches."""
FRAME_BUFFER = 300
"""Frames a source's channel may hold between aiormq's connection reader and its channel
reader (about 100 small messages: a delivery is 3 frames). aiormq's default, 10, stops the
connection reader after 3 messages until the channel reader has run, so a drain reached the
batch loop 3.3 messages at a time (2,700 batches for 9,000 messages, every drain), each batch
paying the route's per-batch costs. Measured on bench amqp-ros2, 5 interleaved rounds of
6,000: the engine's CPU per message 140 us (median) at 10 frames, 114 at 100, 78 at 300, 100
at 3,000 (whole batches of half the prefetch: the broker and the engine overlap less). The
broker sends no more than the prefetch unacknowledged, so memory stays bounded by it in
messages either way; in bytes a buffer of 300 frames may hold up to 300 frame-size chunks of
large messages (39 MB at RabbitMQ's 128 KiB frames), so it is capped at three frames per
prefetched message (a small message's three)."""


class AmqpSource(Source):
    def __init__(self, connection: AmqpLink, route: str, options: AmqpSourceOptions) -> None:
        self._connection = connection
        self._route = route
        self._options = options
        self._channel: aio_pika.abc.AbstractChannel | None = None
        self._queue: aio_pika.abc.AbstractQueue | None = None
        self._consumer: tuple[aiormq.abc.AbstractChannel, str] | None = None
        self._received: Inbox[Delivered] = Inbox(1 << 30)
        """Bounded by the prefetch: the broker sends no more than that unacknowledged."""
        self._stopping = False
        self._loop: asyncio.Task[None] | None = None
        self._max_batch = max(1, options.prefetch // 2)
        """Half the prefetch: the broker keeps streaming the next batch while one is settled."""
        self._deliver: Deliver | None = None
        self._pump: Pump[Delivered] | None = None
        """The engine's read loop (engine/endpoints/pump.py), which reads, settles and acknowledges
        through :meth:`read_batch`, :meth:`inbounds` and :meth:`settle`."""
        self._parked = False
        """The batch loop waits for messages with none in hand (see :meth:`_on_message`)."""
        self._last_received_ns = 0
        self._alone_idle = asyncio.Event()
        """Set while no message is being settled alone in its consumer callback."""
        self._alone_idle.set()
        self._alone_task: asyncio.Task[Any] | None = None
        self._acks = HeldAcks(options.prefetch, lambda: self._last_received_ns, lambda: self._received.wake())
        """The acknowledgement held across batches (acks.py)."""
        self._resumption = Resumption(route, self.queue_name, options, connection.queue_type,
                                      connection.channel_factory, self._consume, self._declare)
        """Takes the subscription up again when the broker cancels it (resume.py)."""

    @property
    def queue_name(self) -> str:
        return self._options.queue or f"rabbitros.{self._route}"

    async def start(self, deliver: Deliver) -> None:
        options = self._options
        try:
            self._channel = await self._connection.channel_factory().channel()
            await self._channel.set_qos(prefetch_count=options.prefetch)
            self._queue = await self._declare(self._channel)
            self._deliver = deliver
            self._pump = Pump(self, deliver, f"route {self._route!r}, amqp queue {self.queue_name!r}", overlapping=True)
            self._loop = asyncio.create_task(self._run(self._pump), name=f"amqp-source:{self._route}")
            await self._consume()
            self._channel.reopen_callbacks.add(self._reconsume)
        except LIBRARY_ERRORS as exc:
            self._stopping = True
            self._received.close()
            raise edge_error(exc, f"route {self._route!r}: amqp source queue {self.queue_name!r}") from exc

    async def _declare(self, channel: aio_pika.abc.AbstractChannel) -> aio_pika.abc.AbstractQueue:
        """Declare what the source consumes (its queue, its exchange and binding) on ``channel``:
        at start, and again when the broker cancelled the subscription (resume.py)."""
        return await declare(channel, self.queue_name, self._options, self._connection.queue_type)

    async def _consume(self) -> None:
        """Consume on the channel's aiormq channel: no aio-pika message object or task per
        delivery; aio-pika still restores the channel, queue and bindings after a reconnect,
        and :meth:`_reconsume` then consumes again."""
        assert self._channel is not None
        channel = await self._channel.get_underlay_channel()
        _widen_frame_buffer(channel, min(FRAME_BUFFER, 3 * self._options.prefetch))
        result = await channel.basic_consume(self.queue_name, self._on_message, no_ack=False)
        tag = result.consumer_tag
        assert tag is not None  # the broker names the consumer it made (Basic.ConsumeOk)
        self._consumer = (channel, tag)
        self._resumption.watch(channel, tag)

    async def _reconsume(self, _channel: Any) -> None:
        if not self._stopping:
            await self._resumption.reopened()

    def degraded_reason(self) -> str | None:
        return self._resumption.reason

    def status(self) -> dict[str, Any]:
        return self._resumption.status()

    async def _on_message(self, message: aiormq.abc.DeliveredMessage) -> None:
        """A message arriving alone (at a robot's pace: more than :data:`ALONE_GAP_NS` after
        the one before, the batch loop idle with nothing queued, one batch at a time) is
        settled here, in aiormq's callback, as a batch of one; anything else is queued for the
        batch loop. Handing it to the loop cost a wake-up and a loop turn per message
        (25-56 us of CT-L1 measured, the largest stage after conversion and publish), which a
        message alone pays in full and a burst shares. Order and acknowledgement are the
        loop's: it takes nothing while a message is being settled here (it waits for it), and
        a message is only settled here while the loop waits with nothing in hand."""
        received_ns = time.monotonic_ns()
        alone = received_ns - self._last_received_ns > ALONE_GAP_NS
        self._last_received_ns = received_ns
        deliver = self._deliver
        if (alone and self._parked and self._alone_idle.is_set() and not self._received.items and not self._in_flight
                and not self._stopping and deliver is not None and deliver.batches_in_flight <= 1):
            await self._settle_alone(deliver, message, received_ns)
            return
        self._received.offer((message, received_ns))
        self._received.wake()

    async def _settle_alone(self, deliver: Deliver, message: aiormq.abc.DeliveredMessage, received_ns: int) -> None:
        self._alone_idle.clear()
        self._alone_task = asyncio.current_task()
        try:
            # acknowledged at once unless a burst's acknowledgement is held (a pause within a
            # drain on a loaded machine): it joins that one
            batch = [(message, received_ns)]
            assert self._pump is not None
            settled = await settle_batch(deliver, self.inbounds(batch), self._pump.where)
            await self._acks.acknowledge([message], settled, hold=self._acks.holding)
        finally:
            self._alone_task = None
            self._alone_idle.set()

    @property
    def _in_flight(self) -> int:
        """Batches in the route's sink beyond the one settled inline (:class:`Pump`)."""
        return self._pump.in_flight if self._pump is not None else 0

    async def _run(self, loop: Pump[Delivered]) -> None:
        """The engine's read loop, which may have several batches in flight (``overlapping``):
        acknowledging cumulatively in the order the batches were taken, a
        ``basic_ack(multiple=True)`` never covers a message of a batch not yet settled. Then
        what is held is acknowledged: a stop or reload leaves nothing settled unacknowledged."""
        try:
            await loop.run()
        except asyncio.CancelledError:
            # The engine stopped waiting (its drain timeout and grace are over): the loop gave
            # up the batches in their sink, and a message being settled alone is given up too;
            # the broker redelivers them once the channel closes.
            if self._alone_task is not None:
                self._alone_task.cancel()
            raise
        finally:
            if not self._alone_idle.is_set():  # settled or given up before the channel closes
                await self._alone_idle.wait()
            self._acks.cancel_timer()
            await self._acks.flush()

    async def read_batch(self) -> list[Delivered]:
        """What the consumer received, up to half the prefetch; while waiting for it, the held
        acknowledgement goes out once the source is idle (:meth:`_park`). Nothing is taken
        while a message is being settled alone: it came before these."""
        self._parked = True
        try:
            if not self._received.items:
                await self._park()
            batch = await self._received.take(self._max_batch)
        finally:
            self._parked = False
        if not self._alone_idle.is_set():
            await self._alone_idle.wait()
        return batch

    def inbounds(self, batch: Sequence[Delivered]) -> list[Inbound]:
        return [_inbound(message, received_ns) for message, received_ns in batch]

    async def settle(self, batch: Sequence[Delivered], settled: list[bool]) -> None:
        """The settled prefix joins the held ``multiple`` ack; the rest is acked or nacked with
        requeue one by one (acks.py)."""
        await self._acks.acknowledge([message for message, _ in batch], settled)

    async def _park(self) -> None:
        """Wait for the next message; once the source goes idle (none for acks.py's ``ACK_IDLE_NS``),
        send the acknowledgement held meanwhile. Only while no message is being settled alone
        nor a batch by the settler: every acknowledgement leaves from one place at a time, in
        order (a ``multiple`` ack sent after a later one would name a tag already acked, which
        closes the channel)."""
        received = self._received
        while not received.items and not received.closed:
            if self._acks.holding:
                if self._acks.due and self._alone_idle.is_set() and not self._in_flight:
                    self._parked = False  # a message arriving meanwhile is queued, not settled alone
                    try:
                        await self._acks.flush()
                    finally:
                        self._parked = True
                    continue
                self._acks.arm_timer()
            await received.arrival()

    async def reply(self, meta: Mapping[str, Any], kind: str, body: bytes) -> None:
        """The AMQP request/reply convention: to the default exchange, routing key = the
        request's ``reply_to``, with its ``correlation_id``; headers ``x-rabbitros-reply`` (the
        kind) and ``x-rabbitros-route``. Transient and not mandatory: a caller that is gone
        (RabbitMQ's direct reply-to ``amq.rabbitmq.reply-to.*`` when its channel closed) is not
        waited for. Published on the connection's confirm channel; accepted once confirmed."""
        properties = spec.Basic.Properties(
            content_type="application/json", correlation_id=meta.get("correlation_id"),
            headers={"x-rabbitros-reply": kind, "x-rabbitros-route": self._route}, delivery_mode=1)
        error = (await self._connection.publish_batch("", [(str(meta["reply_to"]), body, properties)], "direct"))[0]
        if error is not None:
            raise error

    async def stop(self) -> None:
        """Cancel the consumer, settle what was received, then close the channel so anything
        the broker sent but we did not take is requeued. An ``ordered`` (single active consumer)
        source does not cancel first: the broker would activate the next instance's consumer at
        once, and it would send newer messages while this one still sends the older ones in
        hand; closing the channel after settling requeues the rest in place, then hands over."""
        self._stopping = True
        await self._resumption.close()
        if self._consumer is not None and not self._options.ordered:
            channel, tag = self._consumer
            try:
                await channel.basic_cancel(tag)
            except LIBRARY_ERRORS:
                pass
        self._received.close()
        if self._loop is not None:
            await self._loop
        if self._channel is not None:
            try:
                await self._channel.close()
            except LIBRARY_ERRORS:
                pass


def _widen_frame_buffer(channel: aiormq.abc.AbstractChannel, frames: int) -> None:
    """Let ``channel`` hold ``frames`` frames (:data:`FRAME_BUFFER` says why). aio-pika opens
    its channels with aiormq's default and passes no ``frame_buffer_size``, so the bound of the
    channel's frame queue (an ``asyncio.Queue``, read on every ``put``) is raised here, before
    the first delivery, on every channel the source consumes on (a reconnect's too). A
    channel whose queue is not that (another aiormq) is left as it is."""
    queue = getattr(channel, "frames", None)
    if isinstance(queue, asyncio.Queue) and 0 < queue.maxsize < frames and hasattr(queue, "_maxsize"):
        queue._maxsize = frames


def _inbound(message: aiormq.abc.DeliveredMessage, received_ns: int) -> Inbound:
    """The message's meta, read off its ``Basic.Deliver`` frame and properties directly: a
    consumer is only ever given deliveries, and aiormq's ``routing_key``/``exchange``/
    ``redelivered`` properties check the frame's class on every read."""
    properties = message.header.properties
    delivery = cast(spec.Basic.Deliver, message.delivery)  # no check: see above
    headers = properties.headers
    return Inbound(
        body=message.body,
        meta={
            "routing_key": delivery.routing_key,
            "exchange": delivery.exchange,
            "message_id": properties.message_id,
            "correlation_id": properties.correlation_id,
            "reply_to": properties.reply_to,
            "headers": headers,
            "content_type": properties.content_type,
            "redelivered": delivery.redelivered,
            "cancel": headers.get("x-rabbitros-cancel") if headers else None,
        },
        received_ns=received_ns,
    )
