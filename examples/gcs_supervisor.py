"""The supervisory software of the farm demo, speaking only AMQP and canonical JSON.

It watches every canonical message on the ``farm`` exchange; when the UAV reports weeds it
turns the detections into a spraying mission for the ground robot (the paper's scenario),
and it exits with a summary after ``--duration`` seconds: 0 when every flow was seen.
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

UAV_FLOWS = ("position.uav1", "attitude.uav1", "battery.uav1", "status.uav1", "weeds.uav1")



def canonical_stamp() -> dict[str, int]:
    """Now, in the canonical form of every stamp: {sec, nanosec}."""
    ns = time.time_ns()
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}

async def main(url: str, duration: float, robot: str) -> int:
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    farm = await channel.declare_exchange("farm", aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue(exclusive=True)
    await queue.bind(farm, "canonical.#")
    seen: collections.Counter[str] = collections.Counter()
    missions = 0

    async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
        nonlocal missions
        kind = message.routing_key.removeprefix("canonical.")
        seen[kind] += 1
        body = json.loads(message.body)
        if seen[kind] == 1 or kind.startswith(("weeds", "ack")):
            print(f"gcs <- {message.routing_key}: {message.body.decode()[:160]}", flush=True)
        if kind.startswith("weeds") and missions < 3:
            missions += 1
            mission = {
                "agent_id": robot, "id": uuid.uuid4().hex, "type": "mission", "stamp": canonical_stamp(),
                "mission_id": f"spray-{missions}", "task": "spray",
                "waypoints": [{"seq": i, "lat": p["lat"], "lon": p["lon"], "action": "spray"} for i, p in enumerate(body["points"])],
            }
            await farm.publish(aio_pika.Message(json.dumps(mission).encode(), content_type="application/json"), f"mission.{robot}")
            print(f"gcs -> mission.{robot}: {mission['mission_id']} ({len(mission['waypoints'])} waypoints)", flush=True)

    await queue.consume(on_message, no_ack=True)
    await asyncio.sleep(duration)
    await connection.close()
    print("canonical messages seen: " + ", ".join(f"{k}={v}" for k, v in sorted(seen.items())))
    missing = [kind for kind in (*UAV_FLOWS, f"position.{robot}", f"ack.{robot}") if not seen[kind]]
    if missing:
        print(f"flows with no message: {', '.join(missing)}", file=sys.stderr)
    return 1 if missing else 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--url", required=True)
    parser.add_argument("--duration", type=float, default=20)
    parser.add_argument("--robot", default="robot1")
    args = parser.parse_args()
    sys.exit(asyncio.run(main(args.url, args.duration, args.robot)))
