"""The supervisor's admin merges its workers' documents (engine/ops/supervisor_admin.py): a
route's counters summed over the workers that run it, a connection healthy only where it is
in every worker, each counter summed and labelled by worker in /metrics.

Real parts: the workers' documents as a worker's admin writes them (prometheus_client's text
format, the status JSON's keys); no process is started."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from engine.language.specs import RoutesConfig
from engine.ops.supervisor import Supervisor
from engine.ops.supervisor_admin import MergedCollector, merge_status

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def worker_document(received: int, healthy: bool, routes: tuple[str, ...] = ("orders",)) -> dict[str, Any]:
    return {"instance": "farm", "dead_letters": None, "brokers": {}, "generation": 1, "config_hash": "abc",
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
    from prometheus_client import CollectorRegistry, generate_latest

    collector = MergedCollector(supervisor(2))
    collector.scraped = [(0, WORKER_METRICS.format(delivered=7, up=1)), (1, WORKER_METRICS.format(delivered=5, up=1))]
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    text = generate_latest(registry).decode()
    names = {family.name for family in text_string_to_metric_families(text)}
    assert {"rabbitros_messages", "rabbitros_worker_messages", "rabbitros_connection_up", "rabbitros_workers_up"} <= names
