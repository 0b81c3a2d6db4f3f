"""Demo generator: publishes UAV weed detections the way a detector on the UAV would, and
prints the canonical messages the engine routes back, until all have arrived."""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import sys
import time

import aio_pika


def detection(index: int, rng: random.Random) -> dict:
    return {
        "agent": f"uav{1 + index % 2}",
        "id": f"det-{index:05d}",
        "stamp": round(time.time(), 3),
        "detections": [
            {"lat": round(-22.0 + rng.uniform(0, 1e-3), 7), "lon": round(-47.9 + rng.uniform(0, 1e-3), 7),
             "confidence": round(rng.uniform(0.5, 1.0), 3)}
            for _ in range(rng.randint(1, 3))
        ],
    }


async def main(url: str, count: int, rate: float) -> int:
    rng = random.Random(7)
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    farm = await channel.declare_exchange("farm", aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue(exclusive=True)
    await queue.bind(farm, "canonical.#")
    done = asyncio.Event()
    received = 0

    async def show(message: aio_pika.abc.AbstractIncomingMessage) -> None:
        nonlocal received
        received += 1
        print(f"<- {message.routing_key} {message.body.decode()}")
        if received == count:
            done.set()

    await queue.consume(show, no_ack=True)
    for index in range(count):
        body = json.dumps(detection(index, rng)).encode()
        await farm.publish(aio_pika.Message(body, content_type="application/json"), f"weeds.uav{1 + index % 2}")
        print(f"-> weeds.uav{1 + index % 2} {body.decode()}")
        await asyncio.sleep(1 / rate)
    try:
        await asyncio.wait_for(done.wait(), 30)
    except asyncio.TimeoutError:
        print(f"only {received} of {count} canonical messages arrived", file=sys.stderr)
    await connection.close()
    print(f"{received}/{count} detections routed to canonical weed_detection")
    return 0 if received == count else 1


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--url", required=True)
    parser.add_argument("--count", type=int, default=20)
    parser.add_argument("--rate", type=float, default=20.0, help="messages per second")
    args = parser.parse_args()
    sys.exit(asyncio.run(main(args.url, args.count, args.rate)))
