"""ROS 2: an rclpy node of the test's own (tests/support/ros_nodes.py ``SpunNode``) on the
module's ROS 2 domain (tests/support/workers.py, slot 14), publishing std_msgs/String (JSON in
``data``) on ``/TAG/in/rN`` and subscribed to ``/TAG/out/rN``. The source's topic pattern
``/TAG/in/{robot}`` is followed by discovery, its ``{robot}`` segment the metadata the mapping
reads; the sink's topic is rendered from it."""

from __future__ import annotations

import json
import threading
from typing import Any

from tests.endpoints.conformance.harness import Harness, Seen
from tests.support.waiting import wait_for
from tests.support.workers import ros_domain

ROBOTS = (1, 2)
DOMAIN_SLOT = 14


class Ros2Harness(Harness):
    PROTOCOL = "ros2"
    EXCLUDED = {
        "health": "ROS 2 has no broker or peer the connection depends on: DDS discovers participants, and the "
                  "connection (an rclpy node) stays up whoever comes and goes; a sink holds its messages until a "
                  "reader matches (require_subscriber), which the through case shows",
        "kill9": "a ROS 2 topic acknowledges nothing: DDS keeps no message for a process that died, so a source "
                 "cannot redeliver and promises no at-least-once across an engine's death (docs/route-language.md, "
                 "Delivery semantics: ROS 2 source)",
        "cancel": "no broker holds ROS 2 subscriptions to revoke: a publisher that goes is followed again by "
                  "discovery when it comes back (tests/endpoints/ros2/test_ros2_discovery.py)",
    }

    async def open(self, fixtures: dict[str, Any], case: str) -> None:
        from std_msgs.msg import String

        from tests.support.ros_nodes import SpunNode

        self.domain = ros_domain(DOMAIN_SLOT)
        self.peer = SpunNode(self.domain, f"peer_{self.tag}")
        self.lock = threading.Lock()
        self.messages: list[Seen] = []
        self.string = String
        node = self.peer.node
        self.publishers = {robot: node.create_publisher(String, f"/{self.tag}/in/r{robot}", 100) for robot in ROBOTS}
        self.subscriptions = [node.create_subscription(String, f"/{self.tag}/out/r{robot}", self._receiver(robot), 100)
                              for robot in ROBOTS]

    def _receiver(self, robot: int) -> Any:
        def received(message: Any) -> None:  # on the node's executor thread
            body = json.loads(message.data)
            with self.lock:
                self.messages.append(Seen(robot, body["seq"], body["origin"], body["edition"]))
        return received

    async def close(self) -> None:
        self.peer.close()

    def connection(self, case: str) -> str:
        return f"{{ros2: {{domain_id: {self.domain}, node: engine_{self.tag}}}}}"

    def source(self) -> str:
        return f'topic: "/{self.tag}/in/{{robot}}"'

    def sink(self) -> str:
        return f'topic: "/{self.tag}/out/{{origin}}"'

    def origin_expression(self) -> str:
        return "meta('robot')"

    def expected_origin(self, robot: int) -> str:
        return f"r{robot}"

    async def ready(self) -> None:
        """Until the engine discovered every robot's topic and subscribed to it (a volatile writer
        drops what it publishes before a reader matched)."""
        await wait_for(lambda: all(p.get_subscription_count() > 0 for p in self.publishers.values()), 30,
                       "the engine's subscriptions to /TAG/in/r1 and r2 (discovery)")

    async def inject(self, robot: int, seq: int) -> None:
        self.publishers[robot].publish(self.string(data=json.dumps({"seq": seq})))

    async def inject_bad(self, robot: int) -> None:
        self.publishers[robot].publish(self.string(data="not json {"))

    def seen(self) -> list[Seen]:
        with self.lock:
            return list(self.messages)

    def session_of(self, connection: Any) -> Any:
        return connection._node  # the engine's rclpy node (engine/endpoints/ros2/node.py)


HARNESS = Ros2Harness
