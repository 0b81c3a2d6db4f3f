"""Does the ROS 2 endpoint keep up with 10,000 msg/s without burning a core while idle?

A child process publishes with plain rclpy; this process receives through the engine's
Ros2Connection/Ros2Source (or, with ``--baseline poll``, through EventsExecutor.spin_once(0)
polled from the loop, the design it replaced). Prints process CPU % while idle and, per
phase (count@rate): messages received, msg/s, process CPU %, the worst asyncio loop lag
(what an AMQP client on the same loop would feel) and end-to-end latency; then the cost of
Ros2Sink.send on the loop.

    timeout -s KILL 120 python bench/bench_ros2_executor.py [--type sensor_msgs/msg/NavSatFix]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

if TYPE_CHECKING:
    from engine.endpoints.base import Inbound, Inbox

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TOPIC = "/bench/ros2_executor"
PAD = "x" * 60


def _message(cls: type, i: int) -> Any:
    """A message carrying its sequence number and send time (ns) for latency."""
    if cls.__name__ == "String":
        return cls(data=f'{{"agent_id":"uav1","seq":{i},"t":{time.time_ns()},"pad":"{PAD}"}}')
    return cls(latitude=float(i), longitude=float(time.time_ns()), altitude=float("nan"))


def _sent_ns(inbound: Any) -> int:
    return json.loads(inbound.body)["t"] if inbound.body is not None else int(inbound.fields["longitude"])


def publisher(args: argparse.Namespace) -> None:
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from engine.endpoints.ros2.rosmsg import resolve_type

    cls = resolve_type(args.type)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("bench_publisher")
    pub = node.create_publisher(cls, TOPIC, QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE))
    deadline = time.monotonic() + 10
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)
    for phase in args.phases.split(","):
        count, rate = (int(x) for x in phase.split("@"))
        start = time.perf_counter()
        for i in range(count):
            pub.publish(_message(cls, i))
            if rate:
                ahead = start + (i + 1) / rate - time.perf_counter()
                if ahead > 0.0005:
                    time.sleep(ahead)
        took = time.perf_counter() - start
        print(f"  publisher: {count} in {took:.2f} s ({count / took:,.0f} msg/s)",
              file=sys.stderr, flush=True)
        time.sleep(args.gap)
    time.sleep(3)  # keep the writer alive for reliable repairs
    node.destroy_node()
    rclpy.shutdown()


class Meter:
    """Counts what a source delivers; implements the engine's Deliver contract."""

    overflow = "block"
    queue_limit = 10_000
    batches_in_flight = 1

    def __init__(self) -> None:
        self.count = 0
        self.first = self.last = 0.0
        self.latencies: list[float] = []

    async def __call__(self, inbound: Inbound) -> None:
        await self.deliver(inbound)

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        for inbound in inbounds:
            await self.deliver(inbound)
        return [True] * len(inbounds)

    def dropped(self, count: int = 1) -> None:
        pass

    def inbox(self, overflow: str) -> Inbox[Inbound]:
        from engine.endpoints.base import Inbox
        return Inbox(self.queue_limit, overflow)

    async def deliver(self, inbound: Any) -> None:
        now = time.perf_counter()
        if self.count == 0:
            self.first = now
        self.count += 1
        self.last = now
        self.latencies.append((time.time_ns() - _sent_ns(inbound)) / 1e6)


async def idle_cpu(seconds: float) -> float:
    cpu, wall = time.process_time(), time.perf_counter()
    await asyncio.sleep(seconds)
    return 100 * (time.process_time() - cpu) / (time.perf_counter() - wall)


LAG_PROBE = 0.005
"""Period of the loop-lag probe; it costs about 3 % CPU, included in the per-phase CPU."""


async def loop_lag(stop: asyncio.Event, worst: list[float]) -> None:
    while not stop.is_set():
        start = time.perf_counter()
        await asyncio.sleep(LAG_PROBE)
        worst[0] = max(worst[0], time.perf_counter() - start - LAG_PROBE)


async def receive_phase(meter: Meter, count: int, rate: int) -> tuple[int, float, float, float]:
    meter.count, meter.latencies = 0, []
    stop, worst = asyncio.Event(), [0.0]
    deadline = time.monotonic() + 15
    while meter.count == 0 and time.monotonic() < deadline:
        await asyncio.sleep(0.001)
    cpu = time.process_time()
    ticker = asyncio.create_task(loop_lag(stop, worst))
    deadline = time.monotonic() + count / (rate or 2000) + 10
    while meter.count < count and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    stop.set()
    await ticker
    took = meter.last - meter.first
    cpu_percent = 100 * (time.process_time() - cpu) / took if took > 0 else 0.0
    return meter.count, (meter.count - 1) / took if took > 0 else 0.0, worst[0] * 1e3, cpu_percent


async def start_poll_baseline(args: argparse.Namespace, meter: Meter) -> list[asyncio.Task[None]]:
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from engine.endpoints.base import Inbound
    from engine.endpoints.ros2.rosmsg import resolve_type, to_dict

    cls = resolve_type(args.type)
    is_string = cls.__name__ == "String"
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("bench_poll", context=context)
    executor = EventsExecutor(context=context)
    executor.add_node(node)
    queue: asyncio.Queue[Inbound] = asyncio.Queue()

    def callback(msg: Any) -> None:
        queue.put_nowait(Inbound(body=msg.data.encode()) if is_string else Inbound(fields=to_dict(msg)))

    qos = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(cls, TOPIC, callback, qos)

    async def poll() -> None:
        while True:
            executor.spin_once(timeout_sec=0)
            await asyncio.sleep(0)

    async def pump() -> None:
        while True:
            await meter.deliver(await queue.get())

    return [asyncio.create_task(poll()), asyncio.create_task(pump())]


async def bench_sink(connection: Any, type_name: str, count: int) -> tuple[float, float]:
    from engine.endpoints.base import Outbound
    from engine.endpoints.ros2.rosmsg import resolve_type, to_dict

    sink = connection.sink("bench-sink", {"topic": "/bench/sink", "type": type_name})
    cls = resolve_type(type_name)
    sample = _message(cls, 1)
    body = sample.data.encode() if cls.__name__ == "String" else b"{}"
    fields = None if cls.__name__ == "String" else to_dict(sample)
    out = Outbound(body=body, canonical=fields, fields=fields, message_id="1", meta={})
    times = []
    for _ in range(count):
        start = time.perf_counter()
        await sink.send(out)
        times.append(time.perf_counter() - start)
    await sink.close()
    times.sort()
    return statistics.median(times) * 1e6, times[int(len(times) * 0.999)] * 1e6


async def main(args: argparse.Namespace) -> None:
    from engine.endpoints.ros2 import TRANSPORT

    meter = Meter()
    connection: Any = None
    tasks: list[asyncio.Task[None]] = []
    if args.baseline == "poll":
        tasks = await start_poll_baseline(args, meter)
    else:
        connection = TRANSPORT.connect("bench", {"node": "bench_engine"})
        await connection.open()
        source = connection.source("bench", {"topic": TOPIC, "type": args.type})
        await source.start(meter)
    print(f"receiver: {args.baseline or 'engine (waiter thread + takes on the loop)'}, type {args.type}")
    print(f"idle CPU before traffic: {await idle_cpu(2.0):.1f} %")

    phases = [tuple(int(x) for x in p.split("@")) for p in args.phases.split(",")]
    child = subprocess.Popen(
        [sys.executable, __file__, "--publish", "--type", args.type, "--phases", args.phases,
         "--gap", str(args.gap)],
        env=os.environ,
    )
    try:
        for count, rate in phases:
            got, rate_in, lag, cpu = await receive_phase(meter, count, rate)
            label = f"{rate:,} msg/s" if rate else "full speed"
            lat = sorted(meter.latencies) or [0.0]
            print(f"{count} at {label}: received {got} (lost {count - got}), {rate_in:,.0f} msg/s, "
                  f"CPU {cpu:.0f} %, worst loop lag {lag:.1f} ms, "
                  f"latency p50 {statistics.median(lat):.2f} ms p99 {lat[int(len(lat) * 0.99)]:.2f} ms")
        print(f"idle CPU after traffic: {await idle_cpu(2.0):.1f} %")
    finally:
        child.wait(timeout=30)
    if connection is not None:
        median, p999 = await bench_sink(connection, args.type, 5000)
        print(f"Ros2Sink.send on the loop: median {median:.1f} us, p99.9 {p999:.1f} us")
        await connection.close()
    else:
        for task in tasks:
            task.cancel()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--type", default="std_msgs/msg/String")
    parser.add_argument("--phases", default="400@200,20000@10000,20000@0",
                        help="count@rate (0 = full speed), comma separated")
    parser.add_argument("--gap", type=float, default=2.0, help="seconds between phases")
    parser.add_argument("--baseline", choices=["poll"], help="measure the polling design instead")
    parser.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    if args.publish:
        publisher(args)
    else:
        asyncio.run(main(args))
