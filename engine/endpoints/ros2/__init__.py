"""ROS 2 (rclpy): the transport (transport.py, the registry's face) and its parts, one module per
concern: options.py, checks.py, topics.py, errors.py, waiter.py and node.py (a node without an
executor), connection.py, source.py and sink.py (a topic's two ends), calls.py (services and
actions), discovery.py, rosmsg.py (ROS messages as plain dicts and back) and contract.py (what
the core's checks and dry runs ask of a ROS type)."""

from engine.endpoints.ros2.transport import TRANSPORT

__all__ = ["TRANSPORT"]
