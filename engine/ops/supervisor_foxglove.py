"""``run --workers N --foxglove [HOST:]PORT``: the Foxglove view of the engine as a whole.

The supervisor serves the view (engine/ops/foxglove.py: the same channels, schemas and
server) from its workers instead of in-process observers (:class:`WorkersFeed`):

* ``/routes/status``: the status merged over the workers, as the supervisor's ``/status``
  serves it (engine/ops/supervisor_admin.py :func:`status_document`);
* ``/fleet``: each agent's latest position over the workers, as the supervisor's console shows
  it (:func:`~engine.ops.supervisor_admin.console_document`: the workers' ``/console/state``);
* ``/routes/NAME/canonical``: the canonical messages the route's sink took in any worker, read
  from the tap of every worker running the route (``/tap/NAME`` on its private admin, the one
  the supervisor's own ``/tap`` reads), opened when a client subscribes to the channel and
  closed when the last one leaves. A worker started again, or a reload that moves the route,
  is followed (the tap is opened again on the workers running it then).

No client, no cost: nothing is asked of a worker while no client subscribes; the status and the
fleet are asked once a second while subscribed (each one request per worker), and a route's
tap costs its workers one JSON line per message while its channel is subscribed (the tap's own
cost, engine/running/observe.py), the supervisor one parse and one serialisation of it. A tap
line that the worker could not hand over in time is dropped by the worker's tap, never waited
for, as for the supervisor's ``/tap``. Imported only under ``--foxglove`` (the SDK's import
costs some 40 ms).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Any, Hashable, Sequence

import orjson

from engine.language.specs import RoutesConfig
from engine.ops.foxglove import FLEET_WINDOW_S, TICK_S, RouteChannel
from engine.ops.supervisor import Supervisor, Worker
from engine.ops.supervisor_admin import console_document, status_document

class WorkersFeed:
    """A :class:`~engine.ops.foxglove.ViewFeed` of the supervisor's workers (module docstring)."""

    def __init__(self, supervisor: Supervisor, schema_dirs: Sequence[Path]) -> None:
        self.supervisor = supervisor
        self.schema_dirs = tuple(schema_dirs)
        self.name = f"rabbitros-engine {supervisor.args.instance or 'supervisor'} ({len(supervisor.workers)} workers)"
        self.loop = asyncio.get_running_loop()
        self.follows: dict[str, tuple[RouteChannel, Hashable, asyncio.Task[None]]] = {}
        """Route -> the channel its workers' taps feed, for which generation, the task doing it."""
        self._console: tuple[float, dict[str, Any]] | None = None
        self.stopped = False

    def running(self) -> tuple[Hashable, RoutesConfig, Sequence[Path], Sequence[str]] | None:
        supervisor = self.supervisor
        if supervisor.config is None or supervisor.placement is None:
            return None
        return self._generation(), supervisor.config, self.schema_dirs, list(supervisor.placement.routes)

    def _generation(self) -> Hashable:
        config = self.supervisor.config
        return self.supervisor.generation, config.content_hash if config else None

    async def status(self) -> dict[str, Any]:
        return await status_document(self.supervisor)

    async def positions(self) -> dict[str, dict[str, Any]]:
        now = time.time()
        fleet = (await self._console_document())["fleet"]
        return {agent["agent_id"]: agent for agent in fleet if now - (agent.get("at") or 0) <= FLEET_WINDOW_S}

    async def _console_document(self) -> dict[str, Any]:
        """The merged console document, asked at most once a tick."""
        now = time.monotonic()
        if self._console is None or now - self._console[0] > TICK_S / 2:
            self._console = (now, await console_document(self.supervisor))
        return self._console[1]

    def wire(self, route: str, channel: RouteChannel | None, fleet: bool) -> None:
        """Open or close the route's taps on the event loop (the fleet needs no wiring: it is
        the workers' own, asked while subscribed)."""
        self.loop.call_soon_threadsafe(self._follow, route, channel)

    def _follow(self, route: str, channel: RouteChannel | None) -> None:
        if self.stopped:  # a subscription the SDK reported before the view stopped
            return
        held = self.follows.get(route)
        generation = self._generation()
        if held is not None and channel is held[0] and held[1] == generation:
            return
        if held is not None:
            held[2].cancel()
            del self.follows[route]
        if channel is not None:
            task = asyncio.create_task(self._feed(route, channel), name=f"foxglove-{route}")
            self.follows[route] = (channel, generation, task)

    async def _feed(self, route: str, channel: RouteChannel) -> None:
        placement = self.supervisor.placement
        place = placement.routes.get(route) if placement is not None else None
        if place is not None:
            await asyncio.gather(*(self._follow_worker(self.supervisor.workers[index], route, channel)
                                   for index in place.workers))

    async def _follow_worker(self, worker: Worker, route: str, channel: RouteChannel) -> None:
        """The canonical messages the worker's sink took, from its tap, into ``channel``; the
        tap opened again whenever it ended (the worker restarted) until cancelled."""
        async for line in self.supervisor.follow_tap(worker, route):
            with contextlib.suppress(orjson.JSONDecodeError, TypeError, AttributeError):  # not a tap line
                record = orjson.loads(line)
                if record.get("outcome") == "delivered":
                    channel.send(record.get("canonical"))

    async def stop(self) -> None:
        self.stopped = True
        tasks = [task for _, _, task in self.follows.values()]
        self.follows.clear()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
