"""A source's subscription the broker cancelled, taken up again.

The broker cancels a consumer on its own when the queue goes (an operator deletes it, a queue
policy's ``x-expires``, a node failover of a non-replicated queue): RabbitMQ sends
``basic.cancel`` (the ``consumer_cancel_notify`` capability aiormq announces) and delivers
nothing more on that consumer. aiormq logs ``Consumer ... cancelled by the broker`` and calls
the channel's ``on_consumer_cancel_callbacks``; nothing else happens, so a source without this
said ``running``, ``/healthz`` answered 200, and when the queue was declared and bound again it
had 0 consumers: the route never consumed again.

:class:`Resumption` watches every channel its source consumes on; on a cancel it marks the
source degraded (:attr:`Resumption.reason`, shown in the route's status and in ``/healthz``),
declares again what the route declares (:func:`declare`: the queue, the exchange, the binding)
and consumes again, at once and then after each failed attempt with the engine's one backoff
(engine/common/backoff.py), until it consumes or the source stops. Declarations are made on a
plain channel of their own, opened for each attempt: a declaration the broker refuses (406 an
exchange of that name and another type, 403 no permission) closes that channel only, never the
source's (aio-pika would restore the source's robust channel, re-declaring what it remembers,
and fail again in a loop of its own). The same loop takes over when consuming again after a
reconnect fails (before, that was one log line and a dead source).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Awaitable, Callable

import aio_pika
import aio_pika.abc
import aiormq.abc

import engine.endpoints.amqp.cluster as amqp_cluster
from engine.common.backoff import Backoff
from engine.endpoints.amqp.channels import open_plain_channel
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error, ignored
from engine.endpoints.amqp.options import AmqpSourceOptions

log = logging.getLogger("engine.amqp")


async def declare(channel: aio_pika.abc.AbstractChannel, queue: str, options: AmqpSourceOptions,
                  queue_type: str | None) -> aio_pika.abc.AbstractQueue:
    """Declare what a source with ``options`` declares: its queue and, with an exchange, the
    exchange and the queue's binding to it."""
    declared = await channel.declare_queue(
        queue, durable=options.durable,
        arguments=amqp_cluster.queue_arguments(options, queue_type, options.ordered))
    if options.exchange:
        exchange = await channel.declare_exchange(
            options.exchange, aio_pika.ExchangeType(options.exchange_type), durable=options.durable)
        await declared.bind(exchange, options.binding_key)
    return declared


class Resumption:
    """Takes a source's subscription up again after the broker cancelled it (module docstring).

    ``consume`` consumes the queue again on the source's own channel (and calls :meth:`watch`
    with the new consumer); ``connection`` gives the robust connection the declarations'
    channels are opened on; ``declaration``, if given, declares instead of :func:`declare`."""

    def __init__(self, route: str, queue: str, options: AmqpSourceOptions, queue_type: str | None,
                 connection: Callable[[], aio_pika.abc.AbstractConnection], consume: Callable[[], Awaitable[None]],
                 declaration: Callable[[aio_pika.abc.AbstractChannel], Awaitable[Any]] | None = None) -> None:
        self._route = route
        self._queue = queue
        self._options = options
        self._queue_type = queue_type
        self._connection = connection
        self._consume = consume
        self._declaration = declaration
        """What the source declares (default :func:`declare` of its options); a partition's
        source declares its whole partitioned topology (partitions.py)."""
        self._consumer_tag: str | None = None
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        self._backoff = Backoff()
        self.reason: str | None = None
        """Why the source is not consuming (None while it is)."""
        self.cancels = 0
        """Subscriptions the broker cancelled."""
        self.resumed = 0
        """Subscriptions taken up again."""
        self.last_cancel: str | None = None
        """The last cancel and when (UTC), kept once it is taken up again: what happened meanwhile."""

    @property
    def resuming(self) -> bool:
        return self._task is not None and not self._task.done()

    def watch(self, channel: aiormq.abc.AbstractChannel, consumer_tag: str | None) -> None:
        """Hear of the broker's cancel of ``consumer_tag`` on ``channel`` (once per channel: a
        set of callbacks, the same bound method)."""
        self._consumer_tag = consumer_tag
        channel.on_consumer_cancel_callbacks.add(self._on_cancel)

    def _on_cancel(self, frame: Any) -> None:
        if self._closed or frame.consumer_tag != self._consumer_tag:
            return
        self.cancels += 1
        self.last_cancel = (f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}: the broker cancelled the consumer of "
                            f"queue {self._queue!r} (deleted, or its node went)")
        self.lost(f"the broker cancelled the consumer of queue {self._queue!r} (deleted, or its node went); "
                  "declaring it again")

    def lost(self, reason: str) -> None:
        """The source consumes no more: say why, and take its subscription up again."""
        if self._closed:
            return
        self.reason = reason
        log.warning("amqp source not consuming; taking it up again",
                    extra={"route": self._route, "queue": self._queue, "reason": reason})
        if not self.resuming:
            self._task = asyncio.get_running_loop().create_task(self._take_up(), name=f"amqp-resume:{self._route}")

    async def reopened(self) -> None:
        """The source's channel was reopened (a reconnect): consume on it again, unless the loop
        is taking the subscription up (it consumes on the new channel itself)."""
        if self._closed or self.resuming:
            return
        try:
            await self._consume()
        except LIBRARY_ERRORS as exc:
            self.lost(f"cannot consume queue {self._queue!r} again after reconnecting: {edge_error(exc, 'consume')}")

    async def _take_up(self) -> None:
        first = self.reason
        while not self._closed:
            try:
                await self._declare()
                await self._consume()
            except LIBRARY_ERRORS as exc:
                self.reason = f"{first}; failed: {edge_error(exc, 'declare and consume')}"
                await asyncio.sleep(self._backoff.next())
                continue
            self._backoff.reset()
            self.reason = None
            self.resumed += 1
            log.info("amqp source consuming again", extra={"route": self._route, "queue": self._queue})
            return

    async def _declare(self) -> None:
        channel = await open_plain_channel(self._connection(), publisher_confirms=False)
        try:
            if self._declaration is not None:
                await self._declaration(channel)
            else:
                await declare(channel, self._queue, self._options, self._queue_type)
        finally:
            with ignored():
                await channel.close()

    def status(self) -> dict[str, Any]:
        return {"consuming": self.reason is None, "cancelled_by_broker": self.cancels, "taken_up_again": self.resumed,
                "last_cancel": self.last_cancel}

    async def close(self) -> None:
        self._closed = True
        task, self._task = self._task, None
        if task is not None and not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
