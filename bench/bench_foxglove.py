"""Cost of ``--foxglove`` (issue 33: with no client, nothing measurable; with a client
subscribed to every channel, route latency p99 within 10 % of without).

Three engines as child processes on one private RabbitMQ node, at the same time, each with one
route (AMQP queue -> position mapping -> ``position`` schema -> AMQP queue) on queues of its own:
``plain`` (no ``--foxglove``), ``view`` (``--foxglove``, no client) and ``subscribed`` (a
``websockets`` client subscribed to the route's channel, ``/fleet`` and ``/routes/status``,
reading every frame). Running the three in the same seconds puts a shared machine's load on all
alike (one after the other, the p99 of separate runs moved between 5 and 400 ms with the
machine's load). Per round:

- CPU: COUNT messages published to each engine at once (confirmed), each engine's CPU time
  (user + system, every thread: the SDK's server threads included) from before the first to the
  last delivered, per message;
- latency: LATENCY_COUNT messages published at RATE per second, each one to the three engines
  back to back (the order turning with each message, so none is always first), each timed from
  its publish to its arrival in its engine's output queue (this process holds both clocks): p50
  and p99 per mode, and the ratio of ``subscribed`` and ``view`` to ``plain`` in that round.

The medians over the rounds are reported.

    .venv/bin/python -m bench.bench_foxglove [--count 10000] [--latency-count 2000] [--rate 200] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aio_pika
import websockets
from websockets.typing import Subprotocol

from bench.position_route import body, routes_yaml, status
from bench.throughput import Broker, process_cpu_seconds
import foxglove

from engine.common.processes import listening_port
from engine.endpoints.amqp.broker import LocalBroker
from engine.endpoints.base import Outbound
from engine.ops.foxglove import RouteChannel
from engine.running.observe import RouteObserver

REPO = Path(__file__).resolve().parent.parent
MODES = ("plain", "view", "subscribed")


class Viewer:
    """A Foxglove client subscribed to every channel, reading (and counting) every frame."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.frames = 0
        self.channels: dict[str, int] = {}
        self._task: asyncio.Task[None] | None = None
        self.ws: Any = None

    async def start(self) -> None:
        self.ws = await websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=[Subprotocol("foxglove.sdk.v1")])
        self._task = asyncio.create_task(self._read())
        deadline = time.monotonic() + 30
        while len(self.channels) < 3:
            if time.monotonic() > deadline:
                raise RuntimeError(f"channels not advertised: {self.channels}")
            await asyncio.sleep(0.05)
        await self.subscribe()

    async def subscribe(self) -> None:
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": index, "channelId": channel} for index, channel in enumerate(self.channels.values())]}))

    async def _read(self) -> None:
        async for frame in self.ws:
            if isinstance(frame, bytes):
                self.frames += 1
            else:
                message = json.loads(frame)
                if message["op"] == "advertise":
                    self.channels.update((c["topic"], c["id"]) for c in message["channels"])

    async def stop(self) -> None:
        await self.ws.close()
        if self._task is not None:
            await asyncio.gather(self._task, return_exceptions=True)


class Engine:
    """One engine of a round, on queues of its own (``fox-in-MODE``, ``fox-out-MODE``)."""

    def __init__(self, url: str, work: Path, mode: str) -> None:
        self.mode, self.work = mode, work
        self.queue, self.out = f"fox-in-{mode}", f"fox-out-{mode}"
        routes = work / "routes"
        routes.mkdir(parents=True, exist_ok=True)
        (routes / "bench.yaml").write_text(routes_yaml(url, self.queue, self.out))
        self.status_file = work / "status.json"
        self.port = listening_port()
        extra = [] if mode == "plain" else ["--foxglove", str(self.port)]
        with open(work / "engine.log", "w") as log:
            self.process = subprocess.Popen([sys.executable, "-m", "engine", "--routes", str(routes), "--schemas",
                                             str(REPO / "schemas"), "--status-file", str(self.status_file),
                                             "--stats-interval", "0.2", *extra],
                                            cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        self.viewer = Viewer(self.port) if mode == "subscribed" else None

    async def started(self, deadline: float) -> None:
        while status(self.status_file).get("generation", 0) < 1:
            if time.monotonic() > deadline or self.process.poll() is not None:
                raise RuntimeError((self.work / "engine.log").read_text()[-2000:])
            await asyncio.sleep(0.1)

    async def cpu_us(self, broker: Broker, count: int, deadline: float) -> float:
        began = process_cpu_seconds(self.process.pid)
        await broker.prefill_confirmed(self.queue, [body(seq) for seq in range(count)])
        while status(self.status_file).get("routes", {}).get("position", {}).get("delivered", 0) < count:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{self.mode}: stalled")
            await asyncio.sleep(0.05)
        return (process_cpu_seconds(self.process.pid) - began) / count * 1e6

    async def stop(self) -> None:
        if self.viewer is not None and self.viewer.ws is not None:
            await self.viewer.stop()
        self.process.terminate()
        await asyncio.to_thread(self.process.wait, 60)


async def one_round(url: str, work: Path, count: int, latency_count: int, rate: float) -> dict[str, dict[str, float]]:
    broker = Broker(url)
    await broker.open()
    engines = [Engine(url, work / mode, mode) for mode in MODES]
    try:
        for engine in engines:
            await broker.channel.queue_declare(engine.out, durable=True)
            await broker.channel.queue_purge(engine.out)
        deadline = time.monotonic() + 60
        await asyncio.gather(*(engine.started(deadline) for engine in engines))
        await asyncio.sleep(2)  # the same settling for all: the view's channels are made once the routes run
        for engine in engines:
            if engine.viewer is not None:
                await engine.viewer.start()
        costs = await asyncio.gather(*(engine.cpu_us(broker, count, deadline + 300) for engine in engines))
        latencies = await paced_latencies(url, engines, latency_count, rate, offset=count)
        results = {engine.mode: {"cpu_us": cost, "p50_ms": percentile(latencies[engine.mode], 0.5) * 1e3,
                                 "p99_ms": percentile(latencies[engine.mode], 0.99) * 1e3}
                   for engine, cost in zip(engines, costs)}
        for engine in engines:
            if engine.viewer is not None:
                results[engine.mode]["frames"] = engine.viewer.frames
        return results
    finally:
        for engine in engines:
            await engine.stop()
        await broker.close()


async def paced_latencies(url: str, engines: list[Engine], count: int, rate: float, offset: int) -> dict[str, list[float]]:
    """Seconds from publish to arrival of ``count`` messages sent at ``rate`` to every engine,
    each message to all of them back to back (the order turning), sorted, by mode."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    sent: dict[tuple[str, str], float] = {}
    arrived: dict[tuple[str, str], float] = {}
    done = asyncio.Event()

    def consumer(mode: str) -> Any:
        async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
            arrived[(mode, json.loads(message.body)["id"])] = time.monotonic()
            if len(arrived) >= count * len(engines):
                done.set()
        return on_message

    for engine in engines:
        queue = await channel.declare_queue(engine.out, durable=True)
        await queue.purge()
        await queue.consume(consumer(engine.mode), no_ack=True)
    began = time.monotonic()
    for index in range(count):
        seq = offset + index
        turn = index % len(engines)
        for engine in engines[turn:] + engines[:turn]:
            sent[(engine.mode, str(seq))] = time.monotonic()
            await channel.default_exchange.publish(aio_pika.Message(body(seq), content_type="application/json"), engine.queue)
        delay = began + (index + 1) / rate - time.monotonic()
        if delay > 0.0005:
            await asyncio.sleep(delay)
    await asyncio.wait_for(done.wait(), 60)
    await connection.close()
    return {engine.mode: sorted(arrived[key] - sent[key] for key in sent if key[0] == engine.mode and key in arrived)
            for engine in engines}


def percentile(values: list[float], fraction: float) -> float:
    return values[min(len(values) - 1, int(fraction * len(values)))]


def hot_path_us(count: int = 200_000) -> tuple[float, float]:
    """What ``RouteObserver.accepted`` costs per message, in process: with no watcher (no client
    subscribed) and with a route's channel watching (one serialisation and the SDK's log call)."""
    outbound = Outbound(body(1), json.loads(body(1)), {}, "m", {}, received_ns=1)
    observer = RouteObserver("bench")
    costs = []
    for watchers in ((), (RouteChannel("bench", "position.v1", {"type": "object"}, foxglove.Context()),)):
        observer.watchers = watchers
        began = time.process_time()  # CPU time: the machine is shared, wall time counts others' turns
        for _ in range(count):
            observer.accepted(None, outbound, 1000)
        costs.append((time.process_time() - began) / count * 1e6)
    return costs[0], costs[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=10_000)
    parser.add_argument("--latency-count", type=int, default=2_000)
    parser.add_argument("--rate", type=float, default=200.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    idle, watched = hot_path_us()
    print(f"hot path (RouteObserver.accepted, in process): {idle:.3f} us per message with no client, "
          f"{watched:.3f} us with the route's channel subscribed", flush=True)
    results: dict[str, list[dict[str, float]]] = {mode: [] for mode in MODES}
    with LocalBroker() as broker, tempfile.TemporaryDirectory() as directory:
        for index in range(args.rounds):
            round_results = asyncio.run(one_round(broker.url, Path(directory) / str(index), args.count, args.latency_count, args.rate))
            plain = round_results["plain"]
            for mode in MODES:
                result = round_results[mode]
                result["cpu_ratio"] = result["cpu_us"] / plain["cpu_us"] - 1
                result["p99_ratio"] = result["p99_ms"] / plain["p99_ms"] - 1
                results[mode].append(result)
                print(f"round {index}: {mode:10} {result['cpu_us']:7.1f} us CPU per message ({result['cpu_ratio']:+.1%}), "
                      f"latency p50 {result['p50_ms']:6.2f} ms p99 {result['p99_ms']:6.2f} ms ({result['p99_ratio']:+.1%})"
                      + (f", {result['frames']:.0f} frames to the client" if "frames" in result else ""), flush=True)
    for mode in MODES:
        m = {key: statistics.median(r[key] for r in results[mode]) for key in ("cpu_us", "p50_ms", "p99_ms", "cpu_ratio", "p99_ratio")}
        print(f"median {mode:10}: {m['cpu_us']:6.1f} us CPU per message (per round against plain: {m['cpu_ratio']:+.1%}), "
              f"p50 {m['p50_ms']:.2f} ms, p99 {m['p99_ms']:.2f} ms ({m['p99_ratio']:+.1%})")
    print(f"({os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})")

if __name__ == "__main__":
    main()
