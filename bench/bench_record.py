"""Cost of ``--record`` (issue 33, goal: at most 10 % more engine CPU per message).

Two engines as child processes on one private RabbitMQ node, each with one route (AMQP queue ->
position mapping -> ``position`` schema -> AMQP queue) on queues of its own, one without and one
with ``--record``, run at the same time: COUNT messages published to each at once; each engine's
CPU time (user + system, every thread: the writer thread's serialisation, zstd and writes
included) from before the first message to when the last was delivered and, under ``--record``,
written (status ``recording.written`` = 2 x COUNT). Running both in the same seconds puts the
machine's load (a shared machine's other work) on both alike; one engine after the other, the
plain engine alone moved from 67 to 96 us a message within one session, more than the effect
measured. Per round the ratio of the two; the medians of the rounds and of the ratios are
reported. Beside it, in process: the hot-path part alone
(what the route itself pays per message: ``RouteRecording.received`` + ``sent``, two deque
appends) and the whole recording of a message (those appends and the writer thread's
serialisation, the SDK's ``log`` of the input and of the canonical message, zstd and the file
writes: the process's CPU time over COUNT messages until all are written).

    .venv/bin/python -m bench.bench_record [--count 20000] [--rounds 3]
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

from bench.position_route import body, routes_yaml, status
from bench.throughput import Broker, process_cpu_seconds
from engine.endpoints.amqp.broker import LocalBroker
from engine.endpoints.base import Inbound, Outbound
from engine.running.record import Recorder, RecordLimits

REPO = Path(__file__).resolve().parent.parent


class Engine:
    """One engine of a round: its own queues on the shared broker, with or without ``--record``."""

    def __init__(self, url: str, work: Path, record: bool) -> None:
        self.work, self.record = work, record
        self.queue = f"rec-in-{'record' if record else 'plain'}"
        routes = work / "routes"
        routes.mkdir(parents=True, exist_ok=True)
        (routes / "bench.yaml").write_text(routes_yaml(url, self.queue, f"rec-out-{'record' if record else 'plain'}"))
        self.status_file = work / "status.json"
        extra = ["--record", str(work / "rec")] if record else []
        with open(work / "engine.log", "w") as log:
            self.process = subprocess.Popen([sys.executable, "-m", "engine", "--routes", str(routes), "--schemas",
                                             str(REPO / "schemas"), "--status-file", str(self.status_file),
                                             "--stats-interval", "0.2", *extra],
                                            cwd=REPO, stdout=log, stderr=subprocess.STDOUT)

    async def started(self, deadline: float) -> None:
        while status(self.status_file).get("generation", 0) < 1:
            if time.monotonic() > deadline or self.process.poll() is not None:
                raise RuntimeError((self.work / "engine.log").read_text()[-2000:])
            await asyncio.sleep(0.1)

    async def run(self, broker: Broker, count: int, deadline: float) -> float:
        """Engine CPU microseconds per message: COUNT published, until all delivered (and written)."""
        began = process_cpu_seconds(self.process.pid)
        await broker.prefill_confirmed(self.queue, [body(seq) for seq in range(count)])
        while True:
            current = status(self.status_file)
            route = current.get("routes", {}).get("position", {})
            written = current.get("recording", {}).get("written", 2 * count) if self.record else 2 * count
            if route.get("delivered", 0) >= count and written >= 2 * count:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"stalled: {route}")
            await asyncio.sleep(0.05)
        used = process_cpu_seconds(self.process.pid) - began
        if current.get("recording", {}).get("dropped", 0):
            print(f"  (recording dropped {current['recording']['dropped']} copies)")
        return used / count * 1e6

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(60)


async def one_round(url: str, work: Path, count: int) -> dict[bool, float]:
    """Both engines at once, the same traffic at the same time: the machine's load (a shared
    machine's other work) falls on both alike, which rounds one after the other never gave
    (plain runs of 67 to 96 us in one session). Engine CPU us per message, by ``--record``."""
    broker = Broker(url)
    await broker.open()
    engines = {record: Engine(url, work / ("record" if record else "plain"), record) for record in (False, True)}
    try:
        for record in engines:
            await broker.channel.queue_declare(f"rec-out-{'record' if record else 'plain'}", durable=True)
            await broker.channel.queue_purge(f"rec-out-{'record' if record else 'plain'}")
        deadline = time.monotonic() + 60
        await asyncio.gather(*(engine.started(deadline) for engine in engines.values()))
        costs = await asyncio.gather(*(engine.run(broker, count, deadline + 300) for engine in engines.values()))
        return dict(zip(engines, costs))
    finally:
        for engine in engines.values():
            engine.stop()
        await broker.close()


def hot_path_us(count: int = 200_000) -> float:
    """What the route pays per message while recording: the two appends, the writer not running."""
    recorder = Recorder(Path(tempfile.mkdtemp()), RecordLimits(queue=2 * count + 1))
    recording = recorder.route("bench", "position", {"type": "object"})
    inbounds = [(Inbound(body=body(seq)),) for seq in range(1000)]
    outbound = Outbound(b"{}", {}, {}, "m", {}, received_ns=1)
    began = time.process_time()  # CPU time: the machine is shared, wall time counts others' turns
    for index in range(count):
        recording.received(inbounds[index % 1000])
        recording.sent(outbound)
    return (time.process_time() - began) / count * 1e6


def recording_us(count: int = 50_000) -> float:
    """What recording costs the process per message, route side and writer thread together."""
    limits = RecordLimits(queue=2 * count + 1)
    recorder = Recorder(Path(tempfile.mkdtemp()), limits)
    recording = recorder.route("bench", "position", {"type": "object"})
    inbounds = [Inbound(body=body(seq), meta={"routing_key": "position"}) for seq in range(count)]
    outbounds = [Outbound(inbound.body or b"", {}, {}, "m", {}, received_ns=inbound.received_ns) for inbound in inbounds]
    began = time.process_time()  # every thread of the process: the writer's work included
    recorder.start()
    for inbound, outbound in zip(inbounds, outbounds):
        recording.received((inbound,))
        recording.sent(outbound)
    recorder.stop()  # drains the queue and closes the file
    used = time.process_time() - began
    assert recorder.written == 2 * count, recorder.status()
    return used / count * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=20_000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    print(f"hot path (route side, in process): {hot_path_us():.3f} us per message")
    print(f"recording (route side and writer thread, in process): {recording_us():.2f} us per message", flush=True)
    results: dict[bool, list[float]] = {False: [], True: []}
    with LocalBroker() as broker, tempfile.TemporaryDirectory() as directory:
        for index in range(args.rounds):
            work = Path(directory) / str(index)
            costs = asyncio.run(one_round(broker.url, work, args.count))
            for record, cost in costs.items():
                results[record].append(cost)
            size = sum(f.stat().st_size for f in (work / "record" / "rec").glob("*.mcap"))
            print(f"round {index}: plain {costs[False]:6.1f} us, --record {costs[True]:6.1f} us CPU per message "
                  f"({costs[True] / costs[False] - 1:+.1%}), {size / args.count:.0f} bytes per message on disk", flush=True)
    plain, recorded = statistics.median(results[False]), statistics.median(results[True])
    ratios = [with_ / without - 1 for without, with_ in zip(results[False], results[True])]
    print(f"median: plain {plain:.1f} us, --record {recorded:.1f} us per message: {recorded / plain - 1:+.1%} CPU; "
          f"per round {', '.join(f'{r:+.0%}' for r in ratios)}, median {statistics.median(ratios):+.1%} "
          f"({os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
