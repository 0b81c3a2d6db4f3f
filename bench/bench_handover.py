"""Break-before-make handover of a udpin MAVLink connection while telemetry flows.

A pymavlink sender streams GLOBAL_POSITION_INT at --rate Hz to the engine's udpin port; the
route publishes each message to RabbitMQ (private node). The connection's settings are
changed --runs times (heartbeat rate flipped), each time a reload closes the old socket and
opens the new one. Printed per handover: the gap the engine reports (old routes stopping ->
new routes running), the datagrams that never reached RabbitMQ, and their ratio to what the
gap alone explains (gap x rate): above 1, messages queued in the old source or unread in the
old socket were dropped with it.

    .venv/bin/python -m bench.bench_handover --runs 10 --rate 200
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import uuid
from pathlib import Path

import aio_pika

from engine.endpoints.amqp.broker import LocalBroker
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.udp_vehicle import Vehicle, free_udp_port, telemetry_routes

SCHEMAS = Path(__file__).resolve().parent.parent / "schemas"


async def scenario(url: str, runs: int, rate: float) -> list[tuple[float, int]]:
    port, outbox = free_udp_port(), f"bench-{uuid.uuid4().hex[:8]}"
    with tempfile.TemporaryDirectory() as work:
        routes = Path(work)
        (routes / "radio.yaml").write_text(telemetry_routes(url, outbox, port, heartbeat=1))
        engine = Engine(routes, SCHEMAS)
        await engine.start()
        vehicle = Vehicle(port, rate)
        connection = await aio_pika.connect(url)
        results = []
        try:
            out = await Collector.bind(await connection.channel(), outbox, "telemetry")
            vehicle.start()
            await out.wait_for(int(rate))
            for run in range(runs):
                await asyncio.sleep(0.5)
                before = len(out.messages)
                first = vehicle.sent
                (routes / "radio.yaml").write_text(
                    telemetry_routes(url, outbox, port, heartbeat=2 if run % 2 == 0 else 1))
                assert await engine.reload(), engine.reloads.last_error
                gap_ms = engine.reloads.last_handovers[0]["gap_ms"]
                await asyncio.sleep(0.5)
                last = vehicle.sent
                seen: set[int] = set()
                for _ in range(200):  # one path, in order: once a later message arrived, the rest is missed
                    seen = {json.loads(m.body)["seq"] for m in out.messages[before:]}
                    if seen and max(seen) >= last:
                        break
                    await asyncio.sleep(0.05)
                missed = sum(1 for seq in range(first, last) if seq not in seen) if last > first else 0
                results.append((gap_ms, missed))
        finally:
            vehicle.stop.set()
            await connection.close()
            await engine.stop()
    return results


async def main(runs: int, rate: float) -> None:
    broker = LocalBroker()
    url = await asyncio.to_thread(broker.start)
    try:
        results = await scenario(url, runs, rate)
    finally:
        await asyncio.to_thread(broker.stop)
    print(f"udpin handover, telemetry at {rate:.0f} Hz, {runs} runs")
    print("run   gap ms   missed   missed / (gap x rate)")
    for run, (gap, missed) in enumerate(results):
        explained = gap / 1e3 * rate
        print(f"{run:3} {gap:8.1f} {missed:8}   {missed / explained if explained else float('nan'):6.2f}")
    gaps = [gap for gap, _ in results]
    print(f"gap ms: median {statistics.median(gaps):.1f}, max {max(gaps):.1f}; "
          f"datagrams missed: median {statistics.median(m for _, m in results)}, max {max(m for _, m in results)}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--rate", type=float, default=200.0)
    args = parser.parse_args()
    asyncio.run(main(args.runs, args.rate))
