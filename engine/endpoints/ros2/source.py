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
from dataclasses import dataclass
from typing import Any, Mapping

from rclpy.exceptions import InvalidHandle
from rclpy.qos import DurabilityPolicy

from engine.common.options import given
from engine.endpoints.base import Deliver, EndpointError, Inbound, Inbox, Source, typed
from engine.endpoints.pump import pump
from engine.endpoints.ros2 import discovery, offers, rosmsg
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
"""Seconds between two full reads of a topic's publishers while some of them stay unmatched
(another type, or a QoS that cannot match): the full read builds an object per endpoint
(about 115 us here), the counts checked in between about 10 us."""
MATCH_INTERVAL = discovery.DISCOVERY_INTERVAL
"""Seconds between two looks at whether an adapting source's publishers changed (two counts
per topic: about 10 us)."""
NAME_WAIT = 5.0
"""Most seconds a topic's publishers are read again while one's node is not known yet (DDS
finds a writer before the ROS node it belongs to): then it is reported as unknown, as a
plain DDS program without a node stays."""
_UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
SWITCH_WAIT = 2.0
"""Most seconds a re-created subscription is given to match every publisher before the old
one is let go anyway (DDS matching takes milliseconds between live participants)."""
RECENT_KEYS = 4096
"""Messages (at least; at most twice as many) a subscription remembers (publisher timestamp
and sequence number) so that the one replacing it skips what it took already: what a
replacement is given again is at most the publishers' kept history (a volatile subscription
replaced by a transient_local one) and what both received while they overlapped. Only a
subscription that may be replaced by a transient_local one (durability left out, volatile
now) remembers all along, the others from the moment a replacement is made: about 0.6 us a
message on the shared 2-core machine under a load average of 11-15, where taking a message
costs 5-10 us; a route that states ``qos.durability`` does not pay it."""


class _Reader(Reader):
    """A subscription of a source that may be re-created with another QoS: it remembers the
    keys of what it took recently (``recent``), and a replacement skips those (``skip``)
    among what it had received before it took over (``skip_before``, system-clock ns, as
    DDS's reception timestamps)."""

    __slots__ = ("recent", "older", "skip", "skip_before")

    def __init__(self, source: "Ros2Source", subscription: Any, meta: dict[str, Any], remember: bool) -> None:
        super().__init__(source, subscription, meta)
        self.recent: set[tuple[Any, Any]] | None = set() if remember else None
        self.older: set[tuple[Any, Any]] = set()
        """The generation before ``recent``: between RECENT_KEYS and twice that remembered, for
        one set insertion per message (0.2 us here, against 0.65 us for an exact ring)."""
        self.skip: set[tuple[Any, Any]] | None = None
        self.skip_before = 0

    def remember(self, key: tuple[Any, Any]) -> None:
        recent = self.recent
        assert recent is not None
        recent.add(key)
        if len(recent) >= RECENT_KEYS:
            self.older, self.recent = recent, set()

    def remembered(self) -> set[tuple[Any, Any]] | None:
        """What this subscription took lately, for the one that replaces it to skip."""
        return None if self.recent is None else self.recent | self.older

    def taken_before(self, info: Mapping[str, Any]) -> bool:
        """Whether the subscription this one replaced took this message already."""
        if info["received_timestamp"] > self.skip_before:
            self.skip = None  # received after the switch: the old one never saw it, nor the rest
            return False
        assert self.skip is not None
        return _key(info) in self.skip


@dataclass
class _Switch:
    """A topic's subscription being re-created: the new one (not waited on yet: what it
    receives stays in its DDS history) until it has matched ``expected`` publishers."""

    reader: _Reader
    expected: int
    began: float


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
        self._stated = given(options.qos) & offers.POLICIES if "qos" in given(options) else frozenset()
        """The QoS policies the route states (kept); the others are taken from the publishers."""
        self._adapting = self._stated != offers.POLICIES
        self._queue: Inbox[Inbound] = Inbox(SOURCE_QUEUE)
        self._deliver: Deliver | None = None
        self.paused = False
        self._readers: dict[str, _Reader] = {}
        """Topic -> its reader: the one topic, or each discovered topic being followed."""
        self._discovery: discovery.Discovery | None = None
        if discovery.topic_variables(self._topic):
            settings = connection.settings
            pattern = discovery.compile_pattern(self._topic, settings.node, settings.namespace)
            self._discovery = discovery.Discovery(pattern, self._type_name, options.forget_after, self._where,
                                                  self._follow, self._matched, self._let_go, share=options.share)
        self._pump: asyncio.Task[None] | None = None
        self._watch: asyncio.Task[None] | None = None
        self._stopping = False
        self.received = 0
        self.dropped = 0
        self.mismatched_publishers: list[str] = []
        self._switches: dict[str, _Switch] = {}
        self._looked: dict[str, tuple[int, float]] = {}
        """Topic -> its publisher count at the last full read of its publishers, and when."""
        self._unmatched: dict[str, list[str]] = {}
        self._unnamed_since: dict[str, float] = {}
        """Topic -> its publishers the subscription cannot match (another type, or QoS)."""
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
        self._watch = asyncio.create_task(self._watch_publishers(), name=f"ros2-publishers-{self._route}")
        if self._discovery is not None:
            self._connection.discover(self)

    def _subscribe(self, topic: str, captured: Mapping[str, str]) -> Reader:
        qos = self._qos
        if self._adapting:
            node = self._connection.node
            expanded = node.resolve_topic_name(topic)
            qos = offers.adapted(qos, self._stated, self._offers(expanded, node.get_publishers_info_by_topic(expanded)))
        reader = self._new_reader(topic, {"type": self._type_name, **captured}, qos)
        self._readers[reader.meta["topic"]] = reader
        self._connection.add_reader(reader)
        return reader

    def _new_reader(self, topic: str, meta: Mapping[str, Any], qos: Any) -> _Reader:
        try:
            subscription = self._connection.node.create_subscription(self._cls, topic, _unused_callback, qos)
        except Exception as exc:
            raise setup_error(exc, f"{self._where}: cannot subscribe to {topic!r}") from exc
        may_gain_history = "durability" not in self._stated and qos.durability == DurabilityPolicy.VOLATILE
        return _Reader(self, subscription, {**meta, "topic": subscription.topic_name}, may_gain_history)

    def _offers(self, topic: str, infos: Sequence[Any]) -> list[offers.Offer]:
        return offers.offers_of(topic, infos, self._type_name)

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
        self._cancel_switch(topic)
        self._looked.pop(topic, None)
        self._unmatched.pop(topic, None)
        self._unnamed_since.pop(topic, None)
        reader = self._readers.pop(topic, None)
        if reader is None:
            return
        self._connection.drop_readers([reader])
        self._connection.destroy_subscription(reader.subscription)  # freed once the waiter lets go of it

    def take(self, reader: Reader) -> None:
        """Runs on the loop: take what is ready (bounded by the queue), never waits."""
        assert isinstance(reader, _Reader)  # made by this source
        self._take(reader)

    def _take(self, reader: _Reader) -> bool:
        """:meth:`take`; True when the budget ran out (more may be ready)."""
        sub, cls, queue, meta = reader.subscription, self._cls, self._queue, reader.meta
        block = queue.overflow == "block"
        remember = reader.recent is not None
        taken = 0
        more = False
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
                    if reader.skip is not None and reader.taken_before(message[1]):
                        continue
                    if remember:
                        reader.remember(_key(message[1]))
                    taken += 1
                    self._put(self._inbound(message[0], meta))
                else:
                    more = True
        except InvalidHandle:
            return False
        finally:
            if taken:
                self.received += taken
                reader.received += taken
                queue.wake()
        return more

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

    async def _watch_publishers(self) -> None:
        """Keep each subscription matched to its publishers (an adapting source) and report
        those it cannot match: of another type (never matched), or whose QoS the route's
        stated ``qos`` cannot match (log and status)."""
        interval = MATCH_INTERVAL if self._adapting else _TYPE_CHECK_INTERVAL
        reported: set[str] = set()
        while not self._stopping:
            try:
                self._look_at_publishers(time.monotonic())
            except EndpointError:  # the connection is closing
                pass
            except Exception:  # a bug: say it, keep watching
                log.exception("%s: cannot read the topic's publishers", self._where)
            unmatched = sorted({entry for entries in self._unmatched.values() for entry in entries})
            self.mismatched_publishers = unmatched
            for publisher in set(unmatched) - reported:
                log.error("%s: publisher %s; its messages are not received", self._where, publisher)
            reported = set(unmatched)
            await asyncio.sleep(MATCH_INTERVAL if self._switches or self._unnamed_since else interval)

    def _look_at_publishers(self, now: float) -> None:
        """One look at every followed topic. Counting (rcl_count_publishers, and the matched
        count) builds no endpoint objects, so the full read of a topic's publishers happens
        only when their number changed, or every :data:`_TYPE_CHECK_INTERVAL` while some stay
        unmatched: a fleet's engine with 100 ROS 2 sources spent 11 % of its loop in this check
        with the full read every time (bench/fleet.py, py-spy)."""
        node = self._connection.node
        for topic, reader in list(self._readers.items()):
            switch = self._switches.get(topic)
            if switch is not None:
                self._advance(topic, reader, switch, now)
                continue
            count = node.count_publishers(topic)
            last = self._looked.get(topic)
            if last is not None and last[0] == count and (
                    reader.subscription.get_publisher_count() >= count or now - last[1] < _TYPE_CHECK_INTERVAL):
                continue
            infos = node.get_publishers_info_by_topic(topic)
            offered = self._offers(topic, infos)
            current = reader.subscription.qos_profile
            wanted = offers.adapted(current, self._stated, offered) if self._adapting else current
            refused = offers.refusals(wanted, offered)
            if not offers.same_policies(wanted, current):
                self._begin_switch(topic, reader, wanted, len(offered) - len(refused), now)
            if any(info.node_name == _UNKNOWN_NODE for info in infos) and now - self._unnamed_since.setdefault(topic, now) < NAME_WAIT:
                continue  # a publisher's node is not known yet: read again next time, to name it
            self._unnamed_since.pop(topic, None)
            self._looked[topic] = (count, now)
            wrong = [f"{info.node_namespace.rstrip('/')}/{info.node_name} ({info.topic_type}) on {topic} does not match "
                     f"the route's type {self._type_name}" for info in infos if info.topic_type != self._type_name]
            self._unmatched[topic] = wrong + refused

    def _begin_switch(self, topic: str, reader: _Reader, qos: Any, expected: int, now: float) -> None:
        """Re-create ``topic``'s subscription with ``qos``, make before break: the new one
        receives (into its DDS history, not taken yet) while the old one is still taken from,
        until the new one has matched every publisher (:meth:`_advance`)."""
        try:
            new = self._new_reader(topic, reader.meta, qos)
        except EndpointError as exc:
            log.error("%s", exc)
            return
        if reader.recent is None:
            reader.recent = set()  # from now on: what both subscriptions receive is taken once
        self._switches[topic] = _Switch(new, expected, now)
        log.info("%s: the publishers of %s offer %s: subscribing with it (was %s)", self._where, topic,
                 offers.describe(qos), offers.describe(reader.subscription.qos_profile))

    def _advance(self, topic: str, old: _Reader, switch: _Switch, now: float) -> None:
        """Hand ``topic`` over to the new subscription once it has matched its publishers (or
        :data:`SWITCH_WAIT` passed): the old one is left out of the wait set, what it has left
        taken, then destroyed; the new one skips what the old one took (its ``recent`` keys)."""
        new = switch.reader
        if self.paused or (new.subscription.get_publisher_count() < switch.expected and now - switch.began < SWITCH_WAIT):
            return  # a paused source could not take the old one's rest: it waits
        del self._switches[topic]
        self._connection.drop_readers([old])
        while self._take(old) and not self.paused:
            pass
        new.received = old.received
        new.skip, new.skip_before = old.remembered(), time.time_ns()
        self._readers[topic] = new
        self._connection.add_reader(new)
        self._connection.destroy_subscription(old.subscription)
        self._looked.pop(topic, None)  # read the publishers again: the new one's view of them

    def _cancel_switch(self, topic: str) -> None:
        switch = self._switches.pop(topic, None)
        if switch is not None:
            self._connection.destroy_subscription(switch.reader.subscription)

    def status(self) -> dict[str, Any]:
        status: dict[str, Any] = {"received": self.received, "dropped": self.dropped, "queued": len(self._queue),
                                  "matched_publishers": sum(self._matched(topic) for topic in self._readers),
                                  "mismatched_publishers": self.mismatched_publishers}
        if self._discovery is None:
            reader = self._readers.get(next(iter(self._readers), ""))
            if reader is not None:
                status["qos"] = offers.describe(reader.subscription.qos_profile)
            return status
        variables = self._discovery.pattern.variables
        status["following"] = {topic: {**{name: reader.meta[name] for name in variables}, "received": reader.received,
                                       "qos": offers.describe(reader.subscription.qos_profile)}
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
        for topic in list(self._switches):
            self._cancel_switch(topic)
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


def _key(info: Mapping[str, Any]) -> tuple[Any, Any]:
    """A taken message's identity across two subscriptions of the same publisher: the
    publisher's timestamp (ns) and its sequence number (two publishers colliding on both is
    not expected)."""
    return info["source_timestamp"], info.get("publication_sequence_number")


def _unused_callback(msg: Any) -> None:
    """rclpy wants a callback; messages are taken by Ros2Source.take instead."""
