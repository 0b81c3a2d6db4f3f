"""AMQP 0-9-1 (RabbitMQ) endpoint on aio-pika (robust connections) and aiormq (hot path).

Batch-shaped, as a plain aiormq pass-through would be: a source's consumer callback only
appends to a list (unless the message arrives alone while the source is idle: it is then
settled in the callback, see ``AmqpSource._on_message``); one loop per source hands
everything received (up to half the prefetch; a backlog arrives about 100 messages at a
time, as the source's channel buffers :data:`FRAME_BUFFER` frames, not aiormq's 10) to the
route as one batch, then acknowledges with a single ``basic_ack(multiple=True)`` up to the
highest delivery tag whose whole prefix was settled (accepted by the sink or dead-lettered);
the rest of the batch is acked one by one or nacked with requeue. That ``multiple`` ack is held across batches while a
burst lasts and sent once it covers a quarter of the prefetch, once the source goes idle
(5 ms without a message), after 50 ms at most, and at a stop or reload
(``AmqpSource._acknowledge`` says why). Batches are acknowledged in order, so every earlier
tag is already acked or nacked and at-least-once holds: a crash redelivers instead of
losing. They are settled one at a time unless the route's sink declares it can send more
meanwhile (``Sink.batches_in_flight``: the JSON tunnel over a radio). Sinks publish on the
connection's channel with publisher confirms (configurable), every route's batch of a loop
turn in one shared round (one write, one confirm wait: engine/endpoints/amqp/publisher.py),
each route answered per message, so "accepted" means the broker took responsibility.

One robust connection per named connection is shared by all routes (aio-pika re-opens it,
its channels and consumers after a broker restart); each source has its own channel so its
prefetch and its stop are its own. Deliveries from a channel that has since been replaced
are not acked on the new one: the broker has requeued them already.

The publish channel is the connection's own, not a robust channel: the broker closes it on
its own (a publish to an exchange another client deleted: 404 NOT_FOUND), and aio-pika's
channel restore raced the publisher, which wrote the next round on the half-restored channel
before the restore's ``basic.qos`` returned; the second 404 failed the restore
(``ChannelNotFoundEntity``) and left the channel "not opened" for good: every route of the
connection failed from then on while its health said ``up``. The connection
now reopens a fresh publish channel itself (:meth:`AmqpConnection._reopen_publish_channel`,
the engine's one backoff between attempts), forgets the exchanges it declared (the next
publish declares its exchange again, as the first one did at start), and reports itself
``degraded`` with the broker's error meanwhile.

Exchanges are declared on a channel of their own (the *declare channel*, opened again at the
next declaration once the broker closed it): a declaration the broker refuses (406 an exchange
of that name and another type, 403 no permission) fails its route's messages, named by the
broker's text, and closes no channel another route publishes on. On the publish channel it
closed that channel, so every route's rounds in flight were published again.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from typing import Any, Callable, Iterable, Mapping, Sequence
from urllib.parse import urlsplit

import aio_pika
import aio_pika.abc
import aiormq.abc
import aiormq.exceptions
from aiormq import spec
from yarl import URL

from engine.common import tls as tls_common
from engine.common.backoff import Backoff
from engine.common.options import evolve, given
from engine.common.placeholders import MappingError, compile_template, template_fields, template_problem
from engine.common.redaction import Secret, has_url_password, redact_urls, reveal
from engine.common.schemas import SchemaError, canonical_bytes
from engine.endpoints.amqp.broker import CA_ENV, URL_ENV, URLS_ENV, elsewhere
from engine.endpoints.amqp.calls import AmqpCaller
from engine.endpoints.amqp.channels import open_plain_channel
import engine.endpoints.amqp.cluster as amqp_cluster
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error
from engine.endpoints.amqp.options import AmqpConnectionOptions, AmqpSinkOptions, AmqpSourceOptions
from engine.endpoints.amqp.publisher import SharedPublisher
import engine.endpoints.amqp.tls as amqp_tls
from engine.endpoints.base import (
    CheckResult,
    Connection,
    Deliver,
    EndpointError,
    Inbound,
    Inbox,
    MessageRejected,
    Outbound,
    Sink,
    Source,
    Transport,
    typed,
    typed_or_problem,
)

ALONE_GAP_NS = 1_000_000
"""A message received more than this after the previous one is taken to arrive alone (a
robot's pace: 100-200 msg/s is 5-10 ms apart) and, if the source is idle, settled in its
consumer callback (:meth:`AmqpSource._on_message`); closer together they are a burst, which
the batch loop takes in batches."""
ACK_IDLE_NS = 5_000_000
"""The source is idle once no message arrived for this long: the acknowledgement it holds
(see :meth:`AmqpSource._acknowledge`) goes out then. Its timer fires about once per this
while a burst lasts (at 1 ms it was 0.8 % of the engine's samples in a drain); a message at a
robot's pace (5-10 ms apart) does not wait for it: one settled alone is acknowledged at once."""
ACK_HOLD_NS = 50_000_000
"""The longest an acknowledgement is held while messages keep arriving (50 ms: at 6,000 msg/s
fewer messages than a quarter of the bench's prefetch, which flushes it first)."""
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
DEAD_LETTER_EXCHANGE = "rabbitros.dead-letter"
MAX_ROUTING_KEY = 255
"""Bytes in a routing key (an AMQP short string): a longer one can never be published."""
log = logging.getLogger("engine.amqp")


def redact(url: Any) -> str:
    """The URL with its password hidden, for logs and errors."""
    url = str(url)  # a Secret is already its redacted text
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return parts._replace(netloc=netloc).geturl()


CONNECT_TIMEOUT = 10.0
"""Seconds one attempt to open the connection may take (an unreachable host would otherwise
hold the engine's start for the TCP timeout, minutes)."""
REOPEN_FIRST_S = 0.05
REOPEN_CAP_S = 5.0
"""The engine's backoff (engine/common/backoff.py) between attempts to reopen the publish channel
after the broker closed it: the first attempt at once, then 25-50 ms, doubling up to 2.5-5 s.
A channel that lived :data:`REOPEN_CAP_S` or longer starts the backoff over."""


class AmqpConnection(Connection):
    keeps_dead_letters = True
    holds_leases = True

    settings: AmqpConnectionOptions

    def __init__(self, name: str, settings: AmqpConnectionOptions | Mapping[str, Any]) -> None:
        super().__init__(name, typed(AmqpConnectionOptions, settings, f"amqp connection {name!r}"))
        self._connection: aio_pika.abc.AbstractRobustConnection | None = None
        self._publish_channel: aio_pika.abc.AbstractChannel | None = None
        """The confirm channel every sink publishes on (a plain channel, reopened by this
        connection: module docstring); None while it is being reopened."""
        self._publisher: SharedPublisher | None = None
        """Every route's publishes on the publish channel, one round per loop turn."""
        self._exchanges: set[str] = set()
        """Exchanges declared since the current publish channel opened (forgotten when it
        closes: an exchange deleted behind the engine closed it, and is declared again)."""
        self._declare_channel: aio_pika.abc.AbstractChannel | None = None
        """Where exchanges are declared (module docstring); opened on demand."""
        self._declare_lock = asyncio.Lock()
        self._state = "connecting"
        self._link_up = False
        """The connection itself is open (aio-pika reconnects it)."""
        self._last_error: str | None = None
        self._tls: ssl.SSLContext | None = None
        self._reopening: asyncio.Task[None] | None = None
        self._reopen_backoff = Backoff(REOPEN_FIRST_S, REOPEN_CAP_S)
        self._publish_opened = 0.0
        """When (monotonic) the current publish channel was opened."""
        self.publish_channel_reopens = 0
        """Publish channels opened after the first (the status shows it)."""

    @property
    def url(self) -> str:
        return self.urls[0]

    @property
    def urls(self) -> list[str]:
        return amqp_cluster.connection_urls(self.settings)

    @property
    def queue_type(self) -> str | None:
        """The type of the queues this connection's routes declare unless they say otherwise."""
        return self.settings.queue_type

    @property
    def endpoint(self) -> str | None:
        """``host:port`` of the broker node in use (a cluster connection fails over)."""
        connection = self._connection
        return connection.endpoint if isinstance(connection, amqp_cluster.FailoverConnection) else None

    @property
    def healthy(self) -> bool:
        return self._state == "up"

    def health(self) -> dict[str, Any]:
        """``state``: up, connecting, reconnecting (the connection is lost; aio-pika reconnects
        it), degraded (the connection is up, its publish channel is being reopened: every sink
        and dead letter of the connection waits), down; ``last_error``: the last failure of either."""
        publisher = self._publisher
        return {"state": self._state, "last_error": self._last_error,
                "published": publisher.messages if publisher else 0, "publish_rounds": publisher.rounds if publisher else 0,
                "publish_channel_reopens": self.publish_channel_reopens}

    def _failed(self, error: BaseException | None) -> None:
        if error is not None:
            text = redact_urls(f"{type(error).__name__}: {error}")
            password = urlsplit(self.url).password
            text = text.replace(password, "***") if password else text
            failure = tls_common.tls_failure(error, self._expected_host()) if self._tls is not None else None
            self._last_error = f"TLS: {failure} ({text})" if failure else text

    def _expected_host(self) -> str | None:
        tls = self.settings.tls
        return (tls.server_hostname if tls is not None else None) or urlsplit(self.url).hostname

    def _connect_urls(self) -> list[str]:
        """The URLs as aiormq reads them: ``auth=external`` in the query for certificate login."""
        if self.settings.auth != "external":
            return self.urls
        return [str(URL(url).update_query(auth="external")) for url in self.urls]

    def _on_close(self, _connection: Any, error: BaseException | None = None) -> None:
        self._link_up = False
        if self._state in ("up", "degraded"):
            self._state = "reconnecting"
        self._failed(error)

    def _on_reconnect(self, _connection: Any) -> None:
        self._link_up = True
        if self._state != "down":
            self._state = "up" if self._publish_channel_open() else "degraded"

    def _publish_channel_open(self) -> bool:
        channel = self._publish_channel
        return channel is not None and not channel.is_closed

    async def _open_publish_channel(self) -> None:
        """A fresh confirm channel for the sinks, the publisher moved onto it. A plain
        ``aio_pika.Channel`` (public API) rather than the robust connection's ``channel()``:
        no restore of aio-pika's own races the publisher (module docstring)."""
        assert self._connection is not None
        channel = await open_plain_channel(self._connection, publisher_confirms=self.settings.publisher_confirms)
        channel.close_callbacks.add(self._on_publish_channel_close)
        if channel.is_closed:  # closed before its callback was there: nobody would reopen it
            raise aiormq.exceptions.ChannelInvalidStateError("the publish channel closed as it opened")
        self._exchanges = set()
        self._publish_channel = channel
        self._publish_opened = time.monotonic()
        if self._publisher is None:
            self._publisher = SharedPublisher(channel, self.name)
        else:
            self._publisher.replace(channel)

    def _on_publish_channel_close(self, channel: Any, error: BaseException | None = None) -> None:
        """The broker (or a lost connection) closed the publish channel: forget what was
        declared on it, say so in the health, and reopen it (not when the engine closes)."""
        if channel is not self._publish_channel:
            return
        self._publish_channel = None
        self._exchanges = set()
        if self._publisher is not None:
            self._publisher.replace(None)
        if self._state == "down" or self._connection is None:
            return
        if error is not None and not isinstance(error, asyncio.CancelledError):
            self._failed(error)
            log.warning("amqp publish channel closed; reopening it",
                        extra={"connection": self.name, "error": self._last_error})
        if self._state == "up":
            self._state = "degraded"
        if time.monotonic() - self._publish_opened >= REOPEN_CAP_S:
            self._reopen_backoff.reset()
        if self._reopening is None or self._reopening.done():
            self._reopening = asyncio.get_running_loop().create_task(
                self._reopen_publish_channel(), name=f"amqp-publish-channel:{self.name}")

    async def _reopen_publish_channel(self) -> None:
        """Open the publish channel again: once the connection is up (aio-pika reconnects a
        lost one), at once, then after each failed attempt the engine's backoff (each attempt
        bounded by :data:`CONNECT_TIMEOUT`), until it opens or the engine closes the connection."""
        delay = self._reopen_backoff.next() if self._reopen_backoff.failures else 0.0
        while self._state != "down" and self._connection is not None:
            if delay:
                await asyncio.sleep(delay)
            connection = self._connection
            if connection is None or self._state == "down":
                return
            await connection.ready()  # a lost connection: until aio-pika reconnected it
            if self._state == "down":
                return
            try:
                await self._open_publish_channel()
            except LIBRARY_ERRORS as exc:
                if self._link_up:  # the channel's own failure: the engine's backoff
                    self._failed(exc)
                    delay = self._reopen_backoff.next()
                else:  # the connection went (its close callback came first): wait for it, no backoff
                    delay = REOPEN_FIRST_S
                continue
            self.publish_channel_reopens += 1
            if self._state == "degraded" and self._link_up:
                self._state = "up"
            log.info("amqp publish channel reopened", extra={"connection": self.name})
            return

    async def open(self) -> None:
        nodes = ", ".join(redact(url) for url in self.urls)
        if any(url.lower().startswith("amqps://") for url in self.urls):
            try:  # read now, at every open: a renewed certificate is in effect from the reopen on
                self._tls = tls_common.tls_context(self.settings.tls)
            except ValueError as exc:
                self._state, self._last_error = "down", f"TLS: {exc}"
                raise EndpointError(f"amqp connection {self.name!r} ({nodes}): TLS: {exc}") from None
        try:
            self._connection = await amqp_cluster.connect_failover(
                self._connect_urls(),
                ssl_context=self._tls,
                client_properties={"connection_name": f"rabbitros-engine/{self.name}"},
                heartbeat=self.settings.heartbeat,
                reconnect_interval=self.settings.reconnect_interval,
                timeout=CONNECT_TIMEOUT,
            )
            self._connection.close_callbacks.add(self._on_close)
            self._connection.reconnect_callbacks.add(self._on_reconnect)
            self._link_up = True
            await self._open_publish_channel()
        except LIBRARY_ERRORS as exc:
            self._failed(exc)
            if self._connection is not None:
                await self.close()
            self._state = "down"
            raise EndpointError(f"amqp connection {self.name!r} ({nodes}): {self._last_error}") from exc
        self._state = "up"

    def channel_factory(self) -> aio_pika.abc.AbstractRobustConnection:
        if self._connection is None:
            raise EndpointError(f"amqp connection {self.name!r} is not open")
        return self._connection

    async def declare_exchange(self, name: str, kind: str = "topic", durable: bool = True) -> None:
        """Declare the exchange the sinks publish to (durable topic unless told), once per
        publish channel: a reopened channel declares again what its sinks publish to, as at
        start, so an exchange deleted behind the engine's back is there again. It is declared
        on the declare channel (module docstring), so a refusal closes no publish channel."""
        if name in self._exchanges:
            return
        async with self._declare_lock:
            if name in self._exchanges:
                return
            publishing = self._publish_channel
            if publishing is None:
                raise aiormq.exceptions.ChannelInvalidStateError(
                    f"the publish channel is being reopened ({self._last_error})")
            if name != "":  # the default exchange is always there
                channel = self._declare_channel
                if channel is None or channel.is_closed:
                    assert self._connection is not None
                    channel = await open_plain_channel(self._connection, publisher_confirms=False)
                    self._declare_channel = channel
                await channel.declare_exchange(name, aio_pika.ExchangeType(kind), durable=durable, timeout=CONNECT_TIMEOUT)
            if publishing is self._publish_channel:  # not one that closed meanwhile
                self._exchanges.add(name)

    async def publish_batch(
        self,
        exchange_name: str,
        messages: Sequence[tuple[str, bytes, spec.Basic.Properties]],
        kind: str = "topic",
        durable: bool = True,
    ) -> list[BaseException | None]:
        """Publish ``(routing_key, body, properties)`` on the confirm channel; ``result[i]`` is
        None once the broker took message i. Every route's messages of one loop turn go out
        together, one write and one confirm wait (engine/endpoints/amqp/publisher.py)."""
        if self._state != "up":  # a robust channel would wait for the broker; the engine buffers instead
            error = EndpointError(f"amqp connection {self.name!r} is {self._state}: {self._last_error}")
            return [error] * len(messages)
        try:
            await self.declare_exchange(exchange_name, kind, durable)
        except LIBRARY_ERRORS as exc:
            error = edge_error(exc, f"amqp publish to {exchange_name!r} on {self.name!r}")
            return [error] * len(messages)
        assert self._publisher is not None
        return await self._publisher.publish(exchange_name, messages)

    async def prepare_dead_letters(self, max_length: int | None) -> None:
        """The durable exchange and queue ``rabbitros.dead-letter`` (bounded by ``x-max-length``),
        so dead letters are kept even when nobody listens yet."""
        arguments = amqp_cluster.queue_arguments(
            AmqpSourceOptions(queue_arguments={"x-max-length": max_length} if max_length else {}), self.queue_type
        )
        try:
            await self.declare_exchange(DEAD_LETTER_EXCHANGE)
            channel = await self.channel_factory().channel()
            try:
                try:
                    queue = await channel.declare_queue(DEAD_LETTER_EXCHANGE, durable=True, arguments=arguments)
                except aiormq.exceptions.ChannelPreconditionFailed as exc:
                    log.warning("dead-letter queue exists with other arguments; keeping them",
                                extra={"connection": self.name, "error": str(exc)})
                    await channel.close()
                    channel = await self.channel_factory().channel()
                    queue = await channel.declare_queue(DEAD_LETTER_EXCHANGE, passive=True)
                await queue.bind(DEAD_LETTER_EXCHANGE, "#")
            finally:
                await channel.close()
        except LIBRARY_ERRORS as exc:
            raise edge_error(exc, f"amqp connection {self.name!r}: cannot declare the dead-letter queue") from exc

    async def dead_letter(self, route: str, messages: Sequence[tuple[bytes, Mapping[str, Any]]]) -> None:
        """One confirmed batch to ``rabbitros.dead-letter``, routing key = route name."""
        batch = [
            (route, body, spec.Basic.Properties(headers=dict(headers), delivery_mode=2))
            for body, headers in messages
        ]
        for error in await self.publish_batch(DEAD_LETTER_EXCHANGE, batch):
            if error is not None:
                raise error

    def source(self, route: str, options: AmqpSourceOptions | Mapping[str, Any]) -> Source:
        return AmqpSource(self, route, typed(AmqpSourceOptions, options, f"route {route!r}: amqp source"))

    def lease(self, name: str, instance: str, heartbeat: float) -> amqp_cluster.AmqpLease:
        """The broker-held lease of an ``active_standby`` route (see :class:`AmqpLease`)."""
        return amqp_cluster.AmqpLease(self, name, instance, heartbeat, self.queue_type)

    def dead_letter_destination(self) -> str:
        return f"amqp connection {self.name!r}, queue rabbitros.dead-letter"

    def sink(self, route: str, options: AmqpSinkOptions | Mapping[str, Any]) -> Sink:
        return AmqpSink(self, route, typed(AmqpSinkOptions, options, f"route {route!r}: amqp sink"))

    async def close(self) -> None:
        self._state = "down"
        reopening, self._reopening = self._reopening, None
        if reopening is not None and not reopening.done():
            reopening.cancel()
            await asyncio.gather(reopening, return_exceptions=True)
        if self._connection is not None:
            try:
                await self._connection.close()
            except LIBRARY_ERRORS:
                pass
            self._connection = None


class AmqpSource(Source):
    def __init__(self, connection: AmqpConnection, route: str, options: AmqpSourceOptions) -> None:
        self._connection = connection
        self._route = route
        self._options = options
        self._channel: aio_pika.abc.AbstractChannel | None = None
        self._queue: aio_pika.abc.AbstractQueue | None = None
        self._consumer: tuple[aiormq.abc.AbstractChannel, str] | None = None
        self._received: Inbox[tuple[aiormq.abc.DeliveredMessage, int]] = Inbox(1 << 30)
        """Bounded by the prefetch: the broker sends no more than that unacknowledged."""
        self._stopping = False
        self._loop: asyncio.Task[None] | None = None
        self._max_batch = max(1, options.prefetch // 2)
        """Half the prefetch: the broker keeps streaming the next batch while one is settled."""
        self._in_flight = 0
        """Batches handed to the route and not yet acknowledged, beyond the one settled inline."""
        self._room = asyncio.Event()
        self._deliver: Deliver | None = None
        self._parked = False
        """The batch loop waits for messages with none in hand (see :meth:`_on_message`)."""
        self._last_received_ns = 0
        self._alone_idle = asyncio.Event()
        """Set while no message is being settled alone in its consumer callback."""
        self._alone_idle.set()
        self._alone_task: asyncio.Task[Any] | None = None
        self._acks: dict[int, tuple[aiormq.abc.AbstractChannel, int]] = {}
        """Held acknowledgements: per channel, the highest delivery tag whose whole prefix was
        settled and not acknowledged yet (see :meth:`_acknowledge`)."""
        self._acks_held = 0
        """Messages the held acknowledgements cover."""
        self._acks_since_ns = 0
        """When the oldest of them was settled."""
        self._ack_every = max(1, options.prefetch // 4)
        """Held acknowledgements go out once they cover this many messages: the broker keeps
        three quarters of the prefetch streaming meanwhile."""
        self._ack_due = False
        """The source went idle (or :data:`ACK_HOLD_NS` passed): what is held goes out now."""
        self._ack_timer: asyncio.TimerHandle | None = None

    @property
    def queue_name(self) -> str:
        return self._options.queue or f"rabbitros.{self._route}"

    async def start(self, deliver: Deliver) -> None:
        options = self._options
        try:
            self._channel = await self._connection.channel_factory().channel()
            await self._channel.set_qos(prefetch_count=options.prefetch)
            self._queue = await self._channel.declare_queue(
                self.queue_name,
                durable=options.durable,
                arguments=amqp_cluster.queue_arguments(options, self._connection.queue_type, options.ordered),
            )
            if options.exchange:
                exchange = await self._channel.declare_exchange(
                    options.exchange,
                    aio_pika.ExchangeType(options.exchange_type),
                    durable=options.durable,
                )
                await self._queue.bind(exchange, options.binding_key)
            self._deliver = deliver
            self._loop = asyncio.create_task(self._run(deliver), name=f"amqp-source:{self._route}")
            await self._consume()
            self._channel.reopen_callbacks.add(self._reconsume)
        except LIBRARY_ERRORS as exc:
            self._stopping = True
            self._received.close()
            raise edge_error(exc, f"route {self._route!r}: amqp source queue {self.queue_name!r}") from exc

    async def _consume(self) -> None:
        """Consume on the channel's aiormq channel: no aio-pika message object or task per
        delivery; aio-pika still restores the channel, queue and bindings after a reconnect,
        and :meth:`_reconsume` then consumes again."""
        assert self._channel is not None
        channel = await self._channel.get_underlay_channel()
        _widen_frame_buffer(channel, min(FRAME_BUFFER, 3 * self._options.prefetch))
        result = await channel.basic_consume(self.queue_name, self._on_message, no_ack=False)
        self._consumer = (channel, result.consumer_tag)

    async def _reconsume(self, _channel: Any) -> None:
        if self._stopping:
            return
        try:
            await self._consume()
        except LIBRARY_ERRORS as exc:
            log.error("route %r: cannot consume %r again after reconnecting: %s", self._route, self.queue_name, exc)

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
            await self._acknowledge([message], await self._deliver_batch(deliver, [(message, received_ns)]),
                                    hold=bool(self._acks))
        finally:
            self._alone_task = None
            self._alone_idle.set()

    async def _run(self, deliver: Deliver) -> None:
        """Hand each batch to the route, then acknowledge it. While the route lets more than
        one batch be in flight (``deliver.batches_in_flight``, asked before each batch: a
        reload may swap the sink), the next batch is handed over while earlier ones await
        their sink, and a second task acknowledges them in the order they were taken, so
        ``basic_ack(multiple=True)`` never covers a message of a batch not yet settled. One
        at a time (most routes), a batch is settled and acknowledged here, with no task."""
        taken: asyncio.Queue[tuple[list[tuple[aiormq.abc.DeliveredMessage, int]], asyncio.Task[list[bool]]] | None]
        taken = asyncio.Queue()
        settler = asyncio.create_task(self._acknowledge_in_order(taken), name=f"amqp-settle:{self._route}")
        delivering: set[asyncio.Task[list[bool]]] = set()
        try:
            while True:
                while self._in_flight and self._in_flight >= deliver.batches_in_flight:
                    self._room.clear()
                    await self._room.wait()
                self._parked = True
                try:
                    if not self._received.items:
                        await self._park()
                    batch = await self._received.take(self._max_batch)
                finally:
                    self._parked = False
                if not self._alone_idle.is_set():  # a message settled alone came before these
                    await self._alone_idle.wait()
                if not batch:
                    break
                if not self._in_flight and deliver.batches_in_flight <= 1:
                    await self._acknowledge([message for message, _ in batch], await self._deliver_batch(deliver, batch))
                    continue
                self._in_flight += 1
                task = asyncio.create_task(self._deliver_batch(deliver, batch))
                delivering.add(task)
                task.add_done_callback(delivering.discard)
                taken.put_nowait((batch, task))
        except asyncio.CancelledError:
            # The engine stopped waiting (its drain timeout and grace are over): the batches
            # still in their sink are given up unsettled, as the one awaited inline above is,
            # and the broker redelivers them once the channel closes. Left running, they
            # would hold the stop until their sink answered (a tunnel with a silent vehicle:
            # never).
            for task in delivering:
                task.cancel()
            if self._alone_task is not None:
                self._alone_task.cancel()
            raise
        finally:
            if not self._alone_idle.is_set():  # settled or given up before the channel closes
                await self._alone_idle.wait()
            taken.put_nowait(None)
            await asyncio.gather(settler, return_exceptions=True)
            if self._ack_timer is not None:
                self._ack_timer.cancel()
                self._ack_timer = None
            await self._flush_acks()  # a stop or reload leaves nothing settled unacknowledged

    async def _park(self) -> None:
        """Wait for the next message; once the source goes idle (none for :data:`ACK_IDLE_NS`),
        send the acknowledgement held meanwhile. Only while no message is being settled alone
        nor a batch by the settler: every acknowledgement leaves from one place at a time, in
        order (a ``multiple`` ack sent after a later one would name a tag already acked, which
        closes the channel)."""
        received = self._received
        while not received.items and not received.closed:
            if self._acks:
                if self._ack_due and self._alone_idle.is_set() and not self._in_flight:
                    self._parked = False  # a message arriving meanwhile is queued, not settled alone
                    try:
                        await self._flush_acks()
                    finally:
                        self._parked = True
                    continue
                self._arm_ack_timer()
            await received.arrival()

    def _arm_ack_timer(self) -> None:
        if self._ack_timer is None:
            self._ack_timer = asyncio.get_running_loop().call_later(ACK_IDLE_NS / 1e9, self._ack_idle)

    def _ack_idle(self) -> None:
        """The timer :meth:`_park` armed: is the source idle (or the hold over)? Then wake it."""
        self._ack_timer = None
        if not self._acks:
            return
        now = time.monotonic_ns()
        quiet = now - self._last_received_ns
        if quiet >= ACK_IDLE_NS or now - self._acks_since_ns >= ACK_HOLD_NS:
            self._ack_due = True
            self._received.wake()
        else:
            self._ack_timer = asyncio.get_running_loop().call_later((ACK_IDLE_NS - quiet) / 1e9, self._ack_idle)

    async def _deliver_batch(self, deliver: Deliver, batch: list[tuple[aiormq.abc.DeliveredMessage, int]]) -> list[bool]:
        try:
            return await deliver.batch([_inbound(message, received_ns) for message, received_ns in batch])
        except Exception as exc:  # a bug in the engine must not lose messages: requeue them
            log.exception("route %r: settling a batch failed", self._route, exc_info=exc)
            return [False] * len(batch)

    async def _acknowledge_in_order(self, taken: asyncio.Queue[Any]) -> None:
        """Acknowledge the batches in flight in the order they were taken (see :meth:`_run`)."""
        while (item := await taken.get()) is not None:
            batch, settling = item
            settled = await settling
            await self._acknowledge([message for message, _ in batch], settled)
            self._in_flight -= 1
            self._room.set()

    async def _acknowledge(self, messages: list[aiormq.abc.DeliveredMessage], settled: list[bool],
                           hold: bool = True) -> None:
        """The settled prefix of the batch joins the held acknowledgement: one
        ``basic_ack(multiple=True)`` per channel, sent once it covers a quarter of the
        prefetch, once the source goes idle (:meth:`_park`), after :data:`ACK_HOLD_NS`, at
        once for a message settled alone with nothing held (``hold`` False: at a robot's pace
        every message is alone), and before anything else is acked or nacked: single acks and
        requeueing nacks for the rest of the batch, after it, so no frame names a tag a later
        ``multiple`` ack already covered. Only settled messages are ever acked.

        Why held: a batch is whatever arrived since the last one, a few messages when the
        route keeps up with the broker (3,960 batches for 13,200 messages measured before
        :data:`FRAME_BUFFER`, and still small whenever the engine is faster than the stream),
        and an ack per batch was a tenth of the engine's CPU time in py-spy (a frame, a writer
        task wake-up and a socket write each), besides the broker's own work per ack; held,
        ~2 %. The cost: a crash (not a stop or reload, which send what is held) redelivers up
        to a quarter of the prefetch more messages that had reached the sink, within the
        at-least-once contract a crash already has."""
        prefix = 0
        while prefix < len(settled) and settled[prefix]:
            prefix += 1
        acks = self._acks
        if prefix:
            if not acks:
                self._acks_since_ns = time.monotonic_ns()
            first, last = messages[0], messages[prefix - 1]
            if first.channel is last.channel:
                acks[id(last.channel)] = (last.channel, last.delivery_tag)
            else:  # the batch spans a reconnect: the old channel's tags are requeued by the broker anyway
                for message in messages[:prefix]:
                    acks[id(message.channel)] = (message.channel, message.delivery_tag)
            self._acks_held += prefix
        if acks and (not hold or prefix < len(messages) or self._ack_due or self._acks_held >= self._ack_every
                     or time.monotonic_ns() - self._acks_since_ns >= ACK_HOLD_NS):
            await self._flush_acks()
        elif acks:
            self._arm_ack_timer()  # the settler's batches too, while the loop may be parked already
        for message, ok in zip(messages[prefix:], settled[prefix:]):
            if ok:
                await _settle_frame(message.channel.basic_ack, message.delivery_tag)
            else:
                await _settle_frame(message.channel.basic_nack, message.delivery_tag, requeue=True)

    async def _flush_acks(self) -> None:
        """Send the held acknowledgement (one ``multiple`` ack per channel)."""
        self._ack_due = False
        if not self._acks:
            return
        acks, self._acks, self._acks_held = self._acks, {}, 0
        for channel, tag in acks.values():
            await _settle_frame(channel.basic_ack, tag, multiple=True)

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
        the broker sent but we did not take is requeued."""
        self._stopping = True
        if self._consumer is not None:
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
    delivery = message.delivery
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


async def _settle_frame(method: Any, tag: int | None, **kwargs: Any) -> None:
    """An ack or nack queued for the connection's writer, not waited for (``wait=False``):
    the source moves on to its next batch at once instead of sleeping until the frame is on
    the socket (a loop round trip per batch, which at a robot's pace is one per message).
    Frames leave in the order they were queued; one lost with its connection changes nothing,
    as the broker requeues whatever was not acknowledged."""
    try:
        await method(tag, wait=False, **kwargs)
    except LIBRARY_ERRORS:
        pass  # the channel is gone: the broker requeues whatever was not acked


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

    def __init__(self, connection: AmqpConnection, route: str, options: AmqpSinkOptions) -> None:
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


def _secret(url: str) -> str | Secret:
    return Secret(url) if has_url_password(url) else url


class AmqpTransport(Transport):
    name = "amqp"
    connection_type = AmqpConnection
    default_settings = {"url": "amqp://guest:guest@localhost:5672/"}
    replies = True
    accepts_secrets = True
    connection_options = AmqpConnectionOptions
    source_options = AmqpSourceOptions
    sink_options = AmqpSinkOptions
    connection_shorthand = "url"
    source_meta = ("routing_key", "exchange", "headers", "correlation_id", "reply_to", "message_id")

    def connection_problems(self, options: AmqpConnectionOptions) -> CheckResult:
        problems = list(amqp_cluster.check_urls(options, redact))
        yield from problems
        if not problems:
            yield from amqp_tls.tls_problems(options, amqp_cluster.connection_urls(options))

    def key_files(self, settings: AmqpConnectionOptions | Mapping[str, Any]) -> Iterable[str]:
        """The TLS files: a renewed certificate or CA changes the connection's fingerprint,
        and the reload the watcher starts reopens the connection with it."""
        options, _ = typed_or_problem(AmqpConnectionOptions, settings)
        return amqp_tls.key_files(options) if options is not None else []

    def source_problems(self, options: AmqpSourceOptions, mapping: str | None) -> CheckResult:
        written = given(options)
        if "queue" not in written and "exchange" not in written:
            yield None, "an amqp source needs a queue, an exchange, or both"
        if "binding_key" in written and not options.exchange:
            yield "binding_key", "binding_key needs an exchange to bind to"
        if "exchange_type" in written and not options.exchange:
            yield "exchange_type", "exchange_type is not used without an exchange to declare"
        yield from amqp_cluster.check_queue(options)

    def sink_problems(self, options: AmqpSinkOptions, mapping: str | None) -> CheckResult:
        written = given(options)
        if "exchange" not in written and "routing_key" not in written:
            yield None, "an amqp sink needs an exchange and/or a routing_key"
        problem = template_problem(options.routing_key)
        if problem:
            yield "routing_key", problem
        for key in ("exchange_type", "durable"):
            if key in written and not options.exchange:
                yield key, f"{key} is not used: the default exchange is never declared (name an exchange)"

    async def source_retired(
        self, connection: Connection, route: str, options: Mapping[str, Any],
        remaining: Iterable[tuple[str, Mapping[str, Any]]],
    ) -> None:
        from engine.endpoints.amqp.topology import retire_source

        await retire_source(connection, route, options, remaining)

    def canonical_fields(self, options: AmqpSinkOptions) -> Iterable[tuple[str, str]]:
        return [("routing_key", name) for name in template_fields(options.routing_key)]

    def default_connection_settings(self, env: Mapping[str, str]) -> Mapping[str, Any]:
        """``RABBITROS_AMQP_URL`` (``--local-broker`` sets it), else localhost; a local cluster
        (``--local-broker --cluster N`` sets ``RABBITROS_AMQP_URLS``): every node, replicated queues;
        ``RABBITROS_AMQP_CA_FILE`` (``--local-broker-tls`` sets it): the CA the node's TLS
        certificate is verified against."""
        cluster = env.get(URLS_ENV, "").split()
        if cluster:
            return {"urls": [_secret(url) for url in cluster], "queue_type": "quorum"}
        ca_file = env.get(CA_ENV)
        return {"url": _secret(env.get(URL_ENV, self.default_settings["url"])), **({"tls": {"ca_file": ca_file}} if ca_file else {})}

    def private_broker_warning(self, settings: AmqpConnectionOptions, env: Mapping[str, str]) -> str | None:
        private = env.get(URLS_ENV, "").split() or [env.get(URL_ENV, "")]
        urls = [reveal(url) for url in ([settings.url] if settings.url else settings.urls or ())]
        other = elsewhere(urls, private)
        if not other:
            return None
        return (f"names its own broker ({', '.join(redact_urls(url) for url in other)}), so {{private}} does not serve it "
                "and its routes use that broker; to use the private node, write the URL as "
                f"\"${{{URL_ENV}:-<the URL>}}\", or leave the connection out")

    def redelivers(self, options: AmqpSourceOptions) -> bool:
        """The broker requeues what the engine did not acknowledge."""
        return True

    supports_ordered = True
    shares_sources = True

    def ordered_source(self, options: AmqpSourceOptions) -> AmqpSourceOptions:
        """A single active consumer: one instance at a time consumes the queue, in order."""
        return evolve(options, ordered=True)

    def sink_dry_run(self, route: str, options: AmqpSinkOptions) -> Callable[[Outbound], str | None]:
        render = compile_template(options.routing_key)

        def routing_key(outbound: Outbound) -> str | None:
            try:
                return render(outbound.template_data)
            except MappingError as exc:
                raise MessageRejected(str(exc)) from None

        return routing_key

    def competing_consumers(self, route: str, options: AmqpSourceOptions) -> str | None:
        queue = options.queue
        return f"queue {queue!r}" if queue else None

    def connect(self, name: str, settings: AmqpConnectionOptions | Mapping[str, Any]) -> Connection:
        return AmqpConnection(name, settings)


TRANSPORT = AmqpTransport()
