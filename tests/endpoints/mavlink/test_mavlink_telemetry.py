"""Telemetry from the simulated vehicle, over the emulated SiK radio, through the routes of
``examples/fragments/farm_routes_mavlink.yaml``, to AMQP as canonical position / attitude / battery / status.

Every canonical value is checked against values computed here from ``expected_state(t)``, with
``t`` from the message's ``time_boot_ms``, by math written in this file (numpy rotation matrices),
not by ``engine.common.frames``. The example's JSON tunnel routes are checked with one command that the
vehicle stores and sends back.
"""

from __future__ import annotations

import asyncio
import json
import math
import shutil
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import aio_pika
import numpy as np
import pytest

from bench.roundtrip_mavlink import vehicle_process
from engine.running.runtime import Engine
from rabbitros_sim.sik_radio import SikRadioPair
from rabbitros_sim.vehicle import expected_state
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.waiting import wait_for

EXAMPLE = REPO / "examples" / "fragments" / "farm_routes_mavlink.yaml"

NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""World axes: east = NED y, north = NED x, up = -down."""
FLU_TO_FRD = np.diag([1.0, -1.0, -1.0])
"""Body axes: base_link (forward, left, up) to aircraft (forward, right, down)."""


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body-to-world matrix Rz(yaw) Ry(pitch) Rx(roll), the MAVLink ATTITUDE convention."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def quaternion_of(m: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix, by the largest-diagonal (Shepperd) method, w >= 0."""
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[i], q[j], q[k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    return q if q[3] >= 0 else -q


def expected_attitude(t: float) -> dict[str, Any]:
    """base_link in ENU: R_enu_flu = NED_TO_ENU @ R_ned_frd @ FLU_TO_FRD, angles in degrees."""
    s = expected_state(t)
    m = NED_TO_ENU @ rotation_zyx(s["roll"], s["pitch"], s["yaw"]) @ FLU_TO_FRD
    return {
        "quaternion": quaternion_of(m),
        "roll": math.degrees(math.atan2(m[2, 1], m[2, 2])),
        "pitch": math.degrees(-math.asin(m[2, 0])),
        "yaw": math.degrees(math.atan2(m[1, 0], m[0, 0])),
        "angular_velocity": [s["rollspeed"], -s["pitchspeed"], -s["yawspeed"]],
        "ned_degrees": (math.degrees(s["roll"]), math.degrees(s["pitch"]), math.degrees(s["yaw"])),
    }


def angle_diff(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def check_position(body: dict[str, Any]) -> None:
    s = expected_state(body["time_boot_ms"] / 1000)
    assert body["type"] == "position" and body["agent_id"] == "uav1"
    assert body["lat"] == pytest.approx(s["lat"] * 1e-7, abs=1e-12)
    assert body["lon"] == pytest.approx(s["lon"] * 1e-7, abs=1e-12)
    assert body["alt_msl"] == pytest.approx(s["alt"] * 1e-3, abs=1e-9)
    assert body["alt_rel"] == pytest.approx(s["relative_alt"] * 1e-3, abs=1e-9)
    east, north, up = body["velocity_enu"]
    assert (east, north, up) == pytest.approx((s["vy"] * 0.01, s["vx"] * 0.01, -s["vz"] * 0.01), abs=1e-9)
    assert body["heading"] == pytest.approx(s["hdg"] * 0.01, abs=1e-9)
    # The same numbers seen as geometry: 10.47 m/s along the circle, heading = course over ground.
    assert math.hypot(east, north) == pytest.approx(2 * math.pi * 100 / 60, abs=0.02)
    assert abs(angle_diff(math.degrees(math.atan2(east, north)) % 360, body["heading"])) < 0.2


def check_attitude(body: dict[str, Any]) -> None:
    expected = expected_attitude(body["time_boot_ms"] / 1000)
    assert body["type"] == "attitude" and body["agent_id"] == "uav1"
    q = body["quaternion"]
    got = np.array([q["x"], q["y"], q["z"], q["w"]])
    got = got if got[3] >= 0 else -got
    assert np.allclose(got, expected["quaternion"], atol=1e-6), (got, expected["quaternion"])
    assert math.isclose(np.linalg.norm(got), 1.0, abs_tol=1e-9)
    for key in ("roll", "pitch", "yaw"):
        assert abs(angle_diff(body[key], expected[key])) < 1e-4, key
    # REP-103 in words: same bank, pitch sign flipped, yaw counted from east counter-clockwise.
    roll, pitch, yaw = expected["ned_degrees"]
    assert abs(angle_diff(body["roll"], roll)) < 1e-4
    assert abs(angle_diff(body["pitch"], -pitch)) < 1e-4
    assert abs(angle_diff(body["yaw"], 90.0 - yaw)) < 1e-4
    assert body["angular_velocity"] == pytest.approx(expected["angular_velocity"], abs=1e-6)


def test_vehicle_telemetry_arrives_canonical_in_enu_and_si(tmp_path: Path, amqp_url: str, schemas_dir: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    routes = tmp_path / "routes"
    routes.mkdir()
    shutil.copy(EXAMPLE, routes)
    store = tmp_path / "robot.jsonl"
    command = json.dumps({"agent_id": "uav1", "command": "goto", "target": "uav1",
                          "params": {"lat": -22.0009, "lon": -47.9, "id": uuid.uuid4().hex}}).encode()

    async def scenario() -> tuple[dict[str, list[Any]], dict[str, Any]]:
        async with SikRadioPair(str(tmp_path / "gcs"), str(tmp_path / "uav"), seed=3) as pair, \
                vehicle_process(pair.link_b, store, 60):
            monkeypatch.setenv("RABBITROS_RADIO", pair.link_a)
            monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
            engine = Engine(routes, schemas_dir)
            connection = await aio_pika.connect(amqp_url)
            try:
                channel = await connection.channel()
                # bound before the engine starts: a message to "farm" with no queue bound is held
                # (a mandatory publish returned), which would count as the route's sink_errors
                canonical = await Collector.bind(channel, "farm", "canonical.#")
                replies = await Collector.bind(channel, "farm", "uav.json.#")
                await engine.start()
                farm = await channel.declare_exchange("farm", aio_pika.ExchangeType.TOPIC, durable=True)
                await farm.publish(aio_pika.Message(command, content_type="application/json"), "command.uav1")

                def enough() -> bool:
                    kinds = [m.routing_key for m in canonical.messages]
                    return bool(replies.messages and min(kinds.count(f"canonical.{k}.uav1") for k in ("position", "attitude")) >= 12
                                and min(kinds.count(f"canonical.{k}.uav1") for k in ("battery", "status")) >= 3)

                await wait_for(enough, 20, "a reply and 12 positions/attitudes, 3 batteries/statuses of uav1",
                               lambda: (len(replies.messages), Counter(m.routing_key for m in canonical.messages)))
                status = engine.status()
            finally:
                await connection.close()
                await engine.stop()
        by_key: dict[str, list[Any]] = {}
        for message in canonical.messages + replies.messages:
            by_key.setdefault(str(message.routing_key), []).append(message)  # a delivery always has one
        return by_key, status

    received, status = asyncio.run(asyncio.wait_for(scenario(), 90))
    now = time.time()

    positions = [json.loads(m.body) for m in received.get("canonical.position.uav1", [])]
    attitudes = [json.loads(m.body) for m in received.get("canonical.attitude.uav1", [])]
    assert len(positions) >= 12 and len(attitudes) >= 12, {k: len(v) for k, v in received.items()}
    for body in positions:
        check_position(body)
        assert now - 60 < body["stamp"]["sec"] + body["stamp"]["nanosec"] / 1e9 <= now
    for body in attitudes:
        check_attitude(body)
    stamps = [b["time_boot_ms"] for b in positions]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    assert stamps[-1] - stamps[0] >= 2500, "the vehicle moved along its circle during the test"

    batteries = [json.loads(m.body) for m in received["canonical.battery.uav1"]]
    for body in batteries:
        assert expected_state(60)["voltage_battery"] / 1000 <= body["voltage"] <= expected_state(0)["voltage_battery"] / 1000
        assert body["current"] == pytest.approx(expected_state(0)["current_battery"] / 100)
        assert body["remaining"] in (1.0, 0.99)
    statuses = [json.loads(m.body) for m in received["canonical.status.uav1"]]
    assert all({k: s[k] for k in ("state", "armed", "vehicle_type", "autopilot")} ==
               {"state": "MAV_STATE_ACTIVE", "armed": True, "vehicle_type": "MAV_TYPE_QUADROTOR",
                "autopilot": "MAV_AUTOPILOT_GENERIC"}
               for s in statuses), statuses

    assert [m.body for m in received["uav.json.uav1"]] == [command], "the command came back byte for byte"
    assert store.read_bytes() == command + b"\n", "the vehicle stored exactly the command"
    for name, route in status["routes"].items():
        assert route["failed"] == 0 and route["sink_errors"] == 0, name
