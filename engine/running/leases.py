"""The broker leases of ``active_standby`` routes: one per (connection, lease name), shared by
the routes of this instance that name it, so the routes of one robot fail over together."""

from __future__ import annotations

from typing import Any, Iterable

from engine.endpoints.base import Connection, Lease


class Leases:
    def __init__(self, instance: str) -> None:
        self.instance = instance
        self._leases: dict[tuple[int, str], Lease] = {}

    async def take(self, connection: Connection, name: str, heartbeat: float) -> Lease:
        """The lease ``name`` on ``connection``, started when this is its first route."""
        key = (id(connection), name)
        lease = self._leases.get(key)
        if lease is None:
            lease = connection.lease(name, self.instance, heartbeat)
            await lease.start()
            self._leases[key] = lease
        return lease

    async def release_unused(self, used: Iterable[Any]) -> None:
        """Stop every lease not in ``used`` (the leases of the routes that run now)."""
        keep = {id(lease) for lease in used if lease is not None}
        for key, lease in list(self._leases.items()):
            if id(lease) not in keep:
                del self._leases[key]
                await lease.stop()
