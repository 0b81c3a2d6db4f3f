"""MAVLink endpoints under the engine's delivery policy: bounded sources with the route's
overflow policy, tunnel acknowledgements after settling, reload identity and option checks."""

from __future__ import annotations

import asyncio
import os
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import Inbound, MessageRejected, Outbound  # noqa: E402
from rabbitros_sim.deliver import FunctionDeliver  # noqa: E402
from tests.test_mavlink_endpoint import UdpPeer, packer, run, settle  # noqa: E402


class GatedDeliver(FunctionDeliver):
    """Settles nothing until ``gate`` opens, so the source's inbox fills up behind it."""

    def __init__(self, **deliver: Any) -> None:
        super().__init__(**deliver)
        self.gate = asyncio.Event()
        self.entered = asyncio.Event()
        self.stamps: list[int] = []

    async def __call__(self, inbound: Inbound) -> None:
        self.entered.set()
        await self.gate.wait()
        assert inbound.fields is not None
        self.stamps.append(inbound.fields["time_boot_ms"])


def positions(mav: mavlink2.MAVLink, stamps: range) -> bytes:
    return b"".join(mav.global_position_int_encode(n, 1, 2, 3, 4, 5, 6, 7, 8).pack(mav) for n in stamps)


async def flood(overflow: str, *, stop_while_queued: bool = False) -> tuple[GatedDeliver, dict[str, Any]]:
    """One message in flight (held at the gate), then 100 more into an inbox of 10."""
    conn = mavlink.TRANSPORT.connect("uav", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
    await conn.open()
    peer = await UdpPeer.bind()
    deliver = GatedDeliver(overflow=overflow, queue_limit=10)
    source = conn.source("telemetry", {"message": "GLOBAL_POSITION_INT"})
    await source.start(deliver)
    try:
        mav = packer(1, 1)
        peer.send(positions(mav, range(1)), conn.address[1])
        await asyncio.wait_for(deliver.entered.wait(), 5)
        peer.send(positions(mav, range(1, 101)), conn.address[1])
        await settle(lambda: source.status()["received"] == 101, 5)
        if stop_while_queued:
            stopping = asyncio.create_task(source.stop())
            await asyncio.sleep(0.05)
            deliver.gate.set()
            await asyncio.wait_for(stopping, 5)
        else:
            deliver.gate.set()
            await settle(lambda: len(deliver.stamps) == 11, 5)
        return deliver, source.status()
    finally:
        await source.stop()
        peer.close()
        await conn.close()


@pytest.mark.parametrize(("overflow", "kept"), [
    ("drop_oldest", list(range(91, 101))),
    ("block", list(range(91, 101))),  # a radio link cannot be paused: block drops the oldest
    ("drop_newest", list(range(1, 11))),
])
def test_flooded_source_follows_the_overflow_policy_and_counts_drops(overflow: str, kept: list[int]) -> None:
    deliver, status = run(flood(overflow))
    assert deliver.stamps == [0, *kept]
    assert deliver.drops == 90 and status["dropped"] == 90
    assert status["received"] == 101 and status["queued"] == 0
    assert status["overflow"] == ("drop_oldest" if overflow == "block" else overflow)


def test_stop_hands_queued_telemetry_to_the_route() -> None:
    deliver, status = run(flood("drop_oldest", stop_while_queued=True))
    assert deliver.stamps == [0, *range(91, 101)], "what was queued at stop is delivered, not thrown away"
    assert status["dropped"] == 90 and status["queued"] == 0


def test_unsettled_messages_are_counted_as_dropped() -> None:
    async def scenario() -> dict[str, Any]:
        conn = mavlink.TRANSPORT.connect("uav", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
        await conn.open()
        peer = await UdpPeer.bind()

        async def refuse(inbound: Inbound) -> None:
            raise RuntimeError("route stopping")

        deliver = FunctionDeliver(refuse)
        source = conn.source("telemetry", {"message": "GLOBAL_POSITION_INT"})
        await source.start(deliver)
        try:
            peer.send(positions(packer(1, 1), range(5)), conn.address[1])
            await settle(lambda: deliver.drops == 5, 5)
            return source.status()
        finally:
            await source.stop()
            peer.close()
            await conn.close()

    assert run(scenario())["dropped"] == 5


# -- tunnel: acknowledged to the sender only once the route settled it ------------------------


class HeldBatches(FunctionDeliver):
    """Holds each batch until ``release(settled)``; single messages are not how tunnels deliver."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: asyncio.Queue[tuple[list[Inbound], asyncio.Future[bool]]] = asyncio.Queue()

    async def __call__(self, inbound: Inbound) -> None:
        raise AssertionError("the tunnel settles with Deliver.batch")

    async def batch(self, inbounds: Any) -> list[bool]:
        verdict: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        self.batches.put_nowait((list(inbounds), verdict))
        return [await verdict] * len(inbounds)


def test_tunnel_message_is_acknowledged_only_after_the_route_settled_it() -> None:
    from tests.test_mavlink_tunnel import is_delivered_ack, outbound, udp_pair

    async def scenario() -> None:
        acks: list[Any] = []

        def watch(direction: str, msg: Any) -> bool:
            if is_delivered_ack(direction, msg):
                acks.append(msg)
            return False

        gcs, uav, _ = await udp_pair(drop=watch)
        deliver = HeldBatches()
        source = uav.source("json", {"json_tunnel": True})
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
        await source.start(deliver)
        try:
            body = b'{"n":1,"pad":"' + b"x" * 400 + b'"}'
            sending = asyncio.create_task(sink.send(outbound(body)))
            inbounds, verdict = await asyncio.wait_for(deliver.batches.get(), 5)
            assert [i.body for i in inbounds] == [body]
            await asyncio.sleep(0.3)  # the sender's retransmissions meanwhile earn no DELIVERED
            assert not sending.done() and acks == [] and uav.stats.get("tunnel_delivered", 0) == 0
            verdict.set_result(False)  # not settled: no acknowledgement, the sender sends again
            inbounds, verdict = await asyncio.wait_for(deliver.batches.get(), 10)
            assert [i.body for i in inbounds] == [body] and not sending.done() and acks == []
            assert uav.stats["tunnel_deliver_failed"] == 1
            verdict.set_result(True)
            await asyncio.wait_for(sending, 10)
            assert len(acks) >= 1 and uav.stats["tunnel_delivered"] == 1
        finally:
            await source.stop()
            await gcs.close()
            await uav.close()

    run(scenario())


# -- errors at the edge: permanent failures are MessageRejected, silence is EndpointError -----


def test_encode_failures_are_rejected_and_an_oversize_tunnel_message_too() -> None:
    async def scenario() -> None:
        peer = await UdpPeer.bind()
        conn = mavlink.TRANSPORT.connect("radio", {"url": f"udpout:127.0.0.1:{peer.port}", "heartbeat": 0})
        await conn.open()
        try:
            sink = conn.sink("cmd", {"message": "COMMAND_LONG", "target_system": 1})
            for fields in ({"command": 400, "param1": 1e39}, {"command": 400, "param1": 10**400},
                           {"command": 400, "param9": 1}, {"command": -1}):
                with pytest.raises(MessageRejected):
                    await sink.send(Outbound(b"{}", fields, fields, "m", {}))
            unpackable = mavlink2.MAVLink_command_long_message(1, 1, 400, 0, 1e39, 0, 0, 0, 0, 0, 0)
            with pytest.raises(MessageRejected, match="cannot encode"):
                await conn.send_message(unpackable)
            tunnel = conn.sink("json", {"json_tunnel": True})
            with pytest.raises(MessageRejected, match="exceeds"):
                await tunnel.send(Outbound(bytes(40_000), None, None, "m", {}))
            assert conn.stats["frames_sent"] == 0
        finally:
            peer.close()
            await conn.close()

    run(scenario())
