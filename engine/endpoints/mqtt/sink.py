"""MQTT sink: a batch published pipelined on the connection's session, each message delivered
once the broker acknowledged it (PUBACK at QoS 1, PUBCOMP at QoS 2; at QoS 0, once written).

The topic may interpolate canonical fields (``farm/{agent_id}/cmd``, rendered by
topics.topic_renderer); a message whose fields cannot make a topic is refused for good
(MessageRejected: dead-lettered), as is one the broker refuses by reason code (see errors.py).
A message sent again after a lost connection may reach subscribers twice (at-least-once):
QoS 2's exactly-once holds within one session, and each connection attempt is a new one.
"""

from __future__ import annotations

from typing import Sequence

from engine.endpoints.addressed import send_addressed
from engine.endpoints.base import Outbound, Sink
from engine.endpoints.mqtt.link import MqttLink
from engine.endpoints.mqtt.options import MqttSinkOptions
from engine.endpoints.mqtt.topics import topic_renderer


class MqttSink(Sink):
    def __init__(self, connection: MqttLink, route: str, options: MqttSinkOptions) -> None:
        self._connection = connection
        self._where = f"route {route!r}: mqtt sink"
        self._topic = topic_renderer(options.topic, self._where)
        self._qos = options.qos
        self._retain = options.retain

    async def send(self, message: Outbound) -> None:
        error = (await self.send_batch((message,)))[0]
        if error is not None:
            raise error

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        return await send_addressed(messages, self._topic, self._where,
                                    lambda batch: self._connection.publish_batch(batch, self._qos, self._retain, self._where))
