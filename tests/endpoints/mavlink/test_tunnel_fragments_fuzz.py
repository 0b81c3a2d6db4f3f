"""Damaged tunnel fragments never become messages (issue 8's bad-input property, for the
JSON-over-MAVLink tunnel): whatever arrives, truncated, corrupted, duplicated, reordered or
random, the receiver raises nothing but ``ValueError`` on a payload it cannot parse, never
delivers a body that was not sent, never delivers one message twice, and delivers exactly once
every message whose fragments all arrived intact when nothing damaged could pose as one of them,
sent alone or as a bundle."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

os.environ["MAVLINK20"] = "1"

from engine.endpoints.mavlink import tunnel  # noqa: E402

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

bodies = st.lists(st.binary(min_size=1, max_size=600), min_size=1, max_size=6)
damage = st.sampled_from(["intact", "intact", "flip", "truncate", "drop", "duplicate", "garbage"])


@st.composite
def arrivals(draw: st.DrawFn) -> tuple[list[bytes], list[bytes], set[int]]:
    """(the bodies sent, the tunnel payloads that arrive, the message ids sure to be delivered:
    all fragments intact, and no damaged header or garbage that could pose as one of theirs;
    the sender's retransmission recovers those in real use)."""
    sent = draw(bodies)
    size = draw(st.integers(8, tunnel.MAX_FRAGMENT))
    payloads: list[bytes] = []
    intact: set[int] = set()
    impostors = False
    for msg_id, body in enumerate(sent):
        bundled = draw(st.booleans())  # a bundle of this one message: the same body once unbundled
        fragments = tunnel.fragment(msg_id, tunnel.bundle([body]) if bundled else body, size, bundled=bundled)
        whole = True
        for payload in fragments:
            kind = draw(damage)
            if kind == "intact":
                payloads.append(payload)
            elif kind == "duplicate":
                payloads += [payload, payload]
            elif kind == "drop":
                whole = False
            elif kind == "truncate":
                payloads.append(payload[: draw(st.integers(0, len(payload) - 1))])
                whole = False
            elif kind == "flip":
                at = draw(st.integers(0, len(payload) - 1))
                payloads.append(payload[:at] + bytes([payload[at] ^ draw(st.integers(1, 255))]) + payload[at + 1:])
                whole = False
                impostors = True
            else:
                payloads.append(draw(st.binary(max_size=tunnel.MAX_FRAGMENT + 16)))
                payloads.append(payload)
                impostors = True
        if whole:
            intact.add(msg_id)
    order = draw(st.permutations(range(len(payloads))))
    return sent, [payloads[i] for i in order], set() if impostors else intact


@settings(max_examples=500, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(arrivals())
def test_damaged_fragments_never_become_messages(case: tuple[list[bytes], list[bytes], set[int]]) -> None:
    sent, payloads, intact = case
    reassembler = tunnel.Reassembler(memory=64)
    delivered: dict[int, list[bytes]] = {}
    for now, payload in enumerate(payloads):
        try:
            frame = tunnel.decode(payload)
        except ValueError:
            continue  # not ours or malformed: counted by the link, never a message
        if not isinstance(frame, tunnel.Data):
            continue
        _, done = reassembler.on_data("peer", frame, float(now))
        if done is not None:
            key, body = done
            delivered.setdefault(key[1], []).extend(reassembler.messages(key, body))
            reassembler.delivered(key, float(now))
    for msg_id, copies in delivered.items():
        # a flipped header byte can renumber a fragment (the CRC-32 covers the body, not the
        # header), even into another message's id; but only a body that was sent is ever
        # delivered, and never the same message twice
        assert all(copy in sent for copy in copies) and len(copies) == len(set(copies)), (msg_id, copies)
    for msg_id in intact:
        assert delivered.get(msg_id) == [sent[msg_id]], f"message {msg_id} arrived intact but was not delivered once"
