"""``python -m bench``: every measurement of issue 10 in one run, written to bench/results/<date>/.

Starts a private RabbitMQ node, runs each section (the paper's latency method, CT-L1 at 100
and 200 msg/s against the paper's design re-implemented (bench/ct_l1.py), the
throughput of each route kind against its reference pass-through and the paper's design in
interleaved rounds (bench/throughput.py),
latency at half that rate, throughput against message size, 1/100/1,000 routes, JSON over
the emulated SiK radio at 0 and 5 % loss, ROS 2 topic discovery latency for 20 robots, the round trip of a ROS 2
service call from AMQP next to a plain rclpy client, a fleet of 100 agents (bench/fleet.py), MAVLink latency over
the radio against MAVSDK as the ground station, a 20-waypoint mission uploaded by the engine, pymavlink and MAVSDK,
to the simulated vehicle and to MAVSDK's own behind the radio, a backlog drained by 1 and 2 engine workers (bench/bench_workers.py)) and writes
``results.json``, ``report.md`` (the paper's table format
plus p50/p99) and PNG plots. Throughput is reported as ratios measured in the same run: the
machine is shared, absolute numbers move with its load (recorded in the report).

    .venv/bin/python -m bench                      # everything, about 6-10 minutes
    .venv/bin/python -m bench --rate 1             # the paper's 1 msg/s for the latency method (+25 min)
    .venv/bin/python -m bench --only throughput,routes --count 3000
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import math
import os
import subprocess
import time
import traceback
from pathlib import Path
from typing import Any

from bench import bench_discovery, bench_workers, call_ros2, ct_l1, fleet, mission_upload, radio_latency, sections
from bench import throughput as tp
from bench.report import write_report

REPO = Path(__file__).resolve().parent.parent
SECTIONS = ("latency", "ct_l1", "throughput", "sizes", "routes", "sik", "discovery", "sik5", "calls", "fleet", "radio_latency", "mission", "workers")
KINDS = {
    "amqp-amqp": ("ref-amqp-amqp", None),
    "amqp-ros2": ("ref-amqp-ros2", "paper-amqp-ros2"),
    "ros2-amqp": ("ref-ros2-amqp", "paper-ros2-amqp"),
    "mavlink-amqp": ("ref-mavlink-amqp", None),
}


def machine() -> dict[str, Any]:
    from engine.running.loop import loop_name

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "commit": commit, "cpus": os.cpu_count(), "loadavg": os.getloadavg(), "loop": loop_name()}


async def throughput(broker: tp.Broker, count: int, pairs: int, half_rate_s: float,
                     kinds: list[str] | None = None) -> dict[str, Any]:
    """Each route kind: ``pairs`` interleaved rounds of reference, engine (and the paper's
    design) draining the same backlog (bench/throughput.py ``interleaved``), then the engine's
    latency at half its median rate."""
    out: dict[str, Any] = {}
    domain, count = tp.domain_id(), min(count, tp.MAX_BURST)
    for kind, (reference, paper) in KINDS.items():
        if kinds and kind not in kinds:
            continue
        systems = {"reference": reference, "engine": "engine", **({"paper": paper} if paper else {})}
        row = await tp.interleaved(broker, kind, systems, pairs, count, domain, counts={"paper": count // 6})
        engine_rate = row["engine"].get("msg_per_s", float("nan"))
        if math.isfinite(engine_rate) and engine_rate > 0:
            print(f"  {kind}: latency at half rate ({engine_rate / 2:.0f} msg/s)", flush=True)
            try:
                row["latency_half_rate"] = await tp.engine_latency_at_rate(broker, kind, engine_rate / 2, half_rate_s, domain)
            except Exception as exc:
                row["latency_half_rate"] = {"error": f"{type(exc).__name__}: {exc}"[:2000]}
        out[kind] = row
    return out


async def run(args: argparse.Namespace) -> Path:
    from engine.endpoints.amqp.broker import LocalBroker

    only = set(args.only.split(",")) if args.only else set(SECTIONS)
    out_dir = Path(args.out) if args.out else REPO / "bench" / "results" / datetime.date.today().isoformat()
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"machine_before": machine(), "settings": vars(args)}
    began = time.monotonic()
    node = LocalBroker()
    url = await asyncio.to_thread(node.start)
    broker = tp.Broker(url)
    await broker.open()
    steps = [
        ("latency", lambda: sections.paper_latency(url, args.rate, args.runs, 100)),
        ("ct_l1", lambda: ct_l1.measure(url, tp.domain_id(), [100.0, 200.0], 1000, 3)),
        ("throughput", lambda: throughput(broker, args.count, args.pairs, args.half_rate_seconds,
                                                 args.kinds.split(",") if args.kinds else None)),
        ("sizes", lambda: sections.throughput_by_size(broker, [50, 250, 1000, 4000], args.count)),
        ("routes", lambda: sections.many_routes(broker, [1, 100, 1000], args.count)),
        ("sik", lambda: sections.sik_goodput(url, args.sik_count, 250)),
        ("discovery", lambda: bench_discovery.measure(url, tp.domain_id())),
        ("sik5", lambda: sections.sik_goodput(url, args.sik_count, 250, loss=0.05)),
        ("calls", lambda: call_ros2.measure(url, tp.domain_id(), args.calls)),
        ("fleet", lambda: fleet.fleet(None, ["reference", "templated", "shared", "hand_written"], duration=args.fleet_seconds)),
        ("radio_latency", lambda: radio_latency.run(url, 8.0)),
        ("mission", lambda: asyncio.to_thread(mission_upload.run, [20], [0.0, 0.05], args.mission_repeat)),
        ("workers", lambda: bench_workers.measure(url, args.workers_count, args.workers_rounds,
                                                  node._process.pid if node._process is not None else 0)),
    ]
    try:
        for name, step in steps:
            if name not in only:
                continue
            print(f"[{time.monotonic() - began:5.0f}s] {name}", flush=True)
            try:
                results[name] = await step()
            except Exception as exc:
                traceback.print_exc()
                results[name] = {"error": f"{type(exc).__name__}: {exc}"[:3000]}
            (out_dir / "results.json").write_text(json.dumps(results, indent=1, default=str))
    finally:
        await broker.close()
        await asyncio.to_thread(node.stop)
    results["machine_after"] = machine()
    results["seconds"] = time.monotonic() - began
    (out_dir / "results.json").write_text(json.dumps(results, indent=1, default=str))
    write_report(results, out_dir)
    print(f"[{results['seconds']:5.0f}s] wrote {out_dir}/report.md", flush=True)
    return out_dir


def main() -> None:
    from engine.running.loop import run as run_loop

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate", type=float, default=100.0, help="msg/s of the latency method (the paper: 1)")
    parser.add_argument("--runs", type=int, default=5, help="runs per size of the latency method")
    parser.add_argument("--count", type=int, default=6000,
                        help="messages per throughput drain (well above the prefetch of 1,000; at most 9,000: "
                             "a ROS 2 burst must fit DDS history, a MAVLink one the socket's buffer)")
    parser.add_argument("--pairs", type=int, default=5,
                        help="interleaved rounds per route kind of the throughput section (reference, engine, paper)")
    parser.add_argument("--half-rate-seconds", type=float, default=4.0)
    parser.add_argument("--sik-count", type=int, default=400,
                        help="250-byte messages through the emulated SiK radio (the link's fill and drain, a few "
                             "seconds, weigh less the more there are)")
    parser.add_argument("--calls", type=int, default=500,
                        help="ROS 2 service calls, one at a time, through the engine and by a plain rclpy client")
    parser.add_argument("--fleet-seconds", type=float, default=60.0,
                        help="seconds of the fleet's load (bench/fleet.py), each way of writing its routes")
    parser.add_argument("--mission-repeat", type=int, default=2,
                        help="uploads of the 20-waypoint mission per client, vehicle and loss (about 25 s each round)")
    parser.add_argument("--workers-count", type=int, default=20_000, help="messages per drain of the workers section (1 and 2 workers)")
    parser.add_argument("--workers-rounds", type=int, default=4, help="rounds of the workers section, each a drain with 1 and with 2 workers")
    parser.add_argument("--kinds", help=f"comma-separated route kinds of the throughput section ({', '.join(KINDS)}; default all)")
    parser.add_argument("--only", help=f"comma-separated sections of {', '.join(SECTIONS)}")
    parser.add_argument("--out", help="output directory (default bench/results/<date>)")
    parser.add_argument("--report-only", help="rewrite report.md and plots from this results.json")
    args = parser.parse_args()
    if args.report_only:
        path = Path(args.report_only)
        write_report(json.loads(path.read_text()), path.parent)
        return
    run_loop(run(args))


if __name__ == "__main__":
    main()
