"""The main job in CI: the farm example, run for 30 s from the entry point of ./scripts/demo.sh.

Every part is real: the simulated UAV on MAVLink 2 through the emulated SiK radio, the ROS 2
ground robot, the engine with a private RabbitMQ node, and the AMQP-only supervisory software.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from engine.common.schemas import SchemaRegistry
from engine.endpoints.mavlink.dialect import mavlink2
from tests.support.repo import REPO
from tests.support.workers import ros_domain
from tests.support.schemas import known_schema

DURATION = 30


@pytest.mark.soak
@pytest.mark.timeout(400)  # the demo's own bound is 320 s
def test_farm_example_end_to_end(tmp_path: Path):
    work = tmp_path / "farm"
    result = subprocess.run(
        ["timeout", "-s", "KILL", "300", sys.executable, "examples/farm_demo.py", "--duration", str(DURATION),
         "--work", str(work), "--plain", "--ros-domain", str(ros_domain(11))],
        cwd=REPO, capture_output=True, text=True, timeout=320,
    )
    out = result.stdout
    assert result.returncode == 0, out[-3000:] + result.stderr[-3000:]

    records = [json.loads(line) for line in (work / "canonical.jsonl").read_text().splitlines()]
    by_key: dict[str, list[dict]] = defaultdict(list)
    for record in records:
        by_key[record["routing_key"]].append(record)
    schemas = SchemaRegistry(REPO / "schemas")

    # UAV telemetry arrives in canonical form at the vehicle's rates (4 Hz, 4 Hz, 1 Hz, 1 Hz).
    for kind, rate in (("position", 4.0), ("attitude", 4.0), ("battery", 1.0), ("status", 1.0)):
        seen = by_key[f"canonical.{kind}.uav1"]
        assert len(seen) >= rate * DURATION / 2, f"{kind}: only {len(seen)} messages"
        for record in seen:
            known_schema(schemas, kind).validate(record["body"])
            assert record["body"]["agent_id"] == "uav1" and record["body"]["type"] == kind
        span = seen[-1]["t"] - seen[0]["t"]
        measured = (len(seen) - 1) / span
        print(f"{kind}.uav1: {len(seen)} messages over {span:.1f} s = {measured:.2f}/s (vehicle: {rate}/s)")
        assert 0.8 * rate <= measured <= 1.2 * rate, f"{kind}: {measured:.2f} msg/s, expected {rate}"
    position = by_key["canonical.position.uav1"][-1]["body"]
    assert math.isclose(position["lat"], -22.0, abs_tol=0.01) and math.isclose(position["lon"], -47.9, abs_tol=0.01)

    # Every weed detection the UAV sent reaches RabbitMQ: ids are numbered from 1 with no gap.
    weeds = [record["body"] for record in by_key["canonical.weeds.uav1"]]
    for body in weeds:
        known_schema(schemas, "weed_detection").validate(body)
    numbers = [int(body["id"].removeprefix("weeds-")) for body in weeds]
    assert numbers == list(range(1, len(numbers) + 1)), numbers
    uav_span = by_key["canonical.position.uav1"][-1]["t"] - by_key["canonical.position.uav1"][0]["t"]
    assert len(numbers) >= int(uav_span // 6) - 1 >= 2, f"{len(numbers)} detections in {uav_span:.0f} s (one per 6 s)"
    status = json.loads((work / "status.json").read_text())["routes"]
    assert status["uav1-weeds"]["received"] == status["uav1-weeds"]["delivered"] >= len(numbers)
    assert all(route["failed"] == 0 for route in status.values()), status

    # The supervisory software's missions reach the ground robot, and its acknowledgements come back.
    # (two processes share the output, so a line may hold the end of another: no ^ anchors)
    sent = re.findall(r"gcs -> mission\.ground\.robot1: (spray-\d+)", out)
    received = re.findall(r"robot1: mission (spray-\d+)", out)
    acks = [record["body"] for record in by_key["canonical.ack.robot1"]]
    assert sent and sent == received, out[-3000:]
    assert [ack["ref_id"] for ack in acks] == sent and all(ack["result"] == "accepted" for ack in acks)
    for ack in acks:
        known_schema(schemas, "ack").validate(ack)
    assert by_key["canonical.position.robot1"], "the robot's fix never reached RabbitMQ"

    # The UAV's missions are uploaded over the radio with the MAVLink mission protocol, and the
    # vehicle's MISSION_ACK comes back as a canonical ack (the last one may still be on its way).
    uav_sent = re.findall(r"gcs -> mission\.uav\.uav1: (uav-spray-\d+)", out)
    uav_acks = [record["body"] for record in by_key["canonical.ack.uav1"]]
    for ack in uav_acks:
        known_schema(schemas, "ack").validate(ack)
    assert uav_sent and len(uav_sent) - 1 <= len(uav_acks) <= len(uav_sent), (uav_sent, uav_acks)
    assert all(ack["result"] == "accepted" and ack["detail"] == "MAV_MISSION_ACCEPTED" for ack in uav_acks), uav_acks
    assert status["uav1-missions"]["delivered"] == len(uav_acks) or status["uav1-missions"]["delivered"] == len(uav_sent)
    # ... and the vehicle holds the last one at the supervisor's 20 m above home (alt_rel), not 20 m above the sea.
    [stopped] = [event for event in map(json.loads, (work / "vehicle.log").read_text().splitlines())
                 if event.get("event") == "stopped"]
    assert stopped["mission"] and {(item["frame"], item["z"]) for item in stopped["mission"]} == \
        {(mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 20.0)}, stopped["mission"]

    # The supervisor's command reached the UAV's companion computer through the radio (route
    # uav1-commands): its weed detector runs only once commanded, so the weeds above prove it too.
    assert re.findall(r"gcs -> command\.uav1: detect_weeds", out) == ["gcs -> command.uav1: detect_weeds"], out[-3000:]
    assert status["uav1-commands"]["received"] == status["uav1-commands"]["delivered"] == 1, status["uav1-commands"]

    # The supervisor's calls, answered over AMQP request/reply: the robot's sprayer service through
    # the route's reply mapping; the row goal accepted, followed stop by stop, SUCCEEDED; then the
    # sprayer switched off once the row was done.
    replies: dict[str, list[tuple[str, dict]]] = defaultdict(list)
    for what, kind, body in re.findall(r"gcs <- reply (spray-on|row|spray-off): (\w+) (\{[^{}\n]*\})", out):
        replies[what].append((kind, json.loads(body)))
    assert replies["spray-on"] == [("result", {"ok": True, "detail": "robot1: sprayer on"})], out[-3000:]
    assert replies["row"] == [("accepted", {"kind": "accepted", "status": None, "reached": None}),
                              *[("feedback", {"kind": "feedback", "status": None, "reached": n}) for n in (1, 1, 2, 3)],
                              ("result", {"kind": "result", "status": "SUCCEEDED", "reached": 3})], replies["row"]
    assert replies["spray-off"] == [("result", {"ok": True, "detail": "robot1: sprayer off"})], out[-3000:]
    for route in ("robot1-spray", "robot1-rows"):
        assert status[route]["replies"]["errors"] == 0 and status[route]["failed"] == 0, status[route]
    assert status["robot1-spray"]["replies"]["sent"] == 2 and status["robot1-rows"]["replies"]["sent"] == 6, status

    # Every flow the demo promises carried messages (the demo exits 1 otherwise, naming them).
    assert all(route["delivered"] > 0 for route in status.values()), status
    sys.path.insert(0, str(REPO / "examples"))
    from farm_demo import unkept_promises
    assert unkept_promises(status) == []
    idle = {**status, "uav1-commands": {**status["uav1-commands"], "delivered": 0}}
    assert unkept_promises(idle) == ["flows that carried nothing: uav1-commands"]
    print(f"weeds {len(numbers)}, missions {sent}, acks {len(acks)}, uav missions {uav_sent}, uav acks {len(uav_acks)}, "
          f"calls {dict((what, len(r)) for what, r in replies.items())}")
