"""The engine's connections: opened once, shared by the routes that name them, retried in the
background while unreachable, closed when no route uses them any more.

A connection is identified by ``(name, fingerprint)`` (engine/running/plan.py): a connection whose
settings change is another connection, opened beside the old one (make-before-break) unless
it holds an exclusive resource (:meth:`ConnectionPool.open_exclusive`).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Awaitable, Callable, Iterator, Sequence

from engine import endpoints
from engine.common.backoff import Backoff
from engine.endpoints.base import Connection, EndpointError
from engine.language.specs import ConnectionSpec
from engine.running.plan import ConnectionKey, connection_key

log = logging.getLogger("engine.running.runtime")

OPEN_RETRY_FIRST, OPEN_RETRY_MAX = 0.25, 2.0
"""Backoff between attempts to open a connection that was unreachable at start."""
EXCLUSIVE_RELEASE_S = 2.0
"""How long a handover waits for an exclusive resource the old connection released: the
operating system (or asyncio, which closes a socket on the next loop turn) may free it a
moment after ``close`` returns."""
EXCLUSIVE_RETRY_FIRST, EXCLUSIVE_RETRY_MAX = 0.005, 0.1


class ConnectionPool:
    """Open connections by key; see the module docstring."""

    def __init__(self, require_connections: bool = False,
                 on_opened: Callable[[Connection], Awaitable[None]] | None = None) -> None:
        self.require_connections = require_connections
        """Fail (EndpointError) when a connection cannot be opened, instead of retrying it in
        the background while the routes that do not need it run."""
        self._on_opened = on_opened
        """Called once a connection retried in the background opens."""
        self._connections: dict[ConnectionKey, Connection] = {}
        self._opened: set[int] = set()
        self._openers: dict[int, asyncio.Task[None]] = {}
        self._open_changed = asyncio.Event()

    def items(self) -> list[tuple[ConnectionKey, Connection]]:
        return list(self._connections.items())

    def __iter__(self) -> Iterator[Connection]:
        return iter(list(self._connections.values()))

    async def get(self, spec: ConnectionSpec, retry_in_background: bool = True) -> Connection:
        """The open connection for ``spec``, shared; one that cannot be opened is retried in the
        background (unless ``require_connections`` or ``retry_in_background`` says fail)."""
        key = connection_key(spec)
        connection = self._connections.get(key)
        if connection is None:
            connection = endpoints.transport(spec.protocol).connect(spec.name, spec.options)
            try:
                await connection.open()
            except EndpointError as error:
                if self.require_connections or not retry_in_background:
                    raise
                log.warning("connection unreachable; retrying in the background", extra={"connection": spec.name, "error": str(error)})
                self._openers[id(connection)] = asyncio.create_task(self._keep_opening(connection, str(error)), name=f"open-{spec.name}")
            else:
                self._opened.add(id(connection))
            self._connections[key] = connection
        return connection

    async def _keep_opening(self, connection: Connection, reason: str) -> None:
        """Retry with the engine's backoff. A retry failing as the last did is logged at debug
        only, but a new reason is a warning: the first attempt often fails for another reason
        than the rest (a broker still starting resets the connection, then refuses the client
        certificate), and the log must name what keeps the connection down now."""
        backoff = Backoff(OPEN_RETRY_FIRST, OPEN_RETRY_MAX)
        while True:
            await asyncio.sleep(backoff.next())
            try:
                await connection.open()
            except EndpointError as error:
                now = str(error)
                if now != reason:
                    log.warning("connection still unreachable, now for another reason", extra={"connection": connection.name, "error": now})
                else:
                    log.debug("connection still unreachable", extra={"connection": connection.name, "error": now})
                reason = now
                continue
            self._opened.add(id(connection))
            self._openers.pop(id(connection), None)
            if self._on_opened is not None:
                await self._on_opened(connection)
            self._open_changed.set()
            self._open_changed = asyncio.Event()
            log.info("connection opened", extra={"connection": connection.name})
            return

    def is_open(self, connection: Connection) -> bool:
        """Opened once (it may be reconnecting now: its library takes care of that)."""
        return id(connection) in self._opened

    async def wait_open(self, connections: Sequence[Connection]) -> None:
        while not all(self.is_open(c) for c in connections):
            await self._open_changed.wait()

    async def open_exclusive(self, spec: ConnectionSpec) -> Connection:
        """Open a connection whose exclusive resource was just released, waiting briefly
        for the release to take effect."""
        deadline = time.monotonic() + EXCLUSIVE_RELEASE_S
        backoff = Backoff(EXCLUSIVE_RETRY_FIRST, EXCLUSIVE_RETRY_MAX)
        while True:
            try:
                return await self.get(spec, retry_in_background=False)
            except EndpointError:
                pause = backoff.next()
                if time.monotonic() + pause > deadline:
                    raise
            await asyncio.sleep(pause)

    async def close(self, key: ConnectionKey) -> None:
        connection = self._connections.pop(key, None)
        if connection is not None:
            self._stop_opening(connection)
            self._opened.discard(id(connection))
            await connection.close()

    async def close_unused(self, used: set[int]) -> None:
        """Close every connection whose ``id`` is not in ``used``."""
        for key, connection in list(self._connections.items()):
            if id(connection) not in used:
                await self.close(key)

    def stop_opening(self) -> None:
        """Stop retrying every connection not open yet (the engine stops; the open ones
        still deliver what is in flight)."""
        for connection in self._connections.values():
            self._stop_opening(connection)

    def _stop_opening(self, connection: Connection) -> None:
        opener = self._openers.pop(id(connection), None)
        if opener is not None:
            opener.cancel()

    async def close_all(self) -> None:
        for key in list(self._connections):
            await self.close(key)
