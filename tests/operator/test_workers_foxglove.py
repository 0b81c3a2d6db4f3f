"""``run --workers 2 --foxglove``: the supervisor serves the Foxglove view of the engine as a whole.

Real parts: a private RabbitMQ node (tests/conftest.py), the engine as an operator runs it (the
supervisor and two worker processes, tests/support/engine_process.py), and an independent
Foxglove client (plain ``websockets``, tests/support/foxglove_client.py). Both routes consume a
queue, so both workers carry their messages. The view must advertise every route, send
``/routes/status`` with the counts summed over the workers, ``/fleet`` with every agent, and on a
route's channel every message the route carried, whichever worker carried it (each worker's own
count read from the supervisor's ``/status``), also once a worker killed with -9 is back; and no
worker's tap is open while no client subscribes. The channels follow a reload."""

from __future__ import annotations

import json
import os
import signal
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import aiohttp

from engine.common.processes import listening_port
from engine.ops.foxglove import LOCATION_FIXES_SCHEMA
from tests.support.amqp_helpers import Collector, publish
from tests.support.engine_process import EngineProcess
from tests.support.foxglove_client import connect
from tests.support.waiting import wait_for

ROUTES = """
routes:
  - name: positions
    source: {{amqp: {{exchange: {tag}, binding_key: "pos.#", queue: {tag}-positions}}}}
    mapping: "{{agent_id: agent, type: 'position', lat: lat, lon: lon, alt_msl: alt}}"
    schema: position
    sink: {{amqp: {{exchange: {tag}, routing_key: "out.positions"}}}}
  - name: telemetry
    source: {{amqp: {{exchange: {tag}, binding_key: "tel.#", queue: {tag}-telemetry}}}}
    mapping: "{{agent_id: agent, seq: seq}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {tag}, routing_key: "out.telemetry"}}}}
"""
EXTRA = """
routes:
  - name: extra
    source: {{amqp: {{exchange: {tag}, binding_key: "extra.#", queue: {tag}-extra}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {tag}, routing_key: "out.extra"}}}}
"""
MESSAGES = 300
AGENTS = 6


def test_the_supervisor_serves_the_foxglove_view_of_every_worker(amqp_url: str, tmp_path: Path) -> None:
    tag = "wfox" + uuid.uuid4().hex[:8]
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "fox.yaml").write_text(ROUTES.format(tag=tag))
    admin, view = listening_port(), listening_port()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                           "--workers", "2", "--admin", str(admin), "--foxglove", str(view))

    async def status() -> dict[str, Any]:
        async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{admin}/status") as answer:
            assert answer.status == 200, await answer.text()
            return dict(await answer.json())

    def per_worker(document: dict[str, Any], route: str, counter: str) -> list[int]:
        return [((w.get("status") or {}).get("routes", {}).get(route) or {}).get(counter, 0) for w in document["workers"]]

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        out = await Collector.bind(channel, tag, "out.#")  # the sinks publish mandatory: someone reads
        client = await connect(view)
        try:
            topics = ["/routes/positions/canonical", "/routes/telemetry/canonical", "/fleet", "/routes/status"]
            await wait_for(lambda: all(t in client.channels for t in topics), 30, "every channel advertised",
                           lambda: sorted(client.channels))
            assert client.channels["/routes/positions/canonical"]["schemaName"] == "position.v1"
            assert json.loads(client.channels["/fleet"]["schema"]) == LOCATION_FIXES_SCHEMA
            assert "workers" in client.server_info["name"], client.server_info
            await publish(channel, tag, "tel.x", [json.dumps({"agent": "uav1", "seq": -1}).encode()])
            await wait_for(lambda: status_of("telemetry", "delivered", 1), 30, "a message carried with no client subscribed")
            assert (await status())["routes"]["telemetry"]["taps"] == 0, "a worker's tap open with no subscriber"

            ids = await client.subscribe(topics)
            for route in ("telemetry", "positions"):  # the channels' taps, on both workers
                await wait_for(lambda: status_of(route, "taps", 2), 15, f"the {route} route's tap open on both workers",
                               lambda: seen.get("status", {}).get("routes"))
            bodies = [json.dumps({"agent": f"agent{seq % AGENTS}", "seq": seq}).encode() for seq in range(MESSAGES)]
            await publish(channel, tag, "tel.x", bodies)
            await publish(channel, tag, "pos.x", [json.dumps({"agent": f"agent{n}", "lat": 52.0 + n * 1e-3, "lon": 5.1,
                                                              "alt": 10.0 + n}).encode() for n in range(AGENTS)])

            def carried() -> set[int]:
                return {m["seq"] for m in client.messages(ids["/routes/telemetry/canonical"])}

            await wait_for(lambda: carried() >= set(range(MESSAGES)), 60, "every message on the route's channel",
                           lambda: f"{len(carried())} of {MESSAGES}; {len(out.messages)} at the sinks")
            settled = await wait_for(lambda: settled_status(MESSAGES + 1), 30, "both workers' counts settled")
            await wait_for(lambda: any(m["routes"]["telemetry"]["delivered"] == MESSAGES + 1
                                       for m in client.messages(ids["/routes/status"])), 15, "the summed status on its channel",
                           lambda: client.messages(ids["/routes/status"])[-1:])
            fleet = await wait_for(lambda: [m for m in client.messages(ids["/fleet"]) if len(m["fixes"]) == AGENTS], 15,
                                   "every agent on the fleet channel", lambda: client.messages(ids["/fleet"])[-1:])
            position_channel = await wait_for(lambda: len(m := client.messages(ids["/routes/positions/canonical"])) == AGENTS and m,
                                              15, "every position on the route's channel")

            # a worker killed and started again: its tap is opened again, what it carries then reaches the channel
            victim = settled["workers"][0]["pid"]
            os.kill(victim, signal.SIGKILL)
            await wait_for(lambda: restarted(victim), 120, "worker 0 started again", engine.log)
            await wait_for(lambda: status_of("telemetry", "taps", 2), 30, "the restarted worker's tap open again",
                           lambda: seen["status"]["routes"]["telemetry"])
            again = range(10_000, 10_000 + MESSAGES)
            await publish(channel, tag, "tel.x", [json.dumps({"agent": "uav1", "seq": seq}).encode() for seq in again])
            await wait_for(lambda: carried() >= set(again), 60, "every message after the restart on the channel",
                           lambda: f"{len(carried() & set(again))} of {MESSAGES}")
            by_new = await wait_for(lambda: worker_delivered(0), 15, "the restarted worker's own count")

            # a reload reaches the view as one generation of every worker: a new route advertised, a removed one withdrawn
            extra = tmp_path / "routes" / "extra.yaml"
            extra.write_text(EXTRA.format(tag=tag))
            await wait_for(lambda: "/routes/extra/canonical" in client.channels, 60, "the new route advertised",
                           lambda: sorted(client.channels))
            gone = client.channels["/routes/extra/canonical"]["id"]
            extra.unlink()
            await wait_for(lambda: gone in client.unadvertised, 60, "the removed route withdrawn", lambda: client.unadvertised)
            await client.close()
            await wait_for(lambda: status_of("telemetry", "taps", 0), 15, "the workers' taps closed once the client left")
            return {"settled": settled, "carried": carried(), "fleet": fleet[-1], "positions": position_channel,
                    "by_new": by_new, "again": set(again)}
        finally:
            await client.close()
            await connection.close()

    seen: dict[str, Any] = {}

    async def status_of(route: str, counter: str, value: int) -> bool:
        seen["status"] = await status()
        return bool(seen["status"]["routes"].get(route, {}).get(counter) == value)

    async def restarted(victim: int) -> bool:
        worker = (await status())["workers"][0]
        return bool(worker["up"] and worker["restarts"] == 1 and worker["pid"] != victim)

    async def worker_delivered(index: int) -> int:
        return per_worker(await status(), "telemetry", "delivered")[index]

    async def settled_status(total: int) -> dict[str, Any] | None:
        document = await status()
        return document if sum(per_worker(document, "telemetry", "delivered")) == total else None

    result, _ = engine.run(scenario)
    delivered = per_worker(result["settled"], "telemetry", "delivered")
    assert all(count > 0 for count in delivered), f"one worker carried everything: {delivered}"
    assert result["carried"] == set(range(MESSAGES)) | result["again"]  # not the message carried before the subscription
    assert 0 < result["by_new"] < MESSAGES, result["by_new"]  # the restarted worker carried some of the last batch, not all
    assert sorted(fix["frame_id"] for fix in result["fleet"]["fixes"]) == [f"agent{n}" for n in range(AGENTS)]
    assert {fix["frame_id"]: fix["altitude"] for fix in result["fleet"]["fixes"]}["agent3"] == 13.0
    assert sorted(m["agent_id"] for m in result["positions"]) == [f"agent{n}" for n in range(AGENTS)]
