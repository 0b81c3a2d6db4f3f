"""A vehicle's liveness, as MAVROS shows it (issue 31): a vehicle that stops its HEARTBEAT is
named by ``/healthz`` (503) within ``heartbeat_timeout`` + 1 s, the status and ``/metrics``
show it down, and a command to it fails at once with a reason naming it and when it was last
heard; once it is heard again, all is well again.

Real parts: the engine in process with its admin endpoint, a private RabbitMQ node, a vehicle on
plain pymavlink behind a UDP socket (tests/support/udp_vehicle.py ``FleetVehicle``: HEARTBEAT and
GLOBAL_POSITION_INT at 5 Hz, COMMAND_LONG acknowledged). On main ``/healthz`` stayed 200 with
the vehicle silent, and the command was sent again and again into the silence.
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from pathlib import Path
from typing import Any

import aiohttp
import aio_pika
import pytest
from prometheus_client.parser import text_string_to_metric_families

from engine.ops.admin import AdminServer, status_document
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Caller
from tests.support.udp_vehicle import FleetVehicle, free_udp_port, mavlink_connection
from tests.support.waiting import wait_for

DEFAULT_TIMEOUT = 3.0
ROUTES = """\
connections:
  bus: {{amqp: "{amqp}"}}
  uav: {{mavlink: "udpin:127.0.0.1:{port}"{timeout}}}
agents:
  uav1: {{connection: uav, system_id: 1}}
routes:
  - name: arm-{tag}
    source: {{amqp: {{connection: bus, queue: arm-{tag}}}}}
    schema: command
    sink:
      mavlink: {{connection: uav, message: COMMAND_LONG, target_system: "{{agent_id}}", target_component: 1,
                 acknowledged: true}}
      mapping: "{{command: mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM', 'MAV_CMD'), param1: `1`}}"
"""


def command() -> bytes:
    return json.dumps({"type": "command", "agent_id": "uav1", "id": uuid.uuid4().hex,
                       "stamp": {"sec": int(time.time()), "nanosec": 0}, "command": "arm"}).encode()


async def get(session: aiohttp.ClientSession, admin: AdminServer, path: str) -> tuple[int, str]:
    async with session.get(f"http://127.0.0.1:{admin.port}{path}") as response:
        return response.status, await response.text()


def vehicle_samples(text: str) -> dict[str, tuple[dict[str, str], float]]:
    return {sample.name: (sample.labels, sample.value) for family in text_string_to_metric_families(text)
            for sample in family.samples if sample.name.startswith("rabbitros_vehicle_")}


@pytest.mark.parametrize("timeout", [None, 1.5], ids=["default", "heartbeat_timeout-1.5"])
def test_a_silent_vehicle_is_named_by_healthz_and_a_command_to_it_fails_at_once(
        timeout: float | None, tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """With the default (3 s) and with ``heartbeat_timeout`` given."""
    limit = DEFAULT_TIMEOUT if timeout is None else timeout
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    given = "" if timeout is None else f", heartbeat_timeout: {timeout}"
    (routes / "uav.yaml").write_text(ROUTES.format(amqp=amqp_url, port=port, timeout=given, tag=tag))
    found: dict[str, Any] = {}

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        admin = AdminServer(engine, "127.0.0.1", 0)
        await engine.start()
        await admin.start()
        vehicle = FleetVehicle(1, port, rate=5)
        vehicle.start()
        client = await aio_pika.connect(amqp_url)
        try:
            session = aiohttp.ClientSession()
            caller = await Caller.open(await client.channel())
            probe: dict[str, Any] = {}

            async def probing() -> None:
                """/healthz every 20 ms, as a load balancer would ask it (the waits read the last)."""
                while True:
                    status, body = await get(session, admin, "/healthz")
                    probe.update(status=status, document=json.loads(body))
                    await asyncio.sleep(0.02)  # pacing: a load balancer's probe every 20 ms

            prober = asyncio.create_task(probing())

            def healthy() -> bool:
                return probe.get("status") == 200 and bool(probe["document"]["connections"]["uav"].get("vehicles"))

            await wait_for(healthy, 10, "/healthz 200 with the vehicle heard", lambda: probe)
            up = await caller.call("", f"arm-{tag}", command())
            await caller.wait(lambda r: up in r, 20, "the arm's reply while the vehicle is up")
            found["up_reply"] = json.loads(caller.replies[up][0].body)
            found["up_metrics"] = vehicle_samples((await get(session, admin, "/metrics"))[1])

            vehicle.stop.set()
            silent_from = time.monotonic()
            vehicle.join(5)
            link = mavlink_connection(engine, "uav")
            resends_before = link.stats.get("command_resends", 0)

            found["healthz"] = await wait_for(lambda: probe["status"] == 503 and probe["document"], limit + 3,
                                              "/healthz 503", lambda: probe)
            found["named_after"] = time.monotonic() - silent_from
            found["down_metrics"] = vehicle_samples((await get(session, admin, "/metrics"))[1])
            found["status"] = status_document(engine)["connections"]["uav"]

            asked = time.monotonic()
            down = await caller.call("", f"arm-{tag}", command())
            await caller.wait(lambda r: down in r, 10, "the arm's reply while the vehicle is down")
            found["down_answered_after"] = time.monotonic() - asked
            found["down_reply"] = (caller.replies[down][0].headers["x-rabbitros-reply"],
                                   json.loads(caller.replies[down][0].body))
            found["resent_into_silence"] = link.stats.get("command_resends", 0) - resends_before

            back = FleetVehicle(1, port, rate=5)
            back.start()
            try:
                await wait_for(healthy, 10, "/healthz 200 once the vehicle is heard again", lambda: probe)
            finally:
                back.stop.set()
                back.join(5)
            prober.cancel()
            await asyncio.gather(prober, return_exceptions=True)
            await session.close()
        finally:
            vehicle.stop.set()
            await client.close()
            await admin.stop()
            await engine.stop(drain_timeout=1.0)

    asyncio.run(asyncio.wait_for(scenario(), 90))
    print({key: found[key] for key in ("named_after", "down_answered_after", "healthz", "down_reply")})

    assert found["up_reply"]["result"] == "MAV_RESULT_ACCEPTED", found["up_reply"]
    labels, value = found["up_metrics"]["rabbitros_vehicle_up"]
    assert labels == {"connection": "uav", "agent": "uav1", "system_id": "1"} and value == 1
    labels, _ = found["up_metrics"]["rabbitros_vehicle_frames_lost_total"]
    assert labels == {"connection": "uav", "agent": "uav1", "system_id": "1"}

    assert found["named_after"] <= limit + 1, found["named_after"]
    health = found["healthz"]
    assert health["status"] == "degraded" and health["down"] == [], health
    [reason] = health["unavailable"]["uav"]
    assert reason.startswith("vehicle 1 (uav1): not heard for ") and f"(heartbeat_timeout {limit:g} s)" in reason, reason

    labels, value = found["down_metrics"]["rabbitros_vehicle_up"]
    assert labels["agent"] == "uav1" and value == 0
    _, silent_for = found["down_metrics"]["rabbitros_vehicle_heard_seconds_ago"]
    assert silent_for > limit
    assert [(v["system_id"], v["agent"], v["up"]) for v in found["status"]["liveness"]] == [(1, "uav1", False)]

    kind, error = found["down_reply"]
    assert kind == "error", found["down_reply"]
    assert "vehicle 1/1 (uav1) is down: last heard" in json.dumps(error), error
    assert found["down_answered_after"] < 1.0, found["down_answered_after"]
    assert found["resent_into_silence"] == 0
