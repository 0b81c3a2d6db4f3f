"""Commands that fail fast and say the truth (issue 31).

Real parts: the engine in process (its admin endpoint for ``/metrics``), a private RabbitMQ node
with an AMQP caller on direct reply-to, and a vehicle on plain pymavlink behind a UDP socket
(tests/support/udp_vehicle.py ``FleetVehicle``) that keeps sending HEARTBEAT and telemetry, so
it is *up* for the engine's liveness, and answers commands as told.

- A vehicle whose uplink is lost (it is heard, it never acknowledges): on main the arm was
  answered after 16.7 s, about 30 COMMAND_LONGs on the air (each send's retries, then the
  route's delivery attempts sending it all again), so a vehicle coming back late could act on
  a stale arm. Now the caller's ``error`` reply comes within ``command_timeout`` (+ 1 s for a
  loaded machine), names the vehicle and when it was last heard, and nothing is sent after it.
- A refusal (DENIED) is an answer: main dead-lettered it and replied ``error``, skipping
  ``reply.mapping``. Now the caller gets a ``result`` through ``reply.mapping`` with the result,
  the route counts it ``refused`` (status and ``/metrics``), and there is no dead letter;
  ``refusals: dead_letter`` keeps main's behaviour.
- A ``udpin`` link whose peers all expired said "has not heard from any peer yet", though it
  had; now it says they expired, and when the last was heard.
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import aiohttp
import pytest
from prometheus_client.parser import text_string_to_metric_families
from pymavlink.dialects.v20 import common as mavlink2

from engine.endpoints.mavlink.links import PEER_TTL
from engine.ops.admin import AdminServer
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Caller, Collector, header_text
from tests.support.udp_vehicle import FleetVehicle, free_udp_port, mavlink_connection
from tests.support.waiting import wait_for

ROUTES = """\
connections:
  bus: {{amqp: "{amqp}"}}
  uav: {{mavlink: "udpin:127.0.0.1:{port}"}}
agents:
  uav1: {{connection: uav, system_id: 1}}
routes:
{routes}
"""
ARM = """\
  - name: {name}
    source: {{amqp: {{connection: bus, queue: {name}}}}}
    schema: command
    sink:
      mavlink: {{connection: uav, message: COMMAND_LONG, target_system: "{{agent_id}}", target_component: 1,
                 acknowledged: true{options}}}
      mapping: "{{command: mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM', 'MAV_CMD'), param1: `1`}}"
    reply: {{mapping: "{{armed: result == 'MAV_RESULT_ACCEPTED', result: result}}"}}
"""


def command() -> bytes:
    return json.dumps({"type": "command", "agent_id": "uav1", "id": uuid.uuid4().hex,
                       "stamp": {"sec": int(time.time()), "nanosec": 0}, "command": "arm"}).encode()


def write_routes(tmp_path: Path, amqp_url: str, port: int, routes: str) -> Path:
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "uav.yaml").write_text(ROUTES.format(amqp=amqp_url, port=port, routes=routes))
    return directory


def reply_of(caller: Caller, correlation_id: str) -> tuple[str, Any]:
    message = caller.replies[correlation_id][0]
    return header_text(message, "x-rabbitros-reply"), json.loads(message.body)


@pytest.mark.parametrize("bound", [None, 1.5], ids=["default-3s", "command_timeout-1.5"])
def test_a_command_to_a_vehicle_that_never_acknowledges_fails_within_its_bound_naming_it(
        bound: float | None, tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """The default bound on a network link is (retries + 1) x timeout = 3 s."""
    limit = 3.0 if bound is None else bound
    port = free_udp_port()
    name = f"arm-{uuid.uuid4().hex[:8]}"
    options = "" if bound is None else f", command_timeout: {bound}"
    routes = write_routes(tmp_path, amqp_url, port, ARM.format(name=name, options=options))
    found: dict[str, Any] = {}

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        vehicle = FleetVehicle(1, port, rate=5, answer=None)
        vehicle.start()
        client = await aio_pika.connect(amqp_url)
        try:
            caller = await Caller.open(await client.channel())
            link = mavlink_connection(engine, "uav")
            await wait_for(lambda: link.has_heard(1, 1), 10, "the vehicle's HEARTBEAT")
            dead = await Collector.bind(await client.channel(), "rabbitros.dead-letter", name)
            asked = time.monotonic()
            call = await caller.call("", name, command())
            await caller.wait(lambda r: call in r, 40, "the arm's reply")
            found["answered_after"] = time.monotonic() - asked
            found["reply"] = reply_of(caller, call)
            answered = time.monotonic()
            beats = vehicle.heartbeats
            # two more of the engine's 1 Hz HEARTBEATs at the vehicle: anything sent after the
            # reply would have arrived before them
            await wait_for(lambda: vehicle.heartbeats >= beats + 2, 10, "two more engine HEARTBEATs at the vehicle")
            found["sent_after_reply"] = sum(at > answered for at in vehicle.arrivals)
            found["commands"] = len(vehicle.arrivals)
            found["letters"] = await dead.wait_for(1, 10)
            found["route"] = engine.status()["routes"][name]
        finally:
            vehicle.stop.set()
            await client.close()
            await engine.stop(drain_timeout=1.0)
            vehicle.join(5)

    asyncio.run(asyncio.wait_for(scenario(), 90))
    print({key: found[key] for key in ("answered_after", "commands", "reply")})

    assert found["answered_after"] <= limit + 1.0, found["answered_after"]
    kind, body = found["reply"]
    assert kind == "error", found["reply"]
    error = body["error"]
    assert error.startswith("mavlink connection 'uav': vehicle 1/1 (uav1), last heard "), error
    assert "MAV_CMD_COMPONENT_ARM_DISARM not acknowledged after " in error and \
        f"within command_timeout {limit:g} s; not sent again" in error, error
    assert found["commands"] <= 6, "at most retries + 1 sends"
    assert found["sent_after_reply"] == 0
    assert found["route"]["retries"] == 0 and found["route"]["dead_lettered"] == {"sink": 1}, found["route"]
    assert "not acknowledged after" in found["letters"][0].headers["x-rabbitros-error"]


@pytest.mark.parametrize("refusals", ["reply", "dead_letter"])
def test_a_denied_command_is_a_reply_with_its_result_counted_refused_unless_dead_letter(
        refusals: str, tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """A vehicle that answers every command DENIED; the route's ``refusals`` by default (reply),
    and ``refusals: dead_letter`` (main's behaviour: an ``error`` reply and a dead letter)."""
    port = free_udp_port()
    name = f"arm-{uuid.uuid4().hex[:8]}"
    options = "" if refusals == "reply" else ", refusals: dead_letter"
    routes = write_routes(tmp_path, amqp_url, port, ARM.format(name=name, options=options))
    found: dict[str, Any] = {}

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        admin = AdminServer(engine, "127.0.0.1", 0)
        await engine.start()
        await admin.start()
        vehicle = FleetVehicle(1, port, rate=5, answer=mavlink2.MAV_RESULT_DENIED)
        vehicle.start()
        client = await aio_pika.connect(amqp_url)
        try:
            caller = await Caller.open(await client.channel())
            link = mavlink_connection(engine, "uav")
            await wait_for(lambda: link.has_heard(1, 1), 10, "the vehicle's HEARTBEAT")
            dead = await Collector.bind(await client.channel(), "rabbitros.dead-letter", name)
            call = await caller.call("", name, command())
            await caller.wait(lambda r: call in r, 20, "the arm's reply")
            found["reply"] = reply_of(caller, call)
            route = lambda: engine.status()["routes"][name]  # noqa: E731
            await wait_for(lambda: route().get("refused", 0) + route()["failed"] == 1, 10, "the arm settled", route)
            if refusals == "dead_letter":
                await dead.wait_for(1, 10)
            found["route"] = route()
            async with aiohttp.ClientSession() as session:
                async with session.get(f"http://127.0.0.1:{admin.port}/metrics") as response:
                    text = await response.text()
            found["metrics"] = {sample.labels["outcome"]: sample.value
                                for family in text_string_to_metric_families(text) for sample in family.samples
                                if sample.name == "rabbitros_messages_total" and sample.labels["route"] == name}
            found["letters"] = [m.headers["x-rabbitros-error"] for m in dead.messages]
            found["commands"] = len(vehicle.arrivals)
        finally:
            vehicle.stop.set()
            await client.close()
            await admin.stop()
            await engine.stop(drain_timeout=1.0)
            vehicle.join(5)

    asyncio.run(asyncio.wait_for(scenario(), 90))
    print(found["reply"])

    route = found["route"]
    assert found["commands"] == 1, "a refusal is final: sent once"
    if refusals == "reply":
        assert found["reply"] == ("result", {"armed": False, "result": "MAV_RESULT_DENIED"})
        assert (route["refused"], route["delivered"], route["failed"], route["retries"]) == (1, 0, 0, 0), route
        assert found["metrics"]["refused"] == 1 and found["metrics"]["dead_lettered"] == 0, found["metrics"]
        assert found["letters"] == [], "a refusal is no dead letter"
    else:
        kind, body = found["reply"]
        assert kind == "error" and "refused MAV_CMD_COMPONENT_ARM_DISARM: MAV_RESULT_DENIED" in body["error"], body
        assert len(found["letters"]) == 1 and "MAV_RESULT_DENIED" in found["letters"][0], found["letters"]
        assert (route["refused"], route["failed"]) == (0, 1), route
        assert found["metrics"]["refused"] == 0 and found["metrics"]["dead_lettered"] == 1, found["metrics"]


PLAIN = """\
  - name: {name}
    source: {{amqp: {{connection: bus, queue: {name}}}}}
    schema: command
    sink:
      mavlink: {{connection: uav, message: COMMAND_LONG, target_system: 1, target_component: 1}}
      mapping: "{{command: mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM', 'MAV_CMD'), param1: `1`}}"
"""


def test_a_udpin_link_whose_peers_expired_says_so(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """The vehicle is heard, then stops; once its peer entry expired (PEER_TTL, 30 s) a message
    for it is dead-lettered saying the peers expired and when the last one was heard."""
    port = free_udp_port()
    name = f"plain-{uuid.uuid4().hex[:8]}"
    routes = write_routes(tmp_path, amqp_url, port, PLAIN.format(name=name))
    found: dict[str, Any] = {}

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        vehicle = FleetVehicle(1, port, rate=5)
        vehicle.start()
        client = await aio_pika.connect(amqp_url)
        try:
            link = mavlink_connection(engine, "uav")
            await wait_for(lambda: link.has_heard(1, 1), 10, "the vehicle's HEARTBEAT")
            vehicle.stop.set()
            vehicle.join(5)
            silent_from = time.monotonic()
            await wait_for(lambda: not link.port.ready, PEER_TTL + 10, "the peer to expire")
            channel = await client.channel()
            dead = await Collector.bind(channel, "rabbitros.dead-letter", name)
            await channel.default_exchange.publish(aio_pika.Message(command()), name)
            found["letters"] = await dead.wait_for(1, 30)
            found["silent_for"] = time.monotonic() - silent_from
        finally:
            vehicle.stop.set()
            await client.close()
            await engine.stop(drain_timeout=1.0)

    asyncio.run(asyncio.wait_for(scenario(), 120))
    error = found["letters"][0].headers["x-rabbitros-error"]
    print(error)
    assert f"no peer heard in the last {PEER_TTL:g} s (a peer expires {PEER_TTL:g} s after its last datagram); " \
           "the last, 127.0.0.1:" in error, error
    assert "has not heard from any peer yet" not in error
    heard_ago = float(error.split(", was heard ")[1].split(" s ago")[0])
    assert PEER_TTL <= heard_ago <= found["silent_for"] + 1, (heard_ago, found["silent_for"])
