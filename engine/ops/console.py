"""The web console on the admin port: ``GET /`` and a stream of the engine's state for it.

One static page (engine/ops/console_page/: HTML, vanilla JS, CSS; package data, no build step,
nothing fetched from elsewhere, so it works offline) and one server-sent-event stream:

* ``GET /`` (and ``/console.js``, ``/console.css``): the page;
* ``GET /console/events``: ``text/event-stream``, one ``state`` event at once and then every
  :data:`CONSOLE_PERIOD_S`: the status document ``/status`` serves (each route's state,
  counters, rates and last error; without the routes' last canonical message), the recent dead
  letters (route, stage, reason) and the fleet (each agent's last position from the routes whose
  schema is ``position``; engine/running/recent.py). The browser's ``EventSource`` reconnects
  by itself when the engine restarts;
* ``GET /console/state``: that document once, as JSON: what the supervisor of ``run --workers N``
  reads from each worker to show the engine as a whole (engine/ops/supervisor_admin.py), the
  same document its own console then streams (one state builder, merged there, not a second).

The live tap of a route is the admin's own ``GET /tap/{route}``, read by the page with
``fetch`` as a stream of JSON lines. These paths sit behind the admin's access rules like every
other one (engine/ops/admin.py, :class:`~engine.ops.admin.AdminAccess`): the same token, the
same TLS. A browser cannot add ``Authorization: Bearer`` to a page load or an ``EventSource``,
so the admin also takes the token as the password of HTTP Basic (any user name): the browser
asks for it once and sends it with every request to the origin.
"""

from __future__ import annotations

import asyncio
from importlib.resources import files
from typing import TYPE_CHECKING, Any, Awaitable, Callable

import orjson
from aiohttp import web

from engine.common.json_bytes import json_bytes

if TYPE_CHECKING:
    from engine.running.runtime import Engine

CONSOLE_PERIOD_S = 1.0
"""Between two state events: the rates are sampled every second (engine/ops/admin.py)."""
PAGE_FILES = {"/": ("index.html", "text/html"), "/console.js": ("console.js", "text/javascript"),
              "/console.css": ("console.css", "text/css")}
"""Path -> the page's file and its content type."""
PAGE_HEADERS = {"Cache-Control": "no-cache", "X-Frame-Options": "DENY", "X-Content-Type-Options": "nosniff",
                "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'"}
"""The page loads nothing but itself (no CDN, no inline script) and is not framed by another site."""


def page_file(name: str) -> bytes:
    return files("engine.ops").joinpath("console_page", name).read_bytes()


ConsoleState = Callable[[], Awaitable[dict[str, Any]]]
"""What a console shows, built when asked: one engine's (:func:`engine_state`) or the
supervisor's merge of its workers' (engine/ops/supervisor_admin.py ``console_document``)."""


def console_state(engine: Engine, status: Callable[[Engine], dict[str, Any]]) -> dict[str, Any]:
    """What the console shows: ``status`` (the admin's status document) without the routes'
    last canonical messages, the recent dead letters and the fleet."""
    document = status(engine)
    for route in document["routes"].values():
        route.pop("last_canonical", None)
    return {**document, "recent_dead_letters": engine.observers.recent_dead_letters.view(),
            "fleet": engine.observers.fleet.view()}


def engine_state(engine: Engine, status: Callable[[Engine], dict[str, Any]]) -> ConsoleState:
    """:func:`console_state` of one engine, as a :class:`Console` asks for it."""

    async def state() -> dict[str, Any]:
        return console_state(engine, status)

    return state


def state_bytes(state: dict[str, Any]) -> bytes:
    """The document as JSON; one orjson refuses (a position's unbounded ``alt_msl`` as an integer
    beyond 64 bits) by the standard library, not a failed console (engine/common/json_bytes.py)."""
    return json_bytes(state, orjson.OPT_NON_STR_KEYS)


class Console:
    """The console's handlers, added to an admin's application (behind its middleware): one
    engine's (engine/ops/admin.py) or the supervisor's (engine/ops/supervisor_admin.py)."""

    def __init__(self, state: ConsoleState, streams: set[asyncio.Task[Any]]) -> None:
        self.state = state
        self.streams = streams
        """The admin's set of streaming tasks, ended when the admin stops."""
        self.pages = {path: (page_file(name), content_type) for path, (name, content_type) in PAGE_FILES.items()}

    def add_to(self, app: web.Application) -> None:
        for path in self.pages:
            app.router.add_get(path, self.page)
        app.router.add_get("/console/events", self.events)
        app.router.add_get("/console/state", self.current)

    async def page(self, request: web.Request) -> web.Response:
        body, content_type = self.pages[request.path]
        return web.Response(body=body, content_type=content_type, headers=PAGE_HEADERS)

    async def current(self, request: web.Request) -> web.Response:
        return web.Response(body=state_bytes(await self.state()), content_type="application/json")

    async def events(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-cache"})
        task = asyncio.current_task()
        assert task is not None
        self.streams.add(task)
        try:
            await response.prepare(request)
            while True:
                await response.write(b"event: state\ndata: " + state_bytes(await self.state()) + b"\n\n")
                await asyncio.sleep(CONSOLE_PERIOD_S)
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self.streams.discard(task)
        return response
