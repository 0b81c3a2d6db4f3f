"""One MAVLink link with its writer and reader: the part every MAVLink peer needs.

A :class:`MavlinkPort` owns a link (see :mod:`.links`), packs frames at write time (so sequence
numbers and signing timestamps go out in wire order, which a receiver requires), paces them to
the link rate (a SiK radio's serial buffer is a few hundred bytes to 2 KB and overflows
silently), sends control frames before the routes' frames and those by the routes' priority,
and keeps the routes' frames within the radio's budget (:mod:`.budget`: it follows the
RADIO_STATUS the radio injects).

What the writer sends next (one frame at a time, so a frame waits at most for the one being
written, never for a queue of lower ones):

1. control: commands, mission items, tunnel acknowledgements, heartbeats (``priority`` None),
   paced only to the link rate;
2. then by the route's ``priority`` (``high``, ``normal``, ``low``): at each level a message
   sink's frames, then its tunnel fragments, all within the budget (a frame not due yet
   under it waits; on networks there is no budget).

A frame queued with a ``key`` (a telemetry route's message: its sink, its ``latest_only``
value) that is still waiting when a newer frame with the same key comes is replaced by it in
its place in the queue; the older one's future fails with :class:`Conflated`, and its route
counts it ``conflated``. Frames without a key wait their turn.

Measured on the emulated SiK radio (57,600 baud; tests/endpoints/mavlink/test_link_priority.py): a 200-byte
``high`` tunnel message under a saturating ``low`` tunnel load of 2 KB bundles took 4.1 s
when both queued in one bulk lane; with the lanes it waits for the fragment on the wire and
the bytes already in the radio's buffer, then crosses in its own fragments' time and a TDM
round (see the test for the figure). Received bytes are cut into frames by framing.py (a
datagram on its own, a stream per peer; a rejected frame costs only itself) and decoded by
pymavlink; signatures are checked and every accepted message is handed to ``on_message``. The engine's connection and the
simulated vehicle both run on it.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable

from engine.endpoints.base import Conflated, EndpointError
from engine.endpoints.mavlink.budget import RadioBudget
from engine.endpoints.mavlink.codec import RADIO_STATUS, mavlink2
from engine.endpoints.mavlink.errors import edge_error
from engine.endpoints.mavlink.framing import BAD_FRAME_REASONS, FrameReader
from engine.endpoints.mavlink.links import Link, OnBytes, make_link
from engine.endpoints.mavlink.settings import Address, LinkConfig
from engine.endpoints.mavlink.signing import SignatureCheck, SigningClock
from engine.endpoints.mavlink.tunnel import TUNNEL_PAYLOAD, ignore_result

MAX_PARSERS = 32
STALE_FRAME_S = 0.5
"""A stream frame not complete this long after it started to arrive is given up
(framing.py): a false start byte in noise claims up to 280 bytes, many seconds of a quiet link
(a 21-byte HEARTBEAT a second: 13 s, long past a vehicle's heartbeat_timeout). A real frame
takes 49 ms at 57,600 baud; a SiK radio sends whole frames per air packet, a TDM round (~236 ms)
apart at worst."""

PORT_STATS = (
    "bytes_received", "frames_received", "frames_accepted", "frames_lost", *BAD_FRAME_REASONS,
    "unknown_message", "unsigned_rejected", "unsigned_accepted", "bad_signature", "replayed",
    "frames_sent", "bytes_sent", "send_errors", "budget_queued", "budget_conflated",
)
"""``frames_received`` counts frames with a good CRC, ``frames_accepted`` those that also passed
signing; bad frames (``bad_crc``, ``bad_data``, ``truncated``) and ``unknown_message`` are
counted by the framing (framing.py); ``frames_lost`` sums sequence gaps per sender; rejections: ``unsigned_rejected``,
``bad_signature`` (wrong key or altered), ``replayed`` (timestamp not newer than the stream's
last, or a new stream over 60 s old); ``budget_queued``: route frames that had to wait for the
radio's budget, ``budget_conflated``: those of them a newer one with the same key replaced."""

OnMessage = Callable[[mavlink2.MAVLink_message], None]


class _Queued:
    """A frame waiting for the writer: the message, who waits for it, its conflation key."""

    __slots__ = ("msg", "future", "key")

    def __init__(self, msg: mavlink2.MAVLink_message, future: asyncio.Future[float], key: Hashable | None) -> None:
        self.msg = msg
        self.future = future
        self.key = key


PRIORITIES = ("high", "normal", "low")
"""A route's ``priority`` (engine/language/route_options.py declares it); control frames go before all."""


class MavlinkPort:
    """Paced, signed writing and verified, dispatched reading on one link."""

    def __init__(self, name: str, config: LinkConfig, on_message: OnMessage, stats: dict[str, int]) -> None:
        self.name = name
        self.config = config
        self.on_message = on_message
        self.stats = stats
        for key in PORT_STATS:
            stats.setdefault(key, 0)
        self.mav = mavlink2.MAVLink(None, config.source_system, config.source_component)
        self.budget = RadioBudget(config.bulk_rate)
        """Bytes/s the routes' frames may take, following the radio's RADIO_STATUS."""
        self.on_lost: Callable[[], None] | None = None
        self.make_link: Callable[[Address, OnBytes, dict[str, int]], Link] = make_link
        """The link under the port (a connection split over workers gives its own, split.py)."""
        self._clock: SigningClock | None = None
        self._check: SignatureCheck | None = None
        self._link: Link | None = None
        self._readers: OrderedDict[Hashable, FrameReader] = OrderedDict()
        """A stream's frame reader per peer (a ``tcpin`` server's clients are separate streams)."""
        self._datagram_reader = FrameReader(self.stats)
        self._datagrams = False
        self._stale_timers: dict[Hashable, tuple[int, asyncio.TimerHandle]] = {}
        """Per stream peer: where its waiting frame starts, and the timer that gives it up."""
        self._last_seq: dict[tuple[int, int], int] = {}
        self.lost_by_system: dict[int, int] = {}
        """Frames missing from each system's sequence numbers (its components' streams summed)."""
        self._heard_at: dict[int, Hashable] = {}
        """System id -> the peer its last accepted frame came from (a udpin link with several
        vehicles writes a message targeted at one of them to that peer only)."""
        self._peer: Hashable | None = None
        self._control: deque[_Queued] = deque()
        self._lanes: list[tuple[deque[_Queued], bool]] = [(self._control, False)]
        """In the order the writer serves them: (queue, within the budget)."""
        self._by_priority: dict[tuple[str, bool], deque[_Queued]] = {}
        for priority in PRIORITIES:
            for bulk in (False, True):
                queue: deque[_Queued] = deque()
                self._by_priority[(priority, bulk)] = queue
                self._lanes.append((queue, True))
        self._waiting: dict[Hashable, _Queued] = {}
        """Queued frames with a conflation key, by key."""
        self._wake = asyncio.Event()
        self._tx_ready = 0.0
        self._budget_ready = 0.0
        self._task: asyncio.Task[None] | None = None
        self._closed = False

    @property
    def address(self) -> tuple[str, int] | None:
        """Bound (host, port) of ``udpin``/``tcpin`` links; useful with port 0."""
        return self._link.local_address if self._link else None

    def clock(self) -> float:
        """The loop time the budget's reports are stamped with (the loop's own clock)."""
        try:
            return asyncio.get_running_loop().time()
        except RuntimeError:
            return time.monotonic()

    @property
    def ready(self) -> bool:
        """Whether a frame written now has somewhere to go."""
        return self._link is not None and self._link.ready

    async def open(self) -> None:
        signing = self.config.signing
        if signing is not None:
            self._clock = SigningClock(signing.timestamp_file)
            s = self.mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = signing.key, signing.link_id, True
            s.timestamp = self._clock.start()
            self._check = SignatureCheck(signing, lambda: self.mav.signing.timestamp)
        self._link = self.make_link(self.config.address, self._on_bytes, self.stats)
        self._link.on_lost = self._lost
        self._datagrams = self._link.datagrams
        await self._link.open()
        self._task = asyncio.create_task(self._writer(), name=f"mavlink-writer:{self.name}")

    async def close(self) -> None:
        self._closed = True
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None
        self._waiting.clear()
        for _, timer in self._stale_timers.values():
            timer.cancel()
        self._stale_timers.clear()
        for queue, _ in self._lanes:
            while queue:
                future = queue.popleft().future
                if not future.done():
                    future.set_exception(EndpointError(f"mavlink connection {self.name!r} closed"))
        if self._link is not None:
            await self._link.close()

    def _lost(self) -> None:
        if self.on_lost is not None:
            self.on_lost()

    # writing

    def enqueue(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False,
                priority: str | None = None, key: Hashable | None = None, first: bool = False) -> asyncio.Future[float]:
        """Queue a frame for the writer; the future gives the loop time it was written.
        ``first``: at the front of its lane (a tunnel fragment sent again).
        ``priority`` None is control (before every route's frames, outside the budget);
        ``bulk`` frames (tunnel fragments) go after the message frames of their priority.
        A frame with a ``key`` replaces a waiting one with the same key (whose future fails
        with :class:`Conflated`), in its place."""
        future: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        if self._closed or self._link is None:
            future.set_exception(EndpointError(f"mavlink connection {self.name!r} is not open"))
            return future
        if priority is None and not bulk:
            self._control.append(_Queued(msg, future, None))
        else:
            if self.budget.ceiling:
                self.stats["budget_queued"] += asyncio.get_running_loop().time() < self._budget_ready
            waiting = self._waiting.get(key) if key is not None else None
            if waiting is not None:
                self.stats["budget_conflated"] += 1
                if not waiting.future.done():
                    waiting.future.set_exception(Conflated("a newer message with the same key took its place"))
                waiting.msg, waiting.future = msg, future
                return future
            queued = _Queued(msg, future, key)
            lane = self._by_priority[(priority or "normal", bulk)]
            if first:
                lane.appendleft(queued)
            else:
                lane.append(queued)
            if key is not None:
                self._waiting[key] = queued
        self._wake.set()
        return future

    def post(self, msg: mavlink2.MAVLink_message) -> None:
        """Queue a frame nobody waits for (telemetry, heartbeats): a failure is only counted."""
        self.enqueue(msg).add_done_callback(ignore_result)

    async def send_message(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False,
                           priority: str | None = None, key: Hashable | None = None) -> float:
        return await self.enqueue(msg, bulk=bulk, priority=priority, key=key)

    def send_tunnel(self, payload_type: int, target: tuple[int, int], payload: bytes, *,
                    bulk: bool, priority: str | None = None, first: bool = False) -> asyncio.Future[float]:
        msg = mavlink2.MAVLink_tunnel_message(target[0], target[1], payload_type, len(payload),
                                              payload.ljust(TUNNEL_PAYLOAD, b"\0"))
        return self.enqueue(msg, bulk=bulk, priority=priority, first=first)

    def _next(self, now: float) -> tuple[_Queued, bool] | None:
        """The frame to write now (see the module docstring), and whether it is paced."""
        budget_due = now >= self._budget_ready
        for queue, paced in self._lanes:
            if queue and (budget_due or not paced):
                queued = queue.popleft()
                if queued.key is not None and self._waiting.get(queued.key) is queued:
                    del self._waiting[queued.key]
                return queued, paced
        return None

    def _paced_waiting(self) -> bool:
        return any(queue for queue, paced in self._lanes if paced)

    async def _writer(self) -> None:
        loop = asyncio.get_running_loop()
        rate = self.config.rate
        assert self._link is not None
        while True:
            now = loop.time()
            picked = self._next(now)
            if picked is None:
                self._wake.clear()
                timeout = max(0.0, self._budget_ready - now) if self._paced_waiting() else None
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), timeout)
                continue
            queued, paced = picked
            msg, future = queued.msg, queued.future
            if future.done():
                continue
            if self._tx_ready > now:
                await asyncio.sleep(self._tx_ready - now)
            start = loop.time()
            try:
                data = self._pack(msg)
            except Exception as exc:  # pymavlink struct errors: this message can never be sent
                self.stats["send_errors"] += 1
                if not future.done():
                    future.set_exception(edge_error(exc, f"{msg.get_type()}: cannot encode"))
                continue
            target = getattr(msg, "target_system", 0)
            try:
                await self._link.transmit(data, self._link.peer_for(target, self._heard_at) if target else None)
            except EndpointError as exc:
                self.stats["send_errors"] += 1
                if not future.done():
                    future.set_exception(exc)
                continue
            if self._link.relayed:  # handed to the worker holding a split link, which writes and counts it
                self.stats["split_sent"] += 1
            else:
                self.stats["frames_sent"] += 1
                self.stats["bytes_sent"] += len(data)
            if rate:
                self._tx_ready = max(self._tx_ready, start) + len(data) / rate
            if paced and (budget := self.budget.rate(start)):
                self._budget_ready = max(self._budget_ready, start) + len(data) / budget
                self.budget.sent(len(data))
            if not future.done():
                future.set_result(loop.time())

    def _pack(self, msg: mavlink2.MAVLink_message) -> bytes:
        if self._clock is not None:
            signing = self.mav.signing
            signing.timestamp = self._clock.advance(max(signing.timestamp, self._check.newest if self._check else 0))
        data: bytes = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return data

    # reading

    def _reader(self, peer: Hashable) -> FrameReader:
        reader = self._readers.get(peer)
        if reader is None:
            reader = self._readers[peer] = FrameReader(self.stats)
            while len(self._readers) > MAX_PARSERS:
                self._readers.popitem(last=False)
        return reader

    def _on_bytes(self, data: bytes, peer: Hashable) -> None:
        """A datagram is parsed on its own; a stream's chunk continues its peer's stream
        (framing.py says why)."""
        self.stats["bytes_received"] += len(data)
        if self._datagrams:
            messages = self._datagram_reader.datagram(data)
        else:
            reader = self._reader(peer)
            messages = reader.stream(data)
            self._watch_waiting(peer, reader)
        self._peer = peer
        for msg in messages:
            self._on_frame(msg)

    def _watch_waiting(self, peer: Hashable, reader: FrameReader) -> None:
        """Give up the stream's waiting frame if it is still waiting in :data:`STALE_FRAME_S`;
        one timer per waiting frame, not per chunk."""
        waiting_at = reader.waiting_at
        timer = self._stale_timers.get(peer)
        if timer is not None and timer[0] == waiting_at:
            return
        if timer is not None:
            timer[1].cancel()
            del self._stale_timers[peer]
        if waiting_at is not None and not self._closed:
            handle = asyncio.get_running_loop().call_later(STALE_FRAME_S, self._stale, peer, waiting_at)
            self._stale_timers[peer] = (waiting_at, handle)

    def _stale(self, peer: Hashable, waiting_at: int) -> None:
        self._stale_timers.pop(peer, None)
        reader = self._readers.get(peer)
        if reader is None or reader.waiting_at != waiting_at:
            return
        messages = reader.give_up_waiting()
        self._watch_waiting(peer, reader)
        self._peer = peer
        for msg in messages:
            self._on_frame(msg)

    def _on_frame(self, msg: mavlink2.MAVLink_message) -> None:
        msg_id = msg.get_msgId()
        self.stats["frames_received"] += 1
        if self._check is not None:
            buf = msg.get_msgbuf()
            verdict = self._check(buf)
            if verdict is not None:
                self.stats[verdict] += 1
                return
            if buf[0] != mavlink2.PROTOCOL_MARKER_V2 or not buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
                self.stats["unsigned_accepted"] += 1
        self.stats["frames_accepted"] += 1
        header = msg.get_header()
        self._heard_at[header.srcSystem] = self._peer
        stream = (header.srcSystem, header.srcComponent)
        last = self._last_seq.get(stream)
        if last is not None and (gap := (header.seq - last - 1) % 256):
            self.stats["frames_lost"] += gap
            self.lost_by_system[header.srcSystem] = self.lost_by_system.get(header.srcSystem, 0) + gap
        self._last_seq[stream] = header.seq
        if msg_id == RADIO_STATUS:
            self.budget.report(msg, asyncio.get_running_loop().time())
        self.on_message(msg)

