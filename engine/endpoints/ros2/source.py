"""A ROS 2 topic source: subscriptions taken on the loop (node.py, waiter.py) into one bounded
queue (the route's: ``Deliver.inbox``), handed to the route in batches by the engine's read
loop (engine/endpoints/pump.py).

A source topic with ``{var}`` segments subscribes to every matching topic as it appears in the
graph (engine/endpoints/ros2/discovery.py): one source, many subscriptions, one queue. A full
queue follows the route's ``overflow`` (block: stop taking; or drop and count), and DDS history
(``qos.depth``) is what buffers while the loop itself is busy. A source that offers a service
is calls.py's ``ServiceSource``."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from typing import Any, Mapping

from rclpy.exceptions import InvalidHandle

from engine.endpoints.base import Deliver, EndpointError, Inbound, Inbox, Source, typed
from engine.endpoints.pump import pump
from engine.endpoints.ros2 import discovery, rosmsg
from engine.endpoints.ros2.checks import checked_source
from engine.endpoints.ros2.errors import setup_error
from engine.endpoints.ros2.node import Reader, Ros2Node
from engine.endpoints.ros2.options import STRING_TYPE, Ros2SourceOptions, qos_profile, topic_of

log = logging.getLogger("engine.ros2")

SOURCE_QUEUE = 10_000
"""Messages a source holds between taking them and the pipeline, unless the route says
otherwise (``Deliver.queue_limit``); beyond it, the route's ``overflow`` applies."""
TAKE_BUDGET = 1024
"""Most messages taken from one subscription per wake-up: everything ready, within reason."""
BATCH = 1024
"""Most messages handed to the route in one ``Deliver.batch``. A batch waits for its sink (an
AMQP sink: the broker's confirms) before the next one starts, so a backlogged route carries
at most BATCH per confirm round trip, which reaches tens of ms on a loaded machine: the
MAVLink source's batch of 1,024 (engine/endpoints/mavlink/messages.py) for the same reason;
the reference (bench/systems.py) publishes all it has taken at once."""
_TYPE_CHECK_INTERVAL = 2.0


class Ros2Source(Source):
    """Takes everything its subscriptions have ready in one pass into a bounded queue, and
    hands the queue to the route in batches. A full queue follows the route's ``overflow``:
    ``block`` stops taking (the subscriptions leave the wait set, so DDS history and reliable
    flow control hold the rest), ``drop_oldest`` / ``drop_newest`` drop and count.

    A topic with ``{var}`` segments is a pattern: the source subscribes to each matching topic
    as it appears in the graph, one queue for all of them (so each topic's order is kept),
    each message with the topic's captured values in its metadata (engine/endpoints/ros2/discovery.py).

    ``std_msgs/String`` is taken serialized and its CDR string read directly, so its bytes
    reach the pipeline untouched (invalid UTF-8 is then the decoder's to dead-letter, where
    rclpy would raise while taking it). A typed message rclpy cannot take is handed on as
    undecodable, to be dead-lettered. Publishers of another type on the topic never match;
    the source reports them (log and status).
    """

    def __init__(self, connection: Ros2Node, route: str, options: Ros2SourceOptions | Mapping[str, Any]) -> None:
        self._connection = connection
        self._route = route
        self._topic = topic_of(options)
        self._where = f"route {route!r}, ros2 topic {self._topic!r}"
        problems = checked_source(options)
        if problems:
            raise EndpointError(f"{self._where}: {'; '.join(problems)}")
        options = typed(Ros2SourceOptions, options, self._where)
        self._cls = rosmsg.resolve_type(options.type)
        self._type_name = rosmsg.type_name(self._cls)
        self._is_string = self._type_name == STRING_TYPE
        self._qos = qos_profile(options)
        self._queue: Inbox[Inbound] = Inbox(SOURCE_QUEUE)
        self._deliver: Deliver | None = None
        self.paused = False
        self._readers: dict[str, Reader] = {}
        """Topic -> its reader: the one topic, or each discovered topic being followed."""
        self._discovery: discovery.Discovery | None = None
        if discovery.topic_variables(self._topic):
            settings = connection.settings
            pattern = discovery.compile_pattern(self._topic, settings.node, settings.namespace)
            self._discovery = discovery.Discovery(pattern, self._type_name, options.forget_after, self._where,
                                                  self._follow, self._matched, self._let_go)
        self._pump: asyncio.Task[None] | None = None
        self._watch: asyncio.Task[None] | None = None
        self._stopping = False
        self.received = 0
        self.dropped = 0
        self.mismatched_publishers: list[str] = []
        self._drop_logged = 0.0

    @property
    def where(self) -> str:
        """The route and topic, as every log line and error of this source names them."""
        return self._where

    async def start(self, deliver: Deliver) -> None:
        self._connection.node  # noqa: B018  # raises EndpointError when not open
        self._deliver = deliver
        self._queue = deliver.inbox(deliver.overflow)
        if self._discovery is None:
            self._subscribe(self._topic, {})
        self._pump = asyncio.create_task(pump(self, deliver, self._where), name=f"ros2-source-{self._route}")
        self._connection.source_started(self)
        if self._discovery is None:
            self._watch = asyncio.create_task(self._watch_types(), name=f"ros2-types-{self._route}")
        else:
            self._connection.discover(self)

    def _subscribe(self, topic: str, captured: Mapping[str, str]) -> Reader:
        try:
            subscription = self._connection.node.create_subscription(self._cls, topic, _unused_callback, self._qos)
        except Exception as exc:
            raise setup_error(exc, f"{self._where}: cannot subscribe to {topic!r}") from exc
        reader = Reader(self, subscription, {"topic": subscription.topic_name, "type": self._type_name, **captured})
        self._readers[subscription.topic_name] = reader
        self._connection.add_reader(reader)
        return reader

    def scan(self, topics: Any, now: float) -> None:
        """One read of the graph (called by the connection): follow and let go (discovery only)."""
        if self._discovery is not None and not self._stopping:
            self._discovery.scan(topics, self._connection.publisher_types, now)

    def _follow(self, topic: str, captured: Mapping[str, str]) -> bool:
        try:
            self._subscribe(topic, captured)
        except EndpointError as exc:
            log.debug("%s", exc)
            return False
        return True

    def _matched(self, topic: str) -> int:
        try:
            return self._readers[topic].subscription.get_publisher_count()
        except Exception:  # destroyed meanwhile: nothing matched
            return 0

    def _let_go(self, topic: str) -> None:
        reader = self._readers.pop(topic, None)
        if reader is None:
            return
        self._connection.drop_readers([reader])
        self._connection.destroy_subscription(reader.subscription)  # freed once the waiter lets go of it

    def take(self, reader: Reader) -> None:
        """Runs on the loop: take what is ready (bounded by the queue), never waits."""
        sub, cls, queue, meta = reader.subscription, self._cls, self._queue, reader.meta
        block = queue.overflow == "block"
        taken = 0
        try:
            with sub.handle:
                for _ in range(TAKE_BUDGET):
                    if block and queue.full:
                        self._pause()
                        break
                    try:
                        message = sub.handle.take_message(cls, self._is_string)
                    except InvalidHandle:
                        raise
                    except Exception as exc:  # rclpy could not convert what it took
                        taken += 1
                        self._put(Inbound(meta=dict(meta), undecodable=f"cannot take a {self._type_name}: {exc}"))
                        continue
                    if message is None:
                        break
                    taken += 1
                    self._put(self._inbound(message[0], meta))
        except InvalidHandle:
            return
        finally:
            if taken:
                self.received += taken
                reader.received += taken
                queue.wake()

    def _put(self, inbound: Inbound) -> None:
        if self._queue.offer(inbound):
            self._drop()

    def _inbound(self, msg: Any, meta: dict[str, Any]) -> Inbound:
        if self._is_string:
            try:
                return Inbound(body=_cdr_string(msg), meta=dict(meta))
            except ValueError as exc:
                return Inbound(body=bytes(msg), meta=dict(meta), undecodable=str(exc))
        try:
            return Inbound(fields=rosmsg.to_dict(msg), meta=dict(meta))
        except Exception as exc:
            return Inbound(meta=dict(meta), undecodable=f"cannot convert a {self._type_name}: {exc}")

    def _drop(self) -> None:
        self.dropped += 1
        if self._deliver is not None:
            self._deliver.dropped(1)
        now = time.monotonic()
        if now - self._drop_logged >= 10.0:
            self._drop_logged = now
            log.warning("%s: queue full (%d, overflow %s), dropped %d messages so far",
                        self._where, self._queue.limit, self._queue.overflow, self.dropped)

    def _pause(self) -> None:
        if not self.paused:
            self.paused = True
            self._connection.readers_changed()

    def _resume(self) -> None:
        if self.paused:
            self.paused = False
            self._connection.readers_changed()

    async def read_batch(self) -> list[Inbound]:
        """What was taken, up to :data:`BATCH`; a paused source takes again once its queue is
        down to half."""
        queue = self._queue
        batch = await queue.take(BATCH)
        if self.paused and len(queue) <= queue.limit // 2:
            self._resume()
        return batch

    def inbounds(self, batch: Sequence[Inbound]) -> Sequence[Inbound]:
        return batch

    async def settle(self, batch: Sequence[Inbound], settled: list[bool]) -> None:
        """ROS cannot redeliver: what the route did not settle is counted lost."""
        lost = settled.count(False)
        if lost:
            self.dropped += lost
            assert self._deliver is not None
            self._deliver.dropped(lost)
        if len(self._queue):  # a backlog must not hold the loop from other routes; an empty inbox waits in take()
            await asyncio.sleep(0)  # (at a robot's pace a yield per message is a loop round trip for nothing)

    async def _watch_types(self) -> None:
        """Publishers of another type on our topic never match: say so (log and status)."""
        reported: set[str] = set()
        topic = next(iter(self._readers))
        while not self._stopping:
            try:
                infos = self._publishers_unless_all_matched(topic)
            except Exception:
                infos = []
            wrong = sorted({f"{info.node_namespace.rstrip('/')}/{info.node_name} ({info.topic_type})"
                            for info in infos if info.topic_type != self._type_name})
            self.mismatched_publishers = wrong
            for publisher in set(wrong) - reported:
                log.error("%s: publisher %s does not match the route's type %s; its messages are not received",
                          self._where, publisher, self._type_name)
            reported = set(wrong)
            await asyncio.sleep(_TYPE_CHECK_INTERVAL)

    def _publishers_unless_all_matched(self, topic: str) -> list[Any]:
        """The topic's publishers, or none when every one of them matched our subscription
        (then none is of another type). Counting (rcl_count_publishers, and the matched count)
        builds no endpoint objects: a fleet's engine with 100 ROS 2 sources spent 11 % of its
        loop in this check with the full query every time (bench/fleet.py, py-spy)."""
        reader = self._readers.get(topic)
        node = self._connection.node
        if reader is not None and node.count_publishers(topic) <= reader.subscription.get_publisher_count():
            return []
        return node.get_publishers_info_by_topic(topic)

    def status(self) -> dict[str, Any]:
        status: dict[str, Any] = {"received": self.received, "dropped": self.dropped, "queued": len(self._queue)}
        if self._discovery is None:
            status["mismatched_publishers"] = self.mismatched_publishers
            return status
        variables = self._discovery.pattern.variables
        status["following"] = {topic: {**{name: reader.meta[name] for name in variables}, "received": reader.received}
                               for topic, reader in sorted(self._readers.items())}
        status.update(self._discovery.status())
        return status

    async def stop(self) -> None:
        if self._pump is None:
            return
        connection = self._connection
        if not self._stopping:
            self._stopping = True
            connection.forget(self)
            connection.drop_readers(self._readers.values())
            self._queue.close()
        await self._pump
        if self._watch is not None:
            self._watch.cancel()
            await asyncio.gather(self._watch, return_exceptions=True)
        connection.source_stopped(self)
        readers, self._readers = list(self._readers.values()), {}
        for reader in readers:
            connection.destroy_subscription(reader.subscription)


def _cdr_string(raw: bytes) -> bytes:
    """The bytes of a serialized ``std_msgs/String`` (CDR: encapsulation, uint32 length with
    the NUL, bytes, NUL), without decoding them."""
    if len(raw) < 8:
        raise ValueError(f"serialized String of {len(raw)} bytes is truncated")
    size = int.from_bytes(raw[4:8], "little" if raw[1] & 1 else "big")
    if size < 1 or 8 + size > len(raw):
        raise ValueError(f"serialized String claims {size} bytes, has {len(raw) - 8}")
    return bytes(raw[8:8 + size - 1])


def _unused_callback(msg: Any) -> None:
    """rclpy wants a callback; messages are taken by Ros2Source.take instead."""
