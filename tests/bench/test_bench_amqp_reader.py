"""The fleet benchmark's consumer (bench/amqp_reader.py) reads its own frames, so it is held to
what a library consumer would give on a real broker: every message, in order, with its routing
key and exact body (empty, small, and larger than a frame); and a refused bind raises with the
broker's text instead of hanging."""

from __future__ import annotations

import asyncio
import threading
import time
import uuid

import aiormq
import pytest

from bench.amqp_reader import Arrival, BrokerClosed, QueueReader


async def _publish(url: str, exchange: str, messages: list[tuple[str, bytes]]) -> None:
    connection = await aiormq.connect(url)
    try:
        channel = await connection.channel()
        await channel.confirm_delivery()
        for key, body in messages:
            await channel.basic_publish(body, exchange=exchange, routing_key=key)
    finally:
        await connection.close()


async def _declare(url: str, exchange: str, delete: bool = False) -> None:
    connection = await aiormq.connect(url)
    try:
        channel = await connection.channel()
        if delete:
            await channel.exchange_delete(exchange)
        else:
            await channel.exchange_declare(exchange, exchange_type="topic", auto_delete=False)
    finally:
        await connection.close()


def test_reader_gets_every_message_whole_and_in_order(amqp_url: str) -> None:
    exchange = f"reader-{uuid.uuid4().hex[:6]}"
    asyncio.run(_declare(amqp_url, exchange))
    reader = QueueReader(amqp_url)
    try:
        reader.consume(reader.bind(exchange, "robot.#"))
        large = bytes(range(256)) * 1200  # 307,200 bytes: three body frames at the broker's 131,072
        messages = [("robot.fix", b'{"seq": %d}' % n) for n in range(500)] + [("robot.empty", b""), ("robot.big", large)]
        messages += [("robot.last", b"last")]
        arrived: list[Arrival] = []
        publisher = threading.Thread(target=lambda: asyncio.run(
            _publish(amqp_url, exchange, [("other.key", b"not bound"), *messages])))
        publisher.start()
        deadline = time.monotonic() + 60
        reader.read(arrived.append, lambda: len(arrived) >= len(messages) or time.monotonic() > deadline)
        publisher.join(60)
        assert [(key, body) for _, key, body in arrived] == messages
        stamps = [ns for ns, _, _ in arrived]
        assert stamps == sorted(stamps) and abs(stamps[-1] - time.time_ns()) < 60e9
    finally:
        reader.close()
        asyncio.run(_declare(amqp_url, exchange, delete=True))


def test_reader_bind_to_a_missing_exchange_names_it(amqp_url: str) -> None:
    reader = QueueReader(amqp_url)
    try:
        with pytest.raises(BrokerClosed, match="404.*no-such-exchange-for-reader"):
            reader.bind("no-such-exchange-for-reader", "#")
    finally:
        reader.close()
