"""RabbitROS engine: routes between RabbitMQ, ROS 2 and MAVLink declared in YAML."""

__version__ = "0.1.0"
