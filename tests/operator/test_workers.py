"""``run --workers 2``: a worker killed with -9 under load loses nothing and comes back; a
reload reaches both workers as one generation, a broken one neither.

Real parts: a private RabbitMQ node (tests/conftest.py), the engine as an operator runs it
(tests/support/engine_process.py: the supervisor, which starts its workers as processes), its
admin endpoint over HTTP, SIGKILL to one worker's process."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any, Callable

import aio_pika
import aiohttp
import pytest
from prometheus_client.parser import text_string_to_metric_families

from engine.common.processes import listening_port
from tests.support.engine_process import EngineProcess
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.waiting import wait_for

ROUTES = """
connections:
  broker: {{amqp: "{url}"}}
routes:
  - name: pass-{tag}
    source: {{amqp: {{exchange: {tag}-in, binding_key: "#", queue: {tag}-q, prefetch: 100}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {tag}-out, routing_key: "{key}"}}}}
"""
TOTAL = 12_000


async def admin_status(port: int) -> dict[str, Any]:
    async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/status") as answer:
        assert answer.status == 200, await answer.text()
        return dict(await answer.json())


async def publish(connection: aio_pika.abc.AbstractConnection, tag: str, ids: range) -> None:
    """``ids`` into the route's queue, each confirmed by the broker (so each is in the queue)."""
    channel = await connection.channel()
    queue = await channel.declare_queue(f"{tag}-q", durable=True)
    exchange = await channel.declare_exchange(f"{tag}-in", aio_pika.ExchangeType.TOPIC, durable=True)
    await queue.bind(exchange, "#")
    for first in range(ids.start, ids.stop, 500):
        await asyncio.gather(*(exchange.publish(aio_pika.Message(json.dumps({"seq": seq}).encode(), delivery_mode=2), "m")
                               for seq in range(first, min(first + 500, ids.stop))))


def two_workers(tmp_path: Path, text: str, status: str = "status.json", *extra: str) -> tuple[Path, int, EngineProcess]:
    """``text`` as the routes directory's one file, and ``run --workers 2`` on it with an admin
    port: (the route file, the admin port, the supervisor's process)."""
    routes = tmp_path / "routes"
    routes.mkdir()
    route_file = routes / "r.yaml"
    route_file.write_text(text)
    port = listening_port()
    return route_file, port, EngineProcess(routes, tmp_path / status, {}, "--workers", "2", "--admin", str(port), *extra)


def test_a_worker_killed_under_load_loses_nothing_and_comes_back(tmp_path: Path, amqp_url: str) -> None:
    """12,000 messages published while two workers drain them; worker 0 killed with -9 a quarter of
    the way: every message arrives at least once (what it held unacknowledged the broker hands
    to the others), the supervisor starts it again (status: up, another pid, ``restarts: 1``),
    and a SIGTERM then stops both workers and the supervisor cleanly (exit 0)."""
    tag = "w" + uuid.uuid4().hex[:8]
    _, port, engine = two_workers(tmp_path, ROUTES.format(url=amqp_url, tag=tag, key="out"))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), f"{tag}-out", "#")
        publishing = asyncio.create_task(publish(connection, tag, range(TOTAL)))  # while the workers drain it
        seen: set[int] = set()
        read = [0]

        def arrived() -> int:
            """Distinct ids at the sink (each message body read once)."""
            seen.update(json.loads(m.body)["seq"] for m in out.messages[read[0]:])
            read[0] = len(seen) and len(out.messages)
            return len(seen)

        try:
            await asyncio.to_thread(engine.wait_started)
            before = await admin_status(port)
            assert [w["routes"] for w in before["workers"]] == [[f"pass-{tag}"], [f"pass-{tag}"]], before["workers"]
            victim = before["workers"][0]["pid"]
            await wait_for(lambda: arrived() >= TOTAL // 4, 120, "a quarter of the messages before the kill")
            os.kill(victim, signal.SIGKILL)
            at_kill = arrived()

            async def back() -> dict[str, Any] | None:
                status = await admin_status(port)
                worker = status["workers"][0]
                return status if worker["up"] and worker["restarts"] == 1 and worker["pid"] != victim else None

            status = await wait_for(back, 120, "worker 0 started again", lambda: engine.log())
            await wait_for(lambda: arrived() == TOTAL, 240, f"all {TOTAL} messages at the sink",
                           lambda: f"{arrived()} distinct, {len(out.messages)} in all")
            await publishing
            route = (await admin_status(port))["routes"][f"pass-{tag}"]
            async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/metrics") as answer:
                metrics = await answer.text()
            table = await asyncio.to_thread(subprocess.run, [sys.executable, "-m", "engine", "status", "--admin", str(port)],
                                            capture_output=True, text=True, cwd=REPO)
            return {"at_kill": at_kill, "status": status, "route": route, "received": len(out.messages), "metrics": metrics,
                    "table": table.stdout + table.stderr}
        finally:
            publishing.cancel()
            await connection.close()

    result, _ = engine.run(scenario)
    assert result["at_kill"] < TOTAL, "the kill came after the drain: nothing was in flight"
    worker = result["status"]["workers"][0]
    assert worker["last_exit"] == -signal.SIGKILL and worker["restarts"] == 1
    assert worker["cpu_s"] >= 0 and worker["rss_mib"] > 10  # a running engine process, read from /proc
    assert result["received"] >= TOTAL  # at least once: what worker 0 held may arrive twice
    assert result["route"]["workers"] == [0, 1]
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for family in text_string_to_metric_families(result["metrics"]) for s in family.samples}
    delivered = {labels: value for (name, labels), value in samples.items() if name == "rabbitros_worker_messages_total"
                 and ("outcome", "delivered") in labels}
    assert len(delivered) == 2  # one series a worker; the restarted worker's counters begin at 0
    assert samples[("rabbitros_messages_total", (("outcome", "delivered"), ("route", f"pass-{tag}")))] == sum(delivered.values())
    assert samples[("rabbitros_worker_restarts_total", (("worker", "0"),))] == 1
    assert samples[("rabbitros_workers_up", (("worker", "0"),))] == samples[("rabbitros_workers_up", (("worker", "1"),))] == 1
    assert "workers 2/2 up" in result["table"] and "restarts 1" in result["table"], result["table"]


def stopped_under_load(tmp_path: Path, amqp_url: str, stop: Callable[[EngineProcess, int], int | None]) -> tuple[list[int], int | None, int, str]:
    """Two workers draining a backlog are stopped a quarter of the way by ``stop(supervisor,
    its pid)``; once both workers are gone, one engine started afterwards must carry the rest
    (every message at the sink at least once). The workers' pids, what ``stop`` returned, the
    messages at the sink when it was called, and the supervisor's log."""
    tag = "s" + uuid.uuid4().hex[:8]
    route_file, port, first = two_workers(tmp_path, ROUTES.format(url=amqp_url, tag=tag, key="out"), "status-first.json")

    async def scenario() -> tuple[list[int], int | None, int]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), f"{tag}-out", "#")
        try:
            await asyncio.to_thread(first.wait_started)
            status = await admin_status(port)
            pids = [w["pid"] for w in status["workers"]]
            publishing = asyncio.create_task(publish(connection, tag, range(TOTAL)))  # while the workers drain it
            await wait_for(lambda: len(out.messages) >= TOTAL // 4, 120, "a quarter of the messages before the stop")
            stopped = await asyncio.to_thread(stop, first, status["pid"])
            at_stop = len(out.messages)
            await wait_for(lambda: all(process_gone(pid) for pid in pids), 60, "both workers gone after their supervisor",
                           lambda: [pid for pid in pids if not process_gone(pid)])
            await publishing
            second = EngineProcess(route_file.parent, tmp_path / "status-second.json", {})
            try:
                await asyncio.to_thread(second.wait_started)
                await wait_for(lambda: len({json.loads(m.body)["seq"] for m in out.messages}) == TOTAL, 240,
                               f"all {TOTAL} messages at the sink", lambda: f"{len(out.messages)} in all")
            finally:
                assert await asyncio.to_thread(second.stop) == 0, second.log()
            return pids, stopped, at_stop
        finally:
            await connection.close()

    try:
        pids, stopped, at_stop = asyncio.run(scenario())
    finally:
        first.stop()
    return pids, stopped, at_stop, (tmp_path / "status-first.log").read_text()


def process_gone(pid: int) -> bool:
    """The process exited (a zombie waits only for its parent to reap it)."""
    try:
        return "zombie" in Path(f"/proc/{pid}/status").read_text().lower()
    except FileNotFoundError:
        return True


def test_a_stop_under_load_drains_both_workers_and_loses_nothing(tmp_path: Path, amqp_url: str) -> None:
    """SIGTERM to the supervisor while both workers drain a backlog: both stop (each drains
    what it holds), the supervisor exits 0 and no worker outlives it; one engine started
    afterwards carries the rest, and every message arrived at least once."""
    _, exited, at_stop, log = stopped_under_load(tmp_path, amqp_url, lambda supervisor, _: supervisor.stop())
    assert exited == 0, log[-3000:]
    assert at_stop < TOTAL, "the stop came after the drain: nothing was in flight"
    assert log.count('"msg": "stopped"') == 3, log[-3000:]  # the two workers and the supervisor, each after its drain


def test_a_supervisor_killed_with_9_leaves_no_worker_and_loses_nothing(tmp_path: Path, amqp_url: str) -> None:
    """SIGKILL to the supervisor (no chance to stop anything) while both workers drain a
    backlog: each worker is told by the kernel (PR_SET_PDEATHSIG), drains and exits, so none
    goes on consuming the queue unsupervised; an engine started afterwards carries the rest and
    every message arrives at least once."""
    _, _, at_stop, log = stopped_under_load(tmp_path, amqp_url, lambda _, pid: os.kill(pid, signal.SIGKILL))
    assert at_stop < TOTAL, "the kill came after the drain: nothing was in flight"
    assert log.count('"msg": "stopped"') == 2, log[-3000:]  # each worker after its drain; the supervisor was killed


SPAWN_AND_DIE = """\
import os, subprocess, sys
log = open(sys.argv[1], "w")
worker = subprocess.Popen(sys.argv[2:] + ["--supervisor-pid", str(os.getpid())], stdout=log, stderr=log)
print(worker.pid, flush=True)
"""
"""A stand-in supervisor that starts a worker and dies at once, while the worker still imports."""


def test_a_worker_whose_supervisor_died_before_it_ran_stops(tmp_path: Path, amqp_url: str) -> None:
    """A supervisor killed in the second a worker (re)starts, before the worker asked the kernel
    for PR_SET_PDEATHSIG: the worker finds its parent is not the supervisor that started it and
    stops, instead of consuming the queue unsupervised."""
    tag = "d" + uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(ROUTES.format(url=amqp_url, tag=tag, key="out"))
    worker = [sys.executable, "-m", "engine", "run", "--routes", str(routes), "--schemas", str(REPO / "schemas"),
              "--no-watch", "--workers", "2", "--worker", "0", "--log-format", "json"]
    parent = subprocess.run([sys.executable, "-c", SPAWN_AND_DIE, str(tmp_path / "worker.log"), *worker],
                            capture_output=True, text=True, cwd=REPO, timeout=60)
    assert parent.returncode == 0, parent.stderr
    pid = int(parent.stdout)
    try:
        asyncio.run(wait_for(lambda: process_gone(pid), 60, "the worker gone after its supervisor",
                             lambda: (tmp_path / "worker.log").read_text()[-2000:]))
    finally:
        if not process_gone(pid):
            os.kill(pid, signal.SIGKILL)


def test_a_reload_reaches_both_workers_and_a_broken_one_neither(tmp_path: Path, amqp_url: str) -> None:
    """An edit of the routes: the supervisor checks it once, both workers run the new config
    hash and the supervisor's generation is 2; a file that does not compile is rejected once,
    by the supervisor, and both workers keep running the hash they had."""
    tag = "r" + uuid.uuid4().hex[:8]
    route_file, port, engine = two_workers(tmp_path, ROUTES.format(url=amqp_url, tag=tag, key="first"))

    async def scenario() -> tuple[dict[str, Any], dict[str, Any]]:
        first = await admin_status(port)
        route_file.write_text(ROUTES.format(url=amqp_url, tag=tag, key="second"))

        async def applied() -> dict[str, Any] | None:
            status = await admin_status(port)
            hashes = {w["status"]["config_hash"] for w in status["workers"] if w["status"]}
            return status if status["generation"] == 2 and hashes == {status["config_hash"]} != {first["config_hash"]} else None

        reloaded = await wait_for(applied, 60, "both workers on generation 2", lambda: engine.log())
        route_file.write_text(route_file.read_text().replace("schema: raw_json", "schema: no_such_schema"))

        async def rejected() -> dict[str, Any] | None:
            status = await admin_status(port)
            return status if status["reloads"]["rejected"] == 1 else None

        broken = await wait_for(rejected, 60, "the broken edit rejected", lambda: engine.log())
        return reloaded, broken

    reloaded, broken = engine.run(scenario)[0]
    assert [w["status"]["generation"] for w in reloaded["workers"]] == [2, 2]
    assert broken["generation"] == 2 and broken["config_hash"] == reloaded["config_hash"]
    assert {w["status"]["config_hash"] for w in broken["workers"]} == {reloaded["config_hash"]}
    assert [w["status"]["reloads"]["rejected"] for w in broken["workers"]] == [0, 0]  # no worker was asked
    assert "no_such_schema" in " ".join(broken["reloads"]["last_error"])


@pytest.mark.fast
def test_workers_is_a_count_or_auto() -> None:
    from engine.ops.supervisor import worker_count

    assert worker_count("3") == 3 and worker_count("auto") == len(os.sched_getaffinity(0))
    for bad in ("0", "-1", "two"):
        with pytest.raises(Exception, match="--workers"):
            worker_count(bad)


MQTT_ROUTES = """
connections:
  field: {{mqtt: "{mqtt}"}}
  broker: {{amqp: "{url}"}}
routes:
  - name: weather-{tag}
    source: {{mqtt: {{connection: field, topic: "{tag}/+/weather", shared: engines}}}}
    schema: raw_json
    sink: {{amqp: {{connection: broker, exchange: {tag}-out, routing_key: wx}}}}
"""
MQTT_TOTAL = 2_000


def test_an_mqtt_shared_subscription_is_split_between_the_workers(tmp_path: Path, mosquitto: Any, amqp_url: str) -> None:
    """A route on an MQTT shared subscription (``shared: engines``) runs on both workers
    (check says so); mosquitto 2.0 hands each QoS 1 message to one of them: both carry some,
    every message arrives at least once."""
    from tests.endpoints.mqtt.test_mqtt import publish as mqtt_publish

    tag = "m" + uuid.uuid4().hex[:8]
    _, port, engine = two_workers(tmp_path, MQTT_ROUTES.format(mqtt=mosquitto.url, url=amqp_url, tag=tag))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), f"{tag}-out", "#")
        try:
            placed = await admin_status(port)
            assert placed["placement"] == {f"weather-{tag}": [0, 1]}
            sent = await mqtt_publish(mosquitto, ((f"{tag}/field{seq % 4}/weather", {"seq": seq}) for seq in range(MQTT_TOTAL)))
            assert sent == MQTT_TOTAL
            await wait_for(lambda: len({json.loads(m.body)["seq"] for m in out.messages}) == MQTT_TOTAL, 120,
                           f"all {MQTT_TOTAL} messages at the sink", lambda: f"{len(out.messages)} in all")
            return await admin_status(port)
        finally:
            await connection.close()

    status, _ = engine.run(scenario)
    received = [w["status"]["routes"][f"weather-{tag}"]["received"] for w in status["workers"]]
    print(f"MQTT shared subscription over 2 workers: received {received}")
    assert all(count > 0 for count in received) and sum(received) >= MQTT_TOTAL, received


ROLLBACK_ROUTES = """
connections:
  broker: {{amqp: "{url}"}}
  vehicle: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 0}}
routes:
  - name: pass-{tag}
    source: {{amqp: {{connection: broker, exchange: {tag}-in, binding_key: "#", queue: {tag}-q}}}}
    schema: raw_json
    sink: {{amqp: {{connection: broker, exchange: {tag}-out, routing_key: "{key}"}}}}
  - name: heartbeats-{tag}
    source: {{mavlink: {{connection: vehicle, message: HEARTBEAT}}}}
    schema: raw_json
    mapping: '{{type: type}}'
    sink: {{amqp: {{connection: broker, exchange: {tag}-out, routing_key: heartbeat}}}}
"""


def test_a_generation_one_worker_refuses_is_rolled_back_on_the_others(tmp_path: Path, amqp_url: str) -> None:
    """``--require-connections``: an edit changes the queue route's routing key (every worker)
    and moves the vehicle's link to a UDP port another socket holds. The supervisor accepts the
    files; the worker that must open the link cannot and refuses; the worker that switched is
    told to go back. Every worker then runs the first generation (its hash), the reload counts
    as rejected naming the worker, and messages published afterwards still get the first
    routing key: no worker converts with the refused generation."""
    import socket

    tag = "b" + uuid.uuid4().hex[:8]
    free, busy = listening_port(kind=socket.SOCK_DGRAM), listening_port(kind=socket.SOCK_DGRAM)
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # no SO_REUSEADDR: the engine's bind must fail
    holder.bind(("127.0.0.1", busy))
    route_file, port, engine = two_workers(tmp_path, ROLLBACK_ROUTES.format(url=amqp_url, tag=tag, key="first", port=free),
                                           "status.json", "--require-connections")

    async def scenario() -> tuple[dict[str, Any], dict[str, Any], list[str]]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), f"{tag}-out", "#")
        try:
            first = await admin_status(port)
            route_file.write_text(ROLLBACK_ROUTES.format(url=amqp_url, tag=tag, key="second", port=busy))

            async def rejected() -> dict[str, Any] | None:
                status = await admin_status(port)
                return status if status["reloads"]["rejected"] == 1 else None

            after = await wait_for(rejected, 90, "the generation refused by one worker and rolled back", lambda: engine.log())

            async def back() -> dict[str, Any] | None:
                status = await admin_status(port)
                hashes = {w["status"]["config_hash"] for w in status["workers"] if w["status"]}
                return status if hashes == {first["config_hash"]} and all(w["up"] for w in status["workers"]) else None

            after = await wait_for(back, 60, "every worker back on the first generation", lambda: engine.log())
            await publish(connection, tag, range(50))
            await wait_for(lambda: len([m for m in out.messages if m.routing_key != "heartbeat"]) >= 50, 60, "50 messages")
            return first, after, sorted({m.routing_key or "" for m in out.messages})
        finally:
            await connection.close()

    try:
        (first, after, keys), _ = engine.run(scenario)
    finally:
        holder.close()
    assert after["generation"] == first["generation"] == 1 and after["config_hash"] == first["config_hash"]
    assert "refused generation" in " ".join(after["reloads"]["last_error"]), after["reloads"]
    assert after["reloads"]["split"] == {}
    assert [w["restarts"] for w in after["workers"]] == [0, 0]  # went back in place, no restart
    assert keys == ["first"] or keys == ["first", "heartbeat"], keys


@pytest.mark.fast
def test_invalid_routes_start_no_worker(tmp_path: Path) -> None:
    """The supervisor checks the routes before it starts anything: a file with a problem exits
    2 naming the file, line and route, and no worker process was started."""
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text("routes:\n  - name: typo\n    source: {amqp: {queue: q, prefetchh: 10}}\n"
                                   "    schema: raw_json\n    sink: {amqp: {exchange: out}}\n")
    result = subprocess.run([sys.executable, "-m", "engine", "run", "--routes", str(routes), "--workers", "2", "--no-watch"],
                            capture_output=True, text=True, cwd=REPO, timeout=120)
    assert result.returncode == 2, result.stderr
    assert f"{routes / 'r.yaml'}:3" in result.stderr and "prefetchh" in result.stderr
    assert "worker" not in result.stderr.replace("--workers", "")  # no worker's line: none started
