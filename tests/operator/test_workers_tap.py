"""The supervisor's ``/tap/ROUTE`` under ``run --workers 2`` (what its web console's live tap
reads) follows a worker killed with -9 and started again, as its Foxglove view does.

Real parts: a private RabbitMQ node (tests/conftest.py), the engine as an operator runs it (the
supervisor and two worker processes), a plain HTTP client on the supervisor's admin. The route
consumes a queue, so both workers carry its messages: every one must come over the tap, also
those the restarted worker carried."""

from __future__ import annotations

import asyncio
import json
import os
import signal
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
    source: {{amqp: {{exchange: {tag}, binding_key: "in.#", queue: {tag}-in}}}}
    mapping: "{{agent_id: agent, seq: seq}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {tag}, routing_key: "out.relay"}}}}
"""
MESSAGES = 200


def test_the_supervisors_tap_follows_a_restarted_worker(amqp_url: str, tmp_path: Path) -> None:
    tag = "wtap" + uuid.uuid4().hex[:8]
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "relay.yaml").write_text(ROUTES.format(tag=tag))
    admin = listening_port()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                           "--workers", "2", "--admin", str(admin))

    async def scenario() -> dict[str, Any]:
        seen: dict[str, Any] = {}
        lines: list[dict[str, Any]] = []

        async def status() -> dict[str, Any]:
            async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{admin}/status") as answer:
                assert answer.status == 200, await answer.text()
                seen["status"] = dict(await answer.json())
                return seen["status"]

        async def taps(value: int) -> bool:
            return bool((await status())["routes"].get("relay", {}).get("taps") == value)

        async def restarted(victim: int) -> bool:
            worker = (await status())["workers"][0]
            return bool(worker["up"] and worker["restarts"] == 1 and worker["pid"] != victim)

        async def read(tap: aiohttp.ClientResponse) -> None:
            async for line in tap.content:
                lines.append(json.loads(line))

        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        out = await Collector.bind(channel, tag, "out.#")  # the sink publishes mandatory: someone reads
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=None)) as session, \
                session.get(f"http://127.0.0.1:{admin}/tap/relay") as tap:
            reading = asyncio.create_task(read(tap))
            try:
                await wait_for(lambda: taps(2), 30, "the route's tap open on both workers", lambda: seen.get("status"))
                victim = (await status())["workers"][0]["pid"]
                os.kill(victim, signal.SIGKILL)
                await wait_for(lambda: restarted(victim), 120, "worker 0 started again", engine.log)
                await wait_for(lambda: taps(2), 30, "the restarted worker's tap open again",
                               lambda: seen["status"]["routes"].get("relay"))
                await publish(channel, tag, "in.x", [json.dumps({"agent": "uav1", "seq": seq}).encode() for seq in range(MESSAGES)])
                await wait_for(lambda: len(out.messages) == MESSAGES, 60, "every message at the sink")
                await wait_for(lambda: {line["canonical"]["seq"] for line in lines} >= set(range(MESSAGES)), 30,
                               "every message on the supervisor's tap", lambda: f"{len(lines)} of {MESSAGES}")
                document = await status()
            finally:
                reading.cancel()
                await asyncio.gather(reading, return_exceptions=True)
                await connection.close()
        return document

    document, _ = engine.run(scenario)
    by_worker = [((w.get("status") or {}).get("routes", {}).get("relay") or {}).get("delivered", 0) for w in document["workers"]]
    assert by_worker[0] > 0, f"the restarted worker carried nothing: {by_worker}"
