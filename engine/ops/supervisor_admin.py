"""The admin endpoint of ``run --workers N``: the engine as a whole, and each worker.

The supervisor (engine/ops/supervisor.py) serves ``--admin`` with the same access rules as a
single engine (engine/ops/admin.py: a token off loopback, TLS), and answers from its workers'
private admin endpoints, asked at once when a request comes:

* ``/status``: the supervisor's part (generation, config hash, reloads, the placement, each
  worker's pid, up, restarts and routes) and the workers' documents merged: a route's
  counters summed over the workers that run it (``workers`` names them), its mean latency
  over all, its latest error, its other fields from the first (:func:`merge_route`); a connection healthy only when it is in every worker holding it; each
  worker's own document under ``workers[i].status``;
* ``/metrics``: every worker's counters and histograms summed under their own names (a
  dashboard of one engine keeps working) and, labelled ``worker``, as ``rabbitros_worker_*``.
  No gauge the engine exports adds up over processes, so none is summed (:func:`merge_gauge`):
  a gauge named ``*_up`` is the least any worker reports (a connection is up only when it is up
  in each), ``rabbitros_config_generation`` is the supervisor's (a restarted worker counts its
  own from 1), any other the largest (``vehicle_heard_seconds_ago``: the stalest); the sums
  never go down when a worker restarts (:class:`MergedCollector`); plus
  ``rabbitros_workers_up`` and ``rabbitros_worker_restarts_total``;
* ``/healthz``: 200 when every worker is up and answers 200 itself; else 503 naming them;
* ``/tap/{route}``: the lines of every worker that runs the route, interleaved as they come (a
  worker started again is followed again, :meth:`~engine.ops.supervisor.Supervisor.follow_tap`);
* ``/`` (the web console, engine/ops/console.py) and its ``/console/events``: the engine as a
  whole, from each worker's ``/console/state`` (the document a single engine's console streams)
  merged as ``/status`` is, with the workers' pid, up, restarts, CPU and memory, the recent dead
  letters of every worker (newest first) and the fleet (each agent's latest position, whichever
  worker carried it): :func:`console_document`. The workers are asked once a second while a
  console is open, and not at all otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import json
import logging
from typing import Any, Iterator

from aiohttp import web
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.parser import text_string_to_metric_families

from engine.ops.admin import AdminAccess, authenticate, listen
from engine.ops.console import Console
from engine.ops.supervisor import Supervisor, Worker
from engine.running.observe import COUNTERS
from engine.running.recent import FLEET_AGENTS, RECENT_DEAD_LETTERS

log = logging.getLogger("engine.ops.supervisor_admin")


SUMMED = frozenset((*COUNTERS, "latency_ns_total", "lease_changes", "taps", "tap_dropped", "received_per_s",
                    "delivered_per_s", "messages", "dead_letters", "dead_lettered", "dropped_by_agent", "replies", "sinks"))
"""A route's status fields that add up over workers: its counters (engine/running/observe.py's
one set), the rates, and the dictionaries of counts (per outcome, stage, agent, sink)."""
LATEST = ("last_at", "last_error_at")
"""Timestamps: the merged route shows the latest, with the worker's ``last_error`` /
``last_canonical`` that goes with it."""


def add_counts(total: dict[str, Any], more: dict[str, Any]) -> None:
    """``more``'s counts added into ``total``, key by key (nested per sink); a sink can take
    messages only when it can in every worker, and is taken over when it is in any."""
    for key, value in more.items():
        held = total.get(key)
        if isinstance(value, dict) and isinstance(held, dict):
            add_counts(held, value)
        elif isinstance(value, bool) or isinstance(held, bool):
            total[key] = (bool(held) or value) if key == "taking_over" else (held is not False and value)
        elif isinstance(value, (int, float)):
            total[key] = (held if isinstance(held, (int, float)) else 0) + value
        elif key not in total:
            total[key] = value


def latency_count(route: dict[str, Any]) -> float:
    """How many latencies a route's ``latency_mean_s`` averages (its total over its mean)."""
    mean = route.get("latency_mean_s")
    return route.get("latency_ns_total", 0) / (mean * 1e9) if mean else 0.0


def merge_route(merged: dict[str, Any], route: dict[str, Any]) -> None:
    """One more worker's status of a route merged into ``merged``: counts summed (:data:`SUMMED`),
    the largest ``latency_ns_max``, the latest error and message (:data:`LATEST`), the mean
    latency over both; every other field (file, role, state, source) stays the first worker's.
    Summing every number summed a mean, a maximum, a generation and timestamps."""
    count = latency_count(merged) + latency_count(route)
    add_counts(merged, {key: route[key] for key in SUMMED if key in route})
    merged["latency_ns_max"] = max(merged.get("latency_ns_max") or 0, route.get("latency_ns_max") or 0)
    if count:
        merged["latency_mean_s"] = merged.get("latency_ns_total", 0) / count / 1e9
    if (route.get("last_at") or 0) > (merged.get("last_at") or 0):
        merged.update(last_at=route["last_at"], last_canonical=route.get("last_canonical"))
    if (route.get("last_error_at") or 0) > (merged.get("last_error_at") or 0):
        merged.update(last_error_at=route["last_error_at"], last_error=route.get("last_error"))


def merge_split(merged: dict[str, Any], health: dict[str, Any]) -> None:
    """One more worker's health of a connection split over the workers (placement rule 1b),
    which reports only its own share of what the connection carries (a MAVLink link's
    vehicles): its counters added, its lists (the vehicles heard, their liveness) joined, so
    the merged connection names each vehicle once; the rest (the link's ``state``, ``split``:
    the workers connected to it) is the holder's, whichever worker answered first."""
    split = health.get("split")
    holder = isinstance(split, dict) and split.get("worker") == split.get("owner")
    for key, value in health.items():
        held = merged.get(key)
        if isinstance(value, list) and isinstance(held, list):
            merged[key] = held + copy.deepcopy(value)
        elif key in ("counters", "rejected") and isinstance(value, dict) and isinstance(held, dict):
            add_counts(held, value)
        elif holder and key not in ("healthy", "up", "workers"):
            merged[key] = copy.deepcopy(value)


def merge_status(own: dict[str, Any], documents: list[dict[str, Any] | None]) -> dict[str, Any]:
    """The supervisor's status with the workers' merged into it (see the module docstring)."""
    routes: dict[str, dict[str, Any]] = {}
    connections: dict[str, dict[str, Any]] = {}
    for index, document in enumerate(documents):
        if document is None:
            continue
        for name, route in document.get("routes", {}).items():
            merged = routes.get(name)
            if merged is None:
                routes[name] = {**copy.deepcopy(route), "workers": [index]}  # the worker's own stays as it was
                continue
            merged["workers"].append(index)
            merge_route(merged, route)
        for name, health in document.get("connections", {}).items():
            held = connections.get(name)
            if held is None:
                held = connections[name] = {**copy.deepcopy(health), "workers": []}
            elif health.get("split"):
                merge_split(held, health)
            held["workers"].append(index)
            held["healthy"] = bool(held.get("healthy", True)) and bool(health.get("healthy", True))
            held["up"] = held["healthy"]
    answered = [d for d in documents if d is not None]
    first = answered[0] if answered else {}
    dead_letters = copy.deepcopy(first.get("dead_letters"))
    for document in answered[1:]:  # one destination, each worker's stored and spooled letters
        if isinstance(dead_letters, dict) and isinstance(document.get("dead_letters"), dict):
            add_counts(dead_letters, document["dead_letters"])
    workers = [{**worker, "status": documents[i]} for i, worker in enumerate(own["workers"])]
    return {"instance": first.get("instance"), "brokers": first.get("brokers"), "dead_letters": dead_letters, **own, "workers": workers,
            "routes": dict(sorted(routes.items())), "connections": connections, "elsewhere": []}


async def status_document(supervisor: Supervisor) -> dict[str, Any]:
    """The status of the engine as a whole: the supervisor's, with every worker's asked now."""
    answers = await supervisor.documents("/status")
    return merge_status(supervisor.status(), [json.loads(body) if code == 200 else None for _, code, body in answers])


def merge_dead_letters(documents: list[dict[str, Any] | None]) -> list[dict[str, Any]]:
    """The workers' recent dead letters as one list, newest first, each naming its worker, as
    many as one engine keeps (:data:`RECENT_DEAD_LETTERS`)."""
    letters = [{**letter, "worker": index} for index, document in enumerate(documents) if document is not None
               for letter in document.get("recent_dead_letters") or ()]
    letters.sort(key=lambda letter: letter.get("at") or 0, reverse=True)
    return letters[:RECENT_DEAD_LETTERS]


def merge_fleet(documents: list[dict[str, Any] | None]) -> list[dict[str, Any]]:
    """Each agent's latest position over the workers (a fleet's agents spread over workers, and
    an agent whose messages compete on a queue is heard by several), naming the worker that
    carried it; the least recently heard first, at most :data:`FLEET_AGENTS`, as one engine's."""
    latest: dict[str, dict[str, Any]] = {}
    for index, document in enumerate(documents):
        for agent in (document or {}).get("fleet") or ():
            held = latest.get(agent["agent_id"])
            if held is None or (agent.get("at") or 0) > (held.get("at") or 0):
                latest[agent["agent_id"]] = {**agent, "worker": index}
    return sorted(latest.values(), key=lambda agent: agent.get("at") or 0)[-FLEET_AGENTS:]


async def console_document(supervisor: Supervisor) -> dict[str, Any]:
    """What the supervisor's console shows: every worker's console document (``/console/state``,
    engine/ops/console.py) asked now and merged: the status as :func:`merge_status` merges it
    (without each worker's whole document, which the page does not show), the dead letters
    (:func:`merge_dead_letters`) and the fleet (:func:`merge_fleet`)."""
    answers = await supervisor.documents("/console/state")
    documents = [json.loads(body) if code == 200 else None for _, code, body in answers]
    merged = merge_status(supervisor.status(), documents)
    for worker in merged["workers"]:
        worker.pop("status", None)
    for route in merged["routes"].values():
        route.pop("last_canonical", None)
    return {**merged, "recent_dead_letters": merge_dead_letters(documents), "fleet": merge_fleet(documents)}


GENERATION_GAUGE = "rabbitros_config_generation"
"""The workers' generation gauge: in the merged metrics the supervisor's generation."""


def merge_gauge(name: str, seen: float, value: float) -> float:
    """Two workers' values of one gauge series as the engine's one value: none of the engine's
    gauges adds up over processes (a connection up in each, a generation, a vehicle heard some
    seconds ago), so ``*_up`` is the least (up only where up in every worker), any other the
    largest (the stalest vehicle; a device's gauge comes from the one worker that holds it)."""
    return min(seen, value) if name.endswith("_up") else max(seen, value)


Series = tuple[str, str, tuple[tuple[str, str], ...]]
"""One sample series: its family, its sample name, its labels."""
ADDS_UP = frozenset(("counter", "histogram"))
"""The metric types whose samples sum over workers (a histogram's buckets, count and sum)."""


class MergedCollector:
    """prometheus_client collector over the workers' scraped text (see the module docstring).

    The merged counters never go down, as Prometheus' ``rate()`` needs (it takes a drop for a
    reset to 0 and counts the whole new value again): a worker that does not answer counts with
    what it said last, and when a worker was started again what its dead predecessor said last
    is carried (:attr:`carried`) beside the new one's counts from 0. Its per-worker series
    (``rabbitros_worker_*``) do restart from 0: a reset of that process, as Prometheus expects."""

    def __init__(self, supervisor: Supervisor) -> None:
        self.supervisor = supervisor
        self.scraped: list[tuple[int, str]] = []
        self.auth_failures = 0
        self.families: dict[str, tuple[str, str]] = {}
        """Family name -> (help, type), of every family any worker reported."""
        self.last: dict[int, tuple[int, dict[Series, float]]] = {}
        """Worker index -> (its restarts when it answered last, its counters then)."""
        self.carried: dict[Series, float] = {}
        """What workers that died had counted, by series."""

    def _remember(self, index: int, counts: dict[Series, float]) -> None:
        restarts = self.supervisor.workers[index].restarts
        before = self.last.get(index)
        if before is not None and before[0] != restarts:  # a new process: its predecessor's counts stay in the sum
            for series, value in before[1].items():
                self.carried[series] = self.carried.get(series, 0.0) + value
        self.last[index] = (restarts, counts)

    def collect(self) -> Iterator[Metric]:
        gauges: dict[Series, float] = {}
        per_worker: dict[str, Metric] = {}
        for index, text in self.scraped:
            counts: dict[Series, float] = {}
            for family in text_string_to_metric_families(text):
                self.families.setdefault(family.name, (family.documentation, family.type))
                if family.name not in per_worker:
                    per_worker[family.name] = Metric("rabbitros_worker_" + family.name.removeprefix("rabbitros_"),
                                                     family.documentation + " (per worker)", family.type)
                for sample in family.samples:
                    series = (family.name, sample.name, tuple(sorted(sample.labels.items())))
                    if family.type in ADDS_UP:
                        counts[series] = sample.value
                    else:
                        seen = gauges.get(series)
                        gauges[series] = sample.value if seen is None else merge_gauge(family.name, seen, sample.value)
                    per_worker[family.name].add_sample("rabbitros_worker_" + sample.name.removeprefix("rabbitros_"),
                                                       {**sample.labels, "worker": str(index)}, sample.value)
            self._remember(index, counts)
        totals = dict(self.carried)
        for _, counts in self.last.values():
            for series, value in counts.items():
                totals[series] = totals.get(series, 0.0) + value
        totals.update(gauges)
        if (GENERATION_GAUGE, GENERATION_GAUGE, ()) in totals:
            totals[(GENERATION_GAUGE, GENERATION_GAUGE, ())] = float(self.supervisor.generation)
        merged = {name: Metric(name, documentation, kind) for name, (documentation, kind) in self.families.items()}
        for (name, sample_name, labels), value in totals.items():  # in the workers' order: a histogram's buckets ascending
            merged[name].add_sample(sample_name, dict(labels), value)
        for name, metric in merged.items():
            if metric.samples:
                yield metric
            if name in per_worker:
                yield per_worker[name]
        up = GaugeMetricFamily("rabbitros_workers_up", "1 while the worker runs its routes", labels=["worker"])
        restarts = CounterMetricFamily("rabbitros_worker_restarts", "Times the supervisor started the worker again", labels=["worker"])
        for worker in self.supervisor.workers:
            up.add_metric([str(worker.index)], 1 if worker.up else 0)
            restarts.add_metric([str(worker.index)], worker.restarts)
        yield up
        yield restarts
        yield CounterMetricFamily("rabbitros_supervisor_admin_auth_failures", "Admin requests refused for a missing or wrong token",
                                  value=self.auth_failures)


class SupervisorAdmin:
    def __init__(self, supervisor: Supervisor, host: str, port: int, access: AdminAccess | None = None) -> None:
        self.supervisor = supervisor
        self.host, self.port = host, port
        self.access = access or AdminAccess()
        self.collector = MergedCollector(supervisor)
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(self.collector)
        middlewares = [authenticate(self.access, self._refused)] if self.access.token is not None else []
        app = web.Application(middlewares=middlewares)
        app.router.add_get("/metrics", self.metrics)
        app.router.add_get("/healthz", self.healthz)
        app.router.add_get("/status", self.status)
        app.router.add_get("/tap/{route}", self.tap)
        # a tap or a console that its client left stops reading the workers at once (engine/ops/admin.py)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=2.0, handler_cancellation=True)
        self._taps: set[asyncio.Task[Any]] = set()
        """The streams open now (taps, consoles), ended when the admin stops."""
        Console(lambda: console_document(supervisor), self._taps).add_to(app)

    def _refused(self) -> None:
        self.collector.auth_failures += 1

    async def start(self) -> None:
        self.port = await listen(self._runner, self.host, self.port, self.access)
        log.info("admin endpoint listening", extra={"url": f"{self.access.scheme}://{self.host}:{self.port}/",
                                                    "workers": len(self.supervisor.workers)})

    async def stop(self) -> None:
        for task in list(self._taps):
            task.cancel()
        await self._runner.cleanup()

    async def status(self, request: web.Request) -> web.Response:
        return web.json_response(await status_document(self.supervisor), dumps=lambda d: json.dumps(d, default=str))

    async def metrics(self, request: web.Request) -> web.Response:
        answers = await self.supervisor.documents("/metrics")
        self.collector.scraped = [(worker.index, body.decode()) for worker, code, body in answers if code == 200]
        return web.Response(body=generate_latest(self.registry), headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def healthz(self, request: web.Request) -> web.Response:
        answers = await self.supervisor.documents("/healthz")
        workers = {str(worker.index): json.loads(body) if body else {"status": "down"} for worker, _, body in answers}
        failing = sorted(str(worker.index) for worker, code, _ in answers if code != 200)
        document = {"status": "ok" if not failing else "down" if any(not w.up for w in self.supervisor.workers) else "degraded",
                    "failing_workers": failing, "workers": workers, "generation": self.supervisor.generation}
        return web.json_response(document, status=503 if failing else 200)

    async def tap(self, request: web.Request) -> web.StreamResponse:
        route = request.match_info["route"]
        placement = self.supervisor.placement
        place = placement.routes.get(route) if placement is not None else None
        if place is None:
            known = ", ".join(sorted(placement.routes)) if placement is not None else ""
            return web.json_response({"error": f"unknown route {route!r} (running: {known})"}, status=404)
        lines: asyncio.Queue[bytes] = asyncio.Queue(maxsize=1024)
        response = web.StreamResponse(headers={"Content-Type": "application/x-ndjson", "Cache-Control": "no-cache"})
        readers = [asyncio.create_task(self._follow(self.supervisor.workers[index], route, lines)) for index in place.workers]
        task = asyncio.current_task()
        assert task is not None
        self._taps.add(task)
        try:
            await response.prepare(request)
            while True:
                await response.write(await lines.get())
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self._taps.discard(task)
            for reader in readers:
                reader.cancel()
            await asyncio.gather(*readers, return_exceptions=True)
        return response

    async def _follow(self, worker: Worker, route: str, lines: asyncio.Queue[bytes]) -> None:
        """One worker's tap lines into ``lines`` (a full queue drops, as the engine's tap does),
        also once it was started again (:meth:`Supervisor.follow_tap`)."""
        async for line in self.supervisor.follow_tap(worker, route):
            with contextlib.suppress(asyncio.QueueFull):
                lines.put_nowait(line)
