"""An engine running in its own thread's event loop, with AMQP, ROS 2 and MAVLink peers, so
property-based tests can throw messages at it between examples while it keeps running."""

from __future__ import annotations

import asyncio
import json
import threading
from collections import Counter
from pathlib import Path
from typing import Any, Coroutine

import aio_pika

from engine.running.runtime import Engine
from tests.support import workers


class LoopThread:
    """An asyncio loop in a daemon thread; ``run(coro)`` runs a coroutine there and waits."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True, name="engine-loop")
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 120.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


def dead_letter_key(message: aio_pika.abc.AbstractIncomingMessage) -> tuple[str, str, bytes]:
    return message.routing_key or "", str(message.headers.get("x-rabbitros-stage")), message.body


def outputs_by_route(messages: list[aio_pika.abc.AbstractIncomingMessage]) -> Counter[tuple[str, int]]:
    return Counter((m.routing_key or "", json.loads(m.body)["seq"]) for m in messages)


def start_engine(loop: LoopThread, routes: Path, schemas: Path) -> Engine:
    async def start() -> Engine:
        engine = Engine(routes, schemas)
        await engine.start()
        return engine

    return loop.run(start())


def ros_domain() -> int:
    return workers.ros_domain(1)
