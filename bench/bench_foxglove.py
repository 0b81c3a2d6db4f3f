"""Cost of ``--foxglove`` (issue 33: with no client, nothing measurable; with a client
subscribed to every channel, route latency p99 within 10 % of without).

The engine as a child process on a private RabbitMQ node, one route (AMQP queue -> position
mapping -> ``position`` schema -> AMQP queue), in three modes: ``plain`` (no ``--foxglove``),
``view`` (``--foxglove``, no client) and ``subscribed`` (a ``websockets`` client subscribed to
the route's channel, ``/fleet`` and ``/routes/status``, reading every frame). Each round runs
the modes one after the other on the same broker, so the machine's load moves them alike; the
medians of the rounds are reported. Per mode and round:

- CPU: COUNT messages published at once (confirmed), the engine's CPU time (user + system,
  every thread: the SDK's server threads included) from before the first to the last delivered,
  per message;
- latency: LATENCY_COUNT messages published at RATE per second, each timed from its publish to
  its arrival in the output queue (this process holds both clocks), p50 and p99. In
  ``subscribed`` the client unsubscribes and subscribes again every second, so the same run
  also gives the latency without a subscriber, under the same load (a shared machine's load
  moves between runs far more than the view could).

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
        self.ws = await websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=["foxglove.sdk.v1"])  # type: ignore[list-item]
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

    async def unsubscribe(self) -> None:
        await self.ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": list(range(len(self.channels)))}))

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


async def one_round(url: str, work: Path, mode: str, count: int, latency_count: int, rate: float) -> dict[str, float]:
    routes = work / "routes"
    routes.mkdir(exist_ok=True)
    (routes / "bench.yaml").write_text(routes_yaml(url, "fox-in", "fox-out"))
    status_file = work / "status.json"
    port = listening_port()
    extra = [] if mode == "plain" else ["--foxglove", str(port)]
    broker = Broker(url)
    await broker.open()
    await broker.channel.queue_declare("fox-out", durable=True)
    await broker.channel.queue_purge("fox-out")
    with open(work / "engine.log", "w") as log:
        engine = subprocess.Popen([sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", str(REPO / "schemas"),
                                   "--status-file", str(status_file), "--stats-interval", "0.2", *extra],
                                  cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    viewer = Viewer(port) if mode == "subscribed" else None
    try:
        deadline = time.monotonic() + 60
        while status(status_file).get("generation", 0) < 1:
            if time.monotonic() > deadline or engine.poll() is not None:
                raise RuntimeError((work / "engine.log").read_text()[-2000:])
            await asyncio.sleep(0.1)
        await asyncio.sleep(2)  # the same settling in every mode: the view's channels are made once the routes run
        if viewer is not None:
            await viewer.start()
        began = process_cpu_seconds(engine.pid)
        await broker.prefill_confirmed("fox-in", [body(seq) for seq in range(count)])
        while status(status_file).get("routes", {}).get("position", {}).get("delivered", 0) < count:
            if time.monotonic() > deadline + 300:
                raise RuntimeError("stalled")
            await asyncio.sleep(0.05)
        cpu_us = (process_cpu_seconds(engine.pid) - began) / count * 1e6
        latencies = await paced_latencies(url, latency_count, rate, offset=count, viewer=viewer)
        result = {"cpu_us": cpu_us, "p50_ms": percentile(latencies[True], 0.5) * 1e3,
                  "p99_ms": percentile(latencies[True], 0.99) * 1e3}
        if viewer is not None:
            result["frames"] = viewer.frames
            result["off_p50_ms"] = percentile(latencies[False], 0.5) * 1e3
            result["off_p99_ms"] = percentile(latencies[False], 0.99) * 1e3
        return result
    finally:
        if viewer is not None:
            await viewer.stop()
        engine.terminate()
        engine.wait(60)
        await broker.close()


async def paced_latencies(url: str, count: int, rate: float, offset: int, viewer: Viewer | None = None) -> dict[bool, list[float]]:
    """Seconds from publish to arrival in ``fox-out`` of ``count`` messages sent at ``rate``.
    With a ``viewer``, it unsubscribes and subscribes again every second: the latencies while
    subscribed (``True``) and not (``False``) come from the same minutes of the same engine,
    so the machine's load (other work on a shared machine) moves both alike; messages sent
    within 0.1 s of a switch are left out."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    queue = await channel.declare_queue("fox-out", durable=True)
    await queue.purge()
    sent: dict[str, float] = {}
    subscribed: dict[str, bool | None] = {}
    arrived: dict[str, float] = {}
    state, switched = True, time.monotonic()
    done = asyncio.Event()

    async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
        arrived[json.loads(message.body)["id"]] = time.monotonic()
        if len(arrived) >= count:
            done.set()

    await queue.consume(on_message, no_ack=True)
    began = time.monotonic()
    for index in range(count):
        seq = offset + index
        now = time.monotonic()
        if viewer is not None and now - switched >= 1.0:
            state, switched = not state, now
            await (viewer.subscribe() if state else viewer.unsubscribe())
        sent[str(seq)] = now
        subscribed[str(seq)] = state if viewer is None or now - switched >= 0.1 else None
        await channel.default_exchange.publish(aio_pika.Message(body(seq), content_type="application/json"), "fox-in")
        delay = began + (index + 1) / rate - time.monotonic()
        if delay > 0.0005:
            await asyncio.sleep(delay)
    await asyncio.wait_for(done.wait(), 60)
    await connection.close()
    if viewer is not None and not state:
        await viewer.subscribe()
    return {flag: sorted(arrived[key] - sent[key] for key in sent if key in arrived and subscribed[key] is flag)
            for flag in (True, False)}


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
            for mode in MODES:
                work = Path(directory) / f"{index}-{mode}"
                work.mkdir()
                result = asyncio.run(one_round(broker.url, work, mode, args.count, args.latency_count, args.rate))
                results[mode].append(result)
                print(f"round {index}: {mode:10} {result['cpu_us']:7.1f} us CPU per message, latency p50 "
                      f"{result['p50_ms']:6.2f} ms p99 {result['p99_ms']:6.2f} ms"
                      + (f" subscribed; p50 {result['off_p50_ms']:6.2f} ms p99 {result['off_p99_ms']:6.2f} ms in the "
                         f"seconds between, unsubscribed; {result['frames']} frames to the client" if "frames" in result else ""),
                      flush=True)
    medians = {mode: {key: statistics.median(r[key] for r in results[mode]) for key in ("cpu_us", "p50_ms", "p99_ms")}
               for mode in MODES}
    plain = medians["plain"]
    for mode in MODES:
        m = medians[mode]
        print(f"median {mode:10}: {m['cpu_us']:6.1f} us CPU per message ({m['cpu_us'] / plain['cpu_us'] - 1:+.1%}), "
              f"p50 {m['p50_ms']:.2f} ms, p99 {m['p99_ms']:.2f} ms ({m['p99_ms'] / plain['p99_ms'] - 1:+.1%})")
    alternating = {key: statistics.median(r[key] for r in results["subscribed"]) for key in ("p99_ms", "off_p99_ms")}
    print(f"same engine, alternating each second: p99 subscribed {alternating['p99_ms']:.2f} ms, unsubscribed "
          f"{alternating['off_p99_ms']:.2f} ms ({alternating['p99_ms'] / alternating['off_p99_ms'] - 1:+.1%})")
    print(f"({os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
