"""A ground robot of the farm demo, as a plain ROS 2 node (it knows nothing of the engine).

It publishes its GNSS fix (``sensor_msgs/NavSatFix``) at 1 Hz, takes missions as canonical
JSON in a ``std_msgs/String`` and acknowledges each one as canonical JSON. It offers a service
that switches its sprayer (``/<name>/set_spray``, ``std_srvs/srv/SetBool``) and an action that
sends it along a row (``/<name>/follow_row``): ``test_msgs/action/Fibonacci`` stands in for a
navigation action (no such package is installed with the engine): the goal's ``order`` is the
number of stops along the row, each feedback's ``sequence`` the stops reached so far (metres
along the row), the result the whole row.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import threading
import time

import rclpy
from rclpy.action import ActionServer, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import NavSatFix, NavSatStatus
from std_msgs.msg import String
from std_srvs.srv import SetBool
from test_msgs.action import Fibonacci

ROW_STOP_S = 0.2
"""Seconds between two stops along a row (the demo's rows are short)."""
MAX_STOPS = 50


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--name", default="robot1")
    parser.add_argument("--duration", type=float, default=0, help="seconds, 0 = until SIGTERM")
    args = parser.parse_args()

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"{args.name}_base")
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    fix_pub = node.create_publisher(NavSatFix, f"/{args.name}/fix", qos)
    ack_pub = node.create_publisher(String, f"/{args.name}/ack", qos)
    started = time.time()

    def on_mission(msg: String) -> None:
        mission = json.loads(msg.data)
        print(f"{args.name}: mission {mission.get('mission_id')} with {len(mission.get('waypoints', []))} waypoints, task {mission.get('task')}", flush=True)
        ack = {"agent_id": args.name, "ref_id": mission.get("mission_id", "?"), "result": "accepted",
               "detail": f"{len(mission.get('waypoints', []))} waypoints queued"}
        ack_pub.publish(String(data=json.dumps(ack)))

    def publish_fix() -> None:
        t = time.time() - started
        fix = NavSatFix()
        fix.header.frame_id = f"{args.name}/gps"
        fix.header.stamp = node.get_clock().now().to_msg()
        fix.status.status = NavSatStatus.STATUS_FIX
        fix.latitude = -22.0005 + 1e-5 * math.sin(t / 10)
        fix.longitude = -47.9005 + 1e-5 * math.cos(t / 10)
        fix.altitude = 600.0
        fix_pub.publish(fix)

    def set_spray(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        response.success = True
        response.message = f"{args.name}: sprayer {'on' if request.data else 'off'}"
        print(response.message, flush=True)
        return response

    def follow_row(goal: Fibonacci.Goal) -> GoalResponse:
        return GoalResponse.ACCEPT if 0 < goal.order <= MAX_STOPS else GoalResponse.REJECT

    def drive_row(goal_handle: ServerGoalHandle) -> Fibonacci.Result:
        stops = goal_handle.request.order
        print(f"{args.name}: along the row, {stops} stops", flush=True)
        reached = [0]
        for _ in range(1, stops):
            time.sleep(ROW_STOP_S)
            reached.append(reached[-1] + (reached[-2] if len(reached) > 1 else 1))
            goal_handle.publish_feedback(Fibonacci.Feedback(sequence=reached))
        goal_handle.succeed()
        print(f"{args.name}: row done at {reached[-1]} m", flush=True)
        return Fibonacci.Result(sequence=reached)

    node.create_service(SetBool, f"/{args.name}/set_spray", set_spray)
    ActionServer(node, Fibonacci, f"/{args.name}/follow_row", drive_row, goal_callback=follow_row)
    missions_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, f"/{args.name}/mission", on_mission, missions_qos)
    node.create_timer(1.0, publish_fix)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    while not stop.is_set() and (not args.duration or time.time() - started < args.duration):
        executor.spin_once(timeout_sec=0.2)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
