"""The tunnel's receiving side and its per-connection dispatch, on asyncio: the
:class:`TunnelHub` of a connection hands each TUNNEL frame to the sink waiting for its
acknowledgement or to the :class:`TunnelChannel` of its ``payload_type``, which reassembles
(arq.py) and settles each message with every :class:`TunnelSource` reading it. The settings
every tunnel of a link shares (:class:`TunnelSettings`) are here too."""

from __future__ import annotations

import asyncio
import contextlib
import random
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any, Protocol, cast

from engine.endpoints.base import Deliver, Inbound, Inbox, Source
from engine.endpoints.mavlink.tunnel.arq import Key, Reassembler, RttEstimator
from engine.endpoints.mavlink.tunnel.frames import (
    DEFAULT_PAYLOAD_TYPE, MAX_FRAGMENT, SIK_FRAGMENT, Ack, Data, decode,
)
from engine.endpoints.pump import settle_batch

DELIVERY_BATCH = 64
"""Most reassembled messages settled together (one ``Deliver.batch`` per route)."""


class TunnelLink(Protocol):
    """What the drivers need from a MAVLink connection."""

    stats: dict[str, int]

    def send_tunnel(self, payload_type: int, target: tuple[int, int], payload: bytes, *,
                    bulk: bool, priority: str | None = None, first: bool = False) -> asyncio.Future[float]:
        """Queue a TUNNEL frame; the future gives the loop time it was written (cancelling it
        before then takes the frame off the queue). ``priority``: the route's, for the writer's
        order (None: before every route's frames, as acknowledgements are); ``first``: at the
        front of its lane (a fragment sent again)."""
        ...


@dataclass(frozen=True, slots=True)
class TunnelSettings:
    """Per-connection tuning; defaults depend on the link (a SiK radio needs patience)."""

    fragment_size: int = MAX_FRAGMENT
    rto_min: float = 0.5
    rto_max: float = 8.0
    retries: int = 8
    sack_delay: float = 0.25
    window: int = 8
    """Transfers (messages or bundles) in flight per sink: enough to keep a radio busy through
    its round trip (a TDM round, ~240 ms, plus settling); the writer's pacing, not the window,
    keeps the radio's buffer from overflowing."""
    bundle: int = 2048
    """Largest bundle, in bytes of its body; 0 sends every message on its own."""
    reassembly_timeout: float = 60.0
    memory: int = 1024
    memory_ttl: float = 300.0
    rate: float = 0.0
    """Bytes/s ceiling of the link's budget when the connection sets no ``budget`` (every route's frames
    share it: engine/endpoints/mavlink/budget.py); 0 = half the serial rate on serial links, unpaced on networks."""

    @classmethod
    def from_settings(cls, raw: Any, *, serial: bool) -> TunnelSettings:
        """The link's defaults with what ``raw`` (the typed ``tunnel:`` options) sets."""
        base = cls(fragment_size=SIK_FRAGMENT) if serial else cls(rto_min=0.2, sack_delay=0.1)
        if raw is None:
            return base
        values = {name: getattr(base, name) for name in cls.__slots__}
        for name in cls.__slots__:
            value = getattr(raw, name)
            if value is None:
                continue
            kind = type(values[name])
            if isinstance(value, bool) or not isinstance(value, (int, float)) or (kind is int and not isinstance(value, int)):
                raise ValueError(f"tunnel.{name} must be a {kind.__name__}")
            values[name] = kind(value)
        out = cls(**values)
        if not 1 <= out.fragment_size <= MAX_FRAGMENT:
            raise ValueError(f"tunnel.fragment_size must be 1..{MAX_FRAGMENT}")
        if out.rto_min <= 0 or out.rto_max < out.rto_min or out.retries < 0 or out.window < 1 or out.rate < 0 \
                or out.bundle < 0:
            raise ValueError("tunnel timing settings out of range")
        return out


class TunnelHub:
    """Per-connection dispatch of tunnel frames to the sinks and sources using them.

    Reassembly state (and so the memory of delivered ids) belongs to the connection, one
    :class:`TunnelChannel` per ``payload_type``, not to a source: every route reading a
    payload type gets every message, and a reload, which starts a route's new source before
    stopping its old one, hands the same state to the new source without delivering twice.
    """

    def __init__(self, link: TunnelLink, settings: TunnelSettings) -> None:
        self.link = link
        self.settings = settings
        self._channels: dict[int, TunnelChannel] = {}
        self._senders: set[int] = set()
        self._waiting: dict[tuple[int, int], Callable[[Ack], None]] = {}
        self._next_id: dict[int, int] = {}
        self._rtt: dict[int, RttEstimator] = {}

    def on_frame(self, payload_type: int, peer: tuple[int, int], payload: bytes) -> bool:
        """Handle a TUNNEL payload addressed to us; False when no route uses its type."""
        channel = self._channels.get(payload_type)
        if (channel is None or not channel.routes) and payload_type not in self._senders:
            return False
        try:
            frame = decode(payload)
        except ValueError:
            self.link.stats["tunnel_malformed"] = self.link.stats.get("tunnel_malformed", 0) + 1
            return True
        if isinstance(frame, Data):
            if channel is not None:
                channel.on_data(peer, frame)
        else:
            waiter = self._waiting.get((payload_type, frame.msg_id))
            if waiter is not None:
                waiter(frame)
        return True

    def channel(self, payload_type: int) -> TunnelChannel:
        channel = self._channels.get(payload_type)
        if channel is None:
            channel = self._channels[payload_type] = TunnelChannel(self, payload_type)
        return channel

    def reassembler(self, payload_type: int) -> Reassembler:
        return self.channel(payload_type).reassembler

    def add_sender(self, payload_type: int) -> None:
        self._senders.add(payload_type)

    def new_id(self, payload_type: int) -> int:
        """Ids start at random so a restarted sender does not collide with the receiver's memory."""
        value = self._next_id.get(payload_type)
        if value is None:
            value = random.getrandbits(16)
        while (payload_type, value) in self._waiting:
            value = (value + 1) & 0xFFFF
        self._next_id[payload_type] = (value + 1) & 0xFFFF
        return value

    def rtt(self, payload_type: int) -> RttEstimator:
        est = self._rtt.get(payload_type)
        if est is None:
            est = self._rtt[payload_type] = RttEstimator(self.settings.rto_min, self.settings.rto_max)
        return est

    def watch(self, payload_type: int, msg_id: int, callback: Callable[[Ack], None]) -> None:
        self._waiting[(payload_type, msg_id)] = callback

    def unwatch(self, payload_type: int, msg_id: int) -> None:
        self._waiting.pop((payload_type, msg_id), None)

    def count(self, name: str, n: int = 1) -> None:
        self.link.stats[name] = self.link.stats.get(name, 0) + n


class TunnelChannel:
    """The receiving side of one ``payload_type``: one reassembly, each message handed to every
    route that reads it (the newest source of each route), and acknowledged DELIVERED to the
    sender only once every one of them settled it. A route that failed gets the message again
    when the sender retransmits; the routes that settled it do not."""

    def __init__(self, hub: TunnelHub, payload_type: int) -> None:
        self.hub = hub
        self.payload_type = payload_type
        s = hub.settings
        self.reassembler = Reassembler(sack_delay=s.sack_delay, timeout=s.reassembly_timeout, memory=s.memory,
                                       memory_ttl=s.memory_ttl)
        self.routes: dict[str, list[TunnelSource]] = {}
        self._settled: OrderedDict[tuple[Key, int], set[str]] = OrderedDict()
        """Routes that settled each message (key, part) of a transfer not yet settled by all."""
        self._ready: Inbox[tuple[Key, bytes]] = Inbox(1 << 30)
        """Reassembled messages waiting to be settled (bounded by the senders' windows)."""
        self._wake = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []

    def readers(self, peer: tuple[int, int]) -> list[TunnelSource]:
        """The newest source of each route that accepts messages from ``peer``."""
        return [sources[-1] for sources in self.routes.values() if sources[-1].accepts(peer)]

    def add(self, source: TunnelSource) -> None:
        self.routes.setdefault(source.route, []).append(source)
        if not self._tasks:
            self._tasks = [
                asyncio.create_task(self._timers(), name=f"tunnel-timers:{self.payload_type}"),
                asyncio.create_task(self._deliveries(), name=f"tunnel-deliver:{self.payload_type}"),
            ]

    async def remove(self, source: TunnelSource) -> None:
        sources = self.routes.get(source.route, [])
        if source in sources:
            sources.remove(source)
        if not sources:
            self.routes.pop(source.route, None)
        if self.routes or not self._tasks:
            return
        timers, deliveries = self._tasks
        self._tasks = []
        timers.cancel()
        ready, self._ready = self._ready, Inbox(1 << 30)
        for key, _ in ready.items:  # unacknowledged: the sender retransmits them
            self.reassembler.failed(key)
        ready.items.clear()
        ready.close()
        await asyncio.gather(timers, deliveries, return_exceptions=True)

    def on_data(self, peer: tuple[int, int], data: Data) -> None:
        if not self.readers(peer):
            return
        acks, complete = self.reassembler.on_data(peer, data, asyncio.get_running_loop().time())
        for ack in acks:
            self._send_ack(peer, ack)
        if complete is not None:
            self._ready.offer(complete)
            self._ready.wake()
        self._wake.set()

    def _send_ack(self, peer: Hashable, ack: bytes) -> None:
        assert isinstance(peer, tuple)
        sent = asyncio.ensure_future(self.hub.link.send_tunnel(self.payload_type, peer, ack, bulk=False))
        sent.add_done_callback(ignore_result)

    async def _timers(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            deadline = self.reassembler.next_deadline()
            self._wake.clear()
            timeout = None if deadline is None else max(0.0, deadline - loop.time())
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), timeout)
            for peer, ack in self.reassembler.poll(loop.time()):
                self._send_ack(peer, ack)

    async def _deliveries(self) -> None:
        """Settle every ready message with every route reading it (one ``Deliver.batch`` per
        route, the routes in parallel); acknowledge DELIVERED each message every route settled.
        Not the engine's read loop (engine/endpoints/pump.py), which serves one route: one
        reassembly feeds several routes here, each route's batch through ``settle_batch``."""
        ready = self._ready
        while batch := await ready.take(DELIVERY_BATCH):
            await self._settle(batch)

    async def _settle(self, batch: list[tuple[Key, bytes]]) -> None:
        loop = asyncio.get_running_loop()
        messages = [((key, part), body) for key, whole in batch
                    for part, body in enumerate(self.reassembler.messages(key, whole))]
        settled_by = [self._settled.pop(slot, set()) for slot, _ in messages]
        wanted: dict[TunnelSource, list[int]] = {}
        for position, ((key, _), _) in enumerate(messages):
            for source in self.readers(cast(tuple[int, int], key[0])):
                if source.route not in settled_by[position]:
                    wanted.setdefault(source, []).append(position)
        readers = list(wanted)
        results = await asyncio.gather(*(source.deliver_batch([self._inbound(*messages[i]) for i in wanted[source]])
                                         for source in readers))
        unsettled: set[Key] = set()
        for source, result in zip(readers, results):
            for position, ok in zip(wanted[source], result):
                if ok:
                    settled_by[position].add(source.route)
                else:
                    unsettled.add(messages[position][0][0])
        for key, _ in batch:
            if not self.readers(cast(tuple[int, int], key[0])):
                unsettled.add(key)
        for position, (slot, _) in enumerate(messages):
            if slot[0] in unsettled:  # what some routes settled, they do not get again
                self._settled[slot] = settled_by[position]
        while len(self._settled) > self.reassembler.memory:
            self._settled.popitem(last=False)
        for key, _ in batch:
            if key in unsettled:
                self.reassembler.failed(key)
                self.hub.count("tunnel_deliver_failed")
                continue
            self.hub.count("tunnel_delivered")
            self._send_ack(cast(tuple[int, int], key[0]), self.reassembler.delivered(key, loop.time()))

    def _inbound(self, slot: tuple[Key, int], body: bytes) -> Inbound:
        (peer, msg_id), part = cast(tuple[tuple[int, int], int], slot[0]), slot[1]
        return Inbound(body=body, meta={"message": "TUNNEL", "system_id": peer[0], "component_id": peer[1],
                                        "payload_type": self.payload_type, "tunnel_id": msg_id, "tunnel_part": part})


class TunnelSource(Source):
    """One route reading the messages of a ``payload_type`` (see :class:`TunnelChannel`)."""

    def __init__(self, hub: TunnelHub, *, route: str, payload_type: int = DEFAULT_PAYLOAD_TYPE,
                 system_id: int | None = None, component_id: int | None = None) -> None:
        self.hub = hub
        self.route = route
        self.payload_type = payload_type
        self.system_id = system_id
        self.component_id = component_id
        self.channel = hub.channel(payload_type)
        self.reassembler = self.channel.reassembler
        self._deliver: Deliver | None = None
        self._busy = 0
        self._idle = asyncio.Event()
        self._idle.set()

    def accepts(self, peer: tuple[int, int]) -> bool:
        return (self.system_id is None or peer[0] == self.system_id) and \
            (self.component_id is None or peer[1] == self.component_id)

    async def start(self, deliver: Deliver) -> None:
        self._deliver = deliver
        self.channel.add(self)

    async def stop(self) -> None:
        """Take no new messages; return once those being delivered are settled."""
        await self.channel.remove(self)
        await self._idle.wait()

    async def deliver_batch(self, inbounds: list[Inbound]) -> list[bool]:
        """Settle ``inbounds`` with the route; which of them were settled (an engine failure
        settles none: the sender retransmits them)."""
        assert self._deliver is not None
        self._busy += 1
        self._idle.clear()
        try:
            return await settle_batch(self._deliver, inbounds, f"tunnel route {self.route!r}")
        finally:
            self._busy -= 1
            if not self._busy:
                self._idle.set()



def ignore_result(future: asyncio.Future[Any]) -> None:
    """Acknowledgements are best effort: the sender's timer covers one that was not written."""
    if not future.cancelled():
        future.exception()
