"""Which worker of ``run --workers N`` runs each route: one pure function of the configuration.

:func:`place_routes` reads a compiled :class:`~engine.language.specs.RoutesConfig` and the
worker count and says, for every route, on which workers it runs and why. Like the reload
plan (engine/running/plan.py) it is a value, tested on its own (tests/running/test_placement.py);
the supervisor (engine/ops/supervisor.py) prints it for ``check --workers N`` and each worker
(engine/running/worker.py) runs the routes it is given. The rules, first that applies:

1. **Something one process must hold alone**: a route whose source, sink or fallback connection
   has an exclusive resource (a serial device, a listening port, an MQTT client id) or a
   worker affinity (``Transport.worker_affinity``: a MAVLink link) runs on exactly one worker,
   the one that owns it. Routes that share one (every route of the farm's radio) share the owner;
   affinities a route joins (a radio to a listening port) are owned together (union-find), so
   two workers never open one device. The owner is a stable hash of the group's first key:
   the same configuration places the same way in every process and after every restart.
   A connection split over the workers (``Transport.splits_connection``: a MAVLink ``udpin``
   link with ``split_over_workers``) is held the same way by one worker, its *owner*, but
   holds no route that reads it (rule 1b) nor one that runs on every worker anyway (rules 3
   and 4: a command queue's consumers), which send through the owner; a route that writes to
   it from one worker is held with it, so the owner always runs one of its routes.
1b. **A connection split over the workers**: a route that reads one runs on every worker,
   each worker's connection getting its share of what comes in (a MAVLink link's vehicles by
   system id, engine/endpoints/mavlink/split.py). Such a route cannot also hold a resource
   or keep state in the process (rules 1 and 2: one worker would see a share only):
   :class:`PlacementError` names it.
2. **State the process keeps across messages**: the latest-value stores (``remember:`` and
   ``recall()``) are one table per process, so every route that writes or reads one runs with
   the others on one worker (the key ``stores``); a route's own state (``dedupe:``,
   ``window:``, ``throttle:``, ``sequence()``) would see only part of the messages on several
   workers, and a buffer's spill directory (``spill_dir/<route>/``) or a dedupe key file
   belongs to one process, so such a route runs on one worker, by the hash of its name.
3. **Competing consumers**: a source whose consumers compete for one stream
   (``Transport.spreads_over_workers``: an AMQP queue, an MQTT shared subscription) runs on
   every worker; the broker hands each message to one of them, and what a worker that died
   had not acknowledged to another (an AMQP queue; MQTT as the broker treats a shared
   subscription's in-flight messages of a session that ended).
4. **Discovered streams**: a source that follows the streams it discovers
   (``Transport.splits_over_workers``: a ROS 2 topic pattern, ``/{agent}/fix``) runs on every
   worker, and each worker follows only the streams whose stable hash falls in its share
   (engine/common/shares.py): a fleet's agents spread over the workers, every agent on one.
5. **Everything else** (a ROS 2 topic, a plain MQTT subscription, a Zenoh key: each subscriber
   gets every message) runs on one worker, by a stable hash of the route's name.

A hash, not a balancer: placement must not depend on what runs now, or a restart or a reload
would move routes between processes. With few one-worker routes the split can be uneven;
``check --workers N`` shows it. What is not built: a serial radio shared by the workers
(one owner through which every worker sends: a radio's routes run on its owner alone), and a
route that reads a split connection while keeping state in the process.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

from engine import endpoints
from engine.common.shares import share_of
from engine.language.specs import ConnectionSpec, RoutesConfig, RouteSpec

STORES = "stores"
"""The affinity key of the routes that share the latest-value stores (rule 2)."""


class PlacementError(ValueError):
    """The worker count cannot place the routes: ``file`` and ``line`` of the route at fault,
    where one is (``check`` and the supervisor report it as a problem of that file)."""

    def __init__(self, message: str, file: str = "", line: int = 0) -> None:
        super().__init__(f"{file}:{line}: {message}" if file else message)
        self.message, self.file, self.line = message, file, line


@dataclass(frozen=True)
class RoutePlace:
    """Where one route runs: its workers (all of them for a competing source) and why."""

    workers: tuple[int, ...]
    reason: str
    split: bool = False
    """Every worker runs it, each following its share of the streams the source discovers
    (``Transport.splits_over_workers``): the worker gives the source its share."""


@dataclass(frozen=True)
class WorkerPlacement:
    workers: int
    routes: Mapping[str, RoutePlace]
    owners: Mapping[str, int] = field(default_factory=dict)
    """Each connection split over the workers (rule 1b) -> the worker that holds it."""

    def on(self, worker: int) -> frozenset[str]:
        """The routes worker ``worker`` runs."""
        return frozenset(name for name, place in self.routes.items() if worker in place.workers)

    def lines(self) -> list[str]:
        """What ``check --workers N`` prints: one line a route, then each worker's count."""
        shown = []
        for name, place in sorted(self.routes.items()):
            where = "every worker" if len(place.workers) == self.workers > 1 else f"worker {place.workers[0]}"
            shown.append(f"  {name}: {where} ({place.reason})")
        counts = ", ".join(f"worker {k}: {len(self.on(k))}" for k in range(self.workers))
        held = [f"  connection {name}: split over every worker, held by worker {owner}" for name, owner in sorted(self.owners.items())]
        return [f"placement on {self.workers} workers ({counts} routes):", *shown, *held]


def stable_worker(key: str, workers: int) -> int:
    """The worker a key hashes to, the same in every process (engine/common/shares.py)."""
    return share_of(key, workers)


def held_alone(spec: ConnectionSpec) -> str | None:
    """The connection's exclusive resource, else its affinity as its protocol states it
    (``Transport.worker_affinity``, engine/endpoints/workers.py)."""
    settings = spec.options if spec.options is not None else spec.settings
    return spec.exclusive or endpoints.transport(spec.protocol).worker_affinity(spec.name, settings)


def splits(spec: ConnectionSpec) -> bool:
    """Whether the connection is split over the workers (``Transport.splits_connection``)."""
    return spec.options is not None and endpoints.transport(spec.protocol).splits_connection(spec.options)


def splits_over_workers(route: RouteSpec) -> bool:
    """Whether the route's source follows streams it discovers, each a worker's share (``Transport.splits_over_workers``)."""
    return endpoints.transport(route.source.protocol).splits_over_workers(route.source.options)


def spreads_over_workers(route: RouteSpec) -> bool:
    """Whether the route's source spreads over every worker (``Transport.spreads_over_workers``)."""
    return endpoints.transport(route.source.protocol).spreads_over_workers(route.source.options)


def place_routes(config: RoutesConfig, workers: int) -> WorkerPlacement:
    """Place every route of ``config`` on ``workers`` workers (see the module docstring)."""
    if workers < 1:
        raise PlacementError(f"--workers {workers}: at least 1")
    split = {name: held_alone(spec) or f"connection {name!r}" for name, spec in config.connections.items() if splits(spec)}
    keys_of = {name: _keys(config, route, split) for name, route in config.routes.items()}
    owner = _union(keys_of.values())
    every = tuple(range(workers))
    places: dict[str, RoutePlace] = {}
    owners = {connection: stable_worker(owner.get(key, key), workers) for connection, key in split.items()}
    for name, route in config.routes.items():
        keys = keys_of[name]
        if (read := route.source.connection) in split:
            held = ", ".join(keys) if keys else _own_state(route)
            if held is not None:
                raise PlacementError(f"route {name!r}: reads connection {read!r}, split over the workers (each worker gets "
                                     f"its share of what comes in), but holds or keeps {held}, which one worker must do; "
                                     "give it a connection without the split, or no such state", route.file, route.line)
            places[name] = RoutePlace(every, f"each worker with its share of connection {read}, held by worker {owners[read]}")
        elif keys:
            group = owner[keys[0]]
            held = ", ".join(keys)
            joined = f"; with {group}" if group not in keys else ""
            places[name] = RoutePlace((stable_worker(group, workers),), f"holds {held}{joined}")
        elif (state := _own_state(route)) is not None:
            places[name] = RoutePlace((stable_worker(name, workers),), f"keeps {state} in the process")
        elif spreads_over_workers(route):
            places[name] = RoutePlace(every, "competing consumers")
        elif splits_over_workers(route):
            places[name] = RoutePlace(every, "each worker follows its share of the discovered streams", split=True)
        else:
            places[name] = RoutePlace((stable_worker(name, workers),), "hash of the route name")
    return WorkerPlacement(workers, places, owners)


def _keys(config: RoutesConfig, route: RouteSpec, split: Mapping[str, str]) -> tuple[str, ...]:
    """What the route holds (rule 1): a split connection only where the route writes to it
    from one worker (then it runs on the connection's owner); never where it reads it (rule 1b)."""
    found = [held_alone(config.connections[endpoint.connection]) for endpoint in route.endpoints() if endpoint.connection not in split]
    if route.remember is not None or any("recall(" in text for text in _expressions(route)):
        found.append(STORES)
    held = {key for key in found if key}
    everywhere = route.source.connection in split or (
        not held and _own_state(route) is None and (spreads_over_workers(route) or splits_over_workers(route)))
    if not everywhere:
        held |= {split[endpoint.connection] for endpoint in route.endpoints() if endpoint.connection in split}
    return tuple(sorted(held))


def _expressions(route: RouteSpec) -> list[str]:
    remembered = route.remember if isinstance(route.remember, tuple) else (route.remember,) if route.remember else ()
    sinks = [*route.sinks, *(sink.fallback for sink in route.sinks if sink.fallback is not None)]
    texts = [route.mapping, route.sink_mapping, route.when, route.reply.mapping if route.reply else None,
             *(getattr(entry, "value", None) for entry in remembered), *(text for sink in sinks for text in (sink.mapping, sink.when))]
    return [text for text in texts if isinstance(text, str)]


def _own_state(route: RouteSpec) -> str | None:
    """What state of its own the route keeps in the process, or None."""
    if route.dedupe is not None:
        return "dedupe keys"
    if route.window is not None:
        return "a window"
    if route.throttle is not None:
        return "a throttle"
    if route.buffer is not None and route.buffer.spill_dir is not None:
        return "a spill directory"
    if any("sequence(" in text for text in _expressions(route)):
        return "a sequence"
    return None


def _union(groups: Iterable[tuple[str, ...]]) -> dict[str, str]:
    """Each key -> its group's representative (the smallest key): keys a route holds together
    are one group."""
    parent: dict[str, str] = {}

    def find(key: str) -> str:
        parent.setdefault(key, key)
        while parent[key] != key:
            parent[key] = parent[parent[key]]
            key = parent[key]
        return key

    for keys in groups:
        for key in keys:
            find(key)
        for key in keys[1:]:
            a, b = find(keys[0]), find(key)
            if a != b:
                parent[max(a, b)] = min(a, b)
    return {key: find(key) for key in parent}
