"""A ROS 2 topic sink: each message published on its topic (fixed, or rendered from the
canonical message), held until a subscriber has matched (``require_subscriber``).

Publishing is synchronous on the loop (a few microseconds for a String; KEEP_LAST never
blocks, which is why KEEP_ALL is not offered). A message that cannot fit its sink (a field
the type lacks, a bad value, a topic placeholder it does not fill) raises MessageRejected;
rclpy failures raise EndpointError, naming the route and topic. A sink that calls a service
or sends an action's goals is calls.py's ``ServiceSink`` or ``ActionSink``."""

from __future__ import annotations

import json
import logging
from typing import Any, Mapping, Sequence

from engine.endpoints.base import EndpointError, Outbound, Sink, typed
from engine.endpoints.ros2 import rosmsg
from engine.endpoints.ros2.checks import checked_sink
from engine.endpoints.ros2.errors import EXCEPTIONS, mapped, setup_error
from engine.endpoints.ros2.node import Ros2Node
from engine.endpoints.ros2.options import STRING_TYPE, Ros2SinkOptions, qos_profile, topic_of
from engine.endpoints.ros2.topics import topic_template

log = logging.getLogger("engine.ros2")


class Ros2Sink(Sink):
    """Publishes each message on its topic (fixed, or rendered from the canonical message).

    Readiness (``require_subscriber``, on by default). A DDS writer with no matched reader
    drops what it publishes, reliable or not, and the source has acknowledged it by then:
    an engine started on an AMQP queue of 10,000 messages for a topic lost all of them before
    discovery matched the subscriber that was waiting. So a sink whose topic no subscriber
    has matched is not :attr:`ready`, and the engine holds the route's messages as it does
    for a connection that is down. Matching is read with ``get_subscription_count()`` (2.8 us
    here), which the engine polls between batches (every 0.2 s while waiting): rclpy's
    matched-event callbacks need an executor, which this endpoint does not run (see the
    module), and a count read where it is needed cannot miss an event.

    A fixed topic's publisher is created with the sink, so discovery is under way before the
    first message. A templated topic's publisher exists only once a message names it: that
    message is refused (a transient error, which the engine does not count as an attempt
    because the sink then says it is not ready) and the sink is not ready until the topic has
    a subscriber. A subscriber that goes away makes the sink not ready
    again, at the next batch; DDS notices one that crashed only when its lease expires, and
    what was published to it meanwhile is lost (for commands that must arrive, have the
    robot answer on a topic of its own).
    """

    def __init__(self, connection: Ros2Node, route: str, options: Ros2SinkOptions | Mapping[str, Any]) -> None:
        self._connection = connection
        self._template = topic_of(options)
        self._where = f"route {route!r}, ros2 topic {self._template!r}"
        problems = checked_sink(options)
        if problems:
            raise EndpointError(f"{self._where}: {'; '.join(problems)}")
        options = typed(Ros2SinkOptions, options, self._where)
        self._cls = rosmsg.resolve_type(options.type)
        self._string = self._cls() if rosmsg.type_name(self._cls) == STRING_TYPE else None
        self._qos = qos_profile(options)
        self._require_subscriber = options.require_subscriber
        self._publishers: dict[str, Any] = {}
        self._unmatched: dict[str, Any] = {}
        """Templated topics a message was refused for, until a subscriber matches them."""
        self._was_ready = True
        self._fixed: Any = None
        self._topic_for = topic_template(self._template)
        if self._topic_for is None:
            self._fixed = self._publisher(self._template)  # early, so discovery is under way before the first send

    @property
    def ready(self) -> bool:
        if not self._require_subscriber:
            return True
        try:
            if self._fixed is not None:
                ready = self._fixed.get_subscription_count() > 0
            else:
                for topic, publisher in list(self._unmatched.items()):
                    if publisher.get_subscription_count() > 0:
                        del self._unmatched[topic]
                ready = not self._unmatched
        except Exception:  # the publisher is gone (the sink or the connection closed)
            ready = False
        if ready is not self._was_ready:
            self._was_ready = ready
            if ready:
                log.info("%s: a subscriber matched; publishing", self._where)
            else:
                log.warning("%s: %s; holding the route's messages", self._where, self.not_ready_reason())
        return ready

    def not_ready_reason(self) -> str | None:
        if not self._require_subscriber:
            return None
        waiting = [self._fixed] if self._fixed is not None else list(self._unmatched.values())
        reasons = []
        for publisher in waiting:
            try:
                if publisher.get_subscription_count() > 0:
                    continue
                topic = publisher.topic_name
                seen = self._connection.node.count_subscribers(topic)
            except Exception:
                continue
            reason = f"no subscriber has matched {topic}"
            if seen:
                reason += f" ({seen} on the topic did not match: incompatible QoS, or discovery under way)"
            reasons.append(reason)
        return "; ".join(reasons) + " (require_subscriber)" if reasons else None

    def _publisher(self, topic: str) -> Any:
        publisher = self._publishers.get(topic)
        if publisher is None:
            with mapped(f"{self._where}: cannot publish on {topic!r}"):
                publisher = self._connection.acquire_publisher(self._cls, topic, self._qos)
            self._publishers[topic] = publisher
        return publisher

    async def send(self, message: Outbound) -> None:
        self._publish(message)

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        """Publishing is synchronous: one pass over the batch, no coroutine per message."""
        results: list[BaseException | None] = []
        for message in messages:
            try:
                self._publish(message)
            except Exception as error:  # classified by the engine's delivery policy
                results.append(error)
            else:
                results.append(None)
        return results

    def _publish(self, message: Outbound) -> None:
        topic = self._template if self._topic_for is None else self._topic_for(message.template_data, self._where)
        publisher = self._publisher(topic)
        if self._string is not None:
            msg = self._string  # publish() serialises at once, so one instance is reused
            try:  # ``with mapped(...)`` spelt out: its generator context manager cost ~1 us a message
                msg.data = _string_data(message)
            except EndpointError:
                raise
            except EXCEPTIONS.catches as exc:
                raise EXCEPTIONS.edge_error(exc, self._where) from exc
        else:
            msg = typed_message(self._cls, message, self._where)
        if publisher is not self._fixed and self._require_subscriber and publisher.get_subscription_count() == 0:
            self._unmatched[topic] = publisher
            raise EndpointError(f"{self._where}: no subscriber has matched {topic} yet (require_subscriber)")
        try:
            publisher.publish(msg)
        except Exception as exc:  # the message was built: whatever rcl says now is not its fault
            raise setup_error(exc, f"{self._where}: publish failed") from exc

    async def close(self) -> None:
        publishers, self._publishers = list(self._publishers.values()), {}
        for publisher in publishers:
            await self._connection.release_publisher(publisher)
        self._connection.sink_closed(self)


def typed_message(cls: rosmsg.RosClass, message: Outbound, where: str) -> Any:
    """The message of a typed sink, as the sink publishes it and ``rabbitros-engine test``
    builds it. Fields the data does not name keep the message's defaults (a Header without a
    stamp is stamped now). From a sink mapping a null is refused wherever it is (a
    ``sink mapping`` error naming the field): JMESPath gives null for a path the message
    lacks, and neither a default nor NaN may stand in for a value that was not found.
    Without a sink mapping the canonical message is the data, and a null float is NaN (the
    ROS -> JSON -> ROS round trip; see rosmsg.py)."""
    with mapped(where):
        return rosmsg.from_dict(cls, message.fields, null_as_nan=message.fields is message.canonical)


def _string_data(message: Outbound) -> str:
    """The canonical JSON bytes as they came (identity routes stay byte-exact); when the route
    has a mapping, its result: a string as is, anything else as compact JSON."""
    if message.fields is message.canonical:
        return message.body.decode("utf-8")
    if isinstance(message.fields, str):
        return message.fields
    return json.dumps(message.fields, ensure_ascii=False, separators=(",", ":"))
