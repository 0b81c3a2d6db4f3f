"""A fleet on one ``udpin`` link with ``split_over_workers``, through 1 and 2 workers in one run
(issue 34; engine/endpoints/mavlink/split.py).

``python -m bench.bench_mavlink_split [--vehicles 40] [--rate 10] [--seconds 20] [--rounds 2]``:
a private RabbitMQ node; ``vehicles`` simulated vehicles (pymavlink, one child process), each
from its own UDP socket, send GLOBAL_POSITION_INT at ``rate`` Hz and a HEARTBEAT at 1 Hz to one
``udpin`` link; one route carries the positions to RabbitMQ (``{vehicle, seq, lat}``, routing
key per vehicle), published with confirms. Each round runs ``run --workers 1`` and
``--workers 2`` (the order alternating from round to round), each for ``seconds`` after a
warm-up; the figure is the CPU seconds of each process of the engine (supervisor, workers)
over the measured span, per message carried, and the messages lost (sent by the vehicles in
the span minus arrived at the sink queue, over the whole run once the sink is drained).
This machine has 2 cores shared with the broker and the vehicles' process: the ratio says
where the time goes, not what a larger machine would carry.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import socket
import statistics
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench.bench_workers import BROKER_GROUP, EngineRun, group_cpu_seconds
from bench.throughput import Broker, process_cpu_seconds

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  fleet: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 1, split_over_workers: true}}
routes:
  - name: position
    source: {{mavlink: {{connection: fleet, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{vehicle: meta('system_id'), seq: time_boot_ms, lat: lat}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {exchange}, routing_key: "uav.{{vehicle}}"}}}}
"""


def fly(port: int, vehicles: int, rate: float, stop: Any, sent: Any) -> None:
    """The vehicles (a child process): each its own socket, positions at ``rate`` Hz, a HEARTBEAT a second."""
    from pymavlink.dialects.v20 import common as mavlink2

    fleet = []
    for system in range(1, vehicles + 1):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        fleet.append((mavlink2.MAVLink(None, srcSystem=system, srcComponent=1), sock))
    started, tick = time.monotonic(), 0
    while not stop.is_set():
        for mav, sock in fleet:
            frames = [mav.global_position_int_encode(tick, -220000000, -479000000, 10000, 5000, 0, 0, 0, 0)]
            if tick % max(1, round(rate)) == 0:
                frames.append(mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC, 0, 0,
                                                   mavlink2.MAV_STATE_STANDBY))
            for frame in frames:
                try:
                    sock.sendto(frame.pack(mav), ("127.0.0.1", port))
                except OSError:
                    pass
        tick += 1
        sent.value = tick * vehicles
        time.sleep(max(0.0, started + tick / rate - time.monotonic()))


async def connected(status_file: Path, workers: int, timeout: float = 60.0) -> None:
    """Until every other worker is connected to the worker holding the link (its status says so)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            docs = [w.get("status") or {} for w in json.loads(status_file.read_text()).get("workers", [])]
            splits = [d.get("connections", {}).get("fleet", {}).get("split") for d in docs]
            if splits and None not in splits:
                owner = splits[0]["owner"]
                if splits[owner]["connected"] == [k for k in range(workers) if k != owner]:
                    return
        except (OSError, ValueError, KeyError):
            pass
        await asyncio.sleep(0.2)
    raise RuntimeError("the workers did not connect to the link's holder")


async def one_run(broker: Broker, workers: int, vehicles: int, rate: float, seconds: float) -> dict[str, Any]:
    tag = uuid.uuid4().hex[:8]
    exchange, sink = f"split-out-{tag}", f"split-sink-{tag}"
    await broker.channel.exchange_declare(exchange, exchange_type="topic", durable=True)
    await broker.channel.queue_declare(sink, durable=True)
    await broker.channel.queue_bind(sink, exchange, routing_key="#")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    context = multiprocessing.get_context("spawn")
    stop, sent = context.Event(), context.Value("q", 0)
    try:
        with tempfile.TemporaryDirectory() as work:
            routes = Path(work) / "routes"
            routes.mkdir()
            (routes / "fleet.yaml").write_text(ROUTES.format(url=broker.url, port=port, exchange=exchange))
            engine = EngineRun(routes, workers, Path(work), stats_interval=1.0)
            flying = context.Process(target=fly, args=(port, vehicles, rate, stop, sent), daemon=True)
            try:
                pids = await engine.running()
                processes = [engine.process.pid, *(pid for pid in pids if pid != engine.process.pid)]
                if workers > 1:
                    await connected(engine.status_file, workers)
                flying.start()
                await asyncio.sleep(3.0)  # warm-up: every vehicle heard, the routes' first batches
                before = ([process_cpu_seconds(pid) for pid in processes], group_cpu_seconds(BROKER_GROUP[0]),
                          await broker.count(sink), sent.value, time.monotonic())
                await asyncio.sleep(seconds)
                after = ([process_cpu_seconds(pid) for pid in processes], group_cpu_seconds(BROKER_GROUP[0]),
                         await broker.count(sink), sent.value, time.monotonic())
                stop.set()
                flying.join(10)
                total, last_change, last = sent.value, time.monotonic(), -1
                while time.monotonic() - last_change < 3.0:  # the sink drained: nothing more arrives
                    seen = await broker.count(sink)
                    if seen != last:
                        last, last_change = seen, time.monotonic()
                    await asyncio.sleep(0.1)
                status = json.loads(engine.status_file.read_text())
            finally:
                stop.set()
                exit_code = await engine.stop()
    finally:
        await broker.channel.queue_delete(sink)
    carried = after[2] - before[2]
    cpu = [round(b - a, 2) for a, b in zip(before[0], after[0])]
    names = ["engine"] if workers == 1 else ["supervisor", *(f"worker {k}" for k in range(workers))]
    counters = status.get("connections", {}).get("fleet", {}).get("counters", {})
    return {"workers": workers, "seconds": round(after[4] - before[4], 2), "carried": carried,
            "msg_per_s": round(carried / (after[4] - before[4]), 1), "sent": total, "arrived": last, "lost": total - last,
            "cpu_s_by_process": dict(zip(names, cpu)), "broker_cpu_s": round(after[1] - before[1], 2),
            "cpu_us_per_msg": round(sum(cpu) * 1e6 / carried, 1) if carried else float("nan"),
            "split_handed": counters.get("split_handed"), "split_dropped": counters.get("split_dropped"), "exit": exit_code}


async def measure(url: str, vehicles: int, rate: float, seconds: float, rounds: int, broker_group: int) -> dict[str, Any]:
    BROKER_GROUP[0] = broker_group
    broker = Broker(url)
    await broker.open()
    runs: list[dict[str, Any]] = []
    try:
        for round_index in range(rounds):
            for workers in ((1, 2) if round_index % 2 == 0 else (2, 1)):
                result = await one_run(broker, workers, vehicles, rate, seconds)
                print(f"  round {round_index + 1}, {workers} worker(s): {result}", flush=True)
                runs.append(result)
    finally:
        await broker.close()
    per_msg = {k: statistics.median(r["cpu_us_per_msg"] for r in runs if r["workers"] == k) for k in (1, 2)}
    busiest = {k: statistics.median(max(v for name, v in r["cpu_s_by_process"].items() if name != "supervisor") / r["seconds"]
                                    for r in runs if r["workers"] == k) for k in (1, 2)}
    return {"vehicles": vehicles, "rate_hz": rate, "seconds": seconds, "rounds": rounds, "runs": runs,
            "median_cpu_us_per_msg": per_msg, "median_busiest_process_cores": busiest,
            "lost": sum(r["lost"] for r in runs), "cpus": os.cpu_count(), "loadavg": os.getloadavg()}


def report(result: dict[str, Any]) -> list[str]:
    lines = [f"{result['vehicles']} vehicles at {result['rate_hz']:g} Hz on one udpin link with split_over_workers, "
             f"{result['seconds']:g} s measured a run, {result['rounds']} rounds; {result['cpus']} CPUs, load average "
             f"{'/'.join(f'{x:.1f}' for x in result['loadavg'])} after.", "",
             "| round | workers | msg/s | lost | CPU s by process | broker CPU s | engine µs/msg | handed on |",
             "|---|---|---|---|---|---|---|---|"]
    for index, run in enumerate(result["runs"]):
        cpu = ", ".join(f"{name} {seconds}" for name, seconds in run["cpu_s_by_process"].items())
        lines.append(f"| {index // 2 + 1} | {run['workers']} | {run['msg_per_s']} | {run['lost']} | {cpu} | {run['broker_cpu_s']} | "
                     f"{run['cpu_us_per_msg']} | {run['split_handed']} |")
    per_msg, busiest = result["median_cpu_us_per_msg"], result["median_busiest_process_cores"]
    lines += ["", f"Median engine CPU per message: 1 worker {per_msg[1]} µs, 2 workers {per_msg[2]} µs; the busiest "
              f"process: 1 worker {busiest[1]:.2f} of a core, 2 workers {busiest[2]:.2f}; lost {result['lost']}.", ""]
    return lines


def main() -> None:
    from engine.endpoints.amqp.broker import LocalBroker

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, default=40)
    parser.add_argument("--rate", type=float, default=10.0, help="positions per second per vehicle")
    parser.add_argument("--seconds", type=float, default=20.0, help="measured seconds a run")
    parser.add_argument("--rounds", type=int, default=2, help="pairs of runs (1 and 2 workers)")
    parser.add_argument("--out", type=Path, help="write the results as JSON to this file")
    args = parser.parse_args()
    with LocalBroker() as node:
        group = node._process.pid if node._process is not None else 0
        result = asyncio.run(measure(node.url, args.vehicles, args.rate, args.seconds, args.rounds, group))
    print("\n".join(report(result)))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
