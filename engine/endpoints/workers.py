"""What a protocol says about the worker processes of ``run --workers N``: part of the endpoint
contract (``Transport`` inherits it; engine/endpoints/base.py is still where it is imported from).

The placement of routes over workers (engine/running/placement.py) is the core's, one pure
function; it never names a protocol, so it asks each transport two questions: what of a
connection only one process may hold (beyond the exclusive resource every transport already
states, ``Transport.exclusive_resource``), and whether a source's consumers may run in every
worker and compete. Kept apart from engine/endpoints/base.py, which is at its size limit.
"""

from __future__ import annotations

from typing import Any


class WorkerHints:
    """The defaults: a connection holds nothing beyond its exclusive resource, and a source runs
    in one worker (each subscriber of a topic gets every message: two workers would carry each
    message twice)."""

    def worker_affinity(self, connection: str, settings: Any) -> str | None:
        """A key for what connection ``connection`` (these typed settings) is that one process
        must hold alone even without an exclusive resource (a MAVLink link: the vehicle answers
        the address it heard last); its routes run on the one worker that holds it. None: any
        worker may open the connection."""
        return None

    def spreads_over_workers(self, options: Any) -> bool:
        """True when every worker may run a source with these (typed) options: its consumers
        compete for one stream and the broker hands each message to one of them (an AMQP
        queue, an MQTT shared subscription). False: the route runs on one worker."""
        return False
