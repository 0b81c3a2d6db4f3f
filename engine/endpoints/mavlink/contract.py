"""What the route endpoints of a link (message sources and sinks, acknowledged commands, mission
uploads) need of the connection they share, declared below all of them.

:class:`~.connection.MavlinkConnection` implements :class:`SharedLink`; the endpoints are typed
against this narrow protocol instead, so the connection can import them (it builds them) without
an import cycle (connection -> messages -> command/mission -> connection, TYPE_CHECKING imports
included), and a reader of :mod:`.command` or :mod:`.mission` sees exactly what they use.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Hashable
from contextlib import AbstractAsyncContextManager
from typing import Any, Protocol

from engine.endpoints.mavlink.dialect import mavlink2
from engine.endpoints.mavlink.settings import LinkConfig

Listener = Callable[[mavlink2.MAVLink_message], None]


class SharedLink(Protocol):
    """One MAVLink link as its routes use it."""

    name: str
    config: LinkConfig
    stats: dict[str, int]
    """The connection's counters (shown in the status); transactions add theirs."""
    mission_refs: dict[tuple[int, int], str]
    """Per vehicle, the id of the message whose mission was uploaded last (MISSION_ACK's ``ref_id``)."""

    def listen(self, msg_id: int | None, listener: Listener, system_id: int | None = None, answers: bool = False) -> None:
        """Call ``listener`` with every accepted message of ``msg_id`` (None: all), from
        vehicle ``system_id`` only when given; ``answers``: a transaction's listener, which
        also gets the answers to this worker's transactions on a link split over workers."""

    def unlisten(self, msg_id: int | None, listener: Listener, system_id: int | None = None, answers: bool = False) -> None: ...

    async def send_message(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False,
                           priority: str | None = None) -> float:
        """Return once the paced writer wrote ``msg`` (the loop time it was written);
        ``priority`` None (commands, missions) goes before every route's ``priority``."""

    def enqueue(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False, priority: str | None = None,
                key: Hashable | None = None) -> asyncio.Future[float]:
        """Queue ``msg`` for the writer; the future gives the loop time it was written. A route
        frame with a ``key`` replaces a waiting one with that key (whose future fails with
        Conflated): the link's budget (engine/endpoints/mavlink/budget.py)."""

    def post(self, msg: mavlink2.MAVLink_message) -> None:
        """Queue a frame nobody waits for (a failure is only counted)."""

    def transaction_lock(self, key: Hashable) -> AbstractAsyncContextManager[Any]:
        """One mission upload (or command) at a time per target, as the protocols require."""

    async def wait_for_vehicle(self, system: int, component: int, deadline: float) -> None:
        """Return once (system, component) was heard; EndpointError at ``deadline`` (loop time)."""

    def last_heard_text(self, system: int, component: int = 0) -> str:
        """The vehicle named (its agent too), with when its last HEARTBEAT came, for a reason."""
