"""Plain aio-pika clients used by tests to publish and collect, independent of the engine."""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from typing import Any, AsyncIterator

import aio_pika


class Collector:
    """A temporary queue bound to an exchange that records every message it receives."""

    def __init__(self) -> None:
        self.messages: list[aio_pika.abc.AbstractIncomingMessage] = []
        self._arrived = asyncio.Event()

    @classmethod
    async def bind(cls, channel: Any, exchange: str, binding_key: str = "#") -> "Collector":
        collector = cls()
        target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
        queue = await channel.declare_queue(f"test-{uuid.uuid4().hex[:8]}", exclusive=True)
        await queue.bind(target, binding_key)
        await queue.consume(collector._on_message, no_ack=True)
        return collector

    async def _on_message(self, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        self.messages.append(message)
        self._arrived.set()

    async def wait_for(self, count: int, timeout: float = 20.0) -> list[aio_pika.abc.AbstractIncomingMessage]:
        async def enough() -> None:
            while len(self.messages) < count:
                self._arrived.clear()
                await self._arrived.wait()

        try:
            await asyncio.wait_for(enough(), timeout)
        except asyncio.TimeoutError:
            pass
        return self.messages


async def publish(channel: Any, exchange: str, routing_key: str, bodies: list[bytes]) -> None:
    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
    for index, body in enumerate(bodies):
        await target.publish(
            aio_pika.Message(body, content_type="application/json", message_id=f"m{index}"), routing_key
        )


@contextlib.asynccontextmanager
async def started_with_client(engine: Any, amqp_url: str) -> AsyncIterator[aio_pika.abc.AbstractConnection]:
    """Start ``engine`` (an engine.runtime.Engine) and open a plain aio-pika connection beside
    it; on the way out close the connection, then stop the engine."""
    await engine.start()
    try:
        connection = await aio_pika.connect(amqp_url)
        try:
            yield connection
        finally:
            await connection.close()
    finally:
        await engine.stop()
