"""The operator's views against a real engine and RabbitMQ: the status file, a tap and the
console's document keep working whatever a route carried, also values orjson refuses
(engine/common/json_bytes.py)."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import aiohttp

from engine.common.processes import listening_port

from tests.support.amqp_helpers import Collector, publish
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for

ROUTES = """
routes:
  - name: relay
    source: {{amqp: {{exchange: {exchange}, binding_key: "in.#", queue: {exchange}-in}}}}
    mapping: "{{agent_id: agent, seq: seq, count: count}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {exchange}, routing_key: "out.relay"}}}}
"""
LONG_COUNT = 2**70
"""An integer beyond 64 bits: the engine carries it exactly (engine/common/schemas.py), and
it is then the route's last canonical message in the status document."""


def delivered(engine: EngineProcess) -> int:
    """The route's delivered messages, as the status file says now."""
    return int(((engine.status() or {}).get("routes", {}).get("relay", {}).get("messages") or {}).get("delivered", 0))


def test_a_message_with_an_integer_beyond_64_bits_leaves_the_status_file_written(amqp_url: str, tmp_path: Path) -> None:
    """orjson refuses integers beyond 64 bits (and lone surrogates): the status file is then
    encoded by the standard library, and the reporter goes on writing it (it stopped for
    good, and a reload's write stopped the reloader too)."""
    exchange = f"status-file-{uuid.uuid4().hex[:8]}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "relay.yaml").write_text(ROUTES.format(exchange=exchange))
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url})

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            collector = await Collector.bind(channel, exchange, "out.#")
            for seq, count in enumerate((1, LONG_COUNT, 1), 1):  # the long one the last canonical for a while
                await publish(channel, exchange, "in.a", [json.dumps({"agent": "uav1", "seq": seq, "count": count}).encode()])
                await wait_for(lambda: len(collector.messages) == seq, 30, f"message {seq} delivered")
                await wait_for(lambda: delivered(engine) == seq, 30, f"the status file to count message {seq}", engine.status)
            assert json.loads(collector.messages[1].body)["count"] == LONG_COUNT
        finally:
            await connection.close()

    _, status = engine.run(scenario)
    assert status["routes"]["relay"]["messages"]["delivered"] == 3


def test_a_tapped_message_with_an_integer_beyond_64_bits_reaches_the_tap_and_the_route_goes_on(amqp_url: str, tmp_path: Path) -> None:
    """A tap (the admin's ``/tap``, which the supervisor's ``/tap`` and its Foxglove view read
    from each worker) serialises every message with orjson: one it refuses is written by the
    standard library, not raised into the route after its sink took the message."""
    exchange = f"status-tap-{uuid.uuid4().hex[:8]}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "relay.yaml").write_text(ROUTES.format(exchange=exchange))
    port = listening_port()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--admin", str(port))

    async def scenario() -> list[dict[str, Any]]:
        lines: list[dict[str, Any]] = []
        connection = await aio_pika.connect(amqp_url)
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=60)) as session, \
                session.get(f"http://127.0.0.1:{port}/tap/relay") as tap:
            try:
                channel = await connection.channel()
                collector = await Collector.bind(channel, exchange, "out.#")
                await wait_for(lambda: ((engine.status() or {}).get("routes", {}).get("relay") or {}).get("taps") == 1, 30,
                               "the tap to attach")
                for seq, count in enumerate((1, LONG_COUNT, 1), 1):
                    await publish(channel, exchange, "in.a", [json.dumps({"agent": "uav1", "seq": seq, "count": count}).encode()])
                await wait_for(lambda: len(collector.messages) == 3, 30, "the three messages delivered")
                while len(lines) < 3:
                    lines.append(json.loads(await asyncio.wait_for(tap.content.readline(), 30)))
                await wait_for(lambda: delivered(engine) == 3, 30, "the status file to count the three", engine.status)
            finally:
                await connection.close()
        return lines

    lines, status = engine.run(scenario)
    assert [line["canonical"]["count"] for line in lines] == [1, LONG_COUNT, 1]
    assert [line["outcome"] for line in lines] == ["delivered"] * 3
    assert status["routes"]["relay"]["messages"]["delivered"] == 3


POSITIONS = """
routes:
  - name: positions
    source: {{amqp: {{exchange: {exchange}, binding_key: "pos.#", queue: {exchange}-pos}}}}
    mapping: "{{type: 'position', agent_id: agent, lat: lat, lon: lon, alt_msl: alt}}"
    schema: position
    sink: {{amqp: {{exchange: {exchange}, routing_key: "out.positions"}}}}
"""


def test_a_position_with_an_integer_beyond_64_bits_leaves_the_console_document_served(amqp_url: str, tmp_path: Path) -> None:
    """``alt_msl`` has no bound in the position schema: a bogus altitude as a long integer is a
    valid position, on the fleet of the console's document (``/console/state``, which the
    supervisor of ``run --workers`` merges, and ``/console/events``). orjson refused it: a 500,
    and under workers that worker's routes, dead letters and agents gone from the console."""
    exchange = f"view-console-{uuid.uuid4().hex[:8]}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "positions.yaml").write_text(POSITIONS.format(exchange=exchange))
    port = listening_port()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--admin", str(port))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            collector = await Collector.bind(channel, exchange, "out.#")
            await publish(channel, exchange, "pos.a", [json.dumps({"agent": "uav1", "lat": 48.15, "lon": 11.58, "alt": LONG_COUNT}).encode()])
            await wait_for(lambda: len(collector.messages) == 1, 30, "the position delivered")
            seen: dict[str, Any] = {}

            async def with_the_agent() -> dict[str, Any] | None:  # the fleet hears it once the broker confirmed it
                async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/console/state") as answer:
                    seen.update(code=answer.status, body=await answer.text())
                    state = json.loads(seen["body"]) if answer.status == 200 else {}
                    return state if state.get("fleet") else None

            return await wait_for(with_the_agent, 30, "the console's document with the agent", lambda: seen)
        finally:
            await connection.close()

    state, _ = engine.run(scenario)
    assert [(agent["agent_id"], agent["alt_msl"]) for agent in state["fleet"]] == [("uav1", LONG_COUNT)]
