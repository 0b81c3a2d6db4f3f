"""``run --foxglove [HOST:]PORT``: a live, read-only view of the engine in Foxglove (or Lichtblick).

Served by the Foxglove SDK (``foxglove-sdk``: its Rust WebSocket server, subprotocol
``foxglove.sdk.v1``, the same protocol as ``foxglove.websocket.v1`` under its new name), with
its own :class:`foxglove.Context`, so nothing else logged through the SDK's global context
(a recording) shows up here. Channels:

- ``/routes/NAME/canonical``: each route's canonical messages as its sink took them, JSON,
  the route's schema bundled into one JSON Schema (``SchemaRegistry.bundled``) as the
  channel's schema (named after the schema, e.g. ``position.v1``).
- ``/fleet``: ``foxglove.LocationFixes`` (JSON, Foxglove's own JSON Schema of the type, from
  ``@foxglove/schemas`` 2.1.0, MIT, in ``foxglove_location_fixes.schema.json`` beside this
  file): every agent whose canonical position (a route whose schema is ``position``) was taken
  within the last :data:`FLEET_WINDOW_S` seconds, one fix each, with a colour of its own
  derived from its ``agent_id`` (the same on every run and every engine). Sent once a second.
- ``/routes/status``: the routes' state, counters and rates, JSON, once a second.

Where the data comes from is a :class:`ViewFeed`: one engine in this process
(:class:`EngineFeed`, below) or, under ``run --workers N``, the supervisor's workers
(engine/ops/supervisor_foxglove.py: the merged status, the merged fleet and the workers' taps),
so the channels, schemas and subscriptions are this module's in both.

Cost (one engine): a route's channel is wired to its observer (``RouteObserver.watchers``)
only while a client subscribes to it, and the fleet's observer of position routes only while a
client subscribes to ``/fleet``; the SDK tells of each subscribe and unsubscribe through its server
listener. With no client the hot path does nothing more than before (one truth test); with one,
a message costs one ``orjson`` serialisation and the SDK's queueing. The SDK never waits for a
slow client: each client has a bounded queue (``message_backlog_size``) whose oldest message
is dropped, so a view never holds a route. Status and fleet messages are built only when
subscribed. Measured figures: bench/bench_foxglove.py and docs/operations.md.

Read-only: the server advertises no capability (no ``clientPublish``, no parameters, no
services), so a client's ``advertise`` and message data are refused by the SDK with a status
message and reach no route. Keeping a non-local client out: the server binds 127.0.0.1 unless
``--foxglove HOST:PORT`` names another address; the SDK serves TLS (``--foxglove-tls-cert``,
``--foxglove-tls-key``: only ``wss://`` is then accepted) but has no client authentication (no
token), so an address other than loopback should be reached through TLS on a network the
admin trusts, or through an SSH tunnel to the loopback address.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import math
import threading
import time
from argparse import Namespace
from colorsys import hsv_to_rgb
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Hashable, Protocol, Sequence

import foxglove
import orjson
from foxglove.websocket import ChannelView, Client, ServerListener

from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Outbound
from engine.language.specs import RoutesConfig
from engine.ops.admin import status_document

if TYPE_CHECKING:
    from engine.running.runtime import Engine

log = logging.getLogger("engine.ops.foxglove")

ROUTE_TOPIC = "/routes/{route}/canonical"
FLEET_TOPIC = "/fleet"
STATUS_TOPIC = "/routes/status"
FLEET_WINDOW_S = 60.0
"""An agent stays on the map this long after its last position."""
POSITION_SCHEMA = "position"
TICK_S = 1.0
"""The status and the fleet are sent, and the channels follow a reload, once a second."""
_ORJSON_OPTIONS = orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY
LOCATION_FIXES_SCHEMA: dict[str, Any] = json.loads(
    resources.files("engine.ops").joinpath("foxglove_location_fixes.schema.json").read_text(encoding="utf-8"))
STATUS_SCHEMA: dict[str, Any] = {
    "title": "rabbitros.RouteStatus",
    "type": "object",
    "properties": {
        "generation": {"type": "integer"},
        "instance": {"type": "string"},
        "routes": {"type": "object", "additionalProperties": {"type": "object", "properties": {
            "state": {"type": "string"}, "received": {"type": "integer"}, "delivered": {"type": "integer"},
            "failed": {"type": "integer"}, "received_per_s": {"type": "number"}, "delivered_per_s": {"type": "number"},
            "latency_mean_s": {"type": ["number", "null"]}, "last_error": {"type": ["string", "null"]}}}},
    },
    "required": ["routes"],
}
STATUS_FIELDS = ("state", "received", "delivered", "failed", "conflated", "expired", "dropped", "retries", "sink_errors")


def agent_colour(agent_id: str) -> dict[str, float]:
    """A stable RGBA colour for ``agent_id``: a hue from its SHA-256 (not Python's ``hash``,
    which changes per process), full saturation, bright enough to see on a map."""
    hue = int.from_bytes(hashlib.sha256(agent_id.encode()).digest()[:4], "big") / 2**32
    r, g, b = hsv_to_rgb(hue, 0.85, 0.95)
    return {"r": round(r, 4), "g": round(g, 4), "b": round(b, 4), "a": 1.0}


class RouteChannel:
    """One route's canonical stream: called by the route's observer while subscribed (one
    engine), or handed the canonical messages a worker's tap carried (:meth:`send`)."""

    def __init__(self, route: str, schema_name: str, schema: dict[str, Any], context: foxglove.Context) -> None:
        self.route = route
        self.schema_key = (schema_name, orjson.dumps(schema, option=orjson.OPT_SORT_KEYS))
        self.channel = foxglove.Channel(
            ROUTE_TOPIC.format(route=route), context=context, message_encoding="json",
            schema=foxglove.Schema(name=schema_name, encoding="jsonschema", data=self.schema_key[1]),
            metadata={"route": route, "schema": schema_name})
        self.errors = 0

    def __call__(self, outbound: Outbound) -> None:
        self.send(outbound.canonical)

    def send(self, canonical: Any) -> None:
        try:
            self.channel.log(orjson.dumps(canonical, default=str, option=_ORJSON_OPTIONS), log_time=time.time_ns())
        except (TypeError, orjson.JSONEncodeError):  # a view must never fail a route: counted
            self.errors += 1


class Fleet:
    """The latest position of every agent one engine took, kept only while ``/fleet`` is
    subscribed (a watcher of the position routes, :class:`EngineFeed`)."""

    def __init__(self) -> None:
        self.latest: dict[str, tuple[float, dict[str, Any]]] = {}

    def __call__(self, outbound: Outbound) -> None:
        position = outbound.canonical
        if not isinstance(position, dict):
            return
        agent = position.get("agent_id")
        if agent is not None:
            self.latest[str(agent)] = (time.monotonic(), position)

    def recent(self, now: float) -> dict[str, dict[str, Any]]:
        """Agent -> its position, of the agents heard within :data:`FLEET_WINDOW_S`."""
        for agent in [a for a, (at, _) in self.latest.items() if now - at > FLEET_WINDOW_S]:
            del self.latest[agent]
        return {agent: position for agent, (_, position) in self.latest.items()}


def location_fixes(positions: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The ``foxglove.LocationFixes`` of agent -> canonical position, one fix each, by agent."""
    return {"fixes": [location_fix(agent, position) for agent, position in sorted(positions.items())]}


def location_fix(agent: str, position: dict[str, Any]) -> dict[str, Any]:
    """A canonical position (schemas/position.v1.json) as a ``foxglove.LocationFix``: its stamp
    (else now), altitude above mean sea level (else 0), heading from degrees to radians."""
    stamp = position.get("stamp")
    if isinstance(stamp, dict) and isinstance(stamp.get("sec"), int):
        timestamp = {"sec": stamp["sec"], "nsec": int(stamp.get("nanosec", 0))}
    else:
        now = time.time_ns()
        timestamp = {"sec": now // 1_000_000_000, "nsec": now % 1_000_000_000}
    fix: dict[str, Any] = {
        "timestamp": timestamp,
        "frame_id": agent,
        "latitude": float(position["lat"]),
        "longitude": float(position["lon"]),
        "altitude": float(position.get("alt_msl") or 0.0),
        "position_covariance": [0.0] * 9,
        "position_covariance_type": 0,
        "color": agent_colour(agent),
        "metadata": [{"key": "agent_id", "value": agent}],
    }
    heading = position.get("heading")
    if isinstance(heading, (int, float)):
        fix["heading"] = math.radians(heading)
    return fix


def status_message(document: dict[str, Any]) -> dict[str, Any]:
    """``/routes/status`` from a status document (engine/ops/admin.py's, or the supervisor's
    merge of its workers'): each route's state, counters, rates, mean latency and last error."""
    routes = {name: {"state": route.get("state"), **{key: route.get(key, 0) for key in STATUS_FIELDS[1:]},
                     "received_per_s": route.get("received_per_s", 0.0), "delivered_per_s": route.get("delivered_per_s", 0.0),
                     "latency_mean_s": route.get("latency_mean_s"), "last_error": route.get("last_error")}
              for name, route in sorted(document.get("routes", {}).items())}
    return {"generation": document.get("generation"), "instance": document.get("instance"), "routes": routes}


class ViewFeed(Protocol):
    """Where a :class:`FoxgloveView` takes its data from: one engine (:class:`EngineFeed`) or
    the workers of ``run --workers N`` (engine/ops/supervisor_foxglove.py)."""

    name: str
    """The server's name, as a client shows it."""

    def running(self) -> tuple[Hashable, RoutesConfig, Sequence[Path], Sequence[str]] | None:
        """(what changes with every reload, the routes, the schema directories, the names of
        the routes running), None while they are still loading."""

    async def status(self) -> dict[str, Any]:
        """A status document (asked only while ``/routes/status`` is subscribed)."""

    async def positions(self) -> dict[str, dict[str, Any]]:
        """Agent -> its canonical position, heard within :data:`FLEET_WINDOW_S` (asked only
        while ``/fleet`` is subscribed)."""

    def wire(self, route: str, channel: RouteChannel | None, fleet: bool) -> None:
        """Feed ``channel`` with the route's canonical messages (None: no longer), and the fleet
        with its positions when ``fleet``. Called from the SDK's thread too (a subscription)."""

    async def stop(self) -> None:
        """Feed nothing any more."""


class EngineFeed:
    """One engine in this process: its status document and its routes' observers."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.name = f"rabbitros-engine {engine.instance}"
        self.fleet = Fleet()

    def running(self) -> tuple[Hashable, RoutesConfig, Sequence[Path], Sequence[str]] | None:
        config = self.engine.config
        if config is None:
            return None
        return (self.engine.generation, config.content_hash), config, self.engine.schemas_dirs, list(self.engine.runners)

    async def status(self) -> dict[str, Any]:
        return status_document(self.engine)

    async def positions(self) -> dict[str, dict[str, Any]]:
        return self.fleet.recent(time.monotonic())

    def wire(self, route: str, channel: RouteChannel | None, fleet: bool) -> None:
        watchers: list[Any] = [channel] if channel is not None else []
        if fleet:
            watchers.append(self.fleet)
        self.engine.observers.get(route).watchers = tuple(watchers)

    async def stop(self) -> None:
        for route in self.engine.runners:
            self.engine.observers.get(route).watchers = ()


class FoxgloveView(ServerListener):
    """The server and its channels (see the module docstring); also the SDK's server listener."""

    def __init__(self, feed: ViewFeed, host: str, port: int, tls_cert: Path | None = None, tls_key: Path | None = None) -> None:
        self.feed = feed
        self.host, self.port = host, port
        self.tls = (tls_cert.read_bytes(), tls_key.read_bytes()) if tls_cert and tls_key else None
        self.context = foxglove.Context()
        self.routes: dict[str, RouteChannel] = {}
        self.positions: set[str] = set()
        """The routes whose canonical schema is ``position``: what the fleet watches."""
        self.fleet = foxglove.Channel(FLEET_TOPIC, context=self.context, message_encoding="json",
                                      schema=foxglove.Schema(name="foxglove.LocationFixes", encoding="jsonschema",
                                                             data=json.dumps(LOCATION_FIXES_SCHEMA).encode()))
        self.status = foxglove.Channel(STATUS_TOPIC, context=self.context, message_encoding="json",
                                       schema=foxglove.Schema(name="rabbitros.RouteStatus", encoding="jsonschema",
                                                              data=json.dumps(STATUS_SCHEMA).encode()))
        self.subscribers: dict[int, int] = {}
        """Channel id -> subscriptions to it (the SDK calls the listener from its own thread)."""
        self._lock = threading.Lock()
        self._synced: Hashable | None = None
        self._server: Any = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Listen (raises RuntimeError when the address cannot be bound) and follow the engine."""
        cert, key = self.tls if self.tls else (None, None)
        self._server = foxglove.start_server(
            name=self.feed.name, host=self.host, port=self.port, capabilities=[],
            server_listener=self, context=self.context, tls_cert=cert, tls_key=key)
        self.port = self._server.port
        self._task = asyncio.create_task(self._tick(), name="foxglove-view")
        log.info("foxglove view listening", extra={"url": f"{'wss' if self.tls else 'ws'}://{self.host}:{self.port}"})

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        if self._server is not None:
            self._server.stop()
        await self.feed.stop()

    async def _tick(self) -> None:
        while self.feed.running() is None:  # the routes are still loading: their channels as soon as they run
            await asyncio.sleep(0.05)
        while True:
            try:
                await self.sync()
                await self.publish()
            except Exception:  # the view must outlive anything one tick meets
                log.exception("foxglove view tick failed")
            await asyncio.sleep(TICK_S)

    async def publish(self) -> None:
        """The status and the fleet, each only while subscribed."""
        if self.status.has_sinks():
            message = status_message(await self.feed.status())
            self.status.log(orjson.dumps(message, default=str, option=_ORJSON_OPTIONS), log_time=time.time_ns())
        if self.fleet.has_sinks():
            fixes = location_fixes(await self.feed.positions())
            self.fleet.log(orjson.dumps(fixes, default=str, option=_ORJSON_OPTIONS), log_time=time.time_ns())

    async def sync(self) -> None:
        """One channel per running route, with its schema; after a reload, the new ones
        advertised, those gone closed (unadvertised), those whose schema changed replaced."""
        running = self.feed.running()
        if running is None or running[0] == self._synced:
            return
        key, config, schema_dirs, names = running
        schemas = await asyncio.to_thread(SchemaRegistry, list(schema_dirs))  # once per generation
        with self._lock:
            for name in [n for n in self.routes if n not in names]:
                self._close(name)
            self.positions = set()
            for name in names:
                spec = config.routes.get(name)
                entry = schemas.get(spec.schema) if spec else None
                if spec is None or entry is None:
                    continue
                if entry.name == POSITION_SCHEMA:
                    self.positions.add(name)
                schema = schemas.bundled(spec.schema) or {}
                schema_name = f"{entry.name}.v{entry.version}"
                current = self.routes.get(name)
                if current is not None and current.schema_key == (schema_name, orjson.dumps(schema, option=orjson.OPT_SORT_KEYS)):
                    continue
                if current is not None:
                    self._close(name)
                self.routes[name] = RouteChannel(name, schema_name, schema, self.context)
            for name in set(self.routes) | self.positions:
                self._wire(name)
            self._synced = key

    def _close(self, name: str) -> None:
        channel = self.routes.pop(name)
        self.subscribers.pop(channel.channel.id(), None)
        channel.channel.close()
        self._wire(name)

    def _wire(self, name: str) -> None:
        """Hand the feed what of route ``name`` is subscribed now (under ``_lock``)."""
        channel = self.routes.get(name)
        subscribed = channel if channel is not None and self.subscribers.get(channel.channel.id()) else None
        self.feed.wire(name, subscribed, name in self.positions and bool(self.subscribers.get(self.fleet.id())))

    # -- the SDK's server listener (called from the SDK's thread)

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._subscribed(channel.id, +1)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._subscribed(channel.id, -1)

    def _subscribed(self, channel_id: int, change: int) -> None:
        with self._lock:
            self.subscribers[channel_id] = max(0, self.subscribers.get(channel_id, 0) + change)
            if channel_id == self.fleet.id():
                for name in self.positions:
                    self._wire(name)
                return
            for name, route in self.routes.items():
                if route.channel.id() == channel_id:
                    self._wire(name)


async def start_view(feed: ViewFeed, args: Namespace) -> FoxgloveView | None:
    """``--foxglove`` of ``run``, started on ``feed``; None (the reason logged) when it cannot be."""
    if bool(args.foxglove_tls_cert) != bool(args.foxglove_tls_key):
        log.error("--foxglove-tls-cert and --foxglove-tls-key go together")
        return None
    try:
        view = FoxgloveView(feed, args.foxglove[0], args.foxglove[1], args.foxglove_tls_cert, args.foxglove_tls_key)
        await view.start()
    except (OSError, RuntimeError) as exc:
        log.error("foxglove view cannot listen", extra={"address": "%s:%s" % args.foxglove, "error": str(exc)})
        return None
    return view
