"""Cost of ``--record`` (issue 33, goal: at most 10 % more engine CPU per message).

The engine as a child process on a private RabbitMQ node, one route (AMQP queue -> position
mapping -> ``position`` schema -> AMQP queue), COUNT messages published once the engine runs;
the engine's CPU time (user + system, every thread: the writer thread's serialisation, zstd and
writes included) from before the first message to when the last was delivered and, under
``--record``, written (status ``recording.written`` = 2 x COUNT). Rounds alternate without and
with ``--record`` on the same broker, so the machine's load moves both alike; the median of the
rounds is reported. Beside it, the hot-path part alone: what the route itself pays per message
(``RouteRecording.received`` + ``sent``: two deque appends), in process.

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


async def one_round(url: str, work: Path, count: int, record: bool) -> float:
    """Engine CPU microseconds per message for one run."""
    routes = work / "routes"
    routes.mkdir(exist_ok=True)
    (routes / "bench.yaml").write_text(routes_yaml(url, "rec-in", "rec-out"))
    status_file = work / "status.json"
    status_file.unlink(missing_ok=True)
    extra = ["--record", str(work / "rec")] if record else []
    broker = Broker(url)
    await broker.open()
    await broker.channel.queue_declare("rec-out", durable=True)
    await broker.channel.queue_purge("rec-out")
    with open(work / "engine.log", "w") as log:
        engine = subprocess.Popen([sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", str(REPO / "schemas"),
                                   "--status-file", str(status_file), "--stats-interval", "0.2", *extra],
                                  cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while status(status_file).get("generation", 0) < 1:
            if time.monotonic() > deadline or engine.poll() is not None:
                raise RuntimeError((work / "engine.log").read_text()[-2000:])
            await asyncio.sleep(0.1)
        began = process_cpu_seconds(engine.pid)
        await broker.prefill_confirmed("rec-in", [body(seq) for seq in range(count)])
        while True:
            current = status(status_file)
            route = current.get("routes", {}).get("position", {})
            written = current.get("recording", {}).get("written", 2 * count) if record else 2 * count
            if route.get("delivered", 0) >= count and written >= 2 * count:
                break
            if time.monotonic() > deadline + 300:
                raise RuntimeError(f"stalled: {route}")
            await asyncio.sleep(0.05)
        used = process_cpu_seconds(engine.pid) - began
        dropped = current.get("recording", {}).get("dropped", 0)
        if dropped:
            print(f"  (recording dropped {dropped} copies)")
        return used / count * 1e6
    finally:
        engine.terminate()
        engine.wait(60)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=20_000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    print(f"hot path (route side, in process): {hot_path_us():.3f} us per message")
    results: dict[bool, list[float]] = {False: [], True: []}
    with LocalBroker() as broker, tempfile.TemporaryDirectory() as directory:
        for index in range(args.rounds):
            for record in (False, True):
                work = Path(directory) / f"{index}-{record}"
                work.mkdir()
                per_message = asyncio.run(one_round(broker.url, work, args.count, record))
                results[record].append(per_message)
                size = sum(f.stat().st_size for f in (work / "rec").glob("*.mcap")) if record else 0
                print(f"round {index}: {'--record' if record else 'plain   '} {per_message:7.1f} us CPU per message"
                      + (f", {size / args.count:.0f} bytes per message on disk" if record else ""), flush=True)
    plain, recorded = statistics.median(results[False]), statistics.median(results[True])
    print(f"median: plain {plain:.1f} us, --record {recorded:.1f} us per message: {recorded / plain - 1:+.1%} CPU "
          f"({os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
