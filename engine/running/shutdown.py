"""The engine's graceful stop: sources first, then what is in flight, then the connections.

The order is what makes a stop lose nothing: a source that stops taking messages first lets
the pipelines settle what they hold; buffers keep delivering meanwhile (then stay spilled on
disk); closing the connections last returns unacknowledged AMQP messages to their queues, so
whatever was not settled within the drain timeout is redelivered by its broker after the
restart rather than dropped. Apart from engine/running/runtime.py, which holds the reload
phases, because a stop shares none of them.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Protocol

from engine.running.buffer import Buffers
from engine.running.connections import ConnectionPool
from engine.running.dedupe import DedupeKeys
from engine.running.leases import Leases
from engine.running.runner import RouteRunner

log = logging.getLogger("engine.running.runtime")

STOP_GRACE = 2.0
"""Seconds a stop gives sources to hand back what they hold once the drain timeout is over."""


class Stopping(Protocol):
    """What a stop takes down: the engine (engine/running/runtime.py) as this module sees it."""

    runners: dict[str, RouteRunner]
    connections: ConnectionPool
    buffers: Buffers
    leases: Leases
    dedupe: DedupeKeys


async def stop_routes(engine: Stopping, drain_timeout: float) -> None:
    """Sources stop taking messages; what is in flight is settled for at most ``drain_timeout``
    seconds in all; then the leases, the connections and the de-duplication keys close. The
    caller holds the engine's reload lock, so no reload starts routes meanwhile."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + drain_timeout
    runners = list(engine.runners.values())
    engine.connections.stop_opening()
    await _stop_sources(runners, deadline)
    buffers = engine.buffers.take_all()
    await asyncio.gather(*(b.close(max(0.0, deadline - loop.time())) for b in buffers), return_exceptions=True)
    pipelines = asyncio.ensure_future(asyncio.gather(*(r.retire_pipeline(r.pipeline) for r in runners), return_exceptions=True))
    if not await _finished(pipelines, max(deadline, loop.time() + STOP_GRACE)):
        pipelines.cancel()
        await asyncio.gather(pipelines, return_exceptions=True)
    await engine.leases.release_unused(())
    await engine.connections.close_all()
    await engine.dedupe.close()


async def _stop_sources(runners: list[RouteRunner], deadline: float) -> None:
    """Stop every source, letting in-flight messages settle until ``deadline``; then stop
    retrying, so sources settle what they can within STOP_GRACE."""
    for runner in runners:
        runner.stop_starting()
    sources = asyncio.ensure_future(asyncio.gather(*(r.source.stop() for r in runners), return_exceptions=True))
    if await _finished(sources, deadline):
        return
    log.warning("drain timeout: what is not settled yet is redelivered by its broker, or dropped and counted where the source cannot redeliver")
    for runner in runners:
        runner.halt()
    if not await _finished(sources, asyncio.get_running_loop().time() + STOP_GRACE):
        sources.cancel()
        await asyncio.gather(sources, return_exceptions=True)


async def _finished(work: asyncio.Future[Any], deadline: float) -> bool:
    """Wait for ``work`` until ``deadline`` (loop time) without cancelling it; True if done."""
    done, _ = await asyncio.wait({work}, timeout=max(0.0, deadline - asyncio.get_running_loop().time()))
    return bool(done)
