"""The MQTT connection's client side: one client, one session, shared by every route that names it.

aiomqtt (on paho-mqtt 2) runs the socket on the engine's event loop; this module keeps the
connection up (a new client per attempt, waits from engine/common/backoff.py), and owns every
QoS 1 message the broker sent until it is acknowledged:

- **Manual acknowledgement.** paho's ``manual_ack`` is on: a PUBACK goes out only once every
  route the message was handed to settled it (delivered or dead-lettered), on the session
  the message came from. A message from a session that has since been lost is never acked
  on the next one (its packet identifier may name another message there): a persistent
  session gets it again from the broker.
- **Dispatch.** Messages reach the source whose subscription matched: by the MQTT 5
  subscription identifier (stable per filter, see topics.subscription_id), or by matching
  the topic against the filters (3.1.1). With a persistent session the broker resends what
  was unacknowledged, and sends what it queued meanwhile, right after CONNACK, before any
  route has started; such messages are *held* (unacknowledged) until the source they match
  registers. Held messages that no source claims for UNROUTED_GRACE_S after the last
  source started (a subscription a removed route left in the session) are acknowledged and
  counted as ``unrouted``, so they cannot fill the broker's in-flight window for good.
- **Redelivery.** MQTT cannot hand a message back to the broker on a live connection, so a
  stopping source returns what it did not settle here, and the connection gives it to the
  route's next source (a reload's replacement) or holds it.

aiomqtt has no API for manual acknowledgement yet (aiomqtt#345, PR #346), nor for the CONNACK
flags; :func:`_paho` is the one place that reaches the paho client under it for those, as the
maintainers' workaround does. Messages are taken from paho's ``on_message`` directly: a
callback that appends to the source's list, batch-shaped like the AMQP source (aiomqtt's
message iterator costs a task per message).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import ssl
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence
from urllib.parse import unquote, urlsplit

import aiomqtt
import paho.mqtt.client as paho_mqtt
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from engine.common.backoff import Backoff
from engine.common.redaction import MASK, redact_urls, reveal
from engine.common.tls import LastTlsError, TlsOptions, tls_context, tls_failure
from engine.endpoints.base import Connection, EndpointError, typed
from engine.endpoints.mqtt.broker import CA_ENV, URL_ENV
from engine.endpoints.mqtt.errors import describe, edge_error, from_code, mapped
from engine.endpoints.mqtt.options import DEFAULT_URL, MqttConnectionOptions
from engine.endpoints.mqtt.presence import PublishedCounts, rendered
from engine.endpoints.mqtt.topics import subscription_id

log = logging.getLogger("engine.mqtt")

CONNECT_TIMEOUT = 10.0
"""Seconds for CONNACK (paho bounds the TCP connect itself, 5 s)."""
REQUEST_TIMEOUT = 10.0
"""Seconds for SUBACK and UNSUBACK."""
PUBLISH_TIMEOUT = 30.0
"""Seconds a batch waits for its PUBACKs before the rest count as failed (and are retried)."""
RECONNECT_FIRST_S, RECONNECT_CAP_S = 0.1, 2.0
"""Waits between reconnection attempts: a restarted broker is back within a second or two,
and a reconnect attempt costs one TCP connect."""
UNROUTED_GRACE_S = 30.0
SWEEP_INTERVAL_S = 1.0
SESSION_TAKEN_OVER = 0x8E
SCHEMES = {"mqtt": (1883, False), "tcp": (1883, False), "mqtts": (8883, True), "ssl": (8883, True)}


@dataclass(frozen=True)
class Endpoint:
    """Where and as whom to connect, from the url and the options (options win)."""

    host: str
    port: int
    tls: bool
    username: str | None
    password: str | None = field(repr=False)

    @classmethod
    def parse(cls, settings: MqttConnectionOptions) -> Endpoint:
        url = reveal(settings.url) if settings.url is not None else os.environ.get(URL_ENV) or DEFAULT_URL
        parts = urlsplit(url)
        if parts.scheme not in SCHEMES or not parts.hostname:
            raise ValueError(f"url {redact_urls(url)!r}: expected mqtt://host[:port] or mqtts://host[:port]")
        default_port, tls = SCHEMES[parts.scheme]
        return cls(
            parts.hostname, parts.port or default_port, tls,
            settings.username if settings.username is not None else (unquote(parts.username) if parts.username else None),
            reveal(settings.password) if settings.password is not None else (unquote(parts.password) if parts.password else None),
        )

    def shown(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def broker_tls(settings: MqttConnectionOptions) -> TlsOptions | None:
    """The connection's ``tls``; for one that names no url (nor tls), the CA the environment
    names (:data:`CA_ENV`: the private mosquitto's under ``--local-broker-tls``), so it
    verifies the broker that environment points it at."""
    if settings.tls is None and settings.url is None and os.environ.get(CA_ENV):
        return TlsOptions(ca_file=os.environ[CA_ENV])
    return settings.tls


class Session:
    """One connected client (a new one per connection attempt) and what belongs to it alone:
    the packet identifiers of messages received and of publishes awaiting their PUBACK."""

    __slots__ = ("client", "paho", "present", "lost", "publishing")

    def __init__(self, client: aiomqtt.Client) -> None:
        self.client = client
        self.paho = _paho(client)
        self.present = False
        """The broker still had this client_id's session (CONNACK's session present flag)."""
        self.lost = asyncio.Event()
        self.publishing: dict[int, asyncio.Future[Any]] = {}


class Received:
    """A message the broker sent, until every route it was handed to has settled it."""

    __slots__ = ("message", "topic", "session", "routes", "received_ns", "held_at")

    def __init__(self, message: paho_mqtt.MQTTMessage, topic: str, session: Session) -> None:
        self.message = message
        self.topic = topic
        self.session = session
        self.routes: set[str] = set()
        self.received_ns = time.monotonic_ns()
        self.held_at = 0.0


class Subscriber(Protocol):
    """What the link needs of a source (engine/endpoints/mqtt/source.py) to hand it messages."""

    route: str
    filter: str
    subscription_id: int
    matches: Callable[[str], bool]

    @property
    def qos(self) -> int: ...

    def claims(self, received: Received) -> bool: ...

    def offer(self, received: Received) -> None: ...


def _paho(client: aiomqtt.Client) -> paho_mqtt.Client:
    """The paho client under aiomqtt's (see the module docstring for why)."""
    return client._client  # noqa: SLF001


class MqttLink(Connection):
    """Everything of the connection but making its sources and sinks (connection.py)."""

    settings: MqttConnectionOptions

    def __init__(self, name: str, settings: MqttConnectionOptions | Mapping[str, Any]) -> None:
        super().__init__(name, typed(MqttConnectionOptions, settings, f"mqtt connection {name!r}"))
        try:
            self._broker = Endpoint.parse(self.settings)  # not ``endpoint``: the status shows that attribute
        except ValueError as exc:
            raise EndpointError(f"mqtt connection {name!r}: {exc}") from None
        self.where = f"mqtt connection {name!r} ({self._broker.shown()})"
        self._client_log = logging.getLogger(f"engine.mqtt.client.{name}")
        self._tls_log = LastTlsError.on(self._client_log)
        self.v5 = self.settings.protocol == 5
        self.persistent = self.settings.client_id is not None
        self.max_batch = max(1, self.settings.receive_maximum // 2)
        """Half the in-flight window: the broker keeps sending while a batch is settled."""
        self._session: Session | None = None
        self._state = "connecting"
        self._last_error: str | None = None
        self._closing = False
        self._keeper: asyncio.Task[None] | None = None
        self._sources: dict[str, Subscriber] = {}
        self._by_id: dict[int, list[Subscriber]] = {}
        self._held: deque[tuple[Received, str | None]] = deque()
        self._last_registration = time.monotonic()
        self._unrouted = 0
        self._warned: set[str] = set()
        self._published = PublishedCounts((self.settings.will, self.settings.on_stop))
        """For the will's and on_stop's ``{next}`` (presence.py)."""

    # -- health

    @property
    def healthy(self) -> bool:
        return self._state == "up"

    def health(self) -> dict[str, Any]:
        out: dict[str, Any] = {"state": self._state, "last_error": self._last_error,
                               "session": "persistent" if self.persistent else "clean"}
        if self._held:
            out["held"] = len(self._held)
        if self._unrouted:
            out["unrouted"] = self._unrouted
        return out

    def _failed(self, error: BaseException) -> None:
        text = describe(error)
        password = self._broker.password
        text = text.replace(password, MASK) if password else text
        tls = self.settings.tls
        failure = None
        if self._broker.tls:
            failure = tls_failure(error, (tls.server_hostname if tls else None) or self._broker.host, self._tls_log.text)
        self._last_error = f"TLS: {failure} ({text})" if failure else text

    # -- connecting and staying connected

    async def open(self) -> None:
        """Connect once (EndpointError if the broker cannot be reached: the engine retries),
        then keep the connection up in the background."""
        if self._keeper is not None and not self._keeper.done():
            return
        self._closing = False
        try:
            await self._connect()
        except EndpointError as error:
            self._state = "down"
            self._failed(error.__cause__ or error)
            raise
        self._keeper = asyncio.create_task(self._keep(), name=f"mqtt-keep:{self.name}")

    def _tls_context(self) -> ssl.SSLContext:
        """Read the TLS files now, at every connection: a renewed certificate is in effect from
        the reopen on. A file that cannot be read is transient (it may be being renewed)."""
        self._tls_log.text = ""  # what paho logs about this attempt only
        try:
            return tls_context(broker_tls(self.settings))
        except ValueError as exc:
            raise EndpointError(f"{self.where}: TLS: {exc}") from None

    def _client(self) -> aiomqtt.Client:
        settings, endpoint = self.settings, self._broker
        arguments: dict[str, Any] = {}
        if self.v5:
            properties = Properties(PacketTypes.CONNECT)
            properties.SessionExpiryInterval = settings.session_expiry if self.persistent else 0
            properties.ReceiveMaximum = settings.receive_maximum
            arguments.update(clean_start=not self.persistent, properties=properties)
        else:
            arguments.update(clean_session=not self.persistent)
        will = settings.will
        if will is not None:  # filled now: the broker keeps the will as it was at CONNECT
            arguments["will"] = aiomqtt.Will(will.topic, rendered(will, self._published.next(will.topic)), will.qos, will.retain)
        return aiomqtt.Client(
            endpoint.host, endpoint.port,
            identifier=settings.client_id,
            protocol=aiomqtt.ProtocolVersion.V5 if self.v5 else aiomqtt.ProtocolVersion.V311,
            keepalive=settings.keepalive,
            username=endpoint.username, password=endpoint.password,
            tls_context=self._tls_context() if endpoint.tls else None,
            timeout=CONNECT_TIMEOUT,
            logger=self._client_log,
            **arguments,
        )

    async def _connect(self) -> None:
        with mapped(self.where):
            client = self._client()
        session = Session(client)
        self._wire(session)
        try:
            with mapped(self.where):
                await client.__aenter__()
        except EndpointError:
            with contextlib.suppress(Exception):
                session.paho.disconnect()
            raise
        self._session = session
        self._state = "up"
        if not session.present:  # a clean session, or the broker forgot ours: subscribe again
            for filter_, qos in self._subscriptions().items():
                try:
                    await self._subscribe(session, filter_, qos)
                except EndpointError as error:
                    log.error("cannot subscribe again after reconnecting",
                              extra={"connection": self.name, "error": str(error)})
        else:  # what the broker resends now came on this session; older copies are stale
            self._held = deque(item for item in self._held if item[0].session is session)

    def _wire(self, session: Session) -> None:
        paho = session.paho
        paho.manual_ack_set(True)
        # aiomqtt set them, with paho's version 2 signatures (paho types them as either version's)
        on_connect: Callable[..., None] | None = paho.on_connect
        on_disconnect: Callable[..., None] | None = paho.on_disconnect
        on_publish: Callable[..., None] | None = paho.on_publish
        assert on_connect is not None and on_disconnect is not None and on_publish is not None

        def connected(client: Any, userdata: Any, flags: Any, reason: Any, properties: Any = None) -> None:
            session.present = bool(flags.session_present)
            on_connect(client, userdata, flags, reason, properties)

        def disconnected(client: Any, userdata: Any, flags: Any, reason: Any, properties: Any = None) -> None:
            on_disconnect(client, userdata, flags, reason, properties)
            self._lost(session, reason)

        def published(client: Any, userdata: Any, mid: int, reason: Any, properties: Any = None) -> None:
            on_publish(client, userdata, mid, reason, properties)
            future = session.publishing.pop(mid, None)
            if future is not None and not future.done():
                future.set_result(reason)

        paho.on_connect = connected
        paho.on_disconnect = disconnected
        paho.on_publish = published
        paho.on_message = lambda _client, _userdata, message: self._on_message(session, message)

    def _lost(self, session: Session, reason: Any) -> None:
        if session.lost.is_set():
            return
        session.lost.set()
        lost = EndpointError(f"{self.where}: connection lost before the broker acknowledged ({reason})")
        for future in session.publishing.values():
            if not future.done():
                future.set_exception(lost)
        session.publishing.clear()
        if session is self._session and not self._closing:
            self._state = "reconnecting"
            self._last_error = f"connection lost: {reason}"
            if getattr(reason, "value", None) == SESSION_TAKEN_OVER:
                self._last_error += f" (another client connected with client_id {self.settings.client_id!r}: two engines with one client_id?)"

    async def _keep(self) -> None:
        """Reconnect whenever the session is lost, until :meth:`close`; held messages that no
        source claims are released meanwhile."""
        while not self._closing:
            session = self._session
            assert session is not None
            try:
                await asyncio.wait_for(session.lost.wait(), SWEEP_INTERVAL_S)
            except asyncio.TimeoutError:
                self._sweep()
                continue
            with contextlib.suppress(Exception):  # releases aiomqtt's lock; the socket is gone
                await asyncio.wait_for(session.client.__aexit__(None, None, None), 1.0)
            backoff = Backoff(RECONNECT_FIRST_S, RECONNECT_CAP_S)
            while not self._closing:
                await asyncio.sleep(backoff.next())
                try:
                    await self._connect()
                except EndpointError as error:
                    self._failed(error.__cause__ or error)
                    continue
                log.info("connection restored", extra={"connection": self.name})
                break

    async def close(self) -> None:
        """Disconnect cleanly (the broker then drops the will), after publishing ``on_stop``."""
        await self._say_goodbye()
        self._closing = True
        self._state = "down"
        if self._keeper is not None:
            self._keeper.cancel()
            await asyncio.gather(self._keeper, return_exceptions=True)
            self._keeper = None
        session, self._session = self._session, None
        if session is not None and not session.lost.is_set():
            with contextlib.suppress(Exception):
                await asyncio.wait_for(session.client.__aexit__(None, None, None), REQUEST_TIMEOUT)

    async def _say_goodbye(self) -> None:
        """Publish ``on_stop`` and wait for its acknowledgement (at most REQUEST_TIMEOUT): a
        connection that is down says nothing (its will was published, or will be)."""
        message = self.settings.on_stop
        if message is None or self._state != "up":
            return
        where = f"{self.where}: on_stop"
        try:
            [error] = await asyncio.wait_for(
                self.publish_batch([(message.topic, rendered(message, self._published.next(message.topic)))], message.qos,
                                   message.retain, where), REQUEST_TIMEOUT)
        except TimeoutError:
            error = EndpointError(f"{where}: no acknowledgement within {REQUEST_TIMEOUT:.0f} s")
        if error is not None:
            log.warning("on_stop message not published", extra={"connection": self.name, "error": str(error)})

    # -- receiving

    def _on_message(self, session: Session, message: paho_mqtt.MQTTMessage) -> None:
        try:
            topic = message.topic
        except UnicodeDecodeError:
            topic = repr(message._topic)  # noqa: SLF001  (the broker should have refused it)
        received = Received(message, topic, session)
        sources = self._sources_for(received)
        if not sources:
            received.held_at = time.monotonic()
            self._held.append((received, None))
            return
        for source in sources:
            received.routes.add(source.route)
        for source in sources:
            source.offer(received)

    def _sources_for(self, received: Received) -> list[Subscriber]:
        properties = received.message.properties
        ids = getattr(properties, "SubscriptionIdentifier", None) if properties is not None else None
        if ids:
            by_id = self._by_id
            return [source for sid in ids for source in by_id.get(sid, ())]
        topic = received.topic
        return [source for source in self._sources.values() if source.matches(topic)]

    def settled(self, received: Received, route: str) -> None:
        """``route`` settled ``received``; the last route to do so acknowledges it."""
        routes = received.routes
        routes.discard(route)
        if not routes:
            self._acknowledge(received)

    def _acknowledge(self, received: Received) -> None:
        message, session = received.message, received.session
        if message.qos and session is self._session and not session.lost.is_set():
            session.paho.ack(message.mid, message.qos)

    def returned(self, route: str, messages: Iterable[Received]) -> None:
        """Messages a stopping source of ``route`` did not settle: to the route's current
        source if a reload already started one, else held for the next."""
        current = self._sources.get(route)
        now = time.monotonic()
        for received in messages:
            if current is not None:
                current.offer(received)
            else:
                received.held_at = now
                self._held.append((received, route))

    def _sweep(self) -> None:
        """Release held messages nobody claimed within the grace (see the module docstring)."""
        now = time.monotonic()
        if not self._held or now - self._last_registration < UNROUTED_GRACE_S:
            return
        kept: deque[tuple[Received, str | None]] = deque()
        for received, route in self._held:
            if now - received.held_at < UNROUTED_GRACE_S:
                kept.append((received, route))
            elif route is not None:  # its route is gone: it was settled as far as anyone can
                self.settled(received, route)
            else:
                self._unrouted += 1
                self._acknowledge(received)
                if received.topic not in self._warned and len(self._warned) < 100:
                    self._warned.add(received.topic)
                    log.warning("message matches no route; acknowledged and dropped (a subscription "
                                "a removed route left in the persistent session?)",
                                extra={"connection": self.name, "topic": received.topic})
        self._held = kept

    # -- subscriptions

    def _subscriptions(self) -> dict[str, int]:
        """Each filter the registered sources need, with the highest QoS any of them asks."""
        out: dict[str, int] = {}
        for source in self._sources.values():
            out[source.filter] = max(out.get(source.filter, 0), source.qos)
        return out

    async def register(self, source: Subscriber) -> None:
        """Subscribe for ``source`` (it replaces an earlier source of its route) and give it
        the held messages that are its."""
        previous = self._sources.get(source.route)
        self._sources[source.route] = source
        self._index()
        self._last_registration = time.monotonic()
        session = self._session
        if session is not None and not session.lost.is_set():  # else subscribed on reconnecting
            try:
                await self._subscribe(session, source.filter, self._subscriptions()[source.filter])
            except EndpointError:
                if self._sources.get(source.route) is source:
                    if previous is None:
                        del self._sources[source.route]
                    else:
                        self._sources[source.route] = previous
                    self._index()
                raise
        mine = [r for r, route in self._held if route == source.route or (route is None and source.claims(r))]
        if mine:
            self._held = deque(item for item in self._held if item[0] not in mine)
            for received in mine:
                received.routes.add(source.route)
                source.offer(received)

    def unregister(self, source: Subscriber) -> None:
        if self._sources.get(source.route) is source:
            del self._sources[source.route]
            self._index()

    def _index(self) -> None:
        by_id: dict[int, list[Subscriber]] = {}
        for source in self._sources.values():
            by_id.setdefault(source.subscription_id, []).append(source)
        self._by_id = by_id

    async def _subscribe(self, session: Session, filter_: str, qos: int) -> None:
        where = f"{self.where}: subscribe {filter_!r}"
        if self.v5:
            options: SubscribeOptions | None = SubscribeOptions(
                qos=qos, retainHandling=SubscribeOptions.RETAIN_SEND_IF_NEW_SUB)
            identified = Properties(PacketTypes.SUBSCRIBE)
            identified.SubscriptionIdentifier = subscription_id(filter_)
            properties: Properties | None = identified
            request_qos = 0  # paho takes the QoS from the options then
        else:
            options, properties, request_qos = None, None, qos
        with mapped(where):
            codes = await session.client.subscribe(filter_, request_qos, options, properties, timeout=REQUEST_TIMEOUT)
        for code in codes:
            error = from_code(code, where) if not isinstance(code, int) else (
                EndpointError(f"{where}: the broker refused it") if code >= 0x80 else None)
            if error is not None:
                raise error

    async def unsubscribe(self, filter_: str, route: str, keep_subscription: bool = False) -> None:
        """``route`` is gone for good: let go of its held messages and remove ``filter_`` from
        the session unless ``keep_subscription`` (another configured route uses it)."""
        mine = [item for item in self._held if item[1] == route]
        if mine:
            self._held = deque(item for item in self._held if item[1] != route)
            for received, _ in mine:
                self.settled(received, route)
        if keep_subscription or filter_ in self._subscriptions():
            return
        session = self._session
        if session is None or session.lost.is_set():
            return
        with mapped(f"{self.where}: unsubscribe {filter_!r}"):
            await session.client.unsubscribe(filter_, timeout=REQUEST_TIMEOUT)

    # -- publishing

    async def publish_batch(
        self, messages: Sequence[tuple[str, bytes]], qos: int, retain: bool, where: str,
    ) -> list[BaseException | None]:
        """Publish ``(topic, payload)`` pipelined and await the broker's acknowledgements
        together (PUBACK at QoS 1, PUBCOMP at 2; at QoS 0, the write); ``result[i]`` is None
        once message i was accepted, else its edge error."""
        session = self._session
        if self._state != "up" or session is None or session.lost.is_set():
            return [EndpointError(f"{where}: {self.where} is {self._state}: {self._last_error}")] * len(messages)
        loop = asyncio.get_running_loop()
        results: list[BaseException | None] = [None] * len(messages)
        waiting: dict[int, asyncio.Future[Any]] = {}
        paho = session.paho
        for index, (topic, payload) in enumerate(messages):
            try:
                info = paho.publish(topic, payload, qos, retain)
            except Exception as exc:  # the table decides (an invalid topic is permanent)
                results[index] = edge_error(exc, f"{where}: publish on {topic!r}")
                continue
            error = from_code(info.rc, f"{where}: publish on {topic!r}")
            if error is not None:
                results[index] = error
                continue
            if info.is_published():
                continue
            future = session.publishing.get(info.mid)
            if future is None:
                future = session.publishing[info.mid] = loop.create_future()
            waiting[index] = future
        if waiting:
            _, pending = await asyncio.wait(waiting.values(), timeout=PUBLISH_TIMEOUT)
            for index, future in waiting.items():
                if future in pending:
                    future.cancel()
                    results[index] = EndpointError(f"{where}: no acknowledgement from {self.where} within {PUBLISH_TIMEOUT:.0f} s")
                elif future.exception() is not None:
                    results[index] = future.exception()
                else:
                    results[index] = from_code(future.result(), f"{where}: publish on {messages[index][0]!r}")
        self._published.count(messages, results)
        return results
