"""The tunnel's wire format (the package docstring describes it): DATA, ACK and BUNDLE frames
inside ``TUNNEL.payload``, a message cut into fragments with its CRC-32, and bundles of
several messages in one body. Pure functions, no I/O."""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

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
    whole = body + body_crc(body, bundled)
    count = -(-len(whole) // fragment_size)
    if count > MAX_FRAGMENTS or len(whole) > 0xFFFF:
        raise ValueError(f"message of {len(body)} bytes exceeds {MAX_FRAGMENTS} fragments of {fragment_size} bytes")
    return [
        encode_data(Data(msg_id, i, count, whole[i * fragment_size:(i + 1) * fragment_size], bundled))
        for i in range(count)
    ]


def body_crc(body: bytes, bundled: bool) -> bytes:
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
