"""MQTT source: one subscription, messages handed to the route in batches, acknowledged
(PUBACK) once settled.

Batch-shaped like the AMQP source: the connection's message callback only appends to this
source's list; the engine's read loop (engine/endpoints/pump.py) hands everything received
(up to half the connection's ``receive_maximum``) to the route as one batch, then the source
tells the connection which messages were settled, which acknowledges each once every route it went
to has settled it. A message the route did not settle is tried again after a wait
(engine/common/backoff.py), or, when the source stops, returned to the connection for the route's
next source: MQTT has no way to hand a message back to the broker on a live connection.

QoS 1 messages are bounded by the broker's in-flight window (nothing more is sent until some
are acknowledged); QoS 0 messages are not, and a QoS 0 source cannot hold the broker back, so
beyond the route's queue limit they are dropped (the newest, or with ``overflow:
drop_oldest`` the oldest QoS 0 message) and counted.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import Any

from engine.common.backoff import Backoff
from engine.endpoints.base import Deliver, Inbound, Inbox, Source
from engine.endpoints.mqtt.link import MqttLink, Received
from engine.endpoints.mqtt.options import MqttSourceOptions
from engine.endpoints.mqtt.topics import capture_reader, matcher, subscription, subscription_id
from engine.endpoints.pump import pump


class MqttSource(Source):
    """One subscription of a route; a :class:`~engine.endpoints.base.BatchReader` of what the
    connection received for it."""

    def __init__(self, connection: MqttLink, route: str, options: MqttSourceOptions) -> None:
        self._connection = connection
        self.route = route
        self.qos = options.qos
        self.filter = subscription(options.topic, options.shared)
        self.subscription_id = subscription_id(self.filter)
        self.matches = matcher(self.filter)
        self._captures = capture_reader(options.topic)
        """``farm/{station}/weather``: each message's level there, as ``meta('station')`` (topics.py)."""
        self._v5 = connection.v5
        self._inbox: Inbox[Received] = Inbox(1 << 30)
        self._limit = 1 << 30
        self._drop_oldest = False
        self._deliver: Deliver | None = None
        self._loop: asyncio.Task[None] | None = None
        self._stopping = False
        self._returned: list[Received] = []
        self._backoff = Backoff()

    def claims(self, received: Received) -> bool:
        """True when ``received`` came for this source's subscription."""
        properties = received.message.properties
        ids = getattr(properties, "SubscriptionIdentifier", None) if properties is not None else None
        return self.subscription_id in ids if ids else self.matches(received.topic)

    async def start(self, deliver: Deliver) -> None:
        self._deliver = deliver
        self._limit = deliver.queue_limit
        self._drop_oldest = deliver.overflow == "drop_oldest"
        where = f"route {self.route!r}, mqtt subscription {self.filter!r}"
        self._loop = asyncio.create_task(pump(self, deliver, where), name=f"mqtt-source:{self.route}")
        try:
            await self._connection.register(self)
        except BaseException:
            self._stopping = True
            self._inbox.close()
            await asyncio.gather(self._loop, return_exceptions=True)
            raise

    def offer(self, received: Received) -> None:
        """Called by the connection for each message of this source (in the event loop)."""
        inbox = self._inbox
        if received.message.qos == 0 and len(inbox) >= self._limit:
            assert self._deliver is not None
            self._deliver.dropped(1)
            if not (self._drop_oldest and inbox.items[0].message.qos == 0):
                self._connection.settled(received, self.route)
                return
            self._connection.settled(inbox.items.popleft(), self.route)
        inbox.items.append(received)
        inbox.wake()

    async def read_batch(self) -> list[Received]:
        """Everything received, up to half the connection's ``receive_maximum``."""
        return await self._inbox.take(self._connection.max_batch)

    def inbounds(self, batch: Sequence[Received]) -> list[Inbound]:
        return [self._inbound(received) for received in batch]

    async def settle(self, batch: Sequence[Received], settled: list[bool]) -> None:
        """Settled messages are acknowledged through the connection; the rest are tried again
        after a wait, or, once stopping, kept for :meth:`stop` to return to the connection."""
        connection = self._connection
        again = []
        for received, ok in zip(batch, settled):
            if ok:
                connection.settled(received, self.route)
            else:
                again.append(received)
        if not again:
            self._backoff.reset()
        elif self._stopping:
            self._returned.extend(again)
        else:
            await asyncio.sleep(self._backoff.next())
            self._inbox.items.extendleft(reversed(again))

    def _inbound(self, received: Received) -> Inbound:
        message = received.message
        meta: dict[str, Any] = {"topic": received.topic, "qos": message.qos, "retain": bool(message.retain),
                                "redelivered": bool(message.dup)}
        if self._captures is not None:
            meta.update(self._captures(received.topic))
        if self._v5 and message.properties is not None:
            properties = message.properties
            content_type = getattr(properties, "ContentType", None)
            if content_type is not None:
                meta["content_type"] = content_type
            user = getattr(properties, "UserProperty", None)
            if user:
                meta["headers"] = dict(user)
        payload = message.payload  # bytes from paho (aiomqtt's type allows a bytearray)
        return Inbound(body=payload if isinstance(payload, bytes) else bytes(payload), meta=meta, received_ns=received.received_ns)

    async def stop(self) -> None:
        """Take no more messages, settle those received, and return what was not settled to
        the connection (the broker keeps it unacknowledged meanwhile)."""
        self._stopping = True
        self._connection.unregister(self)
        self._inbox.close()
        if self._loop is not None:
            await self._loop
        left = self._returned + list(self._inbox.items)
        self._returned, self._inbox.items = [], type(self._inbox.items)()
        if left:
            self._connection.returned(self.route, left)

    def status(self) -> dict[str, Any]:
        return {"subscription": self.filter, "qos": self.qos}
