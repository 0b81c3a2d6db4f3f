"""What a protocol says about how its sources spread over engine instances and over the worker
processes of ``run --workers N``: part of the endpoint contract (``Transport`` inherits it;
engine/endpoints/base.py is still where the contract is imported from).

The placement of routes over workers (engine/running/placement.py) is the core's, one pure
function; it never names a protocol, so it asks each transport: whether a source's consumers
compete for one stream (then every instance and every worker runs it), and what of a
connection only one process may hold beyond the exclusive resource every transport already
states (``Transport.exclusive_resource``). Kept apart from engine/endpoints/base.py, which is
at its size limit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar


@dataclass(frozen=True)
class ConnectionShare:
    """Where one worker stands on a connection split over the workers
    (:meth:`WorkerHints.splits_connection`): its index of ``workers``, the ``owner`` that holds
    the connection's resource, and the supervisor's private directory of this run, where the
    workers' local sockets are bound (``run --workers N`` makes one and removes it)."""

    index: int
    workers: int
    owner: int
    runtime_dir: str


class WorkerHints:
    """The defaults: a source's subscribers each get every message (one worker runs it), and a
    connection holds nothing beyond its exclusive resource."""

    shares_sources: ClassVar[bool] = False
    """True when every instance's source competes for one stream (a broker queue): each
    message reaches one instance anyway, so ``active_standby`` is refused (use ``ordered``)."""

    def spreads_over_workers(self, options: Any) -> bool:
        """True when every worker may run a source with these (typed) options: its consumers
        compete for one stream and the broker hands each message to one of them (by default
        :attr:`shares_sources`: an AMQP queue; an MQTT shared subscription says so per source).
        False: the route runs on one worker, as each subscriber would get every message."""
        return self.shares_sources

    def splits_over_workers(self, options: Any) -> bool:
        """True when a source with these (typed) options follows streams it discovers (a ROS 2
        topic pattern): every worker runs it, each following its share of them
        (:meth:`split_source`). False by default."""
        return False

    def split_source(self, options: Any, share: int, shares: int) -> Any:
        """The source options of worker ``share`` of ``shares`` for a route that
        :meth:`splits_over_workers` (only called where it does)."""
        raise NotImplementedError(f"{type(self).__name__} does not split its sources over workers")

    def splits_connection(self, settings: Any) -> bool:
        """True when a connection with these (typed) settings is split over the workers: one
        worker, its owner (placed by its exclusive resource or affinity, rule 1), holds it and
        hands each worker its share of what comes in (a MAVLink ``udpin`` link with
        ``split_over_workers``: its vehicles by system id); every worker runs the routes that
        read it, and sends through the owner. False by default."""
        return False

    def split_connection(self, settings: Any, share: ConnectionShare) -> Any:
        """The connection settings worker ``share.index`` opens for a connection that
        :meth:`splits_connection` (only called where it does)."""
        raise NotImplementedError(f"{type(self).__name__} does not split its connections over workers")

    def split_problems(self, side: str, options: Any) -> list[tuple[str | None, str]]:
        """What a route's ``side`` (``source`` or ``sink``) with these (typed) options cannot do
        on a connection that :meth:`splits_connection`, as (key, message); none by default."""
        return []

    def worker_affinity(self, connection: str, settings: Any) -> str | None:
        """A key for what connection ``connection`` (these typed settings) is that one process
        must hold alone even without an exclusive resource (a MAVLink link: the vehicle answers
        the address it heard last); its routes run on the one worker that holds it. None: any
        worker may open the connection."""
        return None
