"""A MAVLink sink field is never guessed: a null, or a path the message lacks, sends nothing.

The engine runs the routes from RabbitMQ to a vehicle on plain pymavlink (tests/support/udp_vehicle.py
``CommandVehicle``, which parses with pymavlink alone). An arm command whose ``param1`` is null,
one without the parameter, and one with a misspelt command name are dead-lettered with the field
(or the close name) in ``x-rabbitros-error``; a good one after them reaches the vehicle, which
proves the path, and nothing else does within a deadline. ``rabbitros-engine test`` on the same
routes reports the same errors, word for word.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika

from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.udp_vehicle import CommandVehicle
from tests.support.waiting import wait_for

QUIET_S = 1.0
"""After the good command arrived, how long the vehicle must hear nothing more."""
ARM = "{command: mav_enum_value(command, 'MAV_CMD'), param1: params.arm}"
GOTO = ("{command: 'MAV_CMD_DO_REPOSITION', frame: 'GLOBAL_RELATIVE_ALT_INT', param1: `-1`, param2: `0`, "
        "param3: `0`, param4: nan(), x: deg_to_deg_e7(params.lat), y: deg_to_deg_e7(params.lon), z: params.alt}")
"""Fly to a point keeping the current yaw: MAVLink says so with NaN in param4."""


def routes_text(amqp_url: str, port: int, tag: str) -> str:
    def route(name: str, acknowledged: bool, mapping: str, message: str = "COMMAND_LONG") -> str:
        options = ", acknowledged: true" if acknowledged else ""
        return f"""
  - name: {name}-{tag}
    source: {{amqp: {{connection: bus, exchange: farm-{tag}, binding_key: {name}, queue: {name}-{tag}}}}}
    schema: command
    sink:
      mavlink: {{connection: uav, message: {message}, target_system: 1, target_component: 1{options}}}
      mapping: "{mapping}"
"""
    return (f'connections:\n  bus: {{amqp: "{amqp_url}"}}\n  uav: {{mavlink: "udpout:127.0.0.1:{port}"}}\nroutes:'
            + route("arm", True, ARM) + route("arm-plain", False, ARM) + route("goto", True, GOTO, "COMMAND_INT"))


def command(name: str, **params: Any) -> dict[str, Any]:
    now = time.time_ns()
    body: dict[str, Any] = {"type": "command", "agent_id": "uav1", "id": uuid.uuid4().hex, "command": name,
                            "stamp": {"sec": now // 1_000_000_000, "nanosec": now % 1_000_000_000}}
    if params:
        body["params"] = params
    return body


ARM_NULL = command("MAV_CMD_COMPONENT_ARM_DISARM", arm=None)
ARM_ABSENT = command("MAV_CMD_COMPONENT_ARM_DISARM")
ARM_MISSPELT = command("MAV_CMD_COMPONENT_ARM_DISARN", arm=1)
ARM_GOOD = command("MAV_CMD_COMPONENT_ARM_DISARM", arm=1)
GOTO_GOOD = command("goto", lat=-22.0001, lon=-47.9002, alt=25.5)
NULL_ERROR = "COMMAND_LONG: field 'param1' is null"
MISSPELT_ERROR = "'MAV_CMD_COMPONENT_ARM_DISARN' is not a MAV_CMD name; did you mean 'MAV_CMD_COMPONENT_ARM_DISARM'?"


def test_null_or_absent_command_field_sends_nothing_and_is_dead_lettered(tmp_path: Path, amqp_url: str,
                                                                        schemas_dir: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    vehicle = CommandVehicle()
    vehicle.start()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "routes.yaml").write_text(routes_text(amqp_url, vehicle.port, tag))

    async def scenario() -> tuple[dict[str, list[Any]], dict[str, float], dict[str, Any]]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            dead = {name: await Collector.bind(channel, "rabbitros.dead-letter", f"{name}-{tag}")
                    for name in ("arm", "arm-plain", "goto")}
            farm = await channel.declare_exchange(f"farm-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            published: dict[str, float] = {}
            for key in ("arm", "arm-plain"):
                for body in (ARM_NULL, ARM_ABSENT, ARM_MISSPELT):
                    await farm.publish(aio_pika.Message(json.dumps(body).encode()), key)
                published[key] = time.monotonic()
                await farm.publish(aio_pika.Message(json.dumps(ARM_GOOD).encode()), key)
            published["goto"] = time.monotonic()
            await farm.publish(aio_pika.Message(json.dumps(GOTO_GOOD).encode()), "goto")
            letters = {name: await collector.wait_for(3 if name != "goto" else 0, 20) for name, collector in dead.items()}
            await wait_for(lambda: len(vehicle.received()) >= 3, 20, "the 3 good commands at the vehicle",
                           lambda: len(vehicle.received()))
            await asyncio.sleep(QUIET_S)  # quiet window: nothing else may arrive: the refused ones were settled before the good ones
            status = engine.status()
        finally:
            await engine.stop()
            await connection.close()
        return letters, published, status

    try:
        letters, published, status = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        vehicle.stop.set()
        vehicle.join(5)

    received = vehicle.received()
    assert len(received) == 3, [msg.to_dict() for _, msg in received]
    arms = [msg for _, msg in received if msg.command == 400]
    assert [(msg.param1, msg.target_system, msg.target_component) for msg in arms] == [(1.0, 1, 1), (1.0, 1, 1)]
    [goto] = [msg for _, msg in received if msg.command != 400]
    assert (goto.get_type(), goto.command, goto.frame) == ("COMMAND_INT", 192, 6) and math.isnan(goto.param4), goto
    assert (goto.param1, goto.x, goto.y, goto.z, goto.current, goto.autocontinue) == (-1.0, -220001000, -479002000, 25.5, 0, 0)
    for key in ("arm", "arm-plain"):
        route = status["routes"][f"{key}-{tag}"]
        assert route["delivered"] == 1, route
        headers = [m.headers for m in letters[key]]
        assert [h["x-rabbitros-stage"] for h in headers] == ["sink mapping"] * 3, headers
        errors = [h["x-rabbitros-error"] for h in headers]
        assert errors[0].startswith(NULL_ERROR) and errors[1].startswith(NULL_ERROR), errors
        assert MISSPELT_ERROR in errors[2], errors
        assert [json.loads(m.body)["id"] for m in letters[key]] == [ARM_NULL["id"], ARM_ABSENT["id"], ARM_MISSPELT["id"]]
    assert letters["goto"] == []
    [arrived] = [at for at, msg in received if msg.command == 192]
    goto_ms = 1000 * (arrived - published["goto"])
    print(f"publish -> vehicle: goto {goto_ms:.1f} ms")  # the figure, for the record (pytest -s)
    assert goto_ms < 5000, goto_ms

    # rabbitros-engine test on the same routes: the same errors, word for word
    (routes / "routes.test.yaml").write_text(json.dumps({"tests": [
        {"name": "param1 null", "route": f"arm-{tag}", "input": ARM_NULL, "expect_error": "sink mapping"},
        {"name": "params absent", "route": f"arm-plain-{tag}", "input": ARM_ABSENT, "expect_error": "sink mapping"},
        {"name": "misspelt command", "route": f"arm-{tag}", "input": ARM_MISSPELT, "expect_error": "sink mapping"},
        {"name": "good", "route": f"arm-{tag}", "input": ARM_GOOD, "expect_sink": {"command": 400, "param1": 1}},
        {"name": "goto with nan", "route": f"goto-{tag}", "input": GOTO_GOOD, "expect_sink": {
            "command": "MAV_CMD_DO_REPOSITION", "frame": "GLOBAL_RELATIVE_ALT_INT", "param1": -1, "param2": 0,
            "param3": 0, "param4": math.nan, "x": -220001000, "y": -479002000, "z": 25.5}},
        {"name": "expects success without params", "route": f"arm-{tag}", "input": ARM_ABSENT,
         "expect_sink": {"command": 400, "param1": None}},
    ]}, allow_nan=True).replace("NaN", ".nan"))
    result = subprocess.run([sys.executable, "-m", "engine", "test", "--routes", str(routes), "--schemas", str(schemas_dir)],
                            capture_output=True, text=True, timeout=120, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    lines = result.stdout.splitlines()
    assert result.returncode == 1, result.stdout + result.stderr
    assert lines[-1] == "5 passed, 1 failed", result.stdout
    [failed] = [line for line in lines if line.startswith("FAIL")]
    expected_error = letters["arm"][1].headers["x-rabbitros-error"]
    assert failed.endswith(f"arm-{tag}: expects success without params: expected it to pass, "
                           f"got a sink mapping error: {expected_error}"), (failed, expected_error)
