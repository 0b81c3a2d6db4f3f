"""ROS 2 (rclpy): the transport (transport.py: connection, node, sources and sinks without an
executor), ROS messages as plain dicts and back (rosmsg.py), and what the core's checks and
dry runs ask of a ROS type (contract.py)."""

from engine.endpoints.ros2.transport import TRANSPORT

__all__ = ["TRANSPORT"]
