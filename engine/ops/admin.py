"""The admin endpoint (``--admin [HOST:]PORT``, off by default): metrics, health, status, taps.

Served by aiohttp on the engine's own event loop:

* ``GET /metrics``: Prometheus text format through prometheus_client. A custom collector
  reads the routes' counters (engine/running/observe.py: the same fields the status and the log's
  counter line show) and the engine at scrape time, so the hot path only increments plain
  integers (no prometheus_client lock per message);
* ``GET /healthz``: 200 when every connection is up and every route's source receives; 503
  naming the connections that are down, the routes whose source is degraded (the broker
  cancelled its subscription) and why, until it is taken up again, and the ``unavailable``
  parts of up connections (``Connection.unavailable``: a MAVLink vehicle not heard);
* ``GET /status``: the status document (generation, config hash, reloads, each route's
  counters, rates, state and last error, the connections);
* ``GET /tap/{route}``: JSON lines, one per message through the route, from now on;
* ``GET /``: the web console (engine/ops/console.py), its stream ``/console/events`` and its
  document once, ``/console/state``.

A bare port binds 127.0.0.1: the admin endpoint exposes message contents (taps), so it is
reachable from elsewhere only when an address is given on purpose, and then only with an
identity (:class:`AdminAccess`): on any address outside 127.0.0.0/8 and ::1 the engine
refuses to start without ``--admin-token-file``, and every path but ``/healthz`` asks for
``Authorization: Bearer <token>``, compared in constant time (``hmac.compare_digest``); the
same token is taken as the password of HTTP Basic (any user name), which is how a browser
sends it to the console (it cannot add a bearer header to a page load or an EventSource). A
failed attempt is counted (``rabbitros_admin_auth_failures_total``) and logged with the
peer's address and the path, never the token. ``--admin-tls-cert/--admin-tls-key`` serve
HTTPS. ``/healthz`` stays open: a load balancer's or systemd's probe carries no token, and it
shows only connection names and their state, and the routes whose source is degraded with the
source's reason (a queue name; no message content, no URL, no counter).
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import hmac
import ipaddress
import json
import logging
import ssl
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Awaitable, Callable, Iterator

from aiohttp import web
from aiohttp.typedefs import Middleware
from multidict import MultiDict
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from engine.ops.console import Console, engine_state
from engine.running.observe import LATENCY_BUCKETS, Tap

if TYPE_CHECKING:
    from engine.running.runtime import Engine

log = logging.getLogger("engine.ops.admin")
RATE_SAMPLE_S = 1.0


def parse_address(text: str) -> tuple[str, int]:
    """``PORT`` (127.0.0.1), ``HOST:PORT`` or ``[v6]:PORT``; ValueError otherwise."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535 or (sep and not host):
        raise ValueError(f"admin address {text!r} is not [HOST:]PORT")
    return host, int(port)


class AdminConfigError(ValueError):
    """The admin options cannot serve safely (no token off loopback, unreadable files)."""


OPEN_PATHS = frozenset({"/healthz"})
"""Paths served without a token (see the module docstring for why /healthz is one)."""


def is_loopback(host: str) -> bool:
    """127.0.0.0/8, ::1 and ``localhost``: addresses no packet from another machine reaches.
    Anything else, the wildcard 0.0.0.0/:: and host names included, is reachable."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class AdminAccess:
    """Who may read the admin endpoint and how: the bearer token (None: anyone who can
    reach a loopback address) and the TLS context (None: plain HTTP)."""

    token: bytes | None = None
    tls: ssl.SSLContext | None = None

    @property
    def scheme(self) -> str:
        return "https" if self.tls is not None else "http"


def read_token(path: Path) -> bytes:
    """A token file's content, one trailing newline stripped; an empty one is refused."""
    from engine.language.route_yaml import SecretFileError, read_secret_file

    try:
        token = read_secret_file(str(path))
    except SecretFileError as exc:
        raise AdminConfigError(f"--admin-token-file: {exc}") from None
    if not token.strip():
        raise AdminConfigError(f"--admin-token-file: {path} is empty")
    return token.encode()


def admin_access(host: str, token_file: Path | None, tls_cert: Path | None, tls_key: Path | None) -> AdminAccess:
    """The access rules for ``--admin host:port``; AdminConfigError when it would be open to
    the network or its files cannot be read."""
    if token_file is None and not is_loopback(host):
        raise AdminConfigError(f"--admin {host}: an address other than loopback (127.0.0.1, ::1) serves taps and "
                               "status to the network; give --admin-token-file FILE (and --admin-tls-cert/--admin-tls-key)")
    if (tls_cert is None) != (tls_key is None):
        raise AdminConfigError("--admin-tls-cert and --admin-tls-key go together")
    tls = None
    if tls_cert is not None and tls_key is not None:
        tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        try:
            tls.load_cert_chain(str(tls_cert), str(tls_key))
        except (OSError, ssl.SSLError) as exc:
            raise AdminConfigError(f"--admin-tls-cert {tls_cert} / --admin-tls-key {tls_key}: {getattr(exc, 'strerror', None) or exc}") from None
    return AdminAccess(read_token(token_file) if token_file is not None else None, tls)


def connection_health(engine: Engine) -> dict[str, dict[str, Any]]:
    """Each connection's health as the engine reports it (``healthy``, ``state``,
    ``last_error``), with ``up`` for /healthz and ``rabbitros_connection_up``."""
    connections = engine.status()["connections"]
    for health in connections.values():
        health["up"] = bool(health.get("healthy", True))
    return connections


def degraded_sources(engine: Engine) -> dict[str, str]:
    """Route -> why its source receives nothing though its connection is up (the broker
    cancelled its subscription), while it takes it up again."""
    reasons = ((name, runner.source.degraded_reason()) for name, runner in sorted(engine.runners.items()))
    return {name: reason for name, reason in reasons if reason}


def status_document(engine: Engine) -> dict[str, Any]:
    """The engine's status with what the observers know: outcome counts and rates."""
    document = engine.status()
    for health in document["connections"].values():
        health["up"] = bool(health.get("healthy", True))
    for name, route in document["routes"].items():
        route.update(engine.observers.get(name).snapshot())
        route.update(engine.observers.rates(name))
    return document


class EngineCollector:
    """prometheus_client custom collector: reads counters at scrape time."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.auth_failures = 0

    def collect(self) -> Iterator[Metric]:
        engine = self.engine
        messages = CounterMetricFamily("rabbitros_messages", "Messages per route and outcome", labels=["route", "outcome"])
        dead = CounterMetricFamily("rabbitros_dead_letters", "Dead-lettered messages per route and stage", labels=["route", "stage"])
        latency = HistogramMetricFamily("rabbitros_route_latency_seconds", "Reception to sink acceptance", labels=["route"])
        dropped = CounterMetricFamily("rabbitros_tap_dropped", "Tap lines dropped for slow clients", labels=["route"])
        sink_errors = CounterMetricFamily("rabbitros_sink_errors", "Transient sink failures per route", labels=["route"])
        unroutable = CounterMetricFamily("rabbitros_unroutable", "Sends routed to nobody (returned by the broker), each attempt",
                                         labels=["route"])
        agent_dropped = CounterMetricFamily("rabbitros_agent_dropped", "Messages a fair route dropped from one agent's queue",
                                            labels=["route", "agent"])
        sink_messages = CounterMetricFamily("rabbitros_sink_messages", "A route with several sinks: copies per sink (or fallback) "
                                            "and outcome", labels=["route", "sink", "outcome"])
        for name in sorted(engine.runners):
            observer = engine.observers.get(name)
            for outcome, count in observer.outcomes().items():
                messages.add_metric([name, outcome], count)
            for stage, count in sorted(observer.dead_lettered.items()):
                dead.add_metric([name, stage], count)
            sink_errors.add_metric([name], observer.sink_errors)
            unroutable.add_metric([name], observer.unroutable)
            for agent, count in sorted(observer.dropped_by_agent.items()):
                agent_dropped.add_metric([name, agent], count)
            for sink, counts in sorted(observer.sinks.items()):
                for outcome, count in counts.as_dict().items():
                    sink_messages.add_metric([name, sink, outcome], count)
            cumulative, buckets = 0, []
            for bound, count in zip((*LATENCY_BUCKETS, float("inf")), observer.latency_buckets):
                cumulative += count
                buckets.append(("+Inf" if bound == float("inf") else repr(bound), cumulative))
            latency.add_metric([name], buckets, observer.latency_ns_total / 1e9)
            dropped.add_metric([name], observer.tap_dropped + sum(t.dropped for t in observer.taps))
        yield from (messages, dead, latency, dropped, sink_errors, unroutable, agent_dropped, sink_messages)
        failures = CounterMetricFamily("rabbitros_admin_auth_failures", "Admin requests refused for a missing or wrong token")
        failures.add_metric([], self.auth_failures)
        yield failures
        reloads = CounterMetricFamily("rabbitros_reloads", "Configuration reloads", labels=["result"])
        reloads.add_metric(["succeeded"], engine.reloads.succeeded)
        reloads.add_metric(["rejected"], engine.reloads.rejected)
        yield reloads
        if engine.recorder is not None:  # --record (engine/running/record.py)
            recording = engine.recorder.status()
            yield CounterMetricFamily("rabbitros_recorded_messages", "Messages written to the recording (inputs and canonical)",
                                      value=recording["written"])
            recording_dropped = CounterMetricFamily("rabbitros_recording_dropped", "Recorded copies dropped: the writer fell "
                                                    "behind (the messages themselves went on)", labels=["route"])
            for name, count in sorted(recording["dropped_by_route"].items()):
                recording_dropped.add_metric([name], count)
            yield recording_dropped
        yield GaugeMetricFamily("rabbitros_config_generation", "Generation of the live configuration", value=engine.generation)
        up = GaugeMetricFamily("rabbitros_connection_up", "1 when the connection is up", labels=["connection", "protocol"])
        for name, health in sorted(connection_health(engine).items()):
            up.add_metric([name, health["protocol"]], 1 if health["up"] else 0)
        yield up
        yield from connection_metrics(engine)


def connection_metrics(engine: Engine) -> Iterator[Metric]:
    """The connections' own samples (``Connection.metrics``), one family per name."""
    families: dict[str, CounterMetricFamily | GaugeMetricFamily] = {}
    for _, connection in sorted(engine.open_connections(), key=lambda held: held[1].name):
        name = connection.name
        for sample in connection.metrics():
            family = families.get(sample.name)
            if family is None:
                kind = CounterMetricFamily if sample.kind == "counter" else GaugeMetricFamily
                family = families[sample.name] = kind(f"rabbitros_{sample.name}", sample.help,
                                                      labels=["connection", *(key for key, _ in sample.labels)])
            family.add_metric([name, *(value for _, value in sample.labels)], sample.value)
    yield from families.values()


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


async def listen(runner: web.AppRunner, host: str, port: int, access: AdminAccess) -> int:
    """Serve ``runner``'s app on ``host:port`` (TLS when ``access`` has it); the bound port,
    the one the system chose when 0 was asked (a worker's private admin, tests). One engine's
    admin and the supervisor's (engine/ops/supervisor_admin.py) listen alike."""
    await runner.setup()
    site = web.TCPSite(runner, host, port, reuse_address=True, ssl_context=access.tls)
    await site.start()
    sockets = getattr(site._server, "sockets", None) or []
    return int(sockets[0].getsockname()[1]) if sockets else port


def basic_password(credentials: bytes) -> bytes:
    """The password of HTTP Basic credentials (base64 of ``user:password``); b"" when they do not decode."""
    try:
        return base64.b64decode(credentials, validate=True).partition(b":")[2]
    except (binascii.Error, ValueError):
        return b""


def authenticate(access: AdminAccess, refused: Callable[[], None]) -> Middleware:
    """The middleware asking every path but /healthz (unknown ones too, so no route name
    leaks) for the bearer token; ``refused`` counts each refusal."""

    @web.middleware
    async def middleware(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.path in OPEN_PATHS:
            return await handler(request)
        scheme, _, given = request.headers.get("Authorization", "").partition(" ")
        assert access.token is not None
        # surrogateescape: aiohttp keeps a header's undecodable bytes as surrogates (a 500 before, found by the fuzz test)
        presented = given.strip().encode("utf-8", "surrogateescape")
        if scheme.lower() == "basic":
            presented = basic_password(presented)
        if scheme.lower() in ("bearer", "basic") and hmac.compare_digest(presented, access.token):
            return await handler(request)
        refused()
        log.warning("admin request refused", extra={"peer": request.remote, "path": request.path[:200],
                                                    "reason": "wrong token" if given else "no bearer token"})
        # two challenges: a program sends the bearer token, a browser (the console) asks its user for it
        headers = MultiDict([("WWW-Authenticate", 'Bearer realm="rabbitros"'), ("WWW-Authenticate", 'Basic realm="rabbitros"')])
        return web.json_response({"error": "a bearer token is required (Authorization: Bearer <token>)"}, status=401,
                                 headers=headers)

    return middleware


class AdminServer:
    def __init__(self, engine: Engine, host: str, port: int, access: AdminAccess | None = None) -> None:
        self.engine = engine
        self.host, self.port = host, port
        self.access = access or AdminAccess()
        self.registry = CollectorRegistry(auto_describe=False)
        self.collector = EngineCollector(engine)
        self.registry.register(self.collector)
        app = web.Application(middlewares=[authenticate(self.access, self._refused)] if self.access.token is not None else [])
        app.router.add_get("/metrics", self.metrics)
        app.router.add_get("/healthz", self.healthz)
        app.router.add_get("/status", self.status)
        app.router.add_get("/tap/{route}", self.tap)
        # handler_cancellation: a stream (a tap, the console's events) ends when its client leaves,
        # not at the next message it would write: a tap the supervisor closed (its Foxglove
        # channel has no subscriber left) costs the route nothing from then on
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=2.0, handler_cancellation=True)
        self._sampler: asyncio.Task[None] | None = None
        self._taps: set[asyncio.Task[Any]] = set()
        Console(engine_state(engine, status_document), self._taps).add_to(app)

    def _refused(self) -> None:
        self.collector.auth_failures += 1

    async def start(self) -> None:
        self.port = await listen(self._runner, self.host, self.port, self.access)
        self._sampler = asyncio.create_task(self._sample(), name="admin-rates")
        log.info("admin endpoint listening", extra={"url": f"{self.access.scheme}://{self.host}:{self.port}/",
                                                    "token": self.access.token is not None})

    async def stop(self) -> None:
        for task in list(self._taps):  # a tap streams until its client leaves: end it
            task.cancel()
        if self._sampler is not None:
            self._sampler.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._sampler
        await self._runner.cleanup()

    async def _sample(self) -> None:
        while True:
            self.engine.observers.sample()
            await asyncio.sleep(RATE_SAMPLE_S)

    async def metrics(self, request: web.Request) -> web.Response:
        body = generate_latest(self.registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def healthz(self, request: web.Request) -> web.Response:
        connections = connection_health(self.engine)
        down = sorted(name for name, health in connections.items() if not health["up"])
        degraded = degraded_sources(self.engine)
        unavailable = {connection.name: parts for _, connection in self.engine.open_connections()
                       if connection.name not in down and (parts := connection.unavailable())}
        status = "down" if down else "degraded" if degraded or unavailable else "ok"
        document = {"status": status, "down": down, "degraded": degraded, "unavailable": unavailable,
                    "connections": connections, "generation": self.engine.generation}
        return web.json_response(document, status=503 if down or degraded or unavailable else 200)

    async def status(self, request: web.Request) -> web.Response:
        return web.json_response(status_document(self.engine), dumps=lambda d: json.dumps(d, default=str))

    async def tap(self, request: web.Request) -> web.StreamResponse:
        route = request.match_info["route"]
        if route not in self.engine.runners:
            known = ", ".join(sorted(self.engine.runners))
            return web.json_response({"error": f"unknown route {route!r} (running: {known})"}, status=404)
        observer = self.engine.observers.get(route)
        tap = Tap(route)
        response = web.StreamResponse(headers={"Content-Type": "application/x-ndjson", "Cache-Control": "no-cache"})
        observer.attach(tap)  # before the headers go out: a client that has them misses nothing from then on
        started = time.monotonic()
        task = asyncio.current_task()
        assert task is not None
        self._taps.add(task)
        try:
            await response.prepare(request)
            while True:
                lines = [await tap.lines.get()]
                while not tap.lines.empty() and len(lines) < 256:
                    lines.append(tap.lines.get_nowait())
                await response.write(b"".join(lines))
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self._taps.discard(task)
            observer.detach(tap)
            log.info("tap closed", extra={"route": route, "dropped": tap.dropped,
                                           "seconds": round(time.monotonic() - started, 1)})
        return response
