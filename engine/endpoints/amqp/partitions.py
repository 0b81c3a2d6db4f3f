"""Partitioned ordered routes on RabbitMQ (``ordered: {partitions: S, key: ...}``).

``ordered: true`` keeps a route's order by letting one engine instance at a time consume its
queue (single active consumer, SAC): order and scale-out exclude each other. Most routes need
order only per agent, so a partitioned route splits the stream by agent:

* **Topology** (:func:`declare_partitions`): a consistent-hash exchange (``x-consistent-hash``,
  the ``rabbitmq_consistent_hash_exchange`` plugin of rabbitmq-server 3.10) bound to the
  source's exchange with its ``binding_key`` (an exchange-to-exchange binding), feeding S
  queues ``rabbitros.<route>.p0`` .. ``p<S-1>`` (``<queue>.p<i>`` when the source names its
  queue), each bound with weight 1 and declared with ``x-single-active-consumer``. The
  exchange hashes the routing key (the cheap default: the publisher puts the agent in it,
  ``telemetry.robot7``) or, with ``key: headers.NAME``, that header (the exchange's
  ``hash-header`` argument). One key always lands in one partition, and a queue is FIFO.
  A key in the body would need a first hop that republishes with it as routing key (a route
  whose sink has ``routing_key: "{agent_id}"``): one more publish and consume per message, so
  it is left to the route file instead of hidden here.
* **Queue type**: classic, whatever the connection's ``queue_type``. When the active consumer
  of a classic queue dies, the broker puts its unacknowledged messages back at their places
  and only then activates the next consumer (one queue process does both), so the next
  instance starts with the oldest message. RabbitMQ 3.10 quorum queues may hand a dead
  consumer's returned messages out after newer ones (rabbitmq-server#6804): a quorum
  ``queue_type`` is refused at check (:func:`partition_problems`). The price: a classic queue
  lives on one node; losing that node stops its partitions (durable queues, persistent
  messages come back with the node) where a quorum queue would fail over.
* **Consumers**: every instance consumes all S queues (:class:`PartitionConsumer`, an
  :class:`~engine.endpoints.amqp.source.AmqpSource` per partition on a channel of its own), so
  when an instance dies the broker activates a waiting consumer of each of its partitions at
  once, with no coordination in the way.
* **Spreading** (:class:`PartitionedSource`): RabbitMQ 3.10 makes the first registered
  consumer active, so the first instance started would carry every partition. Each instance
  publishes, every :data:`REBALANCE_PERIOD`, a small probe straight to every partition queue
  (default exchange, transient, expiring) naming itself and how many partitions it is active
  on. The broker delivers a queue's messages to its active consumer only, so an instance
  learns it is active on a partition from the first message it gets there (probe or data),
  and the instances active somewhere hear everyone's counts. The number of instances is the
  queues' consumer count (a passive ``queue.declare``). An instance active on more than
  ceil(S / instances), or the busiest one (ties: the smallest name) while another is active on
  none, hands one partition over: it stops taking from it, lets what it took settle and
  acknowledges it, then closes that partition's channel (the broker requeues what it had sent
  but the engine had not taken, in order, and activates the next consumer in line) and
  consumes again at the back of the line. Closing, not ``basic.cancel``: a cancelled SAC
  consumer keeps its unacknowledged messages while the next one already receives newer
  ones. One hand-over at a time per instance, then two periods for the counts to follow.

Probes are acknowledged with the data, in order, and never reach the route.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import socket
import time
import uuid
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Mapping, cast

import aio_pika
import aio_pika.abc
import aiormq.abc
import aiormq.exceptions

import engine.endpoints.amqp.cluster as amqp_cluster
from engine.common.options import evolve
from engine.endpoints.amqp.channels import open_plain_channel
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error, ignored
from engine.endpoints.amqp.link import AmqpLink
from engine.endpoints.amqp.options import AmqpSourceOptions
from engine.endpoints.amqp.source import AmqpSource, Delivered
from engine.endpoints.base import Deliver, EndpointError, Inbound, Source

log = logging.getLogger("engine.amqp")

REBALANCE_PERIOD = 1.0
"""Seconds between an instance's probes and its look at the spread. A dead instance's partitions
move at once (the broker); this bounds how soon a new or surviving instance gets its share."""
PEER_EXPIRY = 3 * REBALANCE_PERIOD
"""A peer not heard of for this long is gone (its probes also expire after this)."""
PROBE_HEADER = "x-rabbitros-partition-probe"
"""Names the instance that sent a probe; a message with it never reaches the route."""
ACTIVE_HEADER = "x-rabbitros-partitions-active"
SENT_HEADER = "x-rabbitros-probe-sent"
HASH_WEIGHT = "1"
"""Every partition queue is bound with the same weight: an equal share of the hash ring."""
HEADERS_PREFIX = "headers."

_HANDOVER = cast(Delivered, (None, 0))
"""Queued behind what a partition consumer received to make its read loop hand the partition over."""


def hash_header(key: str) -> str | None:
    """The header a ``headers.NAME`` key hashes, or None (the routing key)."""
    return key[len(HEADERS_PREFIX):] if key.startswith(HEADERS_PREFIX) and len(key) > len(HEADERS_PREFIX) else None


def partition_problems(options: AmqpSourceOptions, key: str) -> Iterator[tuple[str | None, str]]:
    """What ``check`` refuses of a partitioned AMQP source (see the module docstring)."""
    if not options.exchange:
        yield None, ("partitions need the source's exchange (amqp: {exchange: NAME}, not the default exchange ''): "
                     "the broker hashes each message on its way from that exchange to the partitions' queues")
    if key != "routing_key" and hash_header(key) is None:
        yield "key", (f"{key!r} is not routing_key or headers.NAME (to partition by a field of the body, republish it "
                      "first with a route whose amqp sink has routing_key: '{agent_id}')")
    if amqp_cluster.queue_type(options, None) == "quorum":
        yield None, ("partitions are classic queues: the source's queue_type quorum is refused (RabbitMQ 3.10 quorum queues "
                     "may hand a dead consumer's messages out after newer ones, rabbitmq-server#6804, which breaks the order "
                     "each partition keeps)")


def base_name(route: str, options: AmqpSourceOptions) -> str:
    return options.queue or f"rabbitros.{route}"


def partition_queue(route: str, options: AmqpSourceOptions, index: int) -> str:
    return f"{base_name(route, options)}.p{index}"


def hash_exchange(route: str, options: AmqpSourceOptions) -> str:
    """The route's consistent-hash exchange, named after its key: RabbitMQ compares only an
    exchange's type and flags on a new declaration, not its ``hash-header``, so a changed key
    under the same name would go on hashing the old one without a word."""
    header = hash_header(options.partition_key)
    return f"{base_name(route, options)}.partitions" + (f".header.{header}" if header else "")


def partition_arguments(options: AmqpSourceOptions) -> dict[str, Any]:
    """A partition queue's arguments: the source's own, classic, single active consumer."""
    arguments = amqp_cluster.queue_arguments(evolve(options, queue_type="classic"), None, single_active=True) or {}
    return {**arguments, "x-queue-type": "classic"}


async def declare_partitions(channel: aio_pika.abc.AbstractChannel, route: str,
                             options: AmqpSourceOptions) -> list[aio_pika.abc.AbstractQueue]:
    """Declare the hash exchange, its binding from the source's exchange and the partition
    queues bound to it (idempotent: every instance, and every partition at its start, does)."""
    header = hash_header(options.partition_key)
    name = hash_exchange(route, options)
    try:
        hashing = await channel.declare_exchange(name, aio_pika.ExchangeType.X_CONSISTENT_HASH, durable=options.durable,
                                                 arguments={"hash-header": header} if header else None)
    except aiormq.exceptions.ConnectionCommandInvalid as exc:
        raise EndpointError(f"route {route!r}: the broker has no x-consistent-hash exchange type for exchange {name!r} "
                            f"(rabbitmq-plugins enable rabbitmq_consistent_hash_exchange): {exc}") from exc
    except aiormq.exceptions.ChannelPreconditionFailed as exc:
        raise EndpointError(f"route {route!r}: exchange {name!r} exists with another type or key (ordered.key changed?); "
                            "a partitioned route's key cannot change in place: drain the route and delete the exchange "
                            f"(rabbitmqctl eval or the management UI), or give the route a new name: {exc}") from exc
    if options.exchange:
        source = await channel.declare_exchange(options.exchange, aio_pika.ExchangeType(options.exchange_type),
                                                durable=options.durable)
        await hashing.bind(source, options.binding_key)
    queues = []
    arguments = partition_arguments(options)
    for index in range(options.partitions):
        queue = await channel.declare_queue(partition_queue(route, options, index), durable=options.durable, arguments=arguments)
        await queue.bind(hashing, HASH_WEIGHT)
        queues.append(queue)
    return queues


async def retire_partitions(factory: Any, route: str, options: AmqpSourceOptions,
                            remaining: Iterable[tuple[str, AmqpSourceOptions]]) -> dict[str, list[str]]:
    """Undo what a stopped partitioned source made and no remaining source needs (topology.py
    for plain sources): the partitions beyond a successor's count (4 -> 2: p2 and p3 would
    otherwise keep taking their share of keys with no consumer), its exchange-to-exchange
    binding, and its hash exchange unless a successor hashes through it (same key). An emptied
    partition queue is deleted, one still holding messages is unbound and kept (reported):
    nothing is lost."""
    name = hash_exchange(route, options)
    successors = [(r, o) for r, o in remaining if o.partitions > 1 and base_name(r, o) == base_name(route, options)]
    count = max((o.partitions for _, o in successors), default=0)
    same_exchange = [o for r, o in successors if hash_exchange(r, o) == name]
    done: dict[str, list[str]] = {"unbound": [], "deleted": [], "kept": []}
    channel = await factory().channel()
    try:
        for index in range(count, options.partitions):
            queue = partition_queue(route, options, index)
            try:
                if channel.is_closed:
                    channel = await factory().channel()
                declared = await channel.declare_queue(queue, passive=True)
                await declared.unbind(name, HASH_WEIGHT)
                done["unbound"].append(f"{queue} <- {name}")
                await declared.delete(if_unused=False, if_empty=True)
                done["deleted"].append(queue)
            except LIBRARY_ERRORS as exc:  # still holding messages (PRECONDITION_FAILED), or gone
                done["kept"].append(f"{queue}: {exc}")
        with ignored():
            if channel.is_closed:
                channel = await factory().channel()
            if not same_exchange:  # its bindings, to the queues and from the source's exchange, go with it
                await channel.exchange_delete(name)
                done["deleted"].append(name)
            elif options.exchange and all((o.exchange, o.binding_key) != (options.exchange, options.binding_key)
                                          for o in same_exchange):
                hashing = await channel.get_exchange(name, ensure=True)
                await hashing.unbind(options.exchange, options.binding_key)
                done["unbound"].append(f"{name} <- {options.exchange} [{options.binding_key}]")
    finally:
        with ignored():
            await channel.close()
    if any(done.values()):
        log.info("amqp partitions follow the routes", extra={"route": route, **done})
    return done


def _is_probe(message: aiormq.abc.DeliveredMessage | None) -> bool:
    headers = message.header.properties.headers if message is not None else None
    return bool(headers) and PROBE_HEADER in cast(Mapping[str, Any], headers)


def _text(value: Any) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else str(value)


class PartitionConsumer(AmqpSource):
    """One partition's queue, consumed on a channel of its own (the channel is what a hand-over
    closes). Knows whether the broker made it the queue's active consumer (:attr:`active`)."""

    def __init__(self, group: PartitionedSource, connection: AmqpLink, route: str, options: AmqpSourceOptions,
                 index: int) -> None:
        self.index = index
        self._group = group
        super().__init__(connection, route, options)
        self.active = False
        """The broker sent this consumer a message since it last (re)consumed: it is the queue's
        active consumer until its channel goes (SAC never moves the role otherwise)."""
        self.handing_over = False
        self.handovers = 0
        self.taken = 0
        """Messages of this partition handed to the route (probes not counted): the keys' skew."""
        self._retired: weakref.WeakSet[Any] = weakref.WeakSet()
        """Channels this consumer closed: a delivery still arriving from one is the broker's again."""

    @property
    def queue_name(self) -> str:
        return partition_queue(self._route, self._options, self.index)

    async def _declare(self, channel: aio_pika.abc.AbstractChannel) -> aio_pika.abc.AbstractQueue:
        return (await declare_partitions(channel, self._route, self._options))[self.index]

    async def _consume(self) -> None:
        """Consume (again): on a new channel after a hand-over closed the last one; at the back
        of the queue's line of consumers, so not active until the broker says so."""
        if self._channel is None or self._channel.is_closed:
            self._channel = await self._connection.channel_factory().channel()
            await self._channel.set_qos(prefetch_count=self._options.prefetch)
            self._channel.reopen_callbacks.add(self._reconsume)
        self.active = False
        await super()._consume()

    async def _on_message(self, message: aiormq.abc.DeliveredMessage) -> None:
        if message.channel in self._retired:
            return  # requeued by the broker when the channel closed
        self.active = True
        if _is_probe(message):
            self._group.heard(cast(Mapping[str, Any], message.header.properties.headers))
            self._received.offer((message, time.monotonic_ns()))  # acknowledged in order with the data
            self._received.wake()
            return
        await super()._on_message(message)

    def hand_over(self) -> None:
        """Let the next consumer in line take this partition (done by the read loop, between batches)."""
        if self.handing_over or self._stopping:
            return
        self.handing_over = True
        self._received.offer(_HANDOVER)
        self._received.wake()

    async def read_batch(self) -> list[Delivered]:
        """The next batch of data; probes alone are acknowledged here, a hand-over is done here
        (the read loop has nothing of this partition in flight while it waits for this)."""
        while True:
            if self._stopping:
                return []
            batch = await super().read_batch()
            if not batch or self._stopping:
                return []
            if any(item is _HANDOVER for item in batch):
                await self._hand_over()
                continue
            # received on a channel that is gone (a reconnect): the broker requeued it, in order,
            # for whichever consumer it activated; sending it here could put it after newer ones
            batch = [item for item in batch if not item[0].channel.is_closed]
            if not batch:
                continue
            if all(_is_probe(message) for message, _ in batch):
                await self._acks.acknowledge([message for message, _ in batch], [True] * len(batch))
                continue
            return batch

    def inbounds(self, batch: Sequence[Delivered]) -> list[Inbound]:
        """The data of a batch (read here or settled alone), without the probes."""
        data = super().inbounds([item for item in batch if not _is_probe(item[0])])
        self.taken += len(data)
        return data

    async def settle(self, batch: Sequence[Delivered], settled: list[bool]) -> None:
        outcomes = iter(settled)
        await super().settle(batch, [True if _is_probe(message) else next(outcomes) for message, _ in batch])

    async def _hand_over(self) -> None:
        """Acknowledge what was settled, close the channel (the broker requeues what it sent
        and the engine did not take, in order, then activates the next consumer), consume again."""
        with ignored():
            await self._acks.flush()
        if self._consumer is not None:
            self._retired.add(self._consumer[0])
        self._consumer = None
        self.active = False
        if self._channel is not None:
            with ignored():
                await self._channel.close()
        self._received.clear()
        self.handovers += 1
        self.handing_over = False
        log.info("partition handed over", extra={"route": self._route, "queue": self.queue_name})
        try:
            await self._consume()
        except LIBRARY_ERRORS as exc:
            self._resumption.lost(f"cannot consume partition {self.queue_name!r} again after handing it over: "
                                  f"{edge_error(exc, 'consume')}")

    async def stop(self) -> None:
        """Settle and acknowledge what is in hand, then close the channel without cancelling
        first (a cancelled SAC consumer's unacknowledged messages would follow newer ones the
        next consumer already got): what was received and not taken goes back in order."""
        self._stopping = True
        await self._resumption.close()
        self._received.close()
        if self._loop is not None:
            await self._loop
        if self._channel is not None:
            with ignored():
                await self._channel.close()


def should_hand_over(mine: int, partitions: int, instances: int, me: str, peers: Mapping[str, int]) -> bool:
    """Whether an instance active on ``mine`` of ``partitions`` hands one over, with
    ``instances`` consumers on the queues and ``peers`` (name: partitions it is active on, as
    its last probe said): when it has more than ceil(partitions / instances), or when another
    instance has none and this one is the busiest (ties: the smallest name, so that one of
    them moves) with more than one. RabbitMQ activates the next consumer in line, which may be
    a busy one that then hands over in turn; each hand-over sends its instance to the back of
    that queue's line, so the line turns until the idle instance is next: a few steps (the
    cluster test settles three instances in 4-6 s)."""
    if instances < 2 or mine == 0:
        return False
    if mine > math.ceil(partitions / instances):
        return True
    busiest = max([mine, *peers.values()])
    first_busiest = min([me, *(name for name, count in peers.items() if count == busiest)])
    return mine > 1 and mine == busiest and first_busiest == me and any(count == 0 for count in peers.values())


@dataclass
class Peer:
    active: int
    sent: float
    heard: float


class PartitionedSource(Source):
    """A partitioned route's source: a :class:`PartitionConsumer` per partition, and the loop
    that probes, counts the instances and hands a partition over when this instance has more
    than its share (module docstring)."""

    def __init__(self, connection: AmqpLink, route: str, options: AmqpSourceOptions) -> None:
        self._connection = connection
        self._route = route
        self.instance = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        """This source's name in probes (unique per start: a restarted engine is a new peer)."""
        self.partitions = [PartitionConsumer(self, connection, route, options, index) for index in range(options.partitions)]
        self.peers: dict[str, Peer] = {}
        self.instances = 1
        """Consumers of the partition queues: the instances sharing the route."""
        self.handovers = 0
        self._channel: aio_pika.abc.AbstractChannel | None = None
        self._task: asyncio.Task[None] | None = None
        self._quiet_until = 0.0

    async def start(self, deliver: Deliver) -> None:
        started: list[PartitionConsumer] = []
        try:
            for partition in self.partitions:
                await partition.start(deliver)
                started.append(partition)
        except BaseException:
            await asyncio.gather(*(partition.stop() for partition in started), return_exceptions=True)
            raise
        self._task = asyncio.create_task(self._rebalance(), name=f"amqp-partitions:{self._route}")

    @property
    def active(self) -> list[int]:
        return [partition.index for partition in self.partitions if partition.active]

    def heard(self, headers: Mapping[str, Any]) -> None:
        """A probe reached one of this instance's active partitions: its sender's count."""
        name = _text(headers.get(PROBE_HEADER, ""))
        if name == self.instance:
            return
        try:
            active, sent = int(headers.get(ACTIVE_HEADER, 0)), float(headers.get(SENT_HEADER, 0.0))
        except (TypeError, ValueError):
            return
        known = self.peers.get(name)
        if known is None or sent >= known.sent:
            self.peers[name] = Peer(active, sent, time.monotonic())

    async def _rebalance(self) -> None:
        while True:
            await asyncio.sleep(REBALANCE_PERIOD)
            try:
                channel = await self._plain_channel()
                await self._probe(channel)
                self.instances = await self._count(channel)
            except LIBRARY_ERRORS as exc:  # the connection is failing over: the broker keeps each partition with one consumer
                log.debug("partition probe failed", extra={"route": self._route, "error": str(exc)})
                self._channel = None
                continue
            self._spread()

    async def _plain_channel(self) -> aio_pika.abc.AbstractChannel:
        if self._channel is None or self._channel.is_closed:
            self._channel = await open_plain_channel(self._connection.channel_factory(), publisher_confirms=False)
        return self._channel

    async def _probe(self, channel: aio_pika.abc.AbstractChannel) -> None:
        headers: dict[str, Any] = {PROBE_HEADER: self.instance, ACTIVE_HEADER: len(self.active), SENT_HEADER: time.time()}
        for partition in self.partitions:
            await channel.default_exchange.publish(
                aio_pika.Message(b"", headers=headers, expiration=PEER_EXPIRY,
                                 delivery_mode=aio_pika.DeliveryMode.NOT_PERSISTENT), partition.queue_name)

    async def _count(self, channel: aio_pika.abc.AbstractChannel) -> int:
        counts = []
        for partition in self.partitions:
            queue = await channel.declare_queue(partition.queue_name, passive=True)
            counts.append(getattr(queue.declaration_result, "consumer_count", 0) or 0)
        return max(1, *counts)

    def _spread(self) -> None:
        """Hand one partition over if this instance has more than its share (module docstring)."""
        now = time.monotonic()
        if now < self._quiet_until or any(partition.handing_over for partition in self.partitions):
            return
        for name in [name for name, peer in self.peers.items() if now - peer.heard >= PEER_EXPIRY]:
            del self.peers[name]
        mine = [partition for partition in self.partitions if partition.active]
        if should_hand_over(len(mine), len(self.partitions), self.instances, self.instance,
                            {name: peer.active for name, peer in self.peers.items()}):
            mine[-1].hand_over()
            self.handovers += 1
            self._quiet_until = now + 2 * REBALANCE_PERIOD

    def status(self) -> dict[str, Any]:
        return {
            "partitions": len(self.partitions),
            "active": self.active,
            "instances": self.instances,
            "instance": self.instance,
            "peers": {name: peer.active for name, peer in self.peers.items()},
            "handovers": self.handovers,
            "taken": [partition.taken for partition in self.partitions],
            "consuming": all(partition.degraded_reason() is None for partition in self.partitions),
        }

    def degraded_reason(self) -> str | None:
        return next((reason for partition in self.partitions if (reason := partition.degraded_reason())), None)

    async def reply(self, meta: Mapping[str, Any], kind: str, body: bytes) -> None:
        await self.partitions[0].reply(meta, kind, body)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        await asyncio.gather(*(partition.stop() for partition in self.partitions))
        if self._channel is not None:
            with ignored():
                await self._channel.close()
