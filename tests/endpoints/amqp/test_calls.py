"""Request/reply over RabbitMQ (issue 19): a request with ``reply_to`` gets the sink's answer back.

Against the real broker (direct reply-to, ``amq.rabbitmq.reply-to``, consumed no_ack by a plain
aio-pika client) and real vehicles: MAVSDK's ActionServer acknowledges an arm COMMAND_LONG, the
simulated vehicle denies one and accepts a mission. Every reply carries the request's
correlation id and says its kind in ``x-rabbitros-reply``; a request that fails (conversion, a
refusal) gets exactly one ``error`` reply; a request without ``reply_to`` gets none.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika

from engine.running.runtime import Engine
from rabbitros_sim.sik_radio import SikRadioPair
from rabbitros_sim.vehicle import SimVehicle
from tests.support.amqp_helpers import Caller, header_text
from tests.support.mavsdk_vehicle import MavsdkAutopilot
from tests.endpoints.mavlink.test_mavlink_transactions import WEEDS, canonical_mission, canonical_stamp, free_udp_port, run
from tests.support.waiting import wait_for


def _routes(directory: Path, amqp_url: str, link: str, tag: str, extra: str = "") -> Path:
    directory.mkdir(exist_ok=True)
    (directory / "routes.yaml").write_text(f"""\
connections:
  bus: {{amqp: "{amqp_url}"}}
  uav: {{mavlink: "{link}"}}
routes:
  - name: arm-{tag}
    source: {{amqp: {{connection: bus, queue: arm-{tag}}}}}
    schema: command
    sink:
      mavlink: {{connection: uav, message: COMMAND_LONG, target_system: 1, target_component: 1, acknowledged: true, retries: 2}}
      mapping: "{{command: mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM', 'MAV_CMD'), param1: `1`}}"
{extra}""")
    return directory


def _impatient_arm_routes(tmp_path: Path, amqp_url: str, port: int, tag: str, route_keys: str) -> Path:
    """:func:`_routes` on ``udpin`` ``port`` whose arm route asks once (``retries: 0``, a 0.3 s
    ``vehicle_timeout``) and has ``route_keys`` (indented YAML lines) besides. Its
    ``command_timeout`` is 60 s: these tests are about what the route does with a call it holds
    or retries (max_age, the buffer), not about the command's own bound (test_command_bounds.py)."""
    routes = _routes(tmp_path / "routes", amqp_url, f"udpin:127.0.0.1:{port}", tag)
    text = (routes / "routes.yaml").read_text().replace(
        "acknowledged: true, retries: 2}", "acknowledged: true, retries: 0, vehicle_timeout: 0.3, command_timeout: 60}").replace(
        f"  - name: arm-{tag}\n", f"  - name: arm-{tag}\n{route_keys}")
    (routes / "routes.yaml").write_text(text)
    return routes


def _command(**extra: Any) -> bytes:
    return json.dumps({"type": "command", "agent_id": "uav1", "id": uuid.uuid4().hex, "stamp": canonical_stamp(),
                       "command": "arm", **extra}).encode()


def _reply(message: aio_pika.abc.AbstractIncomingMessage) -> tuple[str, Any]:
    return header_text(message, "x-rabbitros-reply"), json.loads(message.body)


async def arm_and_mission(amqp_url: str, tag: str, timeout: float) -> tuple[Caller, str, str]:
    """Call ``arm-TAG`` (an arm command) and ``mission-TAG`` (the weeds mission) at once and wait
    for both replies; the caller with its replies, and the two calls' correlation ids."""
    connection = await aio_pika.connect(amqp_url)
    try:
        channel = await connection.channel()
        caller = await Caller.open(channel)
        arm = await caller.call("", f"arm-{tag}", _command())
        mission = await caller.call("", f"mission-{tag}", json.dumps(canonical_mission(WEEDS)).encode())
        await caller.wait(lambda r: arm in r and mission in r, timeout, "the arm's and the mission's replies")
        for queue in (f"arm-{tag}", f"mission-{tag}"):
            await channel.queue_delete(queue)
        return caller, arm, mission
    finally:
        await connection.close()


def test_arm_command_as_a_call_gets_mav_result_accepted_from_mavsdk(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """An arm COMMAND_LONG published with direct reply-to is answered by MAVSDK's ActionServer:
    one ``result`` reply ``{kind, result: MAV_RESULT_ACCEPTED, command: 400}`` with the
    request's correlation id and route header. A request that fails the schema gets one
    ``error`` reply naming the stage and the route; one without ``reply_to`` is only counted."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = _routes(tmp_path / "routes", amqp_url, f"udpout:127.0.0.1:{port}", tag)
    autopilot = MavsdkAutopilot(port)

    async def scenario() -> tuple[Caller, dict[str, Any], list[str]]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            arm = await caller.call("", f"arm-{tag}", _command())
            bad = await caller.call("", f"arm-{tag}", b'{"type": "command"}')
            await caller.wait(lambda r: arm in r and bad in r, 30, "the arm and the bad request's replies")
            await caller.call("", f"arm-{tag}", _command(), reply_to=None)
            route = f"arm-{tag}"
            await wait_for(lambda: engine.status()["routes"][route]["replies"]["unrequested"] == 1, 20, "the fire-and-forget arm")
            status = engine.status()["routes"][route]
            await channel.queue_delete(route)
        finally:
            await engine.stop()
            await connection.close()
        return caller, status, [arm, bad]

    try:
        caller, status, (arm, bad) = run(scenario(), 60)
    finally:
        autopilot.close()
    assert [_reply(m) for m in caller.replies[arm]] == [
        ("result", {"kind": "result", "result": "MAV_RESULT_ACCEPTED", "command": 400})]
    assert caller.replies[arm][0].headers["x-rabbitros-route"] == f"arm-{tag}"
    assert caller.replies[arm][0].correlation_id == arm
    [(kind, error)] = [_reply(m) for m in caller.replies[bad]]
    assert kind == "error" and error["kind"] == "error" and error["stage"] == "schema" and error["route"] == f"arm-{tag}", error
    assert [arm.arm for arm in autopilot.arm_requests] == [True, True]
    assert status["replies"] == {"sent": 2, "errors": 1, "unrequested": 1, "late": 0, "undelivered": 0}, status
    assert (status["delivered"], status["failed"]) == (2, 1), status


def test_denied_command_is_one_result_reply_and_a_mission_call_is_answered_through_the_reply_mapping(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """The simulated vehicle answers MAV_RESULT_DENIED: the caller gets one ``result`` reply with
    that result (a refusal is an answer, not a dead letter: issue 31); the mission upload's answer
    goes through the route's ``reply: {mapping}`` (a reply mapping failure would be an error reply too)."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = _routes(tmp_path / "routes", amqp_url, f"udpin:127.0.0.1:{port}", tag, f"""\
  - name: mission-{tag}
    source: {{amqp: {{connection: bus, queue: mission-{tag}}}}}
    schema: mission
    sink: {{mavlink: {{connection: uav, mission: upload}}}}
    reply: {{mapping: "{{accepted: result == 'MAV_MISSION_ACCEPTED', waypoints: items}}"}}
""")

    async def scenario() -> tuple[Caller, str, str]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        sim = SimVehicle(f"udpout:127.0.0.1:{port}", command_results=["MAV_RESULT_DENIED"])
        stop = asyncio.Event()
        running = asyncio.create_task(sim.run(stop))
        try:
            return await arm_and_mission(amqp_url, tag, 30)
        finally:
            await engine.stop()
            stop.set()
            await running

    caller, arm, mission = run(scenario(), 60)
    assert [_reply(m) for m in caller.replies[arm]] == [
        ("result", {"kind": "result", "result": "MAV_RESULT_DENIED", "command": 400})]
    assert [_reply(m) for m in caller.replies[mission]] == [("result", {"accepted": True, "waypoints": len(WEEDS)})]


def test_arm_and_mission_calls_through_the_emulated_radio_are_answered_by_mavsdk(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """MAVSDK's vehicle behind the emulated SiK radio (57,600 baud, 5 % air-packet loss): MAVSDK
    opens the radio's vehicle-side pseudo-terminal as a serial port, the engine the ground side.
    The arm call gets MAVSDK's MAV_RESULT_ACCEPTED back through the radio, and the mission call
    MAV_MISSION_ACCEPTED with MAVSDK holding the waypoints in order (a transfer the loss made
    the engine start again is MAVSDK's failed transfer, not a second mission)."""
    tag = uuid.uuid4().hex[:8]

    async def scenario() -> tuple[Caller, str, str, MavsdkAutopilot]:
        async with SikRadioPair(loss=0.05, seed=21) as pair:
            autopilot = MavsdkAutopilot(f"serial://{pair.device_b}:57600")
            try:
                routes = _routes(tmp_path / "routes", amqp_url, pair.link_a, tag, f"""\
  - name: mission-{tag}
    source: {{amqp: {{connection: bus, queue: mission-{tag}}}}}
    schema: mission
    sink: {{mavlink: {{connection: uav, mission: upload, retries: 10}}}}
    reply: {{mapping: "{{accepted: result == 'MAV_MISSION_ACCEPTED', waypoints: items}}"}}
""")
                engine = Engine(routes, schemas_dir)
                await engine.start()
                try:
                    caller, arm, mission = await arm_and_mission(amqp_url, tag, 60)
                finally:
                    await engine.stop()
            finally:
                autopilot.close()
        return caller, arm, mission, autopilot

    caller, arm, mission, autopilot = run(scenario(), 120)
    assert [_reply(m) for m in caller.replies[arm]] == [
        ("result", {"kind": "result", "result": "MAV_RESULT_ACCEPTED", "command": 400})]
    # a lost COMMAND_ACK makes the engine send the command again, and MAVSDK acts on each copy
    assert autopilot.arm_requests and all(arm.arm for arm in autopilot.arm_requests), autopilot.arm_requests
    assert [_reply(m) for m in caller.replies[mission]] == [("result", {"accepted": True, "waypoints": len(WEEDS)})]
    expected = [(seq, round(lat * 1e7), round(lon * 1e7)) for seq, (lat, lon) in enumerate(WEEDS)]
    assert autopilot.missions, autopilot.failed_transfers
    assert all([(item.seq, item.x, item.y) for item in items] == expected for items in autopilot.missions), autopilot.missions


def test_reply_is_checked_at_load(tmp_path: Path, schemas_dir: Path) -> None:
    """``reply:`` needs a source that can answer; its mapping compiles and its schema exists."""
    from engine.common.schemas import SchemaRegistry
    from engine.language.routes import RoutesInvalid, load_routes
    import pytest

    (tmp_path / "a.yaml").write_text("""\
routes:
  - name: from-ros
    source: {ros2: {topic: /cmd, type: std_msgs/msg/String}}
    schema: raw_json
    sink: {amqp: {routing_key: out}}
    reply: {mapping: "ok"}
  - name: from-amqp
    source: {amqp: {queue: calls}}
    schema: raw_json
    sink: {mavlink: {message: COMMAND_LONG, acknowledged: true}}
    reply: {mapping: "{ok: ", schema: comand}
""")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert ("a.yaml:6: route 'from-ros': reply: this ros2 source cannot answer its sender (protocols whose sources can: "
            "amqp, ros2, zenoh; see Calls in route-language.md)") in problems
    assert any(p.startswith("a.yaml:11: route 'from-amqp': reply: bad JMESPath '{ok: '") for p in problems), problems
    assert "a.yaml:11: route 'from-amqp': reply: unknown schema 'comand'; did you mean 'command'?" in problems, problems


def test_route_test_cases_give_a_response_and_expect_the_reply(tmp_path: Path, schemas_dir: Path) -> None:
    """``rabbitros-engine test``: a case's ``response`` (the service's answer) goes through the
    route's ``reply:`` and is compared with ``expect_reply``; a reply the mapping refuses is an
    ``expect_error: reply mapping``; the request is built as the service's Request (a key the
    type lacks is a ``sink`` error)."""
    from engine.common.schemas import SchemaRegistry
    from engine.ops.route_tests import format_result, load_checked, run_tests

    (tmp_path / "calls.yaml").write_text("""\
routes:
  - name: spray
    source: {amqp: {queue: spray}}
    schema: raw_json
    sink:
      ros2: {service: /robot1/set_spray, type: test_msgs/srv/BasicTypes, timeout: 5}
      mapping: "{bool_value: spray}"
    reply: {mapping: "{ok: bool_value, why: string_value, size: length(string_value)}"}
""")
    (tmp_path / "calls.test.yaml").write_text("""\
tests:
  - route: spray
    input: {spray: true}
    expect_sink: {bool_value: true}
    response: {bool_value: true, string_value: spraying}
    expect_reply: {ok: true, why: spraying, size: 8}
  - route: spray
    name: a reply the mapping cannot shape
    input: {spray: true}
    response: {bool_value: true, string_value: 3}
    expect_error: reply mapping
  - route: spray
    name: wrong reply
    input: {spray: false}
    response: {bool_value: false, string_value: ""}
    expect_reply: {ok: true}
""")
    schemas = SchemaRegistry(schemas_dir)
    config, cases, problems, _ = load_checked(tmp_path, schemas)
    assert config is not None and problems == [], problems
    results = list(run_tests(cases, config, schemas))
    assert [r.passed for r in results] == [True, True, False], [format_result(r) for r in results]
    assert results[2].reason == "reply differs", results[2].reason


def test_a_call_that_expires_under_max_age_gets_an_error_reply(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """A command to a vehicle that never answers is retried (transient) until it is older than
    the route's ``max_age``: it expires (no dead letter), and its caller gets one ``error`` reply
    with stage ``max_age`` instead of waiting forever."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = _impatient_arm_routes(tmp_path, amqp_url, port, tag, "    max_age: 1\n    max_attempts: 50\n")

    async def scenario() -> tuple[Caller, str, dict[str, Any], float]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            started = asyncio.get_running_loop().time()
            arm = await caller.call("", f"arm-{tag}", _command())
            await caller.wait(lambda r: arm in r, 20, "the expired call's error reply")
            elapsed = asyncio.get_running_loop().time() - started
            status = engine.status()["routes"][f"arm-{tag}"]
            await channel.queue_delete(f"arm-{tag}")
        finally:
            await engine.stop()
            await connection.close()
        return caller, arm, status, elapsed

    caller, arm, status, elapsed = run(scenario(), 60)
    [(kind, error)] = [_reply(m) for m in caller.replies[arm]]
    assert kind == "error" and error["stage"] == "max_age" and error["route"] == f"arm-{tag}", error
    assert 1.0 <= elapsed < 5.0, elapsed
    assert status["failed"] == 0 and status["replies"]["errors"] == 1, status


def test_a_spilled_call_gets_its_reply_and_one_conflated_by_latest_only_an_error(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """A route with a spilling buffer and ``latest_only`` per agent: two arm calls for the same
    vehicle while it is silent are held on disk. The older is conflated by the newer and its
    caller gets one ``error`` reply naming the stage ``latest_only``; the newer, read back from
    the spill file once the vehicle is there, still reaches its caller: ``MAV_RESULT_ACCEPTED``
    (a held message read from disk had lost its way back)."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = _impatient_arm_routes(tmp_path, amqp_url, port, tag,
                                   "    max_attempts: 1000\n    buffer: {spill_dir: spill, latest_only: {per: agent_id}}\n")

    async def scenario() -> tuple[Caller, str, str, dict[str, Any], list[Path]]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        stop = asyncio.Event()
        running = None
        route = f"arm-{tag}"
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            older = await caller.call("", route, _command())
            newer = await caller.call("", route, _command())
            await caller.wait(lambda r: older in r, 20, "the conflated call's error reply")
            spilled = sorted((routes / "spill").rglob("*.jsonl"))
            sim = SimVehicle(f"udpout:127.0.0.1:{port}")
            running = asyncio.create_task(sim.run(stop))
            await caller.wait(lambda r: newer in r, 20, "the spilled call's reply")
            # the reply is published while the held message is being sent; the buffer counts it
            # delivered once the send returned, a moment after the caller may have its reply
            await wait_for(lambda: engine.status()["routes"][route]["buffer"]["delivered"] == 1, 10, "delivered counted")
            status = engine.status()["routes"][route]
            await channel.queue_delete(route)
        finally:
            await engine.stop()
            stop.set()
            if running is not None:
                await running
            await connection.close()
        return caller, older, newer, status, spilled

    caller, older, newer, status, spilled = run(scenario(), 60)
    assert spilled, "nothing was spilled"
    [(kind, error)] = [_reply(m) for m in caller.replies[older]]
    assert kind == "error" and error["stage"] == "latest_only" and error["route"] == f"arm-{tag}", error
    assert [_reply(m) for m in caller.replies[newer]] == [
        ("result", {"kind": "result", "result": "MAV_RESULT_ACCEPTED", "command": 400})]
    assert status["buffer"]["conflated"] == 1 and status["buffer"]["delivered"] == 1, status["buffer"]
    assert status["replies"] == {"sent": 2, "errors": 1, "unrequested": 0, "late": 0, "undelivered": 0}, status


def test_a_call_conflated_by_the_throttle_gets_an_error_reply(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """``throttle`` at 0.5 per second: the first call goes at once (to an AMQP queue: no answer),
    the second is parked in the slot and conflated by the third; the second's caller gets one
    ``error`` reply naming the stage ``throttle``."""
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "routes.yaml").write_text(f"""\
connections:
  bus: {{amqp: "{amqp_url}"}}
routes:
  - name: slow-{tag}
    source: {{amqp: {{connection: bus, queue: slow-{tag}}}}}
    schema: raw_json
    throttle: {{max_rate: 0.5}}
    sink: {{amqp: {{connection: bus, routing_key: out-{tag}}}}}
""")

    async def scenario() -> tuple[Caller, list[str]]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            await channel.declare_queue(f"out-{tag}", exclusive=True)
            caller = await Caller.open(channel)
            calls = [await caller.call("", f"slow-{tag}", json.dumps({"n": n}).encode()) for n in range(3)]
            await caller.wait(lambda r: calls[1] in r, 10, "the conflated call's error reply")
            await channel.queue_delete(f"slow-{tag}")
        finally:
            await engine.stop()
            await connection.close()
        return caller, calls

    caller, calls = run(scenario(), 60)
    [(kind, error)] = [_reply(m) for m in caller.replies[calls[1]]]
    assert kind == "error" and error["stage"] == "throttle" and error["route"] == f"slow-{tag}", error
    assert calls[0] not in caller.replies


def test_a_call_held_in_memory_when_the_engine_stops_gets_an_error_reply(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """A route whose buffer holds in memory only (no spill_dir): an arm call for a silent
    vehicle is held; when the engine stops it cannot be delivered any more, and its caller gets
    one ``error`` reply naming the stage ``buffer`` instead of waiting forever."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = _impatient_arm_routes(tmp_path, amqp_url, port, tag, "    max_attempts: 1000\n    buffer: {max_messages: 10}\n")

    async def scenario() -> tuple[Caller, str, dict[str, Any]]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        route = f"arm-{tag}"
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            held = await caller.call("", route, _command())
            await wait_for(lambda: (engine.status()["routes"][route]["buffer"] or {}).get("held") == 1, 20, "the call held")
            await channel.queue_delete(route)
            await engine.stop(drain_timeout=0.5)
            status = engine.status()["routes"][route]
            await caller.wait(lambda r: held in r, 10, "the lost call's error reply")
        finally:
            await engine.stop()
            await connection.close()
        return caller, held, status

    caller, held, status = run(scenario(), 60)
    [(kind, error)] = [_reply(m) for m in caller.replies[held]]
    assert kind == "error" and error["stage"] == "buffer" and error["route"] == f"arm-{tag}", error
    assert status["buffer"]["lost"] == 1 and status["replies"]["errors"] == 1, status
