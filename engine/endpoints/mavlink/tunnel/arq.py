"""The tunnel's selective-repeat ARQ as pure state machines driven by frames and a clock
(sans-IO): :class:`Transfer` (the sender's side of one message), :class:`Reassembler` (the
receiver's: reassembly, deduplication, acknowledgements) and the :class:`RttEstimator` they
time retransmissions with. The asyncio drivers are hub.py (receiving) and sink.py (sending)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass

from engine.endpoints.mavlink.tunnel.frames import (
    CRC_SIZE, FLAG_COMPLETE, FLAG_DELIVERED, MAX_FRAGMENT, Ack, Data, body_crc, encode_ack, fragment,
    unbundle,
)


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
            if not _evenly_cut(partial) or len(whole) <= CRC_SIZE or body_crc(body, partial.bundle) != crc \
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
