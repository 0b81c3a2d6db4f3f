"""Zenoh endpoint on eclipse-zenoh 1.x: see session.py for the session and its health,
source.py and sink.py for the routes' two ends (a subscriber, a put), calls.py for queries
answered as calls, keys.py for key expressions and their ``{name}`` captures, errors.py for the
one table of library failures.

eclipse-zenoh because it is the project's own binding of the Rust implementation (the one
``rmw_zenoh`` and zenoh-plugin-ros2dds run on), complete (peer and client modes, queryables,
transport events) and maintained with it. Its API is synchronous, with callbacks on threads
of its own runtime: handoff.py carries messages to the engine's event loop, and blocking
calls run in worker threads.
"""

from engine.endpoints.zenoh.transport import TRANSPORT

__all__ = ["TRANSPORT"]
