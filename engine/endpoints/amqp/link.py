"""An AMQP connection's link to the broker: one robust connection (aio-pika), the publish
channel every sink of the connection publishes on, the declare channel, dead letters, and the
health the status shows. The sources and sinks are made by the connection (connection.py),
and ask of this only what :class:`AmqpLink` offers publicly.

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
now reopens a fresh publish channel itself (:meth:`AmqpLink._reopen_publish_channel`,
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
import re
import ssl
import time
from datetime import datetime, timezone
from typing import Any, Mapping, Sequence
from urllib.parse import urlsplit

import aio_pika
import aio_pika.abc
import aiormq.exceptions
from aiormq import spec
from yarl import URL

import engine.endpoints.amqp.cluster as amqp_cluster
from engine.common import tls as tls_common
from engine.common.backoff import Backoff
from engine.common.redaction import redact_urls
from engine.endpoints.amqp.channels import open_plain_channel
from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error
from engine.endpoints.amqp.options import AmqpConnectionOptions, AmqpSourceOptions
from engine.endpoints.amqp.publisher import SharedPublisher
from engine.endpoints.base import Connection, DeadLetterReader, EndpointError, StoredLetter, typed

DEAD_LETTER_EXCHANGE = "rabbitros.dead-letter"
log = logging.getLogger("engine.amqp")


def redact(url: Any) -> str:
    """The URL with its password hidden, for logs and errors."""
    url = str(url)  # a Secret is already its redacted text
    try:
        parts = urlsplit(url)
    except ValueError:  # not a URL (an unbalanced "[" the route fuzz found): hide what could be a password
        return re.sub(r":[^:@/]*@", ":***@", url)
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


class AmqpLink(Connection):
    """One robust connection to the broker (a cluster's nodes in turn), its publish and declare
    channels, dead letters and leases; the base of :class:`~.connection.AmqpConnection`, which
    makes the routes' sources and sinks."""

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
                "returned": publisher.returned if publisher else 0,
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
        mandatory: bool = False,
    ) -> list[BaseException | None]:
        """Publish ``(routing_key, body, properties)`` on the confirm channel; ``result[i]`` is
        None once the broker took message i (``mandatory``: and routed it to a queue, else
        :class:`~engine.endpoints.base.Unroutable`). Every route's messages of one loop turn go
        out together, one write and one confirm wait (engine/endpoints/amqp/publisher.py)."""
        if self._state != "up":  # a robust channel would wait for the broker; the engine buffers instead
            error = EndpointError(f"amqp connection {self.name!r} is {self._state}: {self._last_error}")
            return [error] * len(messages)
        try:
            await self.declare_exchange(exchange_name, kind, durable)
        except LIBRARY_ERRORS as exc:
            error = edge_error(exc, f"amqp publish to {exchange_name!r} on {self.name!r}")
            return [error] * len(messages)
        assert self._publisher is not None
        return await self._publisher.publish(exchange_name, messages, mandatory)

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
        now = datetime.now(timezone.utc)
        batch = [
            (route, body, spec.Basic.Properties(headers=dict(headers), delivery_mode=2, timestamp=now))
            for body, headers in messages
        ]
        for error in await self.publish_batch(DEAD_LETTER_EXCHANGE, batch):
            if error is not None:
                raise error

    def lease(self, name: str, instance: str, heartbeat: float) -> amqp_cluster.AmqpLease:
        """The broker-held lease of an ``active_standby`` route (see :class:`AmqpLease`)."""
        return amqp_cluster.AmqpLease(self, name, instance, heartbeat, self.queue_type)

    def dead_letter_destination(self) -> str:
        return f"amqp connection {self.name!r}, queue rabbitros.dead-letter"

    async def dead_letter_reader(self) -> DeadLetterReader:
        return AmqpDeadLetterReader(self)

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


class AmqpDeadLetterReader(DeadLetterReader):
    """The queue ``rabbitros.dead-letter`` read with ``basic.get`` and no acknowledgement, on a
    channel of its own: a letter read is acknowledged (removed) only by :meth:`remove`; closing
    the channel hands every other one back to the queue, where it was (RabbitMQ requeues an
    unacknowledged message in its place in a classic queue; a quorum queue counts a delivery)."""

    def __init__(self, link: AmqpLink) -> None:
        self.link = link
        self._channel: Any = None

    async def read(self, limit: int) -> list[StoredLetter]:
        where = self.link.dead_letter_destination()
        try:
            self._channel = await open_plain_channel(self.link.channel_factory(), publisher_confirms=False)
            queue = await self._channel.declare_queue(DEAD_LETTER_EXCHANGE, passive=True)
            letters: list[StoredLetter] = []
            while len(letters) < limit:
                message = await queue.get(no_ack=False, fail=False)
                if message is None:
                    break
                at = message.timestamp.timestamp() if message.timestamp is not None else None
                letters.append(StoredLetter(message.body, dict(message.headers or {}), at, message, where))
            return letters
        except aiormq.exceptions.ChannelNotFoundEntity:
            return []  # no dead letter was ever stored here
        except LIBRARY_ERRORS as exc:
            raise edge_error(exc, f"{where}: cannot read the dead letters") from exc

    async def remove(self, letters: Sequence[StoredLetter]) -> None:
        try:
            for letter in letters:
                await letter.handle.ack()
        except LIBRARY_ERRORS as exc:
            raise edge_error(exc, f"{self.link.dead_letter_destination()}: cannot remove the dead letters") from exc

    async def close(self) -> None:
        if self._channel is not None and not self._channel.is_closed:
            try:
                await self._channel.close()
            except LIBRARY_ERRORS:
                pass  # the connection closes next: the broker requeues them all the same
