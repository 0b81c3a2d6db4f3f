"""An AMQP message that arrives alone is settled in its consumer callback, without the batch
loop's wake-up (engine/endpoints/amqp/source.py ``AmqpSource._on_message``): order,
acknowledgement after the sink accepted, and the route's counters stay the batch loop's.

The hard case is a message alone whose sink cannot take it yet (a ROS 2 topic no reader has
matched): it waits in its callback while the messages behind it are queued for the batch
loop, which must not send them first nor acknowledge past it."""

from __future__ import annotations

import asyncio
import uuid
from pathlib import Path

import aio_pika
import pytest

import rclpy  # noqa: F401  (a missing rclpy fails the run, never skips it)

from engine.endpoints.amqp.source import ALONE_GAP_NS, AmqpSource
from engine.running.runtime import Engine
from tests.support.amqp_helpers import amqp_to_ros2_routes, message_count, publish_burst
from tests.support.repo import REPO
from tests.support.waiting import wait_for


def test_messages_alone_and_a_burst_behind_one_waiting_for_its_reader_arrive_in_order_once(
        amqp_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "a" + uuid.uuid4().hex[:8]
    queue = f"alone-{tag}"
    (tmp_path / "alone.yaml").write_text(amqp_to_ros2_routes("alone", queue, DOMAIN, tag))
    alone: list[int] = []
    settle_alone = AmqpSource._settle_alone

    async def counted(self, deliver, message, received_ns):  # the real method, counted
        alone.append(int(message.delivery_tag))
        await settle_alone(self, deliver, message, received_ns)

    monkeypatch.setattr(AmqpSource, "_settle_alone", counted)
    bodies = [b'{"seq": %d}' % i for i in range(60)]

    async def scenario() -> tuple[list[bytes], int, dict]:
        peer = None
        try:
            engine = Engine(tmp_path, REPO / "schemas")
            await engine.start()
            try:
                connection = await aio_pika.connect(amqp_url)
                async with connection:
                    channel = await connection.channel(publisher_confirms=True)
                    runner = engine.runners["alone"]
                    # 1: alone, and no reader yet: it waits in its callback for the sink
                    await channel.default_exchange.publish(aio_pika.Message(bodies[0]), queue)
                    await wait_for(lambda: runner.observer.received == 1, 30, "the first message was not taken")
                    assert alone == [1]
                    # 2-30: a burst behind it, queued for the batch loop, which must wait for 1
                    await publish_burst(channel, queue, bodies[1:30])
                    source = runner.source
                    assert isinstance(source, AmqpSource), "the route reads an AMQP queue"
                    # the batch loop has taken (some of) the burst: were it to hand it on, it would have in the same step
                    await wait_for(lambda: not source._parked, 30, "the batch loop never took any of the burst")
                    # the route has been handed nothing behind the waiting one: no batch can overtake it
                    # or acknowledge past it (basic_ack multiple=True) before it is settled
                    assert runner.observer.received == 1 and runner.observer.delivered == 0, runner.observer.counters()
                    peer = Peer()
                    received = peer.subscribe(String, f"/{tag}/alone")
                    peer.start()
                    await wait_for(lambda: len(received) == 30, 30, "the first 30 did not all arrive")
                    # 31-60 at a robot's pace: each one alone
                    for body in bodies[30:]:
                        await asyncio.sleep(ALONE_GAP_NS / 1e9 * 5)  # pacing: a robot's pace, each one alone
                        await channel.default_exchange.publish(aio_pika.Message(body), queue)
                    await wait_for(lambda: len(received) == 60, 30, "the last 30 did not all arrive")
                    await wait_for(lambda: runner.observer.delivered == 60, 30, "not counted delivered")
                    counters = runner.observer.counters()
            finally:
                await engine.stop()  # its channel closed: a message it did not acknowledge is ready again
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                declared = await (await connection.channel()).declare_queue(queue, passive=True)
                left = message_count(declared)
            return [m.data.encode() for m in received], left, counters  # all that arrived until the stop
        finally:
            if peer is not None:
                peer.close()

    arrived, left, counters = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert arrived == bodies  # in order, each once
    assert left == 0  # every message acknowledged (none requeued when the engine's channel closed)
    assert counters["received"] == 60 and counters["delivered"] == 60 and counters["failed"] == 0, counters
    assert 1 in alone and len(alone) >= 20, alone  # the paced ones went the alone way (a loaded machine may bunch a few)
