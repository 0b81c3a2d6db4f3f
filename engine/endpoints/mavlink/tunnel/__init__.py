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
One module per concern: frames.py (the wire format), arq.py (the state machines), hub.py (the
connection's dispatch and the receiving side: channels and sources), sink.py (the sending
side). This package names what the MAVLink endpoint, tests, benches and the simulator use.
"""

from engine.endpoints.mavlink.tunnel.arq import Reassembler, RttEstimator, Transfer
from engine.endpoints.mavlink.tunnel.frames import (
    DEFAULT_PAYLOAD_TYPE, FLAG_COMPLETE, FLAG_DELIVERED, MAX_FRAGMENT, MAX_FRAGMENTS, SIK_FRAGMENT, TUNNEL_PAYLOAD, Ack,
    Data, bundle, decode, encode_ack, encode_data, fragment, unbundle,
)
from engine.endpoints.mavlink.tunnel.hub import TunnelChannel, TunnelHub, TunnelLink, TunnelSettings, TunnelSource, ignore_result
from engine.endpoints.mavlink.tunnel.sink import TunnelSink

__all__ = [
    "DEFAULT_PAYLOAD_TYPE",
    "FLAG_COMPLETE",
    "FLAG_DELIVERED",
    "MAX_FRAGMENT",
    "MAX_FRAGMENTS",
    "SIK_FRAGMENT",
    "TUNNEL_PAYLOAD",
    "Ack",
    "Data",
    "Reassembler",
    "RttEstimator",
    "Transfer",
    "TunnelChannel",
    "TunnelHub",
    "TunnelLink",
    "TunnelSettings",
    "TunnelSink",
    "TunnelSource",
    "bundle",
    "decode",
    "encode_ack",
    "encode_data",
    "fragment",
    "ignore_result",
    "unbundle",
]
