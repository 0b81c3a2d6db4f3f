"""Test peers for broker outages: an AMQP publisher and collector that ride out a broker
killed with -9 (robust connections, publisher confirms, manual acks), a ROS 2 peer, and the
bookkeeping of sent / delivered / duplicates and of the time from a broker's restart to the
first message delivered after it."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import aio_pika


@dataclass
class Tally:
    """Arrivals of one flow: seq -> copies, and when each arrival happened (monotonic).

    Not a second collector: it consumes nothing. It is the bookkeeping of one flow that several
    peers feed by seq, whatever the protocol: tests/support/amqp_helpers.py ``Collector``
    (``tally=``) records the AMQP side into it, ``RosPeer`` a ROS 2 subscription, a test its
    MAVLink peer; what it adds to a collector's list of messages is copies per seq
    (duplicates, lost) and arrival times across a broker's restart. Tests wait on it with
    tests/support/waiting.py ``wait_for`` (``lambda: tally.delivered >= n``)."""

    name: str
    sent: int = 0
    copies: dict[int, int] = field(default_factory=dict)
    arrivals: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    probes: int = 0
    """Arrivals of a negative seq: a warm-up's probe, counted apart so that a probe still in
    flight when the flow starts is never a copy, a duplicate or an arrival of the flow."""

    def record(self, seq: int) -> None:
        with self.lock:
            if seq < 0:
                self.probes += 1
                return
            self.copies[seq] = self.copies.get(seq, 0) + 1
            self.arrivals.append(time.monotonic())

    @property
    def delivered(self) -> int:
        return len(self.copies)

    @property
    def duplicates(self) -> int:
        return sum(count - 1 for count in self.copies.values())

    def lost(self, expected: range) -> list[int]:
        return [seq for seq in expected if seq not in self.copies]

    def first_after(self, moment: float) -> float | None:
        """Seconds from ``moment`` to the first arrival after it."""
        later = [t for t in self.arrivals if t >= moment]
        return min(later) - moment if later else None

    def figures(self, expected: range) -> str:
        return (f"{self.name}: sent={self.sent} delivered={self.delivered} "
                f"duplicates={self.duplicates} lost={len(self.lost(expected))}")


async def robust(url: str) -> aio_pika.abc.AbstractRobustConnection:
    return await aio_pika.connect_robust(url, reconnect_interval=0.5)


async def declare_bound_queue(channel: Any, queue: str, exchange: str, key: str = "#") -> Any:
    """The durable queue ``queue`` bound to the durable topic ``exchange`` with ``key`` (both
    declared); the queue, not consumed."""
    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
    declared = await channel.declare_queue(queue, durable=True)
    await declared.bind(target, key)
    return declared


async def publish_reliably(connection: Any, exchange: str, key: str, seqs: range, rate: float,
                           tally: Tally, extra: Callable[[int], dict[str, Any]] = lambda seq: {},
                           window: int = 64) -> None:
    """Publish every seq with publisher confirms at ``rate`` msg/s, up to ``window`` of them
    awaiting their confirm at once; a publish that fails (the broker died) is retried until
    confirmed, and ``tally.sent`` counts the confirmed ones. One at a time, the round trip of a
    loaded machine set the pace instead of ``rate``: 10,000 at a nominal 250 msg/s took 320 s
    beside three test workers."""
    deadline = time.monotonic() + 60
    while True:  # a robust connection may still be reconnecting after a broker restart
        try:
            channel = await connection.channel(publisher_confirms=True)
            target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
            break
        except Exception:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)  # pacing: retries while a robust connection reconnects (deadline above)
    slots = asyncio.Semaphore(window)

    async def confirmed(body: bytes) -> None:
        try:
            while True:
                try:
                    await asyncio.wait_for(target.publish(
                        aio_pika.Message(body, delivery_mode=aio_pika.DeliveryMode.PERSISTENT), key), 30)
                    break
                except Exception:
                    await asyncio.sleep(0.2)  # pacing: retries of a publish the dead broker refused
            tally.sent += 1
        finally:
            slots.release()

    started = time.monotonic()
    publishing: list[asyncio.Task[None]] = []
    for index, seq in enumerate(seqs):
        await slots.acquire()
        publishing.append(asyncio.create_task(confirmed(json.dumps({"seq": seq, **extra(seq)}).encode())))
        delay = started + (index + 1) / rate - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)  # pacing: the publisher's rate
    await asyncio.gather(*publishing)


class RosPeer:
    """The robot side, in its own rclpy context and executor thread: publishes String JSON on
    ``up`` and records ``down`` into a tally."""

    def __init__(self, domain: int, name: str, up: str, down: str, tally_down: Tally) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String

        self._String = String
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        qos = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE)
        self.publisher = self.node.create_publisher(String, up, qos)

        def on_down(msg: Any) -> None:
            tally_down.record(json.loads(msg.data)["seq"])

        self.node.create_subscription(String, down, on_down, qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def publish(self, seq: int) -> None:
        self.publisher.publish(self._String(data=json.dumps({"seq": seq})))

    def publish_paced(self, seqs: range, rate: float, tally: Tally) -> None:
        started = time.monotonic()
        for index, seq in enumerate(seqs):
            self.publish(seq)
            tally.sent += 1
            delay = started + (index + 1) / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # pacing: the publisher's rate

    def subscribers(self, topic: str) -> int:
        return self.node.count_subscribers(topic)

    def close(self) -> None:
        self._stop.set()
        self._spinner.join(5)
        self.executor.shutdown(timeout_sec=1)
        self.node.destroy_node()
        self.context.try_shutdown()

