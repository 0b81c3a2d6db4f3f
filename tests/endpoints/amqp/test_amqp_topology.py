"""AMQP topology follows the routes on a real RabbitMQ node: a changed binding_key removes
the old binding, a removed route's bindings go, its auto-named queue is deleted when
empty, a named queue is kept."""

from __future__ import annotations

import asyncio
import uuid
from pathlib import Path

import aio_pika
import aiormq.exceptions
import pytest

from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, publish, started_with_client

ROUTES = """
connections:
  gcs: {{amqp: "${{TEST_AMQP_URL}}"}}
routes:
  - name: named
    source: {{amqp: {{exchange: {inbox}, binding_key: "{key}", queue: {queue}}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: named}}}}
"""
AUTO = """
  - name: {auto}
    source: {{amqp: {{exchange: {inbox}, binding_key: "auto"}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: auto}}}}
"""


async def queue_exists(connection: aio_pika.abc.AbstractConnection, name: str) -> int | None:
    """The queue's message count, or None when the broker has no such queue."""
    channel = await connection.channel()
    try:
        queue = await channel.declare_queue(name, passive=True)
        return queue.declaration_result.message_count
    except aiormq.exceptions.ChannelNotFoundEntity:
        return None
    finally:
        if not channel.is_closed:
            await channel.close()


def test_bindings_and_queues_follow_the_routes(amqp_url: str, tmp_path: Path, schemas_dir: Path,
                                              monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    tag = uuid.uuid4().hex[:8]
    n = {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}", "auto": f"auto-{tag}"}
    routes = tmp_path / "routes"
    routes.mkdir()
    farm = routes / "farm.yaml"
    farm.write_text(ROUTES.format(key="old", **n) + AUTO.format(**n))

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        engine.retire_after_s = 0.05
        async with started_with_client(engine, amqp_url) as connection:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"])
            await publish(channel, n["inbox"], "old", [b'{"k": "old-1"}'])
            await publish(channel, n["inbox"], "auto", [b'{"k": "auto-1"}'])
            assert len(await out.wait_for(2)) == 2
            assert await queue_exists(connection, f"rabbitros.{n['auto']}") == 0

            farm.write_text(ROUTES.format(key="new", **n) + AUTO.format(**n))
            assert await engine.reload(), engine.reloads.last_error
            await engine.topology_settled()
            await publish(channel, n["inbox"], "old", [b'{"k": "old-2"}'])
            await publish(channel, n["inbox"], "new", [b'{"k": "new-1"}'])
            await out.wait_for(3)
            bodies = [m.body for m in out.messages]
            assert b'{"k": "new-1"}' in bodies, "the new binding was not made"
            assert b'{"k": "old-2"}' not in bodies, "the old binding is still in place"

            farm.write_text(ROUTES.format(key="new", **n))
            assert await engine.reload(), engine.reloads.last_error
            await engine.topology_settled()
            assert await queue_exists(connection, f"rabbitros.{n['auto']}") is None, "auto-named queue left behind"

            farm.write_text("routes: []\n")
            assert await engine.reload(), engine.reloads.last_error
            await engine.topology_settled()
            await publish(channel, n["inbox"], "new", [b'{"k": "new-2"}'])
            await asyncio.sleep(0.3)  # quiet window: the message to the removed binding must not reach the kept queue
            assert await queue_exists(connection, n["queue"]) == 0, "a named queue is kept, without its bindings"

    asyncio.run(scenario())


def test_a_route_missing_for_a_moment_keeps_its_binding(amqp_url: str, tmp_path: Path, schemas_dir: Path,
                                                      monkeypatch: pytest.MonkeyPatch):
    """A save read half-written (a file without routes) and fixed a moment later: the named
    queue stays bound and buffers, so nothing published meanwhile is lost."""
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    tag = uuid.uuid4().hex[:8]
    n = {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}
    routes = tmp_path / "routes"
    routes.mkdir()
    farm = routes / "farm.yaml"
    farm.write_text(ROUTES.format(key="k", **n))

    async def scenario() -> list[bytes]:
        engine = Engine(routes, schemas_dir)
        async with started_with_client(engine, amqp_url) as connection:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"])
            farm.write_text("")
            assert await engine.reload() and not engine.runners
            await publish(channel, n["inbox"], "k", [b'{"k": "meanwhile"}'])
            farm.write_text(ROUTES.format(key="k", **n))
            assert await engine.reload() and set(engine.runners) == {"named"}
            await engine.topology_settled()
            return [m.body for m in await out.wait_for(1)]

    assert asyncio.run(scenario()) == [b'{"k": "meanwhile"}']


def test_a_file_found_empty_is_read_again_before_its_routes_go(amqp_url: str, tmp_path: Path, schemas_dir: Path,
                                                              monkeypatch: pytest.MonkeyPatch):
    """An editor that truncates then writes: the reload that sees the empty file reads it
    again a moment later, so the routes are never stopped."""
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    tag = uuid.uuid4().hex[:8]
    n = {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}
    routes = tmp_path / "routes"
    routes.mkdir()
    farm = routes / "farm.yaml"
    farm.write_text(ROUTES.format(key="k", **n))

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        try:
            runner = engine.runners["named"]
            farm.write_text("")
            reloading = asyncio.create_task(engine.reload())
            await asyncio.sleep(0.05)  # settle: the reload reads the emptied file before the rewrite (the race under test)
            farm.write_text(ROUTES.format(key="k2", **n))
            assert await reloading
            assert engine.runners["named"] is not runner and engine.generation == 2, "one reload, to the rewritten file"
            farm.write_text("")
            assert await engine.reload() and not engine.runners, "a file left empty does remove its routes"
        finally:
            await engine.stop()

    asyncio.run(scenario())
