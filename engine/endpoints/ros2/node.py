"""A ROS 2 connection's node: one rclpy Context (own domain id) and one node, run in step with
the engine's asyncio loop without an executor (waiter.py), and what its sources and sinks share
of it: the readers the waiter waits on, the publishers, one read of the graph for every
discovering source, the node of service calls (calls.py). The sources and sinks themselves
are made by the connection (connection.py); this module names them only by what it asks of
them (:class:`ReadingSource`, :class:`ClosingSink`), so neither imports the other back."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Iterable, Mapping, Protocol

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions

from engine.endpoints.base import Connection, EndpointError, typed
from engine.endpoints.ros2 import calls as ros2_calls, discovery, rosmsg
from engine.endpoints.ros2.errors import setup_error
from engine.endpoints.ros2.options import Ros2ConnectionOptions, env_domain_id
from engine.endpoints.ros2.waiter import Waiter

log = logging.getLogger("engine.ros2")


class Reader:
    """One subscription of a source, and the metadata each of its messages carries."""

    __slots__ = ("source", "subscription", "meta", "received")

    def __init__(self, source: ReadingSource, subscription: Any, meta: dict[str, Any]) -> None:
        self.source = source
        self.subscription = subscription
        self.meta = meta
        self.received = 0


class ReadingSource(Protocol):
    """What the node asks of a topic source (source.py's ``Ros2Source``)."""

    paused: bool
    """Its subscriptions are left out of the wait set (a full queue under ``overflow: block``)."""

    @property
    def where(self) -> str: ...

    def take(self, reader: Reader) -> None: ...

    def scan(self, topics: Any, now: float) -> None: ...

    async def stop(self) -> None: ...


class ClosingSink(Protocol):
    """What the node asks of a topic sink (sink.py's ``Ros2Sink``)."""

    async def close(self) -> None: ...


class Ros2Node(Connection):
    """One rclpy Context (own domain id) and one node, plus the waiter thread."""

    settings: Ros2ConnectionOptions

    def __init__(self, name: str, settings: Ros2ConnectionOptions | Mapping[str, Any]) -> None:
        super().__init__(name, typed(Ros2ConnectionOptions, settings, f"ros2 connection {name!r}"))
        self.domain_id = self.settings.domain_id if self.settings.domain_id is not None else env_domain_id()
        self._context: Context
        self._guard: GuardCondition
        """Both set by :meth:`open` (with the node) and kept after :meth:`close`: nothing reads them before."""
        self._node: Node | None = None
        self._waiter: Waiter | None = None
        self._closing = False
        self._readers: dict[int, Reader] = {}
        """Subscription handle pointer -> its reader (what the waiter reports ready)."""
        self._waited: tuple[Any, ...] = ()
        self._sources: set[ReadingSource] = set()
        self._discovering: set[ReadingSource] = set()
        self._discovery: asyncio.Task[None] | None = None
        self._sinks: set[ClosingSink] = set()
        self._publishers: dict[tuple[str, str, tuple[Any, ...]], tuple[Any, int]] = {}
        self._calls: ros2_calls.CallNode | None = None

    @property
    def node(self) -> Node:
        if self._node is None or self._closing:
            raise EndpointError(f"ros2 connection {self.name!r} is not open")
        return self._node

    async def open(self) -> None:
        await asyncio.to_thread(self._open_node)
        self._waiter = Waiter(self.name, self._context, self._guard, lambda: self._waited, self._take_ready)
        self._waiter.start()

    def _open_node(self) -> None:
        """DDS participant creation takes tens of milliseconds, so it runs off the loop."""
        context = Context()
        try:
            rclpy.init(args=[], context=context, domain_id=self.domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
            node = Node(
                self.settings.node, namespace=self.settings.namespace, context=context,
                start_parameter_services=False,
                parameter_overrides=[Parameter("start_type_description_service", value=False)],
            )
            guard = GuardCondition(None, None, context=context)
        except Exception as exc:
            context.try_shutdown()
            raise setup_error(exc, f"ros2 connection {self.name!r}: cannot create node {self.settings.node!r}") from exc
        self._context, self._node, self._guard = context, node, guard

    def calls(self) -> ros2_calls.CallNode:
        """The node of this connection's service calls, made on first use (engine.endpoints.ros2.calls.py)."""
        if self._calls is None:
            self.node  # noqa: B018  # raises EndpointError when not open
            self._calls = ros2_calls.CallNode(self._context, self.settings.node, self.settings.namespace)
        return self._calls

    def acquire_publisher(self, cls: rosmsg.RosClass, topic: str, qos: QoSProfile) -> Any:
        """Publishers are shared by every sink of the connection with the same topic, type and
        QoS, so a reload that swaps a route's sink keeps the DDS writer the subscribers have
        already matched: a new writer would drop what it publishes before matching."""
        key = (topic, rosmsg.type_name(cls), (qos.history, qos.depth, qos.reliability, qos.durability))
        publisher, users = self._publishers.get(key, (None, 0))
        if publisher is None:
            publisher = self.node.create_publisher(cls, topic, qos)
        self._publishers[key] = (publisher, users + 1)
        return publisher

    async def release_publisher(self, publisher: Any) -> None:
        """The last user gone, wait (bounded) for reliable readers to acknowledge what was
        published before destroying the writer, so a removed route loses nothing in flight."""
        for key, (shared, users) in list(self._publishers.items()):
            if shared is not publisher:
                continue
            if users > 1:
                self._publishers[key] = (shared, users - 1)
                return
            del self._publishers[key]
            await _all_acked(publisher, RELEASE_ACK_WAIT)
            if self._node is not None:
                self._node.destroy_publisher(publisher)
            return

    async def close(self) -> None:
        if self._node is None or self._closing:
            return
        for source in list(self._sources):
            await source.stop()
        if self._discovery is not None:
            self._discovery.cancel()
            await asyncio.gather(self._discovery, return_exceptions=True)
        for sink in list(self._sinks):
            await sink.close()
        if self._calls is not None:
            calls, self._calls = self._calls, None
            await asyncio.to_thread(calls.close)
        self._closing = True
        if self._waiter is not None:
            await self._waiter.stop()
        else:
            self._guard.trigger()
        await asyncio.to_thread(self._close_node)

    def _close_node(self) -> None:
        node = self._node
        assert node is not None  # close() returns early without one
        try:
            self._guard.destroy()
            node.destroy_node()
        finally:
            self._context.try_shutdown()
            self._node = None

    # -- what the sources and sinks tell the node

    def source_started(self, source: ReadingSource) -> None:
        """``source`` is stopped when the connection closes."""
        self._sources.add(source)

    def source_stopped(self, source: ReadingSource) -> None:
        self._sources.discard(source)

    def sink_opened(self, sink: ClosingSink) -> None:
        """``sink`` is closed when the connection closes."""
        self._sinks.add(sink)

    def sink_closed(self, sink: ClosingSink) -> None:
        self._sinks.discard(sink)

    def add_reader(self, reader: Reader) -> None:
        """Wait on ``reader``'s subscription (the waiter rebuilds its wait set)."""
        self._readers[reader.subscription.handle.pointer] = reader
        self.readers_changed()

    def drop_readers(self, readers: Iterable[Reader]) -> None:
        """Stop waiting on these readers' subscriptions (destroy them with
        :meth:`destroy_subscription` once nothing takes from them any more)."""
        for reader in readers:
            self._readers.pop(reader.subscription.handle.pointer, None)
        self.readers_changed()

    def destroy_subscription(self, subscription: Any) -> None:
        """Destroy ``subscription`` unless the node is gone (its subscriptions with it); one
        the waiter still holds is freed once the waiter lets go of it."""
        if self._node is not None:
            self._node.destroy_subscription(subscription)

    def readers_changed(self) -> None:
        """Give the waiter a fresh tuple of subscriptions and make it rebuild its wait set
        (also when a source pauses or resumes: a paused source's subscriptions are left out)."""
        self._waited = tuple(reader.subscription for reader in self._readers.values() if not reader.source.paused)
        self._guard.trigger()

    # -- discovery: one read of the graph per interval for every discovering source

    def discover(self, source: ReadingSource) -> None:
        """Scan the graph for ``source`` now, then at every interval until :meth:`forget`."""
        self._discovering.add(source)
        source.scan(self.node.get_topic_names_and_types(), time.monotonic())
        if self._discovery is None or self._discovery.done():
            self._discovery = asyncio.create_task(self._discover(), name=f"ros2-discovery-{self.name}")

    def forget(self, source: ReadingSource) -> None:
        self._discovering.discard(source)

    async def _discover(self) -> None:
        while self._discovering and not self._closing:
            await asyncio.sleep(discovery.DISCOVERY_INTERVAL)
            try:
                topics = self.node.get_topic_names_and_types()
            except Exception as exc:  # the node is closing, or rcl failed: the next scan tries again
                log.warning("ros2 connection %r: cannot read the graph: %s", self.name, exc)
                continue
            now = time.monotonic()
            for source in list(self._discovering):
                try:
                    source.scan(topics, now)
                except Exception:  # a bug: the other sources keep discovering
                    log.exception("%s: discovery failed", source.where)

    def publisher_types(self, topic: str) -> list[str]:
        """The message types of ``topic``'s publishers (none when the graph cannot be read)."""
        try:
            return [info.topic_type for info in self.node.get_publishers_info_by_topic(topic)]
        except Exception:
            return []

    # -- the hand-over from the waiter thread

    def _take_ready(self, ready: list[int]) -> None:
        """On the loop: each ready subscription's source takes what it has (waiter.py)."""
        for pointer in ready:
            reader = self._readers.get(pointer)
            if reader is None:
                continue
            try:
                reader.source.take(reader)
            except Exception as exc:
                log.error("%s: take failed: %s", reader.source.where, exc)


RELEASE_ACK_WAIT = 2.0
"""Seconds a released publisher waits for its reliable readers to acknowledge what it sent."""
_ACK_POLL = 0.02


async def _all_acked(publisher: Any, timeout: float) -> bool:
    """Whether every reliable reader of ``publisher`` acknowledged what it published, waiting
    at most ``timeout`` s without holding up the loop or the process.

    rclpy's ``wait_for_all_acked`` keeps the GIL for its whole wait: one reader that did not
    answer (a robot stopped or gone, still matched until its lease expires) froze every
    thread of the engine for the 2 s, one publisher after another, so a stop of the fleet's
    50 robot command routes took 100 s (bench/fleet.py, killed at 20 s). It is asked with a
    zero timeout instead (~160 us), between loop turns; a publisher no reader matched has
    nothing to wait for."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    now = Duration(nanoseconds=0)
    while publisher.get_subscription_count() and not publisher.wait_for_all_acked(now):
        if loop.time() >= deadline:
            return False
        await asyncio.sleep(_ACK_POLL)
    return True
