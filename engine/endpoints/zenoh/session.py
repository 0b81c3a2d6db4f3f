"""The Zenoh connection's session side: one ``zenoh.Session`` shared by every route that names it.

eclipse-zenoh keeps the session's links up by itself (a peer retries its ``connect``
endpoints in the background, a client reconnects to a router), so this module only opens and
closes the session, and follows its transports for health. Health follows the session: a
connection that must reach someone (a client, or a peer with ``connect`` endpoints) is
``up`` while at least one transport is open, ``reconnecting`` while none is (its sinks then
hold their messages instead of putting them into the void); a peer that only listens or
scouts is ``up`` once open, as nobody in particular is missing. The transports are counted
every HEALTH_POLL seconds (``SessionInfo.routers_zid`` and ``peers_zid``, 4 us a count here):
stable since eclipse-zenoh 1.0, where the transport events listener is recent and marked
unstable.

The library's calls are blocking: opening a peer whose ``connect`` endpoint is down waits
half a second, closing waits for the links to end, and a put with ``block`` waits while the
send queue is full. They run in a worker thread (``asyncio.to_thread``), never on the loop.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any, Mapping, Sequence

import zenoh

from engine.endpoints.base import Connection, EndpointError, typed
from engine.endpoints.zenoh.errors import describe, mapped
from engine.endpoints.zenoh.options import ZenohConnectionOptions, ZenohSinkOptions

log = logging.getLogger("engine.zenoh")

HEALTH_POLL = 0.2
"""Seconds between two counts of the session's transports (the engine's own health poll)."""
OPEN_TIMEOUT = 30.0
"""Seconds for ``zenoh.open`` (a peer waits for its connect endpoints' first attempt only)."""
CONGESTION = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}
PRIORITY = {name: getattr(zenoh.Priority, name.upper()) for name in (
    "real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background")}


def session_config(settings: ZenohConnectionOptions) -> zenoh.Config:
    """The session's configuration: ``config_file`` if any, the connection's keys over it.
    Raises ZError (a malformed file or endpoint) or OSError (a file that cannot be read)."""
    config = zenoh.Config.from_file(settings.config_file) if settings.config_file else zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.listen:
        config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    return config


class ZenohLink(Connection):
    """Everything of the connection but making its sources and sinks (connection.py)."""

    settings: ZenohConnectionOptions

    def __init__(self, name: str, settings: ZenohConnectionOptions | Mapping[str, Any]) -> None:
        super().__init__(name, typed(ZenohConnectionOptions, settings, f"zenoh connection {name!r}"))
        options = self.settings
        shown = ", ".join((*(f"connect {e}" for e in options.connect), *(f"listen {e}" for e in options.listen)))
        self.where = f"zenoh connection {name!r} ({options.mode}{': ' + shown if shown else ''})"
        self._session: zenoh.Session | None = None
        self._watch: asyncio.Task[None] | None = None
        self._transports = 0
        """Peers and routers with an open transport, at the last count."""
        self._needs_transport = options.mode == "client" or bool(options.connect)
        self._state = "connecting"
        self._last_error: str | None = None

    # -- health

    @property
    def healthy(self) -> bool:
        return self._state == "up"

    def health(self) -> dict[str, Any]:
        return {"state": self._state, "last_error": self._last_error, "mode": self.settings.mode,
                "transports": self._transports}

    def _judge(self) -> None:
        session = self._session
        if session is None:
            return
        info = session.info
        self._transports = len(info.routers_zid()) + len(info.peers_zid())
        if self._transports or not self._needs_transport:
            self._state = "up"
        else:
            self._state = "reconnecting"
            self._last_error = f"no open transport to any of {', '.join(self.settings.connect) or 'the routers'}"

    async def _watch_transports(self) -> None:
        while self._session is not None:
            try:
                self._judge()
            except zenoh.ZError as exc:  # the session closed under us
                self._state, self._last_error = "down", describe(exc)
            await asyncio.sleep(HEALTH_POLL)

    # -- opening and closing

    async def open(self) -> None:
        """Open the session (EndpointError if it cannot be opened: a client whose routers are
        all unreachable; the engine retries) and follow its transports."""
        if self._session is not None:
            return

        def opening() -> zenoh.Session:
            with mapped(self.where):
                return zenoh.open(session_config(self.settings))

        try:
            self._session = await asyncio.wait_for(asyncio.to_thread(opening), OPEN_TIMEOUT)
        except (EndpointError, asyncio.TimeoutError) as error:
            self._state = "down"
            self._last_error = describe(error.__cause__ or error)
            if isinstance(error, asyncio.TimeoutError):
                raise EndpointError(f"{self.where}: not open within {OPEN_TIMEOUT:.0f} s") from None
            raise
        self._judge()
        self._watch = asyncio.create_task(self._watch_transports(), name=f"zenoh-health:{self.name}")

    @property
    def session(self) -> zenoh.Session:
        """The open session; EndpointError when there is none (not opened yet, or closed)."""
        session = self._session
        if session is None:
            raise EndpointError(f"{self.where} is not open")
        return session

    async def close(self) -> None:
        session, self._session = self._session, None
        self._state = "down"
        self._transports = 0
        if self._watch is not None:
            self._watch.cancel()
            await asyncio.gather(self._watch, return_exceptions=True)
            self._watch = None
        if session is None:
            return
        try:
            await asyncio.to_thread(session.close)
        except Exception as exc:  # closing is best effort: the links end with the process anyway
            log.warning("closing the session failed", extra={"connection": self.name, "error": describe(exc)})

    # -- putting

    async def put_batch(self, messages: Sequence[tuple[str, bytes]], options: ZenohSinkOptions,
                        where: str) -> list[BaseException | None]:
        """Put ``(key, payload)`` in order, in one worker thread; ``result[i]`` is None once
        message i was queued for sending, else its edge error."""
        try:
            session = self.session
        except EndpointError as exc:
            return [EndpointError(f"{where}: {exc}")] * len(messages)
        arguments = {"encoding": options.encoding, "congestion_control": CONGESTION[options.congestion_control],
                     "priority": PRIORITY[options.priority], "express": options.express}

        def putting() -> list[BaseException | None]:
            results: list[BaseException | None] = []
            for key, payload in messages:
                try:
                    with mapped(f"{where}: put on {key!r}"):
                        session.put(key, payload, **arguments)
                except EndpointError as exc:
                    results.append(exc)
                else:
                    results.append(None)
            return results

        return await asyncio.to_thread(putting)
