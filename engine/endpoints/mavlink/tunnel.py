"""JSON over MAVLink: whole messages carried in TUNNEL frames with selective-repeat ARQ.

A canonical JSON message is usually larger than one TUNNEL payload (128 bytes) and a SiK
radio loses whole frames, so a message is cut into fragments, reassembled, checked with a
CRC-32 and acknowledged selectively; lost fragments, not whole messages, are sent again.

Wire format, inside ``TUNNEL.payload`` (little endian), ``payload_type`` private (>= 32768,
default 0xA900) and used as the channel, so several tunnel routes can share a link::

    DATA    u8 ver<<4 | 0   u16 msg_id   u8 index   u8 count   data[...]
    ACK     u8 ver<<4 | 1   u16 msg_id   u8 flags   u8 count   bitmap[ceil(count/8)]
    BUNDLE  u8 ver<<4 | 2   as DATA; the body is several messages, each u16 length + bytes

The body is followed by ``crc32(body)`` before cutting (for a BUNDLE, the CRC-32 starts from
``BUNDLE_CRC_START``), so a fragment mixed in from another message (id wrap-around, sender
restart) is caught. Every fragment but the last carries the same number of bytes, so the
length needs no field of its own: version 1 sent it (``u16 total``) in every fragment, two
bytes of 107 (1.9 % of the goodput) that said what the fragments and the CRC already say. ACK ``flags``: 1 = the receiver
holds every fragment (the bitmap is then omitted), 2 = delivered; bit ``i`` of the bitmap
(byte ``i // 8``, bit ``i % 8``) says fragment ``i`` is held.

Bundles: when several messages wait for the sink's window (the link is busy, so they
queued; from one batch of the route or from several in flight), consecutive ones are sent
together as one BUNDLE of at most ``bundle`` bytes, formed when a window slot frees. The
fragments then run full across message boundaries and one acknowledgement covers them all:
a 250-byte message alone needs three fragments (254 bytes with its CRC) and a SiK radio's
TDM window holds five or six, so without bundles two such messages cross per window; eight
in a bundle take 21 fragments.
Each message of a bundle is delivered to the routes on its own, and the bundle is
acknowledged DELIVERED once every route settled every one of them.

Reliability: the receiver acknowledges DELIVERED only once the engine settled the message,
so a completed ``Sink.send`` means at-least-once delivery; ids it delivered recently are
remembered (bounded by count and age) and a repeat only earns another DELIVERED. It sends a
SACK at once when the last fragment arrives with gaps, and after ``sack_delay`` of silence
while incomplete (backing off). The sender retransmits a fragment when a fragment sent after
it is acknowledged (the link keeps order, so it was lost) or when its retransmission timer
(SRTT + 4 RTTVAR, at least ``rto_min``, doubling per unanswered timeout) expires; after
``retries`` timeouts without progress it gives up. A route with ``max_age`` (telemetry) ends a
transfer sooner: once its newest message is older than that, it is not sent (again); each of
its messages is reported :class:`~engine.endpoints.base.Expired` and counted ``expired`` by its
route (``tunnel_expired`` on the link), instead of being retransmitted for as long as an
outage lasts.

:class:`Transfer` and :class:`Reassembler` are pure state machines driven by frames and a
clock; :class:`TunnelSink`, :class:`TunnelSource` and :class:`TunnelHub` drive them on asyncio.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import struct
import time
import zlib
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, cast

from engine.common.schemas import SchemaError, canonical_bytes
from engine.endpoints.base import (
    Deliver,
    EndpointError,
    Expired,
    Inbound,
    Inbox,
    MessageRejected,
    Outbound,
    Sink,
    Source,
)

DEFAULT_PAYLOAD_TYPE = 0xA900
TUNNEL_PAYLOAD = 128
VERSION = 2
KIND_DATA = 0
KIND_ACK = 1
KIND_BUNDLE = 2
FLAG_COMPLETE = 1
FLAG_DELIVERED = 2
_DATA = struct.Struct("<BHBB")
_ACK = struct.Struct("<BHBB")
MAX_FRAGMENT = TUNNEL_PAYLOAD - _DATA.size
MAX_FRAGMENTS = 255
SIK_FRAGMENT = 102
"""Fragment size on serial links: a TUNNEL frame of 124 bytes (12 of MAVLink 2 framing, 5 of
TUNNEL fields, the 5-byte header, 102 of data), so two share a 252-byte SiK air packet; a
123-byte fragment makes 145-byte frames that travel one per packet. On the emulator flooded
with frames of one size (bench/sections.py), TUNNEL payloads of 107 bytes carried 2,260 B/s and
of 121 bytes 2,027 B/s; 94-byte ones (three pairs fit a TDM window with room to spare) carried
2,366 B/s alone but did no better in the round trip, where telemetry shares the packets."""
CRC_SIZE = 4
BUNDLE_CRC_START = 0x42554E44
DELIVERY_BATCH = 64
"""Most reassembled messages settled together (one ``Deliver.batch`` per route)."""

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Data:
    msg_id: int
    index: int
    count: int
    chunk: bytes
    bundle: bool = False
    """The reassembled body is a bundle of messages (see :func:`bundle`)."""


@dataclass(frozen=True, slots=True)
class Ack:
    msg_id: int
    count: int
    flags: int
    held: int
    """Bitmap of fragments the receiver holds (all of them when FLAG_COMPLETE is set)."""


def encode_data(d: Data) -> bytes:
    kind = KIND_BUNDLE if d.bundle else KIND_DATA
    return _DATA.pack(VERSION << 4 | kind, d.msg_id, d.index, d.count) + d.chunk


def encode_ack(a: Ack) -> bytes:
    head = _ACK.pack(VERSION << 4 | KIND_ACK, a.msg_id, a.flags, a.count)
    if a.flags & FLAG_COMPLETE:
        return head
    return head + a.held.to_bytes((a.count + 7) // 8, "little")


def decode(payload: bytes) -> Data | Ack:
    """Parse one tunnel payload; ValueError when it is not ours or is malformed."""
    if not payload or payload[0] >> 4 != VERSION:
        raise ValueError("not a tunnel frame of this version")
    kind = payload[0] & 0x0F
    if kind in (KIND_DATA, KIND_BUNDLE) and len(payload) >= _DATA.size:
        _, msg_id, index, count = _DATA.unpack_from(payload)
        if count == 0 or index >= count or len(payload) == _DATA.size:
            raise ValueError("bad DATA header")
        return Data(msg_id, index, count, bytes(payload[_DATA.size:]), kind == KIND_BUNDLE)
    if kind == KIND_ACK and len(payload) >= _ACK.size:
        _, msg_id, flags, count = _ACK.unpack_from(payload)
        if count == 0:
            raise ValueError("bad ACK header")
        if flags & FLAG_COMPLETE:
            held = (1 << count) - 1
        else:
            held = int.from_bytes(payload[_ACK.size:_ACK.size + (count + 7) // 8], "little")
        return Ack(msg_id, count, flags, held & ((1 << count) - 1))
    raise ValueError("unknown tunnel frame")


def fragment(msg_id: int, body: bytes, fragment_size: int = MAX_FRAGMENT, *, bundled: bool = False) -> list[bytes]:
    """Encoded DATA (BUNDLE when ``bundled``) payloads for ``body``; ValueError when it needs
    more than 255 fragments."""
    if not 1 <= fragment_size <= MAX_FRAGMENT:
        raise ValueError(f"fragment_size must be 1..{MAX_FRAGMENT}")
    whole = body + _crc(body, bundled)
    count = -(-len(whole) // fragment_size)
    if count > MAX_FRAGMENTS or len(whole) > 0xFFFF:
        raise ValueError(f"message of {len(body)} bytes exceeds {MAX_FRAGMENTS} fragments of {fragment_size} bytes")
    return [
        encode_data(Data(msg_id, i, count, whole[i * fragment_size:(i + 1) * fragment_size], bundled))
        for i in range(count)
    ]


def _crc(body: bytes, bundled: bool) -> bytes:
    """CRC-32 of the body; a bundle's starts from another value, so a damaged kind bit in a
    header cannot turn a message into a bundle or back."""
    return zlib.crc32(body, BUNDLE_CRC_START if bundled else 0).to_bytes(CRC_SIZE, "little")


_LENGTH = struct.Struct("<H")


def bundle(bodies: Sequence[bytes]) -> bytes:
    """The body of a BUNDLE: each message as ``u16 length`` + its bytes."""
    return b"".join(_LENGTH.pack(len(body)) + body for body in bodies)


def bundled_size(sizes: Sequence[int]) -> int:
    return sum(sizes) + _LENGTH.size * len(sizes)


def unbundle(body: bytes) -> list[bytes]:
    """The messages of a BUNDLE body; ValueError when the lengths do not add up."""
    out, at = [], 0
    while at < len(body):
        if at + _LENGTH.size > len(body):
            raise ValueError("truncated bundle")
        (size,) = _LENGTH.unpack_from(body, at)
        at += _LENGTH.size
        if at + size > len(body):
            raise ValueError("truncated bundle")
        out.append(body[at:at + size])
        at += size
    if not out:
        raise ValueError("empty bundle")
    return out


@dataclass(slots=True)
class RttEstimator:
    """Jacobson/Karels retransmission timeout, shared by the transfers of one channel."""

    rto_min: float = 0.5
    rto_max: float = 8.0
    srtt: float | None = None
    rttvar: float = 0.0

    def sample(self, rtt: float) -> None:
        if self.srtt is None:
            self.srtt, self.rttvar = rtt, rtt / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - rtt)
            self.srtt = 0.875 * self.srtt + 0.125 * rtt

    @property
    def rto(self) -> float:
        if self.srtt is None:
            return min(self.rto_max, 2 * self.rto_min)
        return min(self.rto_max, max(self.rto_min, self.srtt + 4 * self.rttvar))


class Transfer:
    """Sender side of one message: what the receiver holds and what to (re)send when."""

    def __init__(self, msg_id: int, body: bytes, *, fragment_size: int = MAX_FRAGMENT,
                 rtt: RttEstimator | None = None, retries: int = 8, bundled: bool = False) -> None:
        self.msg_id = msg_id
        self.frames = fragment(msg_id, body, fragment_size, bundled=bundled)
        self.count = len(self.frames)
        self.rtt = rtt or RttEstimator()
        self.max_retries = retries
        self.sent_at: list[float | None] = [None] * self.count
        self.tx_count = [0] * self.count
        self.held = 0
        self.complete = False
        self.delivered = False
        self.failed = False
        self.retries = 0
        self.retransmissions = 0
        self.probe: int | None = None
        """A fragment to send again although the receiver said it held it (see on_timeout)."""
        self._backoff = 1.0
        self._last_tx: float | None = None
        self._waiting_since: float | None = None

    def missing(self) -> list[int]:
        return [i for i in range(self.count) if not self.held >> i & 1]

    def is_held(self, index: int) -> bool:
        return bool(self.held >> index & 1)

    def on_sent(self, index: int, now: float) -> None:
        if self.tx_count[index]:
            self.retransmissions += 1
        self.tx_count[index] += 1
        self.sent_at[index] = now
        self._last_tx = now

    def deadline(self) -> float | None:
        """When to give up waiting for an acknowledgement; None before anything was sent."""
        start = self._last_tx if self._waiting_since is None else max(self._last_tx or 0.0, self._waiting_since)
        if start is None:
            return None
        return start + min(self.rtt.rto_max, self.rtt.rto * self._backoff)

    def on_ack(self, ack: Ack, now: float) -> list[int]:
        """Fragments to retransmit now because of ``ack``."""
        if ack.msg_id != self.msg_id or ack.count != self.count or self.delivered:
            return []
        newly = ack.held & ~self.held
        if ack.flags & FLAG_DELIVERED:
            newly = (1 << self.count) - 1 & ~self.held
        if newly:
            self._sample(newly, now)
        if newly or ack.flags & (FLAG_DELIVERED | FLAG_COMPLETE) and not self.complete:
            self.retries = 0
            self._backoff = 1.0
        self.held = ack.held
        if ack.flags & FLAG_DELIVERED:
            self.held = (1 << self.count) - 1
            self.delivered = self.complete = True
            return []
        if ack.flags & FLAG_COMPLETE:
            self.complete = True
            self._waiting_since = now
            return []
        self.complete = False
        times = [t for i, t in enumerate(self.sent_at) if t is not None and ack.held >> i & 1]
        if not times:
            return []
        newest = max(times)
        return [i for i in self.missing() if (t := self.sent_at[i]) is not None and t < newest]

    def on_timeout(self, now: float) -> list[int]:
        """Fragments to send after the deadline passed; sets ``failed`` when out of retries."""
        self.retries += 1
        if self.retries > self.max_retries:
            self.failed = True
            return []
        self._backoff = min(self._backoff * 2, 64.0)
        self._waiting_since = now
        missing = self.missing()
        if missing:
            return missing
        # The receiver holds it all but has not settled it: probe with the last fragment. If
        # the route failed it, the receiver forgot the message and its SACK asks for the rest.
        self.probe = self.count - 1
        return [self.probe]

    def _sample(self, newly: int, now: float) -> None:
        """Karn's rule: only fragments sent once give an unambiguous round-trip time."""
        candidates = [t for i, t in enumerate(self.sent_at) if t is not None and self.tx_count[i] == 1 and newly >> i & 1]
        if candidates:
            self.rtt.sample(max(0.0, now - max(candidates)))


@dataclass(slots=True)
class _Partial:
    count: int
    bundle: bool
    chunks: dict[int, bytes]
    last_seen: float
    sack_at: float | None = None
    sack_gap: float = 0.0


@dataclass(slots=True)
class _Known:
    count: int
    bundle: bool = False
    until: float = 0.0
    last_ack: float = float("-inf")


@dataclass
class ReassemblerStats:
    fragments: int = 0
    duplicate_fragments: int = 0
    after_delivery: int = 0
    crc_errors: int = 0
    expired: int = 0
    evicted: int = 0
    completed: int = 0
    acks: int = 0


Key = tuple[Hashable, int]


class Reassembler:
    """Receiver side: reassembly, deduplication and the acknowledgements to send.

    ``peer`` identifies the sender (MAVLink sysid/compid); ids are per peer. Returns encoded
    ACK payloads, to be sent back to that peer.
    """

    def __init__(self, *, sack_delay: float = 0.25, sack_max: float = 4.0, timeout: float = 60.0,
                 max_partial: int = 16, memory: int = 1024, memory_ttl: float = 300.0,
                 ack_interval: float = 0.1) -> None:
        self.sack_delay = sack_delay
        self.sack_max = sack_max
        self.timeout = timeout
        self.max_partial = max_partial
        self.memory = memory
        self.memory_ttl = memory_ttl
        self.ack_interval = ack_interval
        self.stats = ReassemblerStats()
        self._partial: dict[Key, _Partial] = {}
        self._delivering: dict[Key, _Known] = {}
        self._done: OrderedDict[Key, _Known] = OrderedDict()

    def on_data(self, peer: Hashable, data: Data, now: float) -> tuple[list[bytes], tuple[Key, bytes] | None]:
        self.stats.fragments += 1
        key = (peer, data.msg_id)
        shape = (data.count, data.bundle)
        known = self._done.get(key)
        if known is not None and (known.count, known.bundle) == shape and now < known.until:
            self.stats.duplicate_fragments += 1
            return self._repeat_ack(known, data, FLAG_DELIVERED | FLAG_COMPLETE, now), None
        if known is not None:
            del self._done[key]
        known = self._delivering.get(key)
        if known is not None and (known.count, known.bundle) == shape:
            self.stats.duplicate_fragments += 1
            return self._repeat_ack(known, data, FLAG_COMPLETE, now), None

        partial = self._partial.get(key)
        if partial is not None and (partial.count, partial.bundle) != shape:
            del self._partial[key]
            partial = None
        if partial is None:
            if len(self._partial) >= self.max_partial:
                oldest = min(self._partial, key=lambda k: self._partial[k].last_seen)
                del self._partial[oldest]
                self.stats.evicted += 1
            partial = self._partial[key] = _Partial(data.count, data.bundle, {}, now)
        if data.index in partial.chunks:
            self.stats.duplicate_fragments += 1
        partial.chunks[data.index] = data.chunk
        partial.last_seen = now

        if len(partial.chunks) == partial.count:
            del self._partial[key]
            whole = b"".join(partial.chunks[i] for i in range(partial.count))
            body, crc = whole[:-CRC_SIZE], whole[-CRC_SIZE:]
            if not _evenly_cut(partial) or len(whole) <= CRC_SIZE or _crc(body, partial.bundle) != crc \
                    or partial.bundle and not _is_bundle(body):
                self.stats.crc_errors += 1
                return [self._ack(Ack(data.msg_id, data.count, 0, 0))], None
            self._delivering[key] = _Known(partial.count, partial.bundle, last_ack=now)
            self.stats.completed += 1
            return [], (key, body)

        if data.index == data.count - 1:
            partial.sack_gap = self.sack_delay
            partial.sack_at = now + 2 * self.sack_delay
            return [self._sack(data.msg_id, partial)], None
        partial.sack_gap = self.sack_delay
        partial.sack_at = now + self.sack_delay
        return [], None

    def messages(self, key: Key, body: bytes) -> list[bytes]:
        """The messages of the reassembled ``body`` of ``key`` (several for a bundle)."""
        known = self._delivering.get(key)
        return unbundle(body) if known is not None and known.bundle else [body]

    def delivered(self, key: Key, now: float) -> bytes:
        """The engine settled ``key``: remember it and return the DELIVERED acknowledgement."""
        known = self._delivering.pop(key)
        known.until = now + self.memory_ttl
        known.last_ack = now
        self._done[key] = known
        self._done.move_to_end(key)
        while len(self._done) > self.memory:
            self._done.popitem(last=False)
        return self._ack(Ack(key[1], known.count, FLAG_DELIVERED | FLAG_COMPLETE, 0))

    def failed(self, key: Key) -> None:
        """Delivery failed: forget the message so the sender's retransmissions rebuild it."""
        self._delivering.pop(key, None)

    def poll(self, now: float) -> list[tuple[Hashable, bytes]]:
        """Timed SACKs for incomplete messages, and expiry of stale state."""
        out: list[tuple[Hashable, bytes]] = []
        for key, partial in list(self._partial.items()):
            if now - partial.last_seen > self.timeout:
                del self._partial[key]
                self.stats.expired += 1
            elif partial.sack_at is not None and now >= partial.sack_at:
                out.append((key[0], self._sack(key[1], partial)))
                partial.sack_gap = min(self.sack_max, partial.sack_gap * 2)
                partial.sack_at = now + partial.sack_gap
        while self._done:
            key, known = next(iter(self._done.items()))
            if known.until > now:
                break
            del self._done[key]
        return out

    def next_deadline(self) -> float | None:
        times = [p.sack_at for p in self._partial.values() if p.sack_at is not None]
        times += [p.last_seen + self.timeout for p in self._partial.values()]
        if self._done:
            times.append(next(iter(self._done.values())).until)
        return min(times) if times else None

    def _repeat_ack(self, known: _Known, data: Data, flags: int, now: float) -> list[bytes]:
        if flags & FLAG_DELIVERED:
            self.stats.after_delivery += 1
        if now - known.last_ack < self.ack_interval:
            return []
        known.last_ack = now
        return [self._ack(Ack(data.msg_id, data.count, flags, 0))]

    def _sack(self, msg_id: int, partial: _Partial) -> bytes:
        held = 0
        for i in partial.chunks:
            held |= 1 << i
        return self._ack(Ack(msg_id, partial.count, 0, held))

    def _ack(self, ack: Ack) -> bytes:
        self.stats.acks += 1
        return encode_ack(ack)


def _evenly_cut(partial: _Partial) -> bool:
    """Every fragment but the last carries the same number of bytes, the last no more."""
    sizes = [len(partial.chunks[i]) for i in range(partial.count)]
    return all(size == sizes[0] for size in sizes[:-1]) and sizes[-1] <= sizes[0]


def _is_bundle(body: bytes) -> bool:
    try:
        unbundle(body)
    except ValueError:
        return False
    return True


# -- asyncio drivers ------------------------------------------------------------------------


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
        route, the routes in parallel); acknowledge DELIVERED each message every route settled."""
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


@dataclass(slots=True)
class _Waiting:
    """A message handed to :meth:`TunnelSink.send_many`, until a transfer carries it."""

    body: bytes
    expires_ns: int | None
    outcome: asyncio.Future[BaseException | None]


class TunnelSink(Sink):
    """Sends ``Outbound.body`` whole; returns once the receiver acknowledged delivery.

    Up to four of a route's batches may be in flight (:attr:`Sink.batches_in_flight`): a
    batch is accepted only once the vehicle acknowledged its last transfer, a TDM round and
    more, seconds when a last fragment or its acknowledgement was lost, and with one batch at
    a time the radio stood idle for that long after every batch (measured on the emulated SiK
    radio at 5 % loss: 4 s of 22 after a batch of 128 messages; bench/results/2026-11-23/goodput/).
    Bundles are formed when a window slot frees, of every message then waiting, whichever
    batch it came in, so small batches in flight still travel as full bundles."""

    batches_in_flight = 4

    def __init__(self, hub: TunnelHub, *, payload_type: int = DEFAULT_PAYLOAD_TYPE,
                 target: tuple[int, int] = (0, 0), priority: str = "normal", max_age: float | None = None) -> None:
        self.hub = hub
        self.payload_type = payload_type
        self.target = target
        self.max_age_ns = None if max_age is None else int(max_age * 1e9)
        """The route's ``max_age``: a transfer still unacknowledged when its newest message is
        older than that is given up, each of its messages :class:`Expired` (never sent again)."""
        self.priority = priority
        """The route's ``priority``: the link's writer sends a ``high`` sink's fragments before
        the ``normal`` and ``low`` ones already queued (engine/endpoints/mavlink/port.py)."""
        self._window = asyncio.Semaphore(hub.settings.window)
        self._waiting: deque[_Waiting] = deque()
        """Messages of :meth:`send_many` not yet in a transfer, in the order they came."""
        self._arrived = asyncio.Event()
        self._dispatcher: asyncio.Task[None] | None = None
        self._transfers: set[asyncio.Task[None]] = set()
        hub.add_sender(payload_type)

    async def send(self, message: Outbound) -> None:
        await self.send_bytes(self._body(message), expires_ns=self._expiry(message.received_ns))

    def _expiry(self, received_ns: int | None) -> int | None:
        """``time.monotonic_ns()`` after which a message received at ``received_ns`` expired."""
        if self.max_age_ns is None or received_ns is None:
            return None
        return received_ns + self.max_age_ns

    @staticmethod
    def _body(message: Outbound) -> bytes:
        """The canonical bytes, or the JSON of what ``sink.mapping`` made of them."""
        if message.fields is message.canonical:
            return message.body
        try:
            return canonical_bytes(message.fields)
        except SchemaError as exc:
            raise MessageRejected(f"tunnel: {exc}") from None

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        results: list[BaseException | None] = [None] * len(messages)
        bodies: list[tuple[int, bytes]] = []
        for index, message in enumerate(messages):
            try:
                bodies.append((index, self._body(message)))
            except MessageRejected as exc:
                results[index] = exc
        expiries = [self._expiry(messages[index].received_ns) for index, _ in bodies]
        for (index, _), result in zip(bodies, await self.send_many([body for _, body in bodies], expiries)):
            results[index] = result
        return results

    async def send_many(self, bodies: Sequence[bytes],
                        expiries: Sequence[int | None] | None = None) -> list[BaseException | None]:
        """Send ``bodies`` in bundles (see the module's docstring), up to ``window`` of them
        in flight at once: a radio's round trip is a TDM round or more, so one transfer after
        another would leave it idle. ``result[i]`` is None once ``bodies[i]`` was delivered.
        ``expiries[i]``: ``time.monotonic_ns()`` after which ``bodies[i]`` is worthless (a
        bundle is given up once its newest message is). The messages wait in the sink's queue,
        behind those of earlier calls, until a window slot frees (:meth:`_dispatch`)."""
        loop = asyncio.get_running_loop()
        waiting = [_Waiting(body, None if expiries is None else expiries[index], loop.create_future())
                   for index, body in enumerate(bodies)]
        self._waiting.extend(waiting)
        self._arrived.set()
        if self._dispatcher is None or self._dispatcher.done():
            self._dispatcher = asyncio.create_task(self._dispatch(), name=f"tunnel-sink:{self.payload_type}")
        # cancelling this call cancels its outcomes: its messages not yet in a transfer are
        # skipped, and a transfer whose every message was cancelled is cancelled
        return list(await asyncio.gather(*(item.outcome for item in waiting)))

    async def _dispatch(self) -> None:
        """Start a transfer whenever a window slot is free and messages wait: one message, or
        a bundle of the consecutive ones that fit (:meth:`_next_group`)."""
        while True:
            while not self._pending():
                self._arrived.clear()
                await self._arrived.wait()
            await self._window.acquire()
            group = self._next_group()
            if not group:
                self._window.release()
                continue
            task = asyncio.create_task(self._transfer(group))
            self._transfers.add(task)
            task.add_done_callback(self._transfers.discard)

    def _pending(self) -> bool:
        waiting = self._waiting
        while waiting and waiting[0].outcome.done():  # its caller gave up
            waiting.popleft()
        return bool(waiting)

    def _next_group(self) -> list[_Waiting]:
        """The waiting messages at the head of the queue while their bundle stays within
        ``bundle`` bytes and the fragments a transfer can have (at least one message)."""
        settings = self.hub.settings
        limit = min(settings.bundle, MAX_FRAGMENTS * settings.fragment_size - CRC_SIZE)
        group: list[_Waiting] = []
        size = 0
        while self._pending():
            cost = bundled_size([len(self._waiting[0].body)])
            if group and size + cost > limit:
                break
            group.append(self._waiting.popleft())
            size += cost
        return group

    async def _transfer(self, group: list[_Waiting]) -> None:
        """One transfer of ``group`` in the window slot :meth:`_dispatch` took for it."""
        task = asyncio.current_task()
        assert task is not None

        def given_up(_: asyncio.Future[BaseException | None]) -> None:
            if all(item.outcome.cancelled() for item in group):
                task.cancel()

        for item in group:
            item.outcome.add_done_callback(given_up)
        expires_ns = _newest([item.expires_ns for item in group])
        outcome: BaseException | None = None
        try:
            if len(group) == 1:
                await self._send_transfer(group[0].body, expires_ns=expires_ns)
            else:
                await self._send_transfer(bundle([item.body for item in group]), bundled=True,
                                          messages=len(group), expires_ns=expires_ns)
        except Exception as exc:
            outcome = exc
        except BaseException:  # cancelled (every caller gave up, or the sink closes)
            for item in group:
                if not item.outcome.done():
                    item.outcome.cancel()
            raise
        finally:
            self._window.release()
        for item in group:
            if not item.outcome.done():
                item.outcome.set_result(outcome)

    async def close(self) -> None:
        """Stop the dispatcher and what it started (the route retired: nothing waits for them)."""
        tasks = [*self._transfers, *([self._dispatcher] if self._dispatcher is not None else [])]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self._dispatcher = None

    async def send_bytes(self, body: bytes, *, bundled: bool = False, messages: int = 1,
                         expires_ns: int | None = None) -> None:
        """Send one transfer (one message, or a bundle of ``messages``); returns once the
        receiver acknowledged it DELIVERED. Raises :class:`Expired` once ``expires_ns``
        (``time.monotonic_ns()``) passed before that: before it was first sent (it waited
        for the window), or while its fragments were being sent again."""
        async with self._window:
            await self._send_transfer(body, bundled=bundled, messages=messages, expires_ns=expires_ns)

    async def _send_transfer(self, body: bytes, *, bundled: bool = False, messages: int = 1,
                             expires_ns: int | None = None) -> None:
        """:meth:`send_bytes` in a window slot already taken."""
        hub, settings = self.hub, self.hub.settings
        if expires_ns is not None and time.monotonic_ns() >= expires_ns:
            hub.count("tunnel_expired", messages)
            raise Expired("tunnel: older than the route's max_age before it could be sent")
        msg_id = hub.new_id(self.payload_type)
        try:
            transfer = Transfer(msg_id, body, fragment_size=settings.fragment_size,
                                rtt=hub.rtt(self.payload_type), retries=settings.retries, bundled=bundled)
        except ValueError as exc:  # larger than a tunnel message can be: never deliverable
            raise MessageRejected(f"tunnel: {exc}") from None
        acks: asyncio.Queue[Ack] = asyncio.Queue()
        hub.watch(self.payload_type, msg_id, acks.put_nowait)
        try:
            await self._run(transfer, acks, expires_ns)
        except Expired:
            hub.count("tunnel_expired", messages)
            raise
        finally:
            hub.unwatch(self.payload_type, msg_id)
            hub.count("tunnel_retransmissions", transfer.retransmissions)
        hub.count("tunnel_sent", messages)

    def _send_fragment(self, transfer: Transfer, index: int, *, first: bool = False) -> asyncio.Future[float]:
        return asyncio.ensure_future(self.hub.link.send_tunnel(self.payload_type, self.target, transfer.frames[index],
                                                               bulk=True, priority=self.priority, first=first))

    async def _run(self, transfer: Transfer, acks: asyncio.Queue[Ack], expires_ns: int | None = None) -> None:
        loop = asyncio.get_running_loop()
        pending: list[int] = list(range(transfer.count))

        def plan(indexes: list[int]) -> None:
            pending.extend(i for i in indexes if i not in pending)

        def expired() -> bool:
            return expires_ns is not None and time.monotonic_ns() >= expires_ns

        while True:
            if pending and not transfer.delivered and expired() and any(transfer.tx_count):
                raise Expired(f"tunnel message {transfer.msg_id}: older than the route's max_age while "
                              "being sent again; not sent any more")
            while pending and not transfer.delivered:
                # Every pending fragment is queued at once, so the writer sends a transfer's
                # fragments back to back: transfers in flight complete one after another (the
                # receiver can settle and answer the first while the next is on the air)
                # rather than all together at the end.
                # Fragments sent again go before every first transmission of their priority
                # (in order, at the front of the writer's lane): a loss is repaired in the time
                # of its fragments, not after the window of transfers queued behind it.
                wanted: list[int] = []
                while pending:
                    index = pending.pop(0)
                    if transfer.is_held(index) and index != transfer.probe:
                        continue
                    if index == transfer.probe:
                        transfer.probe = None
                    wanted.append(index)
                again = [i for i in wanted if transfer.tx_count[i]]
                queued: list[tuple[int, asyncio.Future[float]]] = [
                    (index, self._send_fragment(transfer, index, first=True)) for index in reversed(again)][::-1]
                queued += [(index, self._send_fragment(transfer, index)) for index in wanted if not transfer.tx_count[index]]
                try:
                    for index, written in queued:
                        transfer.on_sent(index, await written)
                        while not acks.empty():
                            plan(transfer.on_ack(acks.get_nowait(), loop.time()))
                        if transfer.delivered:
                            break
                finally:
                    for _, written in queued:  # not written yet and no longer wanted: the writer skips them
                        written.cancel()
            if transfer.delivered:
                return
            deadline = transfer.deadline()
            assert deadline is not None
            wait = deadline - loop.time()
            if expires_ns is not None:  # wake when it expires: a DELIVERED may still come until then
                wait = min(wait, (expires_ns - time.monotonic_ns()) / 1e9)
            try:
                ack = await asyncio.wait_for(acks.get(), max(0.0, wait))
            except TimeoutError:
                if expired():
                    raise Expired(f"tunnel message {transfer.msg_id}: older than the route's max_age before "
                                  "it was acknowledged; not sent again") from None
                plan(transfer.on_timeout(loop.time()))
                if transfer.failed:
                    raise EndpointError(
                        f"tunnel message {transfer.msg_id} not acknowledged after {transfer.max_retries} retries"
                    ) from None
            else:
                plan(transfer.on_ack(ack, loop.time()))


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
            return await self._deliver.batch(inbounds)
        except Exception:
            log.exception("tunnel route %r: settling a batch failed", self.route)
            return [False] * len(inbounds)
        finally:
            self._busy -= 1
            if not self._busy:
                self._idle.set()


def _newest(expiries: Sequence[int | None]) -> int | None:
    """When a transfer of messages with these ``expiries`` is worthless: once its newest
    message is (None: one of them never expires)."""
    return None if any(value is None for value in expiries) else max(expiries)  # type: ignore[type-var]


def ignore_result(future: asyncio.Future[Any]) -> None:
    """Acknowledgements are best effort: the sender's timer covers one that was not written."""
    if not future.cancelled():
        future.exception()


__all__ = [
    "DEFAULT_PAYLOAD_TYPE",
    "MAX_FRAGMENT",
    "Ack",
    "Data",
    "Reassembler",
    "RttEstimator",
    "Transfer",
    "TunnelHub",
    "TunnelLink",
    "TunnelSettings",
    "TunnelSink",
    "TunnelSource",
    "decode",
    "encode_ack",
    "encode_data",
    "fragment",
]
