"""What a new configuration changes, as a value: the reload plan.

:func:`plan_reload` compares the running configuration with a newly loaded one and says, for
every route and every connection, what a reload must do. It is a pure function of two
:class:`~engine.language.specs.RoutesConfig` values (fingerprints already cover the schema contents,
the key files and the connection settings), so it is tested on its own, as Vector's
``ConfigDiff`` is; :meth:`engine.running.runtime.Engine._apply` carries it out.

Routes:

* ``keep``: fingerprint unchanged, nothing is touched;
* ``swap_pipeline``: the source (its options and its connection) is unchanged, so the live
  source keeps running and a new pipeline (mapping, schema, sink) is swapped in;
* ``replace_source``: the source changed, a new runner replaces the old one;
* ``add`` / ``remove``.

Connections are identified by ``(name, fingerprint)``: a changed connection is a new one
to ``open`` and an old one to ``close``. Usually the new one opens first and the old one
closes once nothing uses it (make-before-break). A connection holding an exclusive
resource (a listening port, a serial device) cannot coexist with its successor, so the
plan lists a :class:`Handover`: its routes stop, the old connection closes, the new one
opens and the routes start again (break-before-make), while routes on other connections
are untouched.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from engine.language.specs import ConnectionSpec, RoutesConfig, RouteSpec

ConnectionKey = tuple[str, str]
"""``(connection name, fingerprint)``: a connection whose settings change is another one."""


@dataclass(frozen=True)
class Handover:
    """An exclusive resource passed from an old connection to a new one, break-before-make."""

    resource: str
    close: ConnectionKey
    open: ConnectionKey
    routes: tuple[str, ...]
    """Routes (of either configuration) on either connection: stopped before ``close`` and,
    when still configured, started after ``open``."""


@dataclass(frozen=True)
class ReloadPlan:
    add: tuple[str, ...] = ()
    swap_pipeline: tuple[str, ...] = ()
    replace_source: tuple[str, ...] = ()
    remove: tuple[str, ...] = ()
    keep: tuple[str, ...] = ()
    open: tuple[ConnectionKey, ...] = ()
    close: tuple[ConnectionKey, ...] = ()
    handovers: tuple[Handover, ...] = ()

    @property
    def empty(self) -> bool:
        return not (self.add or self.swap_pipeline or self.replace_source or self.remove or self.open or self.close)

    @property
    def break_before_make(self) -> frozenset[str]:
        """Routes applied in the handover step rather than make-before-break."""
        return frozenset(name for handover in self.handovers for name in handover.routes)

    def summary(self) -> dict[str, list[str]]:
        return {
            "add": list(self.add),
            "swap_pipeline": list(self.swap_pipeline),
            "replace_source": list(self.replace_source),
            "remove": list(self.remove),
            "open": [name for name, _ in self.open],
            "close": [name for name, _ in self.close],
            "break_before_make": [h.resource for h in self.handovers],
        }


def connection_key(spec: ConnectionSpec) -> ConnectionKey:
    return (spec.name, spec.fingerprint)


def route_connections(config: RoutesConfig, route: RouteSpec) -> tuple[ConnectionKey, ...]:
    """The route's source connection, then its sink connection."""
    return tuple(connection_key(config.connections[e.connection]) for e in route.endpoints())


def plan_reload(old: RoutesConfig | None, new: RoutesConfig) -> ReloadPlan:
    """What applying ``new`` over the running ``old`` (None at start) must do."""
    old_routes: Mapping[str, RouteSpec] = old.routes if old is not None else {}
    add, swap, replace, remove, keep = [], [], [], [], []
    for name, route in new.routes.items():
        before = old_routes.get(name)
        if before is None:
            add.append(name)
        elif before.fingerprint == route.fingerprint:
            keep.append(name)
        elif old is not None and _source(old, before) == _source(new, route):
            swap.append(name)
        else:
            replace.append(name)
    remove = [name for name in old_routes if name not in new.routes]

    used_before = _used(old) if old is not None else {}
    used_after = _used(new)
    opened = [key for key in used_after if key not in used_before]
    closed = [key for key in used_before if key not in used_after]

    handovers = []
    for key in closed:
        resource = used_before[key].exclusive
        successor = next((k for k in opened if resource and used_after[k].exclusive == resource), None)
        if successor is None:
            continue
        assert old is not None
        on_either = [n for n, r in old.routes.items() if key in route_connections(old, r)]
        on_either += [n for n, r in new.routes.items() if successor in route_connections(new, r) and n not in on_either]
        handovers.append(Handover(resource or "", key, successor, tuple(sorted(on_either))))
    # A route whose old sink holds the resource cannot keep its source across the gap
    # with nowhere to deliver: it is replaced as a whole in the handover.
    moved = {name for handover in handovers for name in handover.routes}
    replace += [name for name in swap if name in moved]
    swap = [name for name in swap if name not in moved]

    return ReloadPlan(
        add=tuple(sorted(add)),
        swap_pipeline=tuple(sorted(swap)),
        replace_source=tuple(sorted(replace)),
        remove=tuple(sorted(remove)),
        keep=tuple(sorted(keep)),
        open=tuple(sorted(opened)),
        close=tuple(sorted(closed)),
        handovers=tuple(sorted(handovers, key=lambda h: h.resource)),
    )


def _source(config: RoutesConfig, route: RouteSpec) -> tuple[object, ...]:
    """What a live source depends on: its endpoint options, its connection, and where and how
    it runs (``ordered``, ``instances``, ``active_standby``: a single-active-consumer queue or
    a lease cannot be changed under a running consumer)."""
    return (route.source, connection_key(config.connections[route.source.connection]), route.placement)


def _used(config: RoutesConfig) -> dict[ConnectionKey, ConnectionSpec]:
    """Connections some route uses (only those are ever opened)."""
    used: dict[ConnectionKey, ConnectionSpec] = {}
    for route in config.routes.values():
        for endpoint in route.endpoints():
            spec = config.connections[endpoint.connection]
            used[connection_key(spec)] = spec
    return used
