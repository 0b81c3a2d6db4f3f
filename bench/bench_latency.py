"""The paper's latency experiment (CT-L1: RabbitMQ -> ROS 2, CT-L2: ROS 2 -> RabbitMQ).

Processing latency is the time from a message's reception by the engine's source to the
destination's acceptance of it (t2 - t1 / t4 - t3 in the paper), measured inside the engine
for every message. Payloads of 50, 150 and 250 bytes, 5 runs of 100 messages each; the
paper published at 1 msg/s (``--rate 1``), the default here is faster. The AMQP side is
measured with publisher confirms on (the engine's default: acceptance = the broker took
responsibility) and off (the paper's final configuration).

    .venv/bin/python -m bench.bench_latency [--runs 5] [--count 100] [--rate 20]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from typing import Any

import aio_pika

from bench import probes
from bench.roundtrip_ros2 import make_message
from engine.endpoints.amqp.broker import LocalBroker
from engine.endpoints.base import Inbound, Outbound
from engine.running.runtime import Engine

REPO = Path(__file__).resolve().parent.parent
PAPER = {"CT-L1": {50: 0.112, 150: 0.111, 250: 0.113}, "CT-L2": {50: 0.832, 150: 0.838, 250: 0.831}}
ROUTES = """
connections:
  gcs: {{amqp: {{url: "{url}", publisher_confirms: {confirms}}}}}
  ros: {{ros2: {{domain_id: {domain}, node: latency_engine}}}}
routes:
  - name: CT-L1
    source: {{amqp: {{exchange: latency, binding_key: l1, queue: latency-l1}}}}
    schema: raw_json
    sink: {{ros2: {{topic: /latency/l1}}}}
  - name: CT-L2
    source: {{ros2: {{topic: /latency/l2}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: latency, routing_key: l2}}}}
"""


def start_robot(domain: int, store: Path) -> subprocess.Popen[bytes]:
    """The robot in its own process (as on the paper's GCS): echoes /latency/l1 to /latency/l2,
    so one AMQP generator drives both directions."""
    return subprocess.Popen(
        ["timeout", "-s", "KILL", "900", sys.executable, str(REPO / "examples" / "robot_echo.py"),
         "--in", "/latency/l1", "--out", "/latency/l2", "--file", str(store)],
        env={**os.environ, "ROS_DOMAIN_ID": str(domain)}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


async def scenario(
    url: str, confirms: bool, runs: int, count: int, rate: float,
    parts: dict[str, dict[int, dict[str, list[float]]]] | None = None,
) -> dict[str, dict[int, list[float]]]:
    """t2 - t1 of every message, per route and size (ms). With ``parts``, also the two library
    calls of that path timed alone at the same rate: ``convert`` (the route's pipeline) and
    ``sink`` (the sink's send of that message, i.e. rclpy publish or aiormq publish)."""
    domain = 180 + os.getpid() % 50
    results: dict[str, dict[int, list[float]]] = {"CT-L1": {}, "CT-L2": {}}
    with tempfile.TemporaryDirectory() as routes:
        robot = start_robot(domain, Path(routes) / "robot.jsonl")
        Path(routes, "latency.yaml").write_text(ROUTES.format(url=url, confirms=str(confirms).lower(), domain=domain))
        engine = Engine(Path(routes), REPO / "schemas")
        await engine.start()
        seen = {name: remember_inbounds(engine.runners[name].pipeline) for name in results}
        connection = await aio_pika.connect(url)
        try:
            channel = await connection.channel()
            exchange = await channel.declare_exchange("latency", aio_pika.ExchangeType.TOPIC, durable=True)
            station = await channel.declare_queue(exclusive=True)
            await station.bind(exchange, "l2")
            back: list[bytes] = []

            async def came_back(message: aio_pika.abc.AbstractIncomingMessage) -> None:
                back.append(message.body)

            await station.consume(came_back, no_ack=True)
            deadline = time.monotonic() + 30
            while not back and time.monotonic() < deadline:
                await exchange.publish(aio_pika.Message(b'{"probe":1}'), "l1")
                await asyncio.sleep(0.2)
            await asyncio.sleep(0.5)
            for size in (50, 150, 250):
                for name in results:
                    results[name][size] = []
                for run in range(runs):
                    recorded = [probes.latency(engine.runners[name]) for name in results]
                    for seq in range(count):
                        await exchange.publish(aio_pika.Message(make_message(run + 1, size, seq)), "l1")
                        await asyncio.sleep(1 / rate)
                    deadline = time.monotonic() + 10
                    while any(len(probe.samples) < count for probe in recorded) and time.monotonic() < deadline:
                        await asyncio.sleep(0.05)
                    for name, probe in zip(results, recorded):
                        results[name][size].extend(ns / 1e6 for ns in probe.detach())
                if parts is not None:
                    for name in results:
                        parts.setdefault(name, {})[size] = await parts_alone(engine.runners[name], seen[name], count, rate)
        finally:
            await connection.close()
            await engine.stop()
            robot.terminate()
            robot.wait(10)
    return results


def remember_inbounds(pipeline: Any) -> list[Inbound]:
    """The last message the pipeline converted, kept (a copy) to be converted and sent again alone."""
    kept: list[Inbound] = []
    convert = pipeline.convert

    def converting(inbound: Inbound) -> Outbound:
        kept[:] = [Inbound(body=inbound.body, fields=inbound.fields, meta=dict(inbound.meta))]
        return convert(inbound)

    pipeline.convert = converting
    return kept


async def parts_alone(runner: Any, kept: list[Inbound], count: int, rate: float) -> dict[str, list[float]]:
    """What the route's conversion and its sink's send cost each on their own, one message at a
    time at ``rate`` as in the latency runs, then back to back: on this machine an idle pause
    between messages makes every call much slower (cold caches, an idle vCPU to wake)."""
    convert, sink = runner.pipeline.convert, runner.pipeline.sink
    out: dict[str, list[float]] = {}
    for label, pause in (("", 1 / rate), ("back_to_back_", 0.0)):
        converts, sends = out.setdefault(f"{label}convert", []), out.setdefault(f"{label}sink", [])
        for _ in range(count):
            inbound = Inbound(body=kept[0].body, fields=kept[0].fields, meta=dict(kept[0].meta))
            began = time.perf_counter_ns()
            outbound = convert(inbound)
            converted = time.perf_counter_ns()
            await sink.send_batch([outbound])
            converts.append((converted - began) / 1e6)
            sends.append((time.perf_counter_ns() - converted) / 1e6)
            if pause:
                await asyncio.sleep(pause)
    return out


def report(confirms: bool, results: dict[str, dict[int, list[float]]]) -> None:
    print(f"\npublisher_confirms={confirms}")
    print(f"{'scenario':8} {'size':>5} {'mean':>7} {'std':>7} {'min':>7} {'max':>7}   paper mean   ratio paper/ours")
    for name, sizes in results.items():
        for size, samples in sizes.items():
            mean = statistics.fmean(samples)
            print(f"{name:8} {size:>4}B {mean:7.3f} {statistics.pstdev(samples):7.3f} {min(samples):7.3f} "
                  f"{max(samples):7.3f}   {PAPER[name][size]:7.3f} ms   {PAPER[name][size] / mean:6.2f}x")


async def main(runs: int, count: int, rate: float) -> None:
    broker = LocalBroker()
    url = await asyncio.to_thread(broker.start)
    try:
        for confirms in (True, False):
            report(confirms, await scenario(url, confirms, runs, count, rate))
    finally:
        await asyncio.to_thread(broker.stop)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--rate", type=float, default=20.0)
    args = parser.parse_args()
    asyncio.run(main(args.runs, args.count, args.rate))
