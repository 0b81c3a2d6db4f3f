"""A queue's backlog reaches an AMQP route in large batches, not 3 messages at a time: the
source's channel holds more frames between aiormq's connection reader and its channel reader
than aiormq's default of 10 (engine/endpoints/amqp/source.py ``FRAME_BUFFER``). With 10, a
drain was taken exactly 3.3 messages (10 frames) per batch, each batch paying the route's
per-batch costs; every message must still arrive once and in order."""

from __future__ import annotations

import asyncio
import uuid
from pathlib import Path

import aio_pika
import pytest

import rclpy  # noqa: F401  (a missing rclpy fails the run, never skips it)

from engine.endpoints.amqp.source import FRAME_BUFFER, AmqpSource
from engine.running.runtime import Engine
from tests.support.amqp_helpers import amqp_to_ros2_routes, publish_burst
from tests.support.repo import REPO
from tests.support.waiting import wait_for


def test_a_backlog_is_taken_in_batches_larger_than_aiormqs_ten_frames(
        amqp_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "b" + uuid.uuid4().hex[:8]
    queue = f"backlog-{tag}"
    (tmp_path / "backlog.yaml").write_text(amqp_to_ros2_routes("backlog", queue, DOMAIN, tag, 1000))
    sizes: list[int] = []
    inbounds = AmqpSource.inbounds

    def counted(self, batch):  # the real method (every batch the route is handed), its batch sizes recorded
        sizes.append(len(batch))
        return inbounds(self, batch)

    monkeypatch.setattr(AmqpSource, "inbounds", counted)
    bodies = [b'{"seq": %d}' % i for i in range(3000)]

    async def scenario() -> tuple[list[bytes], int]:
        peer = Peer()
        try:
            received = peer.subscribe(String, f"/{tag}/backlog")
            peer.start()
            # the backlog is in the queue before the route starts (the queue declared as the route
            # declares it), so the broker streams it up to the prefetch whatever the machine's load:
            # published beside a running route on a busy machine, the route kept up and batches stayed small
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)
                await channel.declare_queue(queue, durable=True)
                await publish_burst(channel, queue, bodies)
            engine = Engine(tmp_path, REPO / "schemas")
            await engine.start()
            try:
                runner = engine.runners["backlog"]
                source = runner.source
                assert isinstance(source, AmqpSource), "the route reads an AMQP queue"
                assert source._channel is not None, "a started source has its channel"
                frames = (await source._channel.get_underlay_channel()).frames.maxsize
                await wait_for(lambda: len(received) == len(bodies), 60, "the reader did not get them all")
            finally:
                await engine.stop()
            return [m.data.encode() for m in received], frames
        finally:
            peer.close()

    arrived, frames = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert arrived == bodies  # once each, in order
    assert frames == FRAME_BUFFER
    # 10 frames held 3 messages; a loaded machine may split batches, but not all of them
    assert max(sizes) >= 20, sorted(sizes)[-20:]
    assert sum(sizes) == len(bodies), sum(sizes)
