"""JSON over MAVLink: the pure protocol on a simulated clock, then real links.

The real-link tests use the engine's own connections on both ends, joined either by a UDP
forwarder this file controls (exact drops) or by the SiK radio emulator (57600 baud, TDM,
per-packet loss, outages).
"""

from __future__ import annotations

import asyncio
import os
import random
import time
import zlib
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.mavlink import tunnel  # noqa: E402
from engine.endpoints.mavlink.tunnel.hub import TunnelSource  # noqa: E402
from engine.endpoints.base import EndpointError, Inbound, MessageRejected, Outbound  # noqa: E402
from tests.endpoints.mavlink.test_mavlink_endpoint import bound_port  # noqa: E402
from tests.support.collecting_deliver import CollectingDeliver  # noqa: E402
from tests.support.waiting import wait_for

TRANSPORT = mavlink.TRANSPORT


def run(coro: Awaitable[Any], timeout: float = 60.0) -> Any:
    async def bounded() -> Any:
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(bounded())


def body_of(size: int, seed: int = 0) -> bytes:
    """JSON-looking bytes with NULs and trailing zeros, which MAVLink 2 would truncate."""
    rng = random.Random(seed)
    raw = bytes(rng.getrandbits(8) for _ in range(size - 12))
    return b'{"d":"' + raw + b'"}\x00\x00\x00\x00'


# -- wire format ------------------------------------------------------------------------------------


def data_frame(payload: bytes) -> tunnel.Data:
    """``tunnel.decode`` of a frame the test knows carries data."""
    frame = tunnel.decode(payload)
    assert isinstance(frame, tunnel.Data), frame
    return frame


def ack_frame(payload: bytes) -> tunnel.Ack:
    """``tunnel.decode`` of a frame the test knows is an acknowledgement."""
    frame = tunnel.decode(payload)
    assert isinstance(frame, tunnel.Ack), frame
    return frame


def test_wire_format_is_as_documented() -> None:
    frames = tunnel.fragment(0x1234, b"hello", 121)
    crc = zlib.crc32(b"hello").to_bytes(4, "little")
    assert frames == [bytes([0x20, 0x34, 0x12, 0, 1]) + b"hello" + crc]
    frames = tunnel.fragment(7, bytes(300), 100)
    assert [len(f) for f in frames] == [105, 105, 105, 9]
    assert [data_frame(f).index for f in frames] == [0, 1, 2, 3]
    assert {data_frame(f).count for f in frames} == {4}
    assert sum(len(data_frame(f).chunk) for f in frames) == 304  # the length is what the fragments carry
    ack = tunnel.encode_ack(tunnel.Ack(7, 10, 0, 0b1000000101))
    assert ack == bytes([0x21, 7, 0, 0, 10, 0b00000101, 0b10])
    assert tunnel.decode(ack) == tunnel.Ack(7, 10, 0, 0b1000000101)
    done = tunnel.encode_ack(tunnel.Ack(7, 10, tunnel.FLAG_DELIVERED | tunnel.FLAG_COMPLETE, 0))
    assert len(done) == 5 and ack_frame(done).held == 0b1111111111
    with pytest.raises(ValueError):
        tunnel.fragment(1, bytes(255 * 121), 121)
    for bad in (b"", b"\x20\x00", bytes([0x20, 0, 0, 3, 2, 9]), bytes([0x20, 0, 0, 0, 1]),
                bytes([0x10, 0, 0, 0, 1, 9, 0]) + b"v1"):  # index past count, no data, version 1
        with pytest.raises(ValueError):
            tunnel.decode(bad)


# -- protocol on a simulated clock ------------------------------------------------------------------


class Sim:
    """One Transfer against one Reassembler over a FIFO link with loss, outages, duplication.

    Time advances in 1 ms steps; each frame occupies the wire for ``tx_time`` (pacing) and
    arrives ``latency`` later. ``drop(direction, payload)`` can veto individual frames.
    """

    def __init__(self, *, loss: float = 0.0, seed: int = 1, outage: tuple[float, float] | None = None,
                 duplicate: bool = False, latency: float = 0.12, tx_time: float = 0.025,
                 drop: Callable[[str, bytes], bool] | None = None, reassembler: tunnel.Reassembler | None = None,
                 rtt: tunnel.RttEstimator | None = None) -> None:
        self.rng = random.Random(seed)
        self.loss, self.outage, self.duplicate = loss, outage, duplicate
        self.latency, self.tx_time, self.drop = latency, tx_time, drop
        self.reassembler = reassembler or tunnel.Reassembler()
        self.rtt = rtt or tunnel.RttEstimator(rto_min=0.5)
        self.fwd: deque[tuple[float, bytes]] = deque()
        self.rev: deque[tuple[float, bytes]] = deque()
        self.delivered: list[bytes] = []
        self.frames_sent = 0
        self.t = 0.0

    def _lost(self, direction: str, payload: bytes) -> bool:
        if self.outage and self.outage[0] <= self.t < self.outage[0] + self.outage[1]:
            return True
        if self.drop and self.drop(direction, payload):
            return True
        return self.rng.random() < self.loss

    def _send(self, queue: deque[tuple[float, bytes]], direction: str, payload: bytes) -> None:
        if not self._lost(direction, payload):
            queue.append((self.t + self.latency, payload))
            if self.duplicate:
                queue.append((self.t + self.latency + 0.001, payload))

    def transfer(self, body: bytes, msg_id: int = 1, limit: float = 120.0, **kwargs: Any) -> tunnel.Transfer:
        tr = tunnel.Transfer(msg_id, body, rtt=self.rtt, **kwargs)
        pending = list(range(tr.count))
        busy_until = self.t
        end = self.t + limit

        def plan(indexes: list[int]) -> None:
            pending.extend(i for i in indexes if i not in pending)

        while self.t < end and not tr.delivered and not tr.failed:
            while self.fwd and self.fwd[0][0] <= self.t:
                frame = tunnel.decode(self.fwd.popleft()[1])
                assert isinstance(frame, tunnel.Data)
                acks, complete = self.reassembler.on_data("gcs", frame, self.t)
                for ack in acks:
                    self._send(self.rev, "rev", ack)
                if complete is not None:
                    self.delivered.append(complete[1])
                    self._send(self.rev, "rev", self.reassembler.delivered(complete[0], self.t))
            while self.rev and self.rev[0][0] <= self.t:
                answer = tunnel.decode(self.rev.popleft()[1])
                assert isinstance(answer, tunnel.Ack)
                plan(tr.on_ack(answer, self.t))
            deadline = self.reassembler.next_deadline()
            if deadline is not None and deadline <= self.t:
                for _, ack in self.reassembler.poll(self.t):
                    self._send(self.rev, "rev", ack)
            if self.t >= busy_until:
                while pending and tr.is_held(pending[0]):
                    pending.pop(0)
                if pending:
                    index = pending.pop(0)
                    self._send(self.fwd, "fwd", tr.frames[index])
                    self.frames_sent += 1
                    busy_until = self.t + self.tx_time
                    tr.on_sent(index, busy_until)
                elif (d := tr.deadline()) is not None and self.t >= d:
                    plan(tr.on_timeout(self.t))
            self.t = round(self.t + 0.001, 6)
        return tr


@pytest.mark.parametrize("size", [250, 4096])
def test_sim_lossless_sends_each_fragment_once(size: int) -> None:
    sim = Sim()
    body = body_of(size)
    tr = sim.transfer(body)
    assert tr.delivered and sim.delivered == [body]
    assert sim.frames_sent == tr.count == -(-(size + 4) // tunnel.MAX_FRAGMENT)
    assert tr.retransmissions == 0


@pytest.mark.parametrize("loss", [0.05, 0.2])
def test_sim_lossy_link_delivers_every_message_once(loss: float) -> None:
    for seed in range(20):
        sim = Sim(loss=loss, seed=seed)
        for size in (250, 4096):
            body = body_of(size, seed)
            tr = sim.transfer(body, msg_id=size + seed)
            assert tr.delivered, (seed, size)
            assert sim.delivered[-1] == body
        assert len(sim.delivered) == 2


def test_sim_survives_a_three_second_outage_and_gives_up_on_a_dead_link() -> None:
    sim = Sim(outage=(0.3, 3.0))
    body = body_of(4096)
    tr = sim.transfer(body)
    assert tr.delivered and sim.delivered == [body] and sim.t > 3.3
    assert tr.retransmissions < 3 * tr.count

    dead = Sim(outage=(0.0, 1000.0))
    tr = dead.transfer(body_of(250), retries=5)
    assert tr.failed and not tr.delivered and dead.delivered == []
    assert dead.frames_sent <= 3 * (5 + 1)
    assert 20 < dead.t < 60, "retransmission timeouts must back off exponentially, up to rto_max"


def test_sim_duplicates_and_lost_acks_never_deliver_twice() -> None:
    sim = Sim(duplicate=True, loss=0.05, seed=3)
    body = body_of(4096)
    assert sim.transfer(body).delivered
    assert sim.delivered == [body]
    assert sim.reassembler.stats.duplicate_fragments > 0

    lost_done = {"left": 3}

    def drop_done(direction: str, payload: bytes) -> bool:
        frame = tunnel.decode(payload)
        if isinstance(frame, tunnel.Ack) and frame.flags & tunnel.FLAG_DELIVERED and lost_done["left"]:
            lost_done["left"] -= 1
            return True
        return False

    sim = Sim(drop=drop_done)
    tr = sim.transfer(body)
    assert tr.delivered and sim.delivered == [body]
    assert sim.reassembler.stats.after_delivery >= 3

    again = sim.transfer(body, msg_id=1)
    assert again.delivered and sim.delivered == [body]


def test_reassembler_rejects_bad_crc_and_bounds_its_memory() -> None:
    reasm = tunnel.Reassembler(memory=4)
    frames = [data_frame(f) for f in tunnel.fragment(9, b"x" * 200, 100)]
    bad = frames[1]
    frames[1] = tunnel.Data(bad.msg_id, bad.index, bad.count, b"y" + bad.chunk[1:])
    results = [reasm.on_data("p", f, 0.0) for f in frames]
    assert all(done is None for _, done in results)
    assert reasm.stats.crc_errors == 1
    assert tunnel.decode(results[-1][0][0]) == tunnel.Ack(9, 3, 0, 0)

    for msg_id in range(10):
        (frame,) = [data_frame(f) for f in tunnel.fragment(msg_id, b"m%d" % msg_id)]
        _, done = reasm.on_data("p", frame, 1.0)
        assert done is not None
        reasm.delivered(done[0], 1.0)
    assert len(reasm._done) == 4
    reasm.poll(1.0 + reasm.memory_ttl + 1)
    assert len(reasm._done) == 0


# -- real links ------------------------------------------------------------------------------------


def outbound(body: bytes) -> Outbound:
    return Outbound(body=body, canonical=None, fields=None, message_id="m", meta={})


class LossyForwarder(asyncio.DatagramProtocol):
    """UDP relay between an ``udpout`` engine and an ``udpin`` engine that drops as told."""

    def __init__(self, target_port: int, loss: float = 0.0, seed: int = 1,
                 drop: Callable[[str, Any], bool] | None = None) -> None:
        self.target = ("127.0.0.1", target_port)
        self.client: Any = None
        self.rng = random.Random(seed)
        self.loss = loss
        self.drop = drop
        self.outage_until = 0.0
        self.parser = mavlink2.MAVLink(None)
        self.dropped = 0
        self.transport: asyncio.DatagramTransport | None = None

    @classmethod
    async def start(cls, target_port: int, **kwargs: Any) -> LossyForwarder:
        loop = asyncio.get_running_loop()
        _, relay = await loop.create_datagram_endpoint(lambda: cls(target_port, **kwargs), local_addr=("127.0.0.1", 0))
        return relay

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    @property
    def port(self) -> int:
        assert self.transport is not None
        return self.transport.get_extra_info("sockname")[1]

    def datagram_received(self, data: bytes, addr: Any) -> None:
        assert self.transport is not None
        if addr == self.target:
            direction, dest = "rev", self.client
        else:
            direction, dest, self.client = "fwd", self.target, addr
        msgs = self.parser.parse_buffer(data) or []
        if dest is None or time.monotonic() < self.outage_until or self.rng.random() < self.loss or \
                (self.drop is not None and any(self.drop(direction, m) for m in msgs)):
            self.dropped += 1
            return
        self.transport.sendto(data, dest)


async def udp_pair(**forwarder: Any) -> tuple[mavlink.MavlinkConnection, mavlink.MavlinkConnection, LossyForwarder]:
    uav = TRANSPORT.connect("uav", {"url": "udpin:127.0.0.1:0", "source_system": 1, "source_component": 191,
                                    "heartbeat": 0})
    await uav.open()
    relay = await LossyForwarder.start(bound_port(uav), **forwarder)
    gcs = TRANSPORT.connect("gcs", {"url": f"udpout:127.0.0.1:{relay.port}", "heartbeat": 0,
                                    "tunnel": {"rto_min": 0.1, "sack_delay": 0.05}})
    await gcs.open()
    return gcs, uav, relay


def is_delivered_ack(direction: str, msg: Any) -> bool:
    if direction != "rev" or msg.get_type() != "TUNNEL":
        return False
    frame = tunnel.decode(bytes(msg.payload[:msg.payload_length]))
    return isinstance(frame, tunnel.Ack) and bool(frame.flags & tunnel.FLAG_DELIVERED)


def test_udp_five_percent_loss_delivers_byte_identical_messages() -> None:
    async def scenario() -> None:
        gcs, uav, relay = await udp_pair(loss=0.05, seed=11)
        got = CollectingDeliver()
        source = uav.source("json", {"json_tunnel": True, "system_id": 255})
        await source.start(got)
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1, "target_component": 191})
        try:
            bodies = [body_of(250, i) for i in range(10)] + [body_of(4096, i) for i in range(5)]
            for body in bodies:
                await sink.send(outbound(body))
            assert [i.body for i in got.items] == bodies
            assert got.items[0].meta["system_id"] == 255 and got.items[0].meta["message"] == "TUNNEL"
            assert relay.dropped > 0 and gcs.stats["tunnel_retransmissions"] > 0
        finally:
            await source.stop()
            await gcs.close()
            await uav.close()

    run(scenario())


def test_udp_lost_acknowledgements_and_failed_delivery() -> None:
    async def scenario() -> None:
        budget = {"acks": 2}

        def drop(direction: str, msg: Any) -> bool:
            if is_delivered_ack(direction, msg) and budget["acks"]:
                budget["acks"] -= 1
                return True
            return False

        gcs, uav, _ = await udp_pair(drop=drop)
        got = CollectingDeliver(fail_first=1)
        source = uav.source("json", {"json_tunnel": True})
        assert isinstance(source, TunnelSource), "a json_tunnel source reads the tunnel"
        await source.start(got)
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
        try:
            first, second = body_of(600, 1), body_of(250, 2)
            await sink.send(outbound(first))
            await sink.send(outbound(second))
            assert [i.body for i in got.items] == [first, second]
            assert got.calls == 3
            assert uav.stats["tunnel_deliver_failed"] == 1 and uav.stats["tunnel_delivered"] == 2
            assert source.reassembler.stats.after_delivery >= 1
            assert budget["acks"] == 0
        finally:
            await source.stop()
            await gcs.close()
            await uav.close()

    run(scenario())


def test_a_new_source_takes_over_without_losing_state() -> None:
    """A reload starts the new source before stopping the old one (make-before-break)."""

    async def scenario() -> None:
        gcs, uav, _ = await udp_pair()
        old, new = CollectingDeliver(), CollectingDeliver()
        first = uav.source("json", {"json_tunnel": True})
        second = uav.source("json", {"json_tunnel": True})
        assert isinstance(first, TunnelSource) and isinstance(second, TunnelSource), "json_tunnel sources read the tunnel"
        assert first.reassembler is second.reassembler
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
        try:
            await first.start(old)
            await sink.send(outbound(b'{"n":1}'))
            await second.start(new)
            await sink.send(outbound(b'{"n":2}'))
            await first.stop()
            await sink.send(outbound(b'{"n":3}'))
            assert [i.body for i in old.items] == [b'{"n":1}']
            assert [i.body for i in new.items] == [b'{"n":2}', b'{"n":3}']
        finally:
            await second.stop()
            await gcs.close()
            await uav.close()

    run(scenario())


def test_sink_raises_when_nobody_acknowledges() -> None:
    async def scenario() -> None:
        gcs = TRANSPORT.connect("gcs", {"url": "udpout:127.0.0.1:9", "heartbeat": 0,
                                        "tunnel": {"rto_min": 0.05, "rto_max": 0.2, "retries": 3}})
        await gcs.open()
        try:
            sink = gcs.sink("json", {"json_tunnel": True})
            started = time.monotonic()
            with pytest.raises(EndpointError, match="not acknowledged"):
                await sink.send(outbound(body_of(250)))
            assert time.monotonic() - started < 3
            with pytest.raises(MessageRejected, match="exceeds"):
                await sink.send(outbound(bytes(40_000)))
        finally:
            await gcs.close()

    run(scenario())


# -- over the SiK radio emulator ----------------------------------------------------------------------

from rabbitros_sim import sik_radio  # noqa: E402


async def sik_pair(pair: Any) -> tuple[mavlink.MavlinkConnection, mavlink.MavlinkConnection]:
    gcs = TRANSPORT.connect("gcs", {"url": pair.link_a, "baud": 57600})
    uav = TRANSPORT.connect("uav", {"url": pair.link_b, "baud": 57600, "source_system": 1,
                                    "source_component": 191, "mav_type": 18})
    await gcs.open()
    await uav.open()
    return gcs, uav


@pytest.mark.parametrize("loss", [0.0, 0.05])
def test_sik_radio_delivers_250_bytes_and_4_kb(loss: float) -> None:
    async def scenario() -> None:
        async with sik_radio.SikRadioPair(loss=loss, seed=5) as pair:
            gcs, uav = await sik_pair(pair)
            got = CollectingDeliver()
            source = uav.source("json", {"json_tunnel": True})
            await source.start(got)
            sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1, "target_component": 191})
            try:
                for size in (250, 4096, 250, 4096):
                    body = body_of(size, size)
                    started = time.monotonic()
                    await sink.send(outbound(body))
                    elapsed = time.monotonic() - started
                    print(f"\nSiK loss={loss:.0%} {size} B in {elapsed:.2f} s ({size / elapsed:.0f} B/s)", end="")
                    assert got.items[-1].body == body
                assert len(got.items) == 4
                radio = pair.stats()["a"]
                assert radio.serial_rx_dropped == 0, "the radio buffer overflowed: pacing failed"
                if loss:
                    assert radio.air_packets_lost > 0
            finally:
                await source.stop()
                await gcs.close()
                await uav.close()

    run(scenario(), timeout=90)


def test_sik_radio_three_second_outage() -> None:
    async def scenario() -> None:
        async with sik_radio.SikRadioPair(loss=0.0, seed=6) as pair:
            gcs, uav = await sik_pair(pair)
            got = CollectingDeliver()
            source = uav.source("json", {"json_tunnel": True})
            await source.start(got)
            sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
            try:
                await asyncio.sleep(0.3)  # settle: the radio link settles before its scheduled outage
                pair.add_outage(pair.elapsed() + 0.8, 3.0)
                body = body_of(4096, 9)
                started = time.monotonic()
                await sink.send(outbound(body))
                elapsed = time.monotonic() - started
                print(f"\nSiK 3 s outage: 4096 B in {elapsed:.2f} s", end="")
                assert got.items[-1].body == body and len(got.items) == 1
                assert elapsed > 3.0
                assert pair.stats()["a"].air_packets_outage > 0
            finally:
                await source.stop()
                await gcs.close()
                await uav.close()

    run(scenario(), timeout=90)


def test_signed_round_trip_through_radio_and_simulated_vehicle(monkeypatch: pytest.MonkeyPatch) -> None:
    """Telemetry from an independent pymavlink vehicle, and JSON echoed by it, over a lossy
    radio with signing on both ends (the radio's own RADIO_STATUS stays unsigned)."""
    from rabbitros_sim import vehicle as vehicle_sim

    key = bytes(range(32))

    monkeypatch.setenv("RABBITROS_TEST_TUNNEL_KEY", key.hex())

    async def scenario() -> None:
        async with sik_radio.SikRadioPair(loss=0.05, seed=8) as pair:
            vehicle = vehicle_sim.SimVehicle(pair.link_b, signing_key=key, link_id=1, echo_frames=True)
            stop = asyncio.Event()
            running = asyncio.create_task(vehicle.run(stop))
            gcs = TRANSPORT.connect("gcs", {"url": pair.link_a, "baud": 57600,
                                            "signing": {"key_env": "RABBITROS_TEST_TUNNEL_KEY"}})
            await gcs.open()
            positions, echoes = CollectingDeliver(), CollectingDeliver()
            telemetry = gcs.source("pos", {"message": "GLOBAL_POSITION_INT", "system_id": 1})
            json_in = gcs.source("json-in", {"json_tunnel": True, "system_id": 1})
            await telemetry.start(positions)
            await json_in.start(echoes)
            sink = gcs.sink("json-out", {"json_tunnel": True, "target_system": 1, "target_component": 1})
            try:
                body = body_of(250, 77)
                await sink.send(outbound(body))
                assert echoes.items[-1].body == body
                await wait_for(lambda: len(positions.items) >= 4, 20, "4 signed positions", lambda: len(positions.items))
                for item, fields in zip(positions.items, positions.fields()):
                    assert item.meta["signed"] is True
                    expected = vehicle_sim.expected_state(fields["time_boot_ms"] / 1000)
                    assert {k: fields[k] for k in ("lat", "lon", "alt", "vx", "vy", "hdg")} == \
                        {k: expected[k] for k in ("lat", "lon", "alt", "vx", "vy", "hdg")}
                stats = gcs.stats
                await wait_for(lambda: stats["unsigned_accepted"] > 0, 10, "the radio's unsigned RADIO_STATUS accepted")
                assert stats["bad_signature"] == stats["unsigned_rejected"] == stats["replayed"] == 0
                assert vehicle.stats.bad_frames == 0
            finally:
                await telemetry.stop()
                await json_in.stop()
                await gcs.close()
                stop.set()
                await running

    run(scenario(), timeout=60)


async def stop_all(sources: list[Any], connections: list[mavlink.MavlinkConnection]) -> None:
    for source in sources:
        await source.stop()
    for connection in connections:
        await connection.close()


def test_every_route_on_a_tunnel_gets_every_message_and_the_sender_waits_for_all() -> None:
    """Two routes read one payload type: one reassembly, each route gets each message once,
    and the sender's send returns only after both settled it; a route that fails gets the
    retransmitted message again while the one that settled it does not."""

    async def scenario() -> None:
        gcs, uav, _ = await udp_pair()
        first, flaky = CollectingDeliver(), CollectingDeliver(fail_first=1)
        a = uav.source("route-a", {"json_tunnel": True})
        b = uav.source("route-b", {"json_tunnel": True, "system_id": 255})
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
        try:
            await a.start(first)
            await b.start(flaky)
            for n in range(3):
                await sink.send(outbound(b'{"n":%d}' % n))
                assert len(first.items) == len(flaky.items) == n + 1, "acknowledged only after both routes settled it"
            assert [i.body for i in first.items] == [i.body for i in flaky.items] == [b'{"n":0}', b'{"n":1}', b'{"n":2}']
            assert flaky.calls == 4 and first.calls == 3, "the route that settled it is not given it again"
            assert uav.stats["tunnel_deliver_failed"] == 1 and uav.stats["tunnel_delivered"] == 3
        finally:
            await stop_all([a, b], [gcs, uav])

    run(scenario())


class FailOnce(CollectingDeliver):
    """Settles everything but the first attempt at ``body``."""

    def __init__(self, body: bytes) -> None:
        super().__init__()
        self.body, self.failed = body, False

    async def __call__(self, inbound: Inbound) -> None:
        self.calls += 1
        if inbound.body == self.body and not self.failed:
            self.failed = True
            raise RuntimeError("sink down")
        self.items.append(inbound)


def test_a_batch_travels_as_bundles_and_each_message_is_settled_once_per_route() -> None:
    """A batch goes as bundles (one transfer for several messages, within ``bundle`` bytes),
    every route gets every message of a bundle on its own, once; when one route fails one
    message, the bundle is retransmitted, that route gets only that message again, and
    send_batch returns once both routes settled all; a message too large for the tunnel and
    one the mapping made unencodable fail alone."""

    async def scenario() -> None:
        gcs, uav, relay = await udp_pair()
        bodies = [b'{"n":%d,"pad":"%s"}' % (n, b"x" * 300) for n in range(10)]
        steady, flaky = CollectingDeliver(), FailOnce(bodies[4])
        a = uav.source("route-a", {"json_tunnel": True})
        b = uav.source("route-b", {"json_tunnel": True})
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
        try:
            await a.start(steady)
            await b.start(flaky)
            huge = outbound(bytes(tunnel.MAX_FRAGMENTS * tunnel.MAX_FRAGMENT))
            results = await sink.send_batch([outbound(x) for x in bodies[:5]] + [huge] + [outbound(x) for x in bodies[5:]])
            assert results[:5] + results[6:] == [None] * 10
            assert isinstance(results[5], MessageRejected)
            assert sorted(steady.bodies()) == sorted(bodies), "each message once on the steady route"
            assert sorted(flaky.bodies()) == sorted(bodies), "and once on the one that failed one"
            assert flaky.calls == 11 and steady.calls == 10
            parts = {(i.meta["tunnel_id"], i.meta["tunnel_part"]) for i in steady.items}
            transfers = {tunnel_id for tunnel_id, _ in parts}
            assert len(parts) == 10 and 2 <= len(transfers) <= 4, "2 KB bundles of ~320-byte messages"
            assert uav.stats["tunnel_deliver_failed"] == 1 and gcs.stats["tunnel_sent"] == 10
        finally:
            await stop_all([a, b], [gcs, uav])

    run(scenario())


def test_every_route_on_a_message_type_gets_every_message_with_nan_as_null() -> None:
    async def scenario() -> None:
        gcs, uav, _ = await udp_pair()
        one, two = CollectingDeliver(), CollectingDeliver()
        sources = [uav.source("one", {"message": "HIL_GPS"}), uav.source("two", {"message": "HIL_GPS"})]
        try:
            await sources[0].start(one)
            await sources[1].start(two)
            nan = float("nan")
            for n in range(2):
                await gcs.send_message(mavlink2.MAVLink_hil_gps_message(n, 3, 1, 2, 3, 65535, 65535, 0, 0, 0, 0, 0, 255))
            await wait_for(lambda: len(one.items) >= 2 and len(two.items) >= 2, 5, "2 HIL_GPS at each source",
                           lambda: (len(one.items), len(two.items)))
            assert [fields["time_usec"] for fields in one.fields()] == [fields["time_usec"] for fields in two.fields()] == [0, 1]
            vision = mavlink.message_fields(mavlink2.MAVLink_vision_position_estimate_message(1, 1.0, nan, 3.0, 0, 0, 0,
                                                                                             [nan] + [0.0] * 20))
            assert vision["y"] is None and vision["covariance"][:2] == [None, 0.0]
        finally:
            for source in sources:
                await source.stop()
            await gcs.close()
            await uav.close()

    run(scenario())


def test_tunnel_sink_mapping_shapes_the_body() -> None:
    async def scenario() -> None:
        gcs, uav, _ = await udp_pair()
        got = CollectingDeliver()
        source = uav.source("in", {"json_tunnel": True})
        sink = gcs.sink("out", {"json_tunnel": True, "target_system": 1})
        try:
            await source.start(got)
            canonical = {"agent_id": "uav1", "command": "goto"}
            await sink.send(Outbound(b'{"agent_id":"uav1","command":"goto"}', canonical, {"cmd": "goto", "v": 1}, "m", {}))
            same = {"a": 1}
            await sink.send(Outbound(b'{"a": 1}', same, same, "m", {}))
            assert [i.body for i in got.items] == [b'{"cmd":"goto","v":1}', b'{"a": 1}'], "no mapping: the bytes as they came"
            with pytest.raises(MessageRejected):
                await sink.send(Outbound(b"{}", {}, {"x": float("nan")}, "m", {}))
        finally:
            await source.stop()
            await gcs.close()
            await uav.close()

    run(scenario())
