"""The fleet benchmark (bench/fleet.py, issue 20) runs short and loses nothing: ROS 2 robots
(rclpy, a child process) and MAVLink vehicles (pymavlink, several on each UDP link) through
templated routes (and routes shared by the fleet, and the reference bridge written on the
client libraries in the engine's place) to RabbitMQ, and a command to every agent the other
way. Timings are the benchmark's to report (bench/results/), not this test's: it asserts that
every message sent arrived, once the bridge and the load generators ran under ``timeout -s KILL``."""

from __future__ import annotations

import asyncio

import pytest

from bench.fleet import AGENTS_NICE, STREAM_KINDS, run_mode
from tests.support.workers import ros_domain

ROUTES = {"templated": 3 * 3 + 9 * 3,
          "shared": 2 + 3 + 2 * 2 + 9,  # discovery per robot stream, per link and message, a command route per agent
          "reference": None}  # no engine: the bridge on the client libraries (bench/systems.py ref_fleet)


@pytest.mark.parametrize("mode", sorted(ROUTES))
def test_fleet_smoke_loses_nothing(amqp_url: str, mode: str) -> None:
    nice = AGENTS_NICE if mode == "shared" else 0  # the load generators at a lower priority, once
    result = asyncio.run(run_mode(amqp_url, mode, robots_n=3, vehicles_n=9, duration=2.0,
                                  domain=ros_domain(13), agents_nice=nice))
    assert result["agents_nice"] == nice
    assert result["links"] == 2 and result["routes"] == ROUTES[mode]  # nine vehicles need two udpin links
    assert result["unmatched_publishers"] == 0
    assert result["telemetry_sent"] >= (3 * 2 + 9 * 2) * 10  # 10 Hz for 2 s at least (each stream sends whole rounds)
    assert (result["telemetry_lost"], result["commands_lost"]) == (0, 0), (result["lost_streams"], result["lost_commands"])
    assert result["commands_sent"] == 12 * 2
    assert result["foreign_commands"] == 0  # each command reached only the vehicle it names
    assert all(result["latency_ms"][kind]["n"] > 0 for kind in STREAM_KINDS), result["latency_ms"]
    assert all(result["engine_to_sink_ms"][kind]["n"] > 0 for kind in STREAM_KINDS), result["engine_to_sink_ms"]
    if mode != "reference":  # the engine's AMQP publishes (telemetry, from its load on) and the rounds they took
        counts = result["amqp_publish"]["gcs"]
        assert counts["published"] >= result["telemetry_sent"], counts
        assert 0 < counts["publish_rounds"] <= counts["published"], counts


def test_fleet_with_two_workers_loses_nothing_and_measures_each_process(amqp_url: str) -> None:
    """``run --workers 2`` in the bridge's place (bench/bench_fleet_workers.py, issue 34): every
    message arrives both ways, and each process's CPU and RSS is reported (the supervisor, both
    workers, the generators, the consumer) with the whole machine's busy cores."""
    result = asyncio.run(run_mode(amqp_url, "templated", robots_n=3, vehicles_n=9, duration=2.0, domain=ros_domain(13), workers=2))
    assert result["workers"] == 2 and result["routes"] == ROUTES["templated"]
    assert result["unmatched_publishers"] == 0
    assert (result["telemetry_lost"], result["commands_lost"]) == (0, 0), (result["lost_streams"], result["lost_commands"])
    assert result["commands_sent"] == 12 * 2 and result["foreign_commands"] == 0
    assert all(result["latency_ms"][kind]["n"] > 0 for kind in STREAM_KINDS), result["latency_ms"]
    processes = result["processes"]
    assert set(processes) == {"supervisor", "worker 0", "worker 1", "robots 1", "robots 2", "vehicles", "consumer"}, processes
    assert all(processes[name]["rss_mib"] > 0 for name in processes), processes
    assert processes["worker 0"]["cpu_s"] + processes["worker 1"]["cpu_s"] > 0, processes
    assert result["engine_cpu_s"] >= processes["worker 0"]["cpu_s"] + processes["worker 1"]["cpu_s"] - 0.02  # rounded to 0.01 s
    assert result["machine"]["busy_cores"] > 0
