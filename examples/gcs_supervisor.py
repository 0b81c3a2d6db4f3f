"""The supervisory software of the farm demo, speaking only AMQP and canonical JSON.

It watches every canonical message on the ``farm`` exchange. When the UAV first reports, it
commands the UAV's companion computer to start its weed detector (a canonical command on
``command.uav1``, which the engine carries to the vehicle through the radio's JSON tunnel).
When the UAV reports weeds it turns the detections into a spraying mission for the ground robot
(the paper's scenario) and one for the UAV itself (the engine uploads it to the vehicle with the
MAVLink mission protocol; the vehicle's MISSION_ACK comes back as a canonical ack), and it exits
with a summary after ``--duration`` seconds: 0 when every flow was seen and every call answered.

Calls (AMQP request/reply: ``reply_to`` RabbitMQ's direct reply-to, a ``correlation_id``): when
the ground robot first reports, the supervisor switches its sprayer on through the robot's ROS 2
service (``call.robot1.spray``) and sends it along a row with a ROS 2 action goal
(``call.robot1.row``); it prints every reply (``x-rabbitros-reply``: accepted, feedback, result,
rejected or error) and, once the row is done, switches the sprayer off.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import sys
import time
import uuid

import aio_pika

UAV_FLOWS = ("position.uav1", "attitude.uav1", "battery.uav1", "status.uav1", "weeds.uav1", "ack.uav1")
UAV_ALT_M = 20.0
"""Spraying height of the UAV's missions above home: the waypoints' ``alt_rel``, which the engine
uploads in MAV_FRAME_GLOBAL_RELATIVE_ALT_INT (``alt_msl`` would be above mean sea level)."""
DETECT_EVERY_S = 6.0
"""Seconds between the UAV's weed detections, set by the ground station's command."""
ROW_STOPS = 5
"""Stops along the row the robot is sent down (each is a feedback reply)."""
DIRECT_REPLY_TO = "amq.rabbitmq.reply-to"


def canonical_stamp() -> dict[str, int]:
    """Now, in the canonical form of every stamp: {sec, nanosec}."""
    ns = time.time_ns()
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


async def main(url: str, duration: float, robot: str, record: str | None = None, ready_file: str | None = None) -> int:
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    farm = await channel.declare_exchange("farm", aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue(exclusive=True)
    await queue.bind(farm, "canonical.#")
    seen: collections.Counter[str] = collections.Counter()
    missions = 0
    commanded: set[str] = set()
    recording = open(record, "a", encoding="utf-8") if record else None
    calls: dict[str, str] = {}
    """correlation id -> what was asked (spray-on, row, spray-off)."""
    answered: dict[str, str] = {}
    """what was asked -> its final reply's kind."""

    async def call(what: str, routing_key: str, request: dict[str, object]) -> None:
        correlation_id = uuid.uuid4().hex
        calls[correlation_id] = what
        await farm.publish(aio_pika.Message(json.dumps(request).encode(), content_type="application/json",
                                            correlation_id=correlation_id, reply_to=DIRECT_REPLY_TO), routing_key)
        print(f"gcs -> {routing_key}: {what} {json.dumps(request)}", flush=True)

    async def on_reply(message: aio_pika.abc.AbstractIncomingMessage) -> None:
        what = calls.get(message.correlation_id or "", "?")
        kind = (message.headers or {}).get("x-rabbitros-reply")
        kind = kind.decode() if isinstance(kind, bytes) else kind  # a header string may arrive as bytes
        print(f"gcs <- reply {what}: {kind} {message.body.decode()[:160]}", flush=True)
        if kind in ("result", "rejected", "error"):
            answered[what] = str(kind)
            if what == "row":
                await call("spray-off", f"call.{robot}.spray", {"spray": False})

    replies = await channel.get_queue(DIRECT_REPLY_TO, ensure=False)
    await replies.consume(on_reply, no_ack=True)  # before the first call: direct reply-to needs it

    async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
        nonlocal missions
        kind = (message.routing_key or "").removeprefix("canonical.")
        seen[kind] += 1
        body = json.loads(message.body)
        if recording is not None:
            recording.write(json.dumps({"t": time.time(), "routing_key": message.routing_key, "body": body}) + "\n")
        if seen[kind] == 1 or kind.startswith(("weeds", "ack")):
            print(f"gcs <- {message.routing_key}: {message.body.decode()[:160]}", flush=True)
        agent = body.get("agent_id", "")
        if kind == f"position.{robot}" and seen[kind] == 1:  # the robot is up: spray along a row
            await call("spray-on", f"call.{robot}.spray", {"spray": True})
            await call("row", f"call.{robot}.row", {"stops": ROW_STOPS})
        if kind.startswith("status.") and agent.startswith("uav") and agent not in commanded:
            commanded.add(agent)  # the UAV is up: start its weed detector
            command = {"agent_id": agent, "id": uuid.uuid4().hex, "type": "command", "stamp": canonical_stamp(),
                       "command": "detect_weeds", "params": {"every_s": DETECT_EVERY_S}, "target": agent}
            await farm.publish(aio_pika.Message(json.dumps(command).encode(), content_type="application/json"),
                               f"command.{agent}")
            print(f"gcs -> command.{agent}: detect_weeds every {DETECT_EVERY_S:g} s", flush=True)
        if kind.startswith("weeds") and missions < 3:
            missions += 1
            mission = {
                "agent_id": robot, "id": uuid.uuid4().hex, "type": "mission", "stamp": canonical_stamp(),
                "mission_id": f"spray-{missions}", "task": "spray",
                "waypoints": [{"seq": i, "lat": p["lat"], "lon": p["lon"], "action": "spray"} for i, p in enumerate(body["points"])],
            }
            await farm.publish(aio_pika.Message(json.dumps(mission).encode(), content_type="application/json"),
                               f"mission.ground.{robot}")
            print(f"gcs -> mission.ground.{robot}: {mission['mission_id']} ({len(mission['waypoints'])} waypoints)", flush=True)
            if missions <= 2:
                uav = {**mission, "agent_id": body["agent_id"], "id": uuid.uuid4().hex, "mission_id": f"uav-spray-{missions}",
                       "waypoints": [{"lat": p["lat"], "lon": p["lon"], "alt_rel": UAV_ALT_M, "hold_s": 2.0} for p in body["points"]]}
                await farm.publish(aio_pika.Message(json.dumps(uav).encode(), content_type="application/json"),
                                   f"mission.uav.{uav['agent_id']}")
                print(f"gcs -> mission.uav.{uav['agent_id']}: {uav['mission_id']} ({len(uav['waypoints'])} waypoints)", flush=True)

    await queue.consume(on_message, no_ack=True)
    if ready_file:
        with open(ready_file, "w") as ready:
            ready.write("watching\n")
    await asyncio.sleep(duration)
    await connection.close()
    if recording is not None:
        recording.close()
    print("canonical messages seen: " + ", ".join(f"{k}={v}" for k, v in sorted(seen.items())))
    print("calls answered: " + ", ".join(f"{what}={kind}" for what, kind in sorted(answered.items())))
    missing = [kind for kind in (*UAV_FLOWS, f"position.{robot}", f"ack.{robot}") if not seen[kind]]
    if missing:
        print(f"flows with no message: {', '.join(missing)}", file=sys.stderr)
    unanswered = [what for what in ("spray-on", "row", "spray-off") if answered.get(what) != "result"]
    if unanswered:
        print(f"calls without a result: {', '.join(unanswered)}", file=sys.stderr)
    return 1 if missing or unanswered else 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--url", required=True)
    parser.add_argument("--duration", type=float, default=20)
    parser.add_argument("--robot", default="robot1")
    parser.add_argument("--record", help="append every canonical message seen to this file (JSON lines)")
    parser.add_argument("--ready-file", help="write this file once the supervisor is watching")
    args = parser.parse_args()
    sys.exit(asyncio.run(main(args.url, args.duration, args.robot, args.record, args.ready_file)))
