#!/usr/bin/env python3
"""The paper's robot agent: store every JSON message it hears, then send it straight back.

Subscribes to a std_msgs/String topic, appends each ``data`` as one line to a file, and
republishes the same ``data`` unchanged on another topic, so a round trip through the engine
can be checked byte for byte on both ends. Standalone rclpy (it does not import the engine);
run it in the robot's network namespace with the same ROS_DOMAIN_ID as the engine:

    python examples/robot_echo.py --file /tmp/robot.jsonl [--in /uav1/json_in]
        [--out /uav1/json_out] [--count N]

Prints ``ready`` on stdout once subscribed. Exits 0 after N messages (``--count``) or on
SIGTERM/SIGINT, after waiting (up to 5 s) for the echoes to be acknowledged, so the last
messages are not lost with the writer. The signals are handled here, not by rclpy, so that
shutdown is an orderly return from the spin loop rather than an exception inside a callback.
"""

from __future__ import annotations

import argparse
import signal
import sys
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.experimental import EventsExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String

SPIN_SLICE = 0.2
"""Seconds per spin_once: how long a signal may wait before the loop sees it."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--in", dest="topic_in", default="/uav1/json_in", help="String topic to listen on")
    parser.add_argument("--out", dest="topic_out", default="/uav1/json_out", help="String topic to echo on")
    parser.add_argument("--file", default="robot_echo.jsonl", help="file to append each message to")
    parser.add_argument("--count", type=int, default=0,
                        help="exit after this many messages (0: run until signalled)")
    parser.add_argument("--depth", type=int, default=10_000, help="KEEP_LAST history depth")
    parser.add_argument("--node", default="robot_echo")
    args = parser.parse_args(argv)

    stop = False

    def on_signal(signum: int, frame: Any) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.depth,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(args.node)
    received = 0
    with open(args.file, "a", encoding="utf-8") as store:
        publisher = node.create_publisher(String, args.topic_out, qos)

        def on_message(msg: String) -> None:
            nonlocal received, stop
            store.write(msg.data + "\n")
            store.flush()
            publisher.publish(msg)
            received += 1
            if args.count and received >= args.count:
                stop = True

        node.create_subscription(String, args.topic_in, on_message, qos)
        executor = EventsExecutor()
        executor.add_node(node)
        print("ready", flush=True)
        try:
            while not stop:
                executor.spin_once(timeout_sec=SPIN_SLICE)
            publisher.wait_for_all_acked(Duration(seconds=5))
        finally:
            executor.shutdown(timeout_sec=1)
            node.destroy_node()
            rclpy.try_shutdown()
    print(f"robot_echo: {received} messages stored in {args.file} and echoed on {args.topic_out}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
