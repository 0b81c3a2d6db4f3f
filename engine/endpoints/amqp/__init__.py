"""AMQP 0-9-1 (RabbitMQ): the transport (transport.py: connection, source, sink), its typed
options (options.py), cluster URLs, failover and leases (cluster.py), and what a retired
source leaves behind (topology.py)."""

from engine.endpoints.amqp.transport import TRANSPORT, PublishProperties, redact

__all__ = ["TRANSPORT", "PublishProperties", "redact"]
