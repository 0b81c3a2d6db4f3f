"""MAVLink latency over the emulated SiK radio (57,600 baud, TDM ~236 ms): telemetry one way
(vehicle -> radio -> engine -> AMQP) and commands (AMQP call -> engine -> radio -> vehicle's
COMMAND_ACK -> the call's reply on AMQP), p50/p99, with and without MAVLink 2 signing, idle and
under a saturating tunnel (a ``low`` JSON tunnel route with 2 KB messages always queued).

Everything runs in this process so one monotonic clock stamps both ends: the radio pair (a
thread), the simulated vehicle (rabbitros_sim/vehicle.py, its GLOBAL_POSITION_INT carries the
``time_boot_ms`` it was built at, so its send time is ``boot + time_boot_ms``) and the engine;
RabbitMQ is a private node. Telemetry latency = arrival at an AMQP consumer - send time at the
vehicle; command latency = the reply's arrival - the request's publish.

    .venv/bin/python -m bench.radio_latency [--seconds 15] [--json out.json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  radio: {{mavlink: "{link}", baud: 57600{signing}}}
routes:
  - name: telemetry
    source: {{mavlink: {{connection: radio, message: GLOBAL_POSITION_INT, system_id: 1}}}}
    schema: raw_json
    mapping: "{{t: time_boot_ms}}"
    sink: {{amqp: {{connection: gcs, exchange: {exchange}, routing_key: pos}}}}
  - name: command
    source: {{amqp: {{connection: gcs, queue: {exchange}-cmd}}}}
    schema: raw_json
    sink:
      mavlink: {{connection: radio, message: COMMAND_LONG, acknowledged: true, target_system: 1, target_component: 1}}
      mapping: "{{command: `400`, param1: `1`}}"
  - name: bulk
    source: {{amqp: {{connection: gcs, queue: {exchange}-bulk}}}}
    schema: raw_json
    priority: low
    sink: {{mavlink: {{connection: radio, json_tunnel: true, target_system: 1, target_component: 1}}}}
"""
KEY = bytes(range(32))
BULK_MESSAGES = 400
BULK_SIZE = 2000


def percentiles(samples: list[float]) -> dict[str, Any]:
    if not samples:
        return {"n": 0}
    ordered = sorted(samples)
    return {"n": len(ordered), "p50_ms": statistics.median(ordered) * 1000,
            "p99_ms": ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))] * 1000,
            "max_ms": ordered[-1] * 1000}


async def one(url: str, signed: bool, loaded: bool, seconds: float) -> dict[str, Any]:
    import aio_pika

    from engine.runtime import Engine
    from rabbitros_sim.sik_radio import SikRadioPair
    from rabbitros_sim.vehicle import SimVehicle

    exchange = f"lat-{uuid.uuid4().hex[:6]}"
    async with contextlib.AsyncExitStack() as rig:
        work = Path(rig.enter_context(tempfile.TemporaryDirectory(prefix="rabbitros-radio-latency-")))
        pair = rig.enter_context(SikRadioPair(seed=7))
        vehicle = SimVehicle(pair.link_b, signing_key=KEY if signed else None)
        await vehicle.open()
        stop = asyncio.Event()
        runner = asyncio.create_task(vehicle.run(stop))

        async def stop_vehicle() -> None:
            stop.set()
            await asyncio.gather(runner, return_exceptions=True)

        rig.push_async_callback(stop_vehicle)
        signing = ""
        if signed:
            (work / "key").write_bytes(KEY)
            signing = f", signing: {{key_file: \"{work / 'key'}\"}}"
        routes = work / "routes"
        routes.mkdir()
        (routes / "r.yaml").write_text(ROUTES.format(url=url, link=pair.link_a, signing=signing, exchange=exchange))
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        rig.push_async_callback(engine.stop)
        connection = await aio_pika.connect(url)
        rig.push_async_callback(connection.close)
        channel = await connection.channel()
        target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
        positions = await channel.declare_queue(exclusive=True)
        await positions.bind(target, "pos")
        telemetry: list[float] = []
        boot = vehicle._boot  # the loop time its time_boot_ms counts from (loop time is time.monotonic here)

        measuring_from = float("inf")

        async def on_position(message: Any) -> None:
            sent = boot + json.loads(message.body)["t"] / 1000
            if sent >= measuring_from:  # not what waited in the queue before the measurement
                telemetry.append(time.monotonic() - sent)

        replies = await channel.declare_queue(exclusive=True)
        waiting: dict[str, asyncio.Future[float]] = {}

        async def on_reply(message: Any) -> None:
            future = waiting.pop(message.correlation_id or "", None)
            if future is not None and not future.done():
                future.set_result(time.monotonic())

        await replies.consume(on_reply, no_ack=True)
        if loaded:
            pad = "x" * (BULK_SIZE - 20)
            for n in range(BULK_MESSAGES):
                await channel.default_exchange.publish(
                    aio_pika.Message(json.dumps({"n": n, "pad": pad}).encode()), f"{exchange}-bulk")
            await asyncio.sleep(3.0)  # the tunnel's window and the writer's queue are full
        await positions.consume(on_position, no_ack=True)
        await asyncio.sleep(1.0)
        measuring_from = time.monotonic()
        commands: list[float] = []
        failed = 0
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            correlation = uuid.uuid4().hex
            answered: asyncio.Future[float] = asyncio.get_running_loop().create_future()
            waiting[correlation] = answered
            sent = time.monotonic()
            await channel.default_exchange.publish(
                aio_pika.Message(b"{}", reply_to=replies.name, correlation_id=correlation), f"{exchange}-cmd")
            try:
                commands.append(await asyncio.wait_for(answered, 15) - sent)
            except TimeoutError:
                failed += 1
            await asyncio.sleep(0.3)
        link = next(c for c in engine.connections if c.name == "radio")
        bulk = engine.status()["routes"]["bulk"]
        return {"signed": signed, "loaded": loaded, "telemetry": percentiles(telemetry),
                "command": percentiles(commands), "command_timeouts": failed,
                "bulk_delivered": bulk["delivered"], "radio_dropped": pair.stats()["a"].serial_rx_dropped,
                "link_frames_sent": link.stats["frames_sent"]}


async def run(url: str | None = None, seconds: float = 15.0) -> list[dict[str, Any]]:
    """Every combination of signing and load; starts a private broker unless ``url``."""
    from engine.endpoints.amqp.broker import LocalBroker

    broker = None
    if url is None:
        broker = LocalBroker()
        url = await asyncio.to_thread(broker.start)
    try:
        rows = []
        for signed in (False, True):
            for loaded in (False, True):
                row = await one(url, signed, loaded, seconds)
                print(format_row(row), flush=True)
                rows.append(row)
        return rows
    finally:
        if broker is not None:
            await asyncio.to_thread(broker.stop)


def format_row(row: dict[str, Any]) -> str:
    def cell(figures: dict[str, Any], key: str) -> str:
        return f"{figures[key]:.0f}" if key in figures else "-"

    t, c = row["telemetry"], row["command"]
    return (f"| {'signed' if row['signed'] else 'unsigned'} | {'saturating tunnel' if row['loaded'] else 'idle'} | "
            f"{cell(t, 'p50_ms')} | {cell(t, 'p99_ms')} | {t['n']} | {cell(c, 'p50_ms')} | {cell(c, 'p99_ms')} | "
            f"{c['n']} ({row['command_timeouts']} timed out) |")


HEADER = ("| Signing | Load | Telemetry p50 (ms) | p99 | n | Command to COMMAND_ACK reply p50 (ms) | p99 | n |\n"
          "|---|---|---|---|---|---|---|---|")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    os.environ.setdefault("MAVLINK20", "1")
    print(HEADER)
    rows = asyncio.run(run(seconds=args.seconds))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
