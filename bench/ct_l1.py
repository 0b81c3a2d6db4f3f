"""CT-L1 at a robot's pace: the engine against the paper's design, on this machine, in one run.

The paper measured CT-L1 (AMQP -> ROS 2: reception by the bridge to acceptance by ROS 2,
t2 - t1) at 0.11 ms with its own bridge. A published figure from another machine says
nothing about ours, so the paper's design is re-implemented (bench/systems.py
``paper-amqp-ros2``: aio-pika, a consume callback per message, hand-written conversion,
``jsonschema`` validation, rclpy publish, a log line per message) and measured beside the
engine here, the same way:

* both run in a child process of their own, on the same broker, topic and QoS (reliable,
  transient local), publishing the canonical position as ``std_msgs/String``;
* t1 is when the client library hands the message over (aiormq's delivery callback for the
  engine, aio-pika's ``on_message`` for the paper's design), t2 when ``publish`` returned and
  the message is accepted; both on ``time.monotonic_ns``;
* end to end is the GNSS fix's send time (in its body) to its arrival at a plain rclpy
  subscription in this process;
* GNSS fixes are published one at a time at 100 and 200 msg/s (a robot's pace), ``count``
  per measurement after ``warmup`` not counted, the systems alternately (in one order in
  even rounds, the reverse in odd ones), so a slower minute of the shared machine falls on
  all; the ratio engine / paper is taken per round. The paper's design runs twice: as the
  paper describes it (schema validation and a log line per message, ``paper``) and without
  either (``paper_minimal``), the least that design can do per message.

    .venv/bin/python -m bench.ct_l1 [--rates 100,200] [--count 1000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench import throughput as tp

SYSTEMS = {"engine": ("engine", {}), "paper": ("paper-amqp-ros2", {}),
           "paper_minimal": ("paper-amqp-ros2", {"minimal": True})}
"""``paper`` as the paper describes it (schema validation and a log line per message);
``paper_minimal`` without either: the least its design does per message."""


class ArrivalClock:
    """A plain rclpy subscription (taken in a thread): each fix's send-to-arrival time."""

    def __init__(self, domain: int, topic: str) -> None:
        from std_msgs.msg import String

        from bench.systems import TakeLoop, _qos, _ros_context

        self.end_to_end_ms: list[float] = []
        self.context, self.node = _ros_context(domain)
        self.subscription = self.node.create_subscription(String, topic, lambda msg: None, _qos(latched=True))
        self.taker = TakeLoop(self.context, self.subscription, String, self._on_batch)

    def _on_batch(self, batch: list[Any]) -> None:
        now = time.time()
        for message in batch:
            stamp = json.loads(message.data)["stamp"]
            self.end_to_end_ms.append((now - (stamp["sec"] + stamp["nanosec"] / 1e9)) * 1000)

    async def matched(self, timeout: float = 40.0) -> None:
        deadline = time.monotonic() + timeout
        while self.subscription.get_publisher_count() < 1:
            if time.monotonic() > deadline:
                raise RuntimeError("the bridge's publisher never matched the bench's subscription")
            await asyncio.sleep(0.05)

    async def arrived(self, count: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while len(self.end_to_end_ms) < count and time.monotonic() < deadline:
            await asyncio.sleep(0.05)

    def close(self) -> None:
        self.taker.stop()
        self.node.destroy_node()
        self.context.try_shutdown()


def _routes(directory: Path, names: dict[str, str], url: str, domain: int, topic: str) -> Path:
    """The engine's route doing the paper's work: the GNSS mapping, the position schema."""
    (directory / "ct_l1.yaml").write_text(f"""\
connections:
  gcs: {{amqp: {{url: "{url}"}}}}
  ros: {{ros2: {{domain_id: {domain}, node: bench_ct_l1}}}}
routes:
  - name: ct-l1
    source: {{amqp: {{connection: gcs, queue: {names['queue']}, prefetch: 256}}}}
    mapping: "{tp.GNSS_MAPPING}"
    schema: position
    sink: {{ros2: {{connection: ros, topic: {topic}, qos: {{durability: transient_local}}}}}}
""")
    return directory


async def one(broker: tp.Broker, system: str, rate: float, count: int, warmup: int, domain: int) -> dict[str, Any]:
    """``warmup + count`` fixes at ``rate`` through ``system``: CT-L1 and end to end (ms) of
    the last ``count``, and the child's CPU per message."""
    names = await broker.topology(uuid.uuid4().hex[:8])
    topic = f"/bench/ct_l1_{names['queue'].replace('-', '_')}"
    clock = ArrivalClock(domain, topic)
    try:
        with tempfile.TemporaryDirectory() as work:
            latency_out = Path(work) / "latency.json"
            program, extra = SYSTEMS[system]
            args: dict[str, Any] = {"url": broker.url, "domain": domain, "topic": topic, "latency_out": str(latency_out),
                                    **names, **extra}
            if system == "engine":
                args["routes"] = str(_routes(Path(work), names, broker.url, domain, topic))
            async with tp.child(program, args) as bridge:
                await clock.matched()
                await broker.publish_paced(names["queue"], warmup, rate)
                await clock.arrived(warmup, 30)
                cpu_before = bridge.cpu_seconds()
                await broker.publish_paced(names["queue"], count, rate)
                await clock.arrived(warmup + count, 30)
                cpu = bridge.cpu_seconds() - cpu_before
            samples = json.loads(latency_out.read_text())
    finally:
        clock.close()
        await broker.drop(names)
    ct_l1 = [ns / 1e6 for ns in (samples["ct-l1"] if system == "engine" else samples)][warmup:]
    end_to_end = clock.end_to_end_ms[warmup:]
    return {"ct_l1": tp.summary(ct_l1), "end_to_end": tp.summary(end_to_end), "delivered": len(end_to_end),
            "sent": count, "cpu_us_per_msg": cpu / count * 1e6}


async def measure(url: str, domain: int, rates: list[float], count: int, rounds: int, warmup: int = 100) -> dict[str, Any]:
    broker = tp.Broker(url)
    await broker.open()
    out: dict[str, Any] = {"rates": rates, "count": count, "rounds": rounds, "warmup": warmup, "by_rate": {}}
    try:
        for rate in rates:
            rows = []
            for round_ in range(rounds):
                order = list(SYSTEMS) if round_ % 2 == 0 else list(reversed(SYSTEMS))
                row: dict[str, Any] = {system: await one(broker, system, rate, count, warmup, domain) for system in order}
                for paper in ("paper", "paper_minimal"):
                    for measure_ in ("ct_l1", "end_to_end"):
                        row[f"ratio_{measure_}_p50_vs_{paper}"] = row["engine"][measure_]["p50"] / row[paper][measure_]["p50"]
                rows.append(row)
                print(f"  {rate:.0f} msg/s round {round_ + 1}: p50 CT-L1 / end to end (ms): "
                      + "; ".join(f"{system} {row[system]['ct_l1']['p50']:.3f} / {row[system]['end_to_end']['p50']:.3f}"
                                  for system in SYSTEMS), flush=True)
            out["by_rate"][str(int(rate))] = {"rounds": rows, **{
                f"median_{key}": statistics.median(r[key] for r in rows) for key in rows[0] if key.startswith("ratio_")}}
    finally:
        await broker.close()
    return out


def report(result: dict[str, Any]) -> list[str]:
    """Markdown rows: p50/p99 CT-L1 and end to end per system and rate, and the ratios."""
    lines = ["| Rate | Round | System | CT-L1 p50 / p99 (ms) | End to end p50 / p99 (ms) | Delivered | CPU per message (us) |",
             "|---|---|---|---|---|---|---|"]
    for rate, block in result["by_rate"].items():
        for index, row in enumerate(block["rounds"], 1):
            for system in SYSTEMS:
                cell = row[system]
                lines.append(f"| {rate} msg/s | {index} | {system} | {cell['ct_l1']['p50']:.3f} / {cell['ct_l1']['p99']:.3f} | "
                             f"{cell['end_to_end']['p50']:.3f} / {cell['end_to_end']['p99']:.3f} | "
                             f"{cell['delivered']}/{cell['sent']} | {cell['cpu_us_per_msg']:.0f} |")
    lines += ["", "Engine / paper's design, p50, median of the rounds (below 1: the engine is faster):", ""]
    for rate, block in result["by_rate"].items():
        lines.append(f"- {rate} msg/s: " + ", ".join(
            f"{key[len('median_ratio_'):].replace('_p50_vs_', ' vs ')} {value:.2f}"
            for key, value in block.items() if key.startswith("median_")))
    return lines


def main() -> None:
    from engine.endpoints.amqp.broker import LocalBroker
    from engine.running.loop import run

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rates", type=lambda s: [float(x) for x in s.split(",")], default=[100.0, 200.0])
    parser.add_argument("--count", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    with LocalBroker() as node:
        result = run(measure(node.url, tp.domain_id(), args.rates, args.count, args.rounds))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    for rate, block in result["by_rate"].items():
        print(f"{rate} msg/s, engine / paper's design, median of rounds: " + ", ".join(
            f"{key[len('median_ratio_'):]} {value:.2f}" for key, value in block.items() if key.startswith("median_")))


if __name__ == "__main__":
    main()
