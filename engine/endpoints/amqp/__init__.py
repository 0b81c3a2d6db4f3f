"""AMQP 0-9-1 (RabbitMQ): the transport (transport.py, the registry's face) and its parts, one
module per concern: options.py, errors.py, link.py (the connection to the broker),
connection.py, source.py and acks.py (a queue consumed, its held acknowledgements), sink.py
and publisher.py, calls.py, cluster URLs, failover and leases (cluster.py), and what a retired
source leaves behind (topology.py)."""

from engine.endpoints.amqp.link import redact
from engine.endpoints.amqp.sink import PublishProperties
from engine.endpoints.amqp.transport import TRANSPORT

__all__ = ["TRANSPORT", "PublishProperties", "redact"]
