"""An AMQP source holds the acknowledgement of what its route settled across batches and sends
one ``basic_ack(multiple=True)`` for many of them (engine/endpoints/amqp/acks.py,
``HeldAcks.acknowledge``): a quarter of the prefetch at a time, when the source goes idle,
or when it stops. What it must keep: every message reaches the sink once and in order, none is
acknowledged before its sink accepted it, and a stop leaves nothing settled unacknowledged
(the broker would deliver it again to the next engine).

The idle and the age bounds are set out of reach here (60 s), so that what is held is held
until a quarter of the prefetch or the stop: the number of acknowledgement frames is then
known from the design, and the stop is the only way out for the last ones."""

from __future__ import annotations

import asyncio
import uuid
from pathlib import Path

import aio_pika
import pytest

import rclpy  # noqa: F401  (a missing rclpy fails the run, never skips it)

import engine.endpoints.amqp.acks as amqp_acks
from engine.endpoints.amqp.source import AmqpSource
from engine.running.runtime import Engine
from tests.support.amqp_helpers import amqp_to_ros2_routes, message_count, publish_burst
from tests.support.repo import REPO
from tests.support.waiting import wait_for

PREFETCH = 400

def test_a_burst_is_acknowledged_a_quarter_of_the_prefetch_at_a_time_and_the_rest_at_stop(
        amqp_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    monkeypatch.setattr(amqp_acks, "ACK_IDLE_NS", 60_000_000_000)
    monkeypatch.setattr(amqp_acks, "ACK_HOLD_NS", 60_000_000_000)
    tag = "k" + uuid.uuid4().hex[:8]
    queue = f"acks-{tag}"
    (tmp_path / "acks.yaml").write_text(amqp_to_ros2_routes("acks", queue, DOMAIN, tag, PREFETCH))
    frames: list[tuple[str, int, bool]] = []  # (ack or nack, delivery tag, multiple), in the order sent
    premature: list[tuple[int, int]] = []  # a tag acknowledged before the sink had accepted that many messages
    runners: list = []
    settle_frame = amqp_acks._settle_frame

    async def counted_frame(method, tag_, **kwargs):  # the real function, recorded
        frames.append((method.__name__, int(tag_), bool(kwargs.get("multiple"))))
        delivered = runners[0].observer.delivered  # one channel, in order: tag n is the n-th message
        if int(tag_) > delivered:
            premature.append((int(tag_), delivered))
        await settle_frame(method, tag_, **kwargs)

    monkeypatch.setattr(amqp_acks, "_settle_frame", counted_frame)
    alone: list[int] = []
    settle_alone = AmqpSource._settle_alone

    async def counted_alone(self, deliver, message, received_ns):
        alone.append(int(message.delivery_tag))
        await settle_alone(self, deliver, message, received_ns)

    monkeypatch.setattr(AmqpSource, "_settle_alone", counted_alone)
    burst = [b'{"seq": %d}' % i for i in range(2000)]
    tail = [b'{"seq": %d}' % i for i in range(2000, 2010)]

    async def scenario() -> tuple[list[bytes], int, dict, int]:
        peer = Peer()
        try:
            received = peer.subscribe(String, f"/{tag}/acks")
            peer.start()
            engine = Engine(tmp_path, REPO / "schemas")
            await engine.start()
            try:
                runner = engine.runners["acks"]
                runners.append(runner)
                await wait_for(lambda: runner.pipeline.sink.ready, 60, "the reader never matched")
                connection = await aio_pika.connect(amqp_url)
                async with connection:
                    channel = await connection.channel(publisher_confirms=True)
                    await publish_burst(channel, queue, burst)
                    await wait_for(lambda: runner.observer.delivered == len(burst), 60, "the burst was not all delivered")
                    # a short burst after a pause (its first one may be settled alone): held with the rest
                    # until the stop, as the source never goes idle for 60 s
                    await publish_burst(channel, queue, tail)
                    await wait_for(lambda: runner.observer.delivered == len(burst) + len(tail), 60, "the tail was not delivered")
                    await wait_for(lambda: len(received) == len(burst) + len(tail), 60, "the reader did not get them all")
                    source = runner.source
                    assert isinstance(source, AmqpSource), "the route reads an AMQP queue"
                    held = source._acks.held
                    counters = runner.observer.counters()
            finally:
                await engine.stop()  # sends what is held, then closes the channel
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                declared = await (await connection.channel()).declare_queue(queue, passive=True)
                left = message_count(declared)
            return [m.data.encode() for m in received], left, counters, held
        finally:
            peer.close()

    arrived, left, counters, held = asyncio.run(asyncio.wait_for(scenario(), 120))
    total = len(burst) + len(tail)
    assert arrived == burst + tail  # in order, each once
    assert counters["received"] == total and counters["delivered"] == total and counters["failed"] == 0, counters
    assert premature == []  # nothing acknowledged before its sink accepted it
    assert held > 0  # something was still held when the engine stopped...
    assert left == 0  # ...and the stop acknowledged it: nothing went back to the queue
    assert all(name == "basic_ack" and multiple for name, _, multiple in frames), frames
    tags = [t for _, t, _ in frames]
    assert tags == sorted(tags) and tags[-1] == total, tags  # in order, the last one at the stop
    # one frame per quarter of the prefetch, one per message settled alone (each flushes what is
    # held), and the stop's: without the holding, one frame per batch (batches of a few messages)
    assert len(frames) <= total // (PREFETCH // 4) + len(alone) + 1, (len(frames), len(alone), frames[:20])
