"""The supervisor's admin merges its workers' documents (engine/ops/supervisor_admin.py): a
route's counters summed over the workers that run it, a connection healthy only where it is
in every worker, each counter summed and labelled by worker in /metrics.

Beside it, what of the supervisor needs no broker: the run options it passes its workers, and
a worker that cannot be started is tried again.

Real parts: the workers' documents as a worker's admin writes them (prometheus_client's text
format, the status JSON's keys); the only process started is a worker that exited at once."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any

import pytest
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families

from engine.language.specs import RoutesConfig
from engine.ops.supervisor import Supervisor, Worker
from engine.ops.supervisor_admin import MergedCollector, merge_dead_letters, merge_fleet, merge_status
from tests.support.waiting import wait_for

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def worker_document(received: int, healthy: bool, routes: tuple[str, ...] = ("orders",)) -> dict[str, Any]:
    return {"instance": "farm", "dead_letters": {"destination": "amqp dead-letters", "stored": received // 3, "spooled": 1},
            "brokers": {}, "generation": 1, "config_hash": "abc",
            "routes": {name: {"received": received, "delivered": received - 1, "state": "running", "role": "shared"}
                       for name in routes},
            "connections": {"bus": {"protocol": "amqp", "healthy": healthy, "state": "up" if healthy else "down"}}}


def not_compiled() -> RoutesConfig:
    raise AssertionError("these tests compile no routes")


def supervisor(workers: int) -> Supervisor:
    return Supervisor(argparse.Namespace(routes=Path("routes")), workers, not_compiled)


def test_status_sums_a_routes_counters_and_keeps_each_worker() -> None:
    own = supervisor(3).status()
    merged = merge_status(own, [worker_document(10, True), None, worker_document(5, False, ("orders", "fix"))])
    assert merged["routes"]["orders"]["received"] == 15 and merged["routes"]["orders"]["delivered"] == 13
    assert merged["routes"]["orders"]["workers"] == [0, 2] and merged["routes"]["fix"]["workers"] == [2]
    assert merged["routes"]["orders"]["state"] == "running"  # not a number: the first worker's
    assert merged["connections"]["bus"]["up"] is False and merged["connections"]["bus"]["workers"] == [0, 2]
    assert [w["status"] is not None for w in merged["workers"]] == [True, False, True]
    assert merged["instance"] == "farm" and merged["generation"] == 0  # the supervisor's own, not started here
    assert merged["dead_letters"] == {"destination": "amqp dead-letters", "stored": 10 // 3 + 5 // 3, "spooled": 2}


def test_the_console_merges_dead_letters_newest_first_and_each_agents_latest_position() -> None:
    """What the supervisor's console shows beside the merged status (engine/ops/supervisor_admin.py
    console_document): every worker's recent dead letters, newest first, each naming its worker;
    an agent heard by both workers once, at its latest position."""
    first = {"recent_dead_letters": [{"at": 30.0, "route": "a", "stage": "schema", "reason": "x"},
                                     {"at": 10.0, "route": "a", "stage": "mapping", "reason": "y"}],
             "fleet": [{"agent_id": "uav1", "lat": 1.0, "lon": 2.0, "at": 5.0}, {"agent_id": "rover", "lat": 3.0, "lon": 4.0, "at": 9.0}]}
    second = {"recent_dead_letters": [{"at": 20.0, "route": "b", "stage": "sink", "reason": "z"}],
              "fleet": [{"agent_id": "uav1", "lat": 1.5, "lon": 2.5, "at": 7.0}]}
    letters = merge_dead_letters([first, None, second])
    assert [(d["at"], d["worker"]) for d in letters] == [(30.0, 0), (20.0, 2), (10.0, 0)]
    fleet = merge_fleet([first, None, second])
    assert [(a["agent_id"], a["lat"], a["worker"]) for a in fleet] == [("uav1", 1.5, 2), ("rover", 3.0, 0)]  # least recent first


WORKER_METRICS = """\
# HELP rabbitros_messages_total Messages per route and outcome
# TYPE rabbitros_messages_total counter
rabbitros_messages_total{{outcome="delivered",route="orders"}} {delivered}
# HELP rabbitros_connection_up 1 when the connection is up
# TYPE rabbitros_connection_up gauge
rabbitros_connection_up{{connection="bus",protocol="amqp"}} {up}
"""


def test_metrics_are_summed_labelled_by_worker_and_up_only_where_up_everywhere() -> None:
    collector = MergedCollector(supervisor(2))
    collector.scraped = [(0, WORKER_METRICS.format(delivered=7, up=1)), (1, WORKER_METRICS.format(delivered=5, up=0))]
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value for family in collector.collect() for s in family.samples}
    assert samples[("rabbitros_messages_total", (("outcome", "delivered"), ("route", "orders")))] == 12
    assert samples[("rabbitros_worker_messages_total", (("outcome", "delivered"), ("route", "orders"), ("worker", "1")))] == 5
    assert samples[("rabbitros_connection_up", (("connection", "bus"), ("protocol", "amqp")))] == 0
    assert samples[("rabbitros_worker_restarts_total", (("worker", "0"),))] == 0


def test_the_merged_metrics_are_valid_exposition_text() -> None:
    collector = MergedCollector(supervisor(2))
    collector.scraped = [(0, WORKER_METRICS.format(delivered=7, up=1)), (1, WORKER_METRICS.format(delivered=5, up=1))]
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    text = generate_latest(registry).decode()
    names = {family.name for family in text_string_to_metric_families(text)}
    assert {"rabbitros_messages", "rabbitros_worker_messages", "rabbitros_connection_up", "rabbitros_workers_up"} <= names


def route_of_worker(delivered: int, mean_s: float, max_ns: int, last_at: float, error: str) -> dict[str, Any]:
    """A route's status as a worker's admin writes it (engine/ops/admin.py status_document)."""
    return {"file": "routes/orders.yaml:3", "generation": 2, "role": "shared", "state": "running",
            "received": delivered, "delivered": delivered, "latency_ns_total": int(mean_s * 1e9) * delivered,
            "latency_ns_max": max_ns, "latency_mean_s": mean_s, "last_at": last_at, "last_error_at": last_at,
            "last_error": error, "last_canonical": {"from": error}, "messages": {"received": delivered, "delivered": delivered},
            "dead_letters": {"mapping": 1}, "replies": {"sent": 1, "errors": 0},
            "sinks": {"bus": {"delivered": delivered, "can_take": error != "w1"}}}


def test_a_routes_means_maxima_timestamps_and_generation_are_not_summed() -> None:
    documents: list[dict[str, Any] | None] = [
        {"routes": {"orders": route_of_worker(10, 0.002, 9_000_000, 100.0, "w0")}, "connections": {}},
        {"routes": {"orders": route_of_worker(30, 0.006, 4_000_000, 200.0, "w1")}, "connections": {}}]
    merged = merge_status(supervisor(2).status(), documents)["routes"]["orders"]
    assert merged["delivered"] == 40 and merged["messages"] == {"received": 40, "delivered": 40}
    assert merged["dead_letters"] == {"mapping": 2} and merged["replies"] == {"sent": 2, "errors": 0}
    assert merged["sinks"]["bus"] == {"delivered": 40, "can_take": False}  # can take only where it can in each
    assert merged["latency_mean_s"] == pytest.approx((10 * 0.002 + 30 * 0.006) / 40)
    assert merged["latency_ns_max"] == 9_000_000 and merged["generation"] == 2
    assert (merged["last_at"], merged["last_error"], merged["last_canonical"]) == (200.0, "w1", {"from": "w1"})
    assert documents[0] is not None and documents[0]["routes"]["orders"]["messages"]["delivered"] == 10  # untouched


GAUGES = """\
# HELP rabbitros_config_generation Generation of the live configuration
# TYPE rabbitros_config_generation gauge
rabbitros_config_generation {generation}
# HELP rabbitros_vehicle_heard_seconds_ago Seconds since the vehicle's last HEARTBEAT
# TYPE rabbitros_vehicle_heard_seconds_ago gauge
rabbitros_vehicle_heard_seconds_ago{{agent="uav1",connection="radio",system_id="1"}} {heard}
"""


def test_no_gauge_is_summed_and_the_generation_is_the_supervisors() -> None:
    own = supervisor(2)
    own.generation = 3
    collector = MergedCollector(own)
    collector.scraped = [(0, GAUGES.format(generation=3, heard=0.5)), (1, GAUGES.format(generation=1, heard=2.0))]
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    families = {f.name: f for f in text_string_to_metric_families(generate_latest(registry).decode())}
    assert families["rabbitros_config_generation"].type == "gauge"
    assert [s.value for s in families["rabbitros_config_generation"].samples] == [3.0]
    assert [s.value for s in families["rabbitros_vehicle_heard_seconds_ago"].samples] == [2.0]  # the stalest
    per_worker = {s.labels["worker"]: s.value for s in families["rabbitros_worker_config_generation"].samples}
    assert per_worker == {"0": 3.0, "1": 1.0}


HISTOGRAM = """\
# HELP rabbitros_route_latency_seconds Reception to sink acceptance
# TYPE rabbitros_route_latency_seconds histogram
rabbitros_route_latency_seconds_bucket{{le="0.001",route="orders"}} {fast}
rabbitros_route_latency_seconds_bucket{{le="0.01",route="orders"}} {all}
rabbitros_route_latency_seconds_bucket{{le="+Inf",route="orders"}} {all}
rabbitros_route_latency_seconds_count{{route="orders"}} {all}
rabbitros_route_latency_seconds_sum{{route="orders"}} 0.5
"""


def merged_samples(collector: MergedCollector) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """The collector's exposition text as Prometheus parses it, by sample name and labels."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(generate_latest(registry).decode()) for s in family.samples}


def test_the_merged_counters_never_go_down_when_a_worker_restarts_or_does_not_answer() -> None:
    """Prometheus' rate() takes any drop of a counter for a reset to 0: the sum keeps what a
    dead worker counted, and a worker not answering counts with what it said last."""
    own = supervisor(2)
    collector = MergedCollector(own)
    delivered = ("rabbitros_messages_total", (("outcome", "delivered"), ("route", "orders")))
    count = ("rabbitros_route_latency_seconds_count", (("route", "orders"),))
    collector.scraped = [(0, WORKER_METRICS.format(delivered=7, up=1) + HISTOGRAM.format(fast=3, all=7)),
                         (1, WORKER_METRICS.format(delivered=5, up=1) + HISTOGRAM.format(fast=5, all=5))]
    first = merged_samples(collector)
    assert first[delivered] == 12 and first[count] == 12
    own.workers[0].restarts = 1  # worker 0 was killed and started again: its counts begin at 0
    collector.scraped = [(0, WORKER_METRICS.format(delivered=2, up=1) + HISTOGRAM.format(fast=1, all=2))]  # 1 not answering
    second = merged_samples(collector)
    assert second[delivered] == 7 + 2 + 5 and second[count] == 14
    assert second[("rabbitros_route_latency_seconds_bucket", (("le", "0.001"), ("route", "orders")))] == 3 + 1 + 5
    assert second[("rabbitros_worker_messages_total", (("outcome", "delivered"), ("route", "orders"), ("worker", "0")))] == 2
    collector.scraped = [(0, WORKER_METRICS.format(delivered=4, up=1)), (1, WORKER_METRICS.format(delivered=6, up=1))]
    assert merged_samples(collector)[delivered] == 7 + 4 + 6


def test_every_run_option_reaches_the_workers_or_is_the_supervisors() -> None:
    """The supervisor writes its workers' command lines from its own options: one it neither
    passes on nor keeps for itself (SUPERVISOR_OWN_OPTIONS) would be dropped for workers."""
    from engine.ops.cli_parser import build_parser
    from engine.ops.supervisor import SUPERVISOR_OWN_OPTIONS

    run = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["run"]
    options = {o for a in run._actions if a.help != argparse.SUPPRESS for o in a.option_strings} - {"-h", "--help"}
    args = run.parse_args(["--routes", "r", "--schemas", "s", "--instance", "i", "--admin-token-file", "t",
                           "--require-connections", "--test-on-reload", "--record", "rec"])
    passed = {word for word in Supervisor(args, 2, not_compiled).command(Worker(0), 9) if word.startswith("--")}
    assert options - passed - SUPERVISOR_OWN_OPTIONS == set()
    assert passed & SUPERVISOR_OWN_OPTIONS <= {"--workers", "--no-watch", "--admin"}  # each worker's own values


class NoExecutable(Supervisor):
    """A supervisor whose worker program is missing: every start fails with the OS's error."""

    def command(self, worker: Worker, channel: int) -> list[str]:
        return [str(Path("/nonexistent") / "python"), "-c", "pass"]


def test_a_worker_that_cannot_be_started_is_tried_again_until_the_stop() -> None:
    """A start that fails itself (OSError: here no such program; in the field no process slot
    or file descriptor) leaves the worker down only until the next backoff, never for good."""

    async def scenario() -> tuple[int, bool]:
        supervisor = NoExecutable(argparse.Namespace(routes=Path("routes")), 1, not_compiled)
        worker = supervisor.workers[0]
        worker.process = await asyncio.create_subprocess_exec(sys.executable, "-c", "pass")  # a worker that exited
        keeping = asyncio.create_task(supervisor._keep(worker))
        await wait_for(lambda: worker.restarts >= 3 or keeping.done(), 30, "three starts tried")
        alive = not keeping.done()
        supervisor.stopping = True
        await asyncio.wait_for(keeping, 30)
        return worker.restarts, alive

    restarts, alive = asyncio.run(scenario())
    assert alive and restarts >= 3


def test_a_split_links_merged_status_is_its_holders_with_every_workers_vehicles() -> None:
    """A MAVLink link split over the workers (placement rule 1b), held by worker 1: the merged
    connection joins the vehicles and adds the counters of both, and takes the link's own view
    (``state``, ``split``: the workers connected, the locks held) from the holder, not from
    whichever worker answered first (worker 0 has no vehicle heard yet: "waiting for a peer")."""

    def link(worker: int, vehicles: list[int], state: str, split: dict[str, Any]) -> dict[str, Any]:
        return {"routes": {}, "connections": {"fleet": {
            "protocol": "mavlink", "healthy": True, "state": state, "counters": {"frames_received": 10 * len(vehicles)},
            "split": {"worker": worker, "owner": 1, "workers": 2, **split},
            "liveness": [{"system_id": system, "up": True} for system in vehicles]}}}

    merged = merge_status(supervisor(2).status(), [link(0, [], "waiting for a peer", {"connected": True}),
                                                   link(1, [1, 2], "up", {"connected": [0], "locks": {"k": 0}})])
    fleet = merged["connections"]["fleet"]
    assert [v["system_id"] for v in fleet["liveness"]] == [1, 2] and fleet["counters"] == {"frames_received": 20}
    assert fleet["state"] == "up", fleet
    assert fleet["split"] == {"worker": 1, "owner": 1, "workers": 2, "connected": [0], "locks": {"k": 0}}, fleet
    assert fleet["workers"] == [0, 1] and fleet["up"] is True
