"""``max_age`` inside the tunnel's own retransmissions (issue 22), on the emulated SiK radio.

A tunnel message sent into a radio outage is retransmitted (timeouts, doubling) until the
link is back. For a route with ``max_age`` (telemetry) that is pointless once the message is
older than that: the sink gives the transfer up, reports the message ``Expired`` (its route
counts it ``expired``; the link ``tunnel_expired``), and nothing of it arrives once the
outage ends. The control, without ``max_age``, crosses once the link is back: what makes the
difference is the route's ``max_age``, not the outage.
"""

from __future__ import annotations

import asyncio
import os
import time
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from engine.common.options import evolve  # noqa: E402
from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import Expired, Outbound, typed  # noqa: E402
from engine.endpoints.mavlink.options import MavlinkSinkOptions  # noqa: E402
from rabbitros_sim import sik_radio  # noqa: E402
from tests.endpoints.mavlink.test_link_priority import Arrivals  # noqa: E402

MAX_AGE = 1.5
OUTAGE = 4.0


def outbound(body: bytes) -> Outbound:
    canonical: dict[str, Any] = {}
    return Outbound(body, canonical, canonical, "id", {}, received_ns=time.monotonic_ns())


def through_an_outage(max_age: float | None) -> tuple[BaseException | None, float, dict[bytes, float], dict[str, int]]:
    """Send one message as an outage starts; its outcome, how long the send took, what arrived
    (waiting until well after the outage), and the sender's link counters."""

    async def scenario() -> tuple[BaseException | None, float, dict[bytes, float], dict[str, int]]:
        async with sik_radio.SikRadioPair(seed=3) as pair:
            gcs = mavlink.TRANSPORT.connect("gcs", {"url": pair.link_a, "baud": 57600})
            uav = mavlink.TRANSPORT.connect("uav", {"url": pair.link_b, "baud": 57600, "source_system": 1,
                                                    "source_component": 191, "mav_type": 18})
            await gcs.open()
            await uav.open()
            got = Arrivals()
            source = uav.source("tel", {"json_tunnel": True})
            await source.start(got)
            options = typed(MavlinkSinkOptions, {"json_tunnel": True, "target_system": 1, "target_component": 191}, "sink")
            sink = gcs.sink("tel", evolve(options, max_age=max_age) if max_age is not None else options)
            try:
                warm = b'{"warm":true}'
                assert (await asyncio.wait_for(sink.send_batch([outbound(warm)]), 20)) == [None]
                pair.add_outage(pair.elapsed(), OUTAGE)
                body = b'{"position":%s}' % (b"1" * 200)
                began = time.monotonic()
                [result] = await asyncio.wait_for(sink.send_batch([outbound(body)]), 40)
                took = time.monotonic() - began
                end = time.monotonic() + max(0.0, OUTAGE - took) + 2.0  # past the outage, and a TDM round or more
                while time.monotonic() < end and body not in got.at:
                    await asyncio.sleep(0.05)  # poll: until the body arrives or the window past the outage ends (the test asserts which)
                return result, took, {k: v for k, v in got.at.items() if k != warm}, dict(gcs.stats)
            finally:
                await source.stop()
                await gcs.close()
                await uav.close()

    return asyncio.run(asyncio.wait_for(scenario(), 60))


def test_a_tunnel_message_older_than_max_age_is_not_retransmitted_through_an_outage() -> None:
    result, took, arrived, stats = through_an_outage(MAX_AGE)
    print(f"\nmax_age {MAX_AGE} s through a {OUTAGE} s outage: {type(result).__name__} after {took:.2f} s; "
          f"retransmissions {stats.get('tunnel_retransmissions')}, expired {stats.get('tunnel_expired')}")
    assert isinstance(result, Expired), result
    assert MAX_AGE <= took < OUTAGE, f"given up after {took:.2f} s, not at max_age"
    assert stats.get("tunnel_expired") == 1, stats
    assert not arrived, "an expired message reached the far end after the outage"


def test_without_max_age_the_same_message_crosses_once_the_link_is_back() -> None:
    result, took, arrived, _ = through_an_outage(None)
    print(f"\nno max_age through a {OUTAGE} s outage: delivered after {took:.2f} s")
    assert result is None and len(arrived) == 1 and took >= OUTAGE - 0.5, (result, took, arrived)
