"""Broker outages against the real parts (issue 8): a private RabbitMQ node killed with -9 and
restarted on its data directory, the engine as a child process, real rclpy and pymavlink.

Each test prints its figures (sent, delivered, duplicates, lost, and the time from the
broker's restart to the first message delivered after it); run with ``-s`` to see them."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import pytest

from engine.endpoints.amqp.broker import LocalBroker
from tests.support.repo import REPO
from tests.support.engine_process import EngineProcess
from tests.support.amqp_helpers import Collector
from tests.support.outage_helpers import RosPeer, Tally, declare_bound_queue, publish_reliably, robust
from tests.support.udp_vehicle import free_udp_port
from tests.support.workers import ros_domain
from tests.support.waiting import probe_until, wait_for

import rclpy  # noqa: F401,E402  (a missing rclpy fails the run, never skips it)

N_FLOW = 10_000
RATE = 250.0
N_SPILL = 5_000


def _names() -> dict[str, str]:
    tag = "o" + uuid.uuid4().hex[:8]
    return {"tag": tag, "inbox": f"in-{tag}", "outbox": f"out-{tag}", "domain": str(ros_domain(8))}


ROUTES = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: to-ros
    source:
      amqp: {{exchange: {inbox}, binding_key: "r.#", queue: {inbox}-q}}
    schema: raw_json
    sink:
      ros2: {{topic: /{tag}/down}}
  - name: from-ros
    source:
      ros2: {{topic: /{tag}/up}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: up.x}}
{extra}"""


def _status(engine: EngineProcess) -> dict[str, Any]:
    return engine.status() or {}


def _matched_publishers(status: dict[str, Any], route: str) -> int:
    """How many publishers the route's ROS 2 source has matched: its reader knows our writer (a
    reliable message published before it does may be lost), as our writer's count says the converse."""
    return int(((status.get("routes") or {}).get(route) or {}).get("source", {}).get("matched_publishers", 0))


def _connection_healthy(engine: EngineProcess, name: str = "default-amqp") -> bool:
    return bool(_status(engine).get("connections", {}).get(name, {}).get("healthy"))


async def _warm_up(peer: RosPeer, connection: Any, names: dict[str, str], down: Tally, up: Tally,
                   both: bool = True) -> None:
    """DDS matching is asynchronous and a volatile writer drops what it publishes before it
    matches: probe (seq -1) until each direction gets through, then forget the probes."""
    import aio_pika

    channel = await connection.channel()
    inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)
    await wait_for(lambda: peer.subscribers(f"/{names['tag']}/up") > 0, 30, "the engine's ROS subscription")

    async def probe() -> None:
        if both:
            await inbox.publish(aio_pika.Message(b'{"seq": -1}'), "r.x")
        peer.publish(-1)

    await probe_until(lambda: (not both or down.probes) and up.probes, probe, 30,
                      "a probe through each direction (the engine's ROS 2 endpoints matched)")
    await channel.close()


@pytest.fixture(scope="module")
def broker() -> Any:
    """One private node for the tests that kill it: it restarts on its own data directory."""
    node = LocalBroker()
    node.start()
    yield node
    node.stop()


@pytest.mark.soak
def test_broker_killed_twice_under_traffic_both_directions_lose_nothing(tmp_path: Path, broker: LocalBroker) -> None:
    """10,000 AMQP -> ROS 2 and 10,000 ROS 2 -> AMQP at 250 msg/s each while the broker is
    killed with -9 and restarted (same data directory and port) twice."""
    names = _names()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "outage.yaml").write_text(ROUTES.format(extra="", **names))
    to_ros, from_ros = Tally("amqp->ros2"), Tally("ros2->amqp")
    restarts: list[float] = []
    dead_lettered: dict[str, int] = {}
    expected = range(N_FLOW)

    async def scenario(broker: LocalBroker) -> int:
        peer = RosPeer(int(names["domain"]), f"peer_{names['tag']}", f"/{names['tag']}/up", f"/{names['tag']}/down", to_ros)
        engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": broker.url})
        connection = await robust(broker.url)
        try:
            await Collector.bind(await connection.channel(), names["outbox"], "up.#", queue=f"collect-{names['tag']}", ack=True, tally=from_ros, prefetch=500)
            await asyncio.to_thread(engine.wait_started)
            await _warm_up(peer, connection, names, to_ros, from_ros)

            async def outages() -> None:
                for threshold in (N_FLOW * 3 // 10, N_FLOW * 65 // 100):
                    await wait_for(lambda: from_ros.sent >= threshold, 300, "the senders")
                    broker.kill()
                    await asyncio.sleep(1.0)  # outage: the broker stays down 1 s (the outage under test)
                    await asyncio.to_thread(broker.start)
                    restarts.append(time.monotonic())

            await asyncio.gather(
                publish_reliably(connection, names["inbox"], "r.x", expected, RATE, to_ros),
                asyncio.to_thread(peer.publish_paced, expected, RATE, from_ros),
                outages(),
            )
            await wait_for(lambda: not to_ros.lost(expected) and not from_ros.lost(expected), 180, "every message")
        finally:
            await connection.close()
            code = engine.stop()
            peer.close()
        status = engine.status() or {}
        routes_status = status.get("routes", {})
        print("\n" + engine.log()[-1500:] if code else "", routes_status.get("from-ros", {}).get("buffer"))
        dead_lettered.update({name: route.get("failed") for name, route in routes_status.items()})
        return code

    if not broker.running:
        broker.start()
    code = asyncio.run(scenario(broker))
    for tally in (to_ros, from_ros):
        figures = [tally.first_after(moment) for moment in restarts]
        print(f"\n{tally.figures(expected)}; restart->first delivered: "
              + ", ".join(f"{f:.2f}s" if f is not None else "none" for f in figures))
        assert not tally.lost(expected), f"{tally.name}: lost {tally.lost(expected)[:10]}"
        assert all(f is not None for f in figures)
    print(f"dead-lettered: {dead_lettered}")
    assert dead_lettered == {"to-ros": 0, "from-ros": 0}, "an outage must not dead-letter anything"
    assert len(restarts) == 2
    assert code == 0, "graceful stop must exit 0"


@pytest.mark.soak
def test_spilled_messages_survive_an_engine_restart_during_the_outage(tmp_path: Path, broker: LocalBroker) -> None:
    """ROS 2 -> AMQP with spill_dir: broker down, 5,000 messages, engine stopped (SIGTERM) and
    started again while the broker is still down, broker back: all 5,000 delivered."""
    names = _names()
    routes = tmp_path / "routes"
    routes.mkdir()
    spill = tmp_path / "spill"
    extra = "    buffer: {spill_dir: " + str(spill) + "}\n"
    (routes / "outage.yaml").write_text(ROUTES.format(extra="", **names).rstrip("\n") + "\n" + extra)
    arrived, ignored = Tally("ros2->amqp (spilled)"), Tally("unused")
    expected = range(N_SPILL)
    figures: dict[str, Any] = {}

    async def scenario(broker: LocalBroker) -> None:
        peer = RosPeer(int(names["domain"]), f"peer_{names['tag']}", f"/{names['tag']}/up", f"/{names['tag']}/down", ignored)
        first = EngineProcess(routes, tmp_path / "first.json", {"RABBITROS_AMQP_URL": broker.url})
        second: EngineProcess | None = None
        connection = await robust(broker.url)
        try:
            await Collector.bind(await connection.channel(), names["outbox"], "up.#", queue=f"collect-{names['tag']}", ack=True, tally=arrived, prefetch=500)
            await asyncio.to_thread(first.wait_started)
            await _warm_up(peer, connection, names, ignored, arrived, both=False)
            broker.kill()
            await wait_for(lambda: not _connection_healthy(first), 30, "the engine to see the broker down")
            await asyncio.to_thread(peer.publish_paced, expected, 1000.0, arrived)

            def held() -> int:
                buffer = _status(first).get("routes", {}).get("from-ros", {}).get("buffer") or {}
                return int(buffer.get("held", 0))

            await wait_for(lambda: held() >= N_SPILL, 60, "5,000 messages held")
            figures["exit_code"] = first.stop()
            figures["spill_files"] = sorted(p.name for p in (spill / "from-ros").glob("*.jsonl"))
            second = EngineProcess(routes, tmp_path / "second.json", {"RABBITROS_AMQP_URL": broker.url})
            await asyncio.to_thread(second.wait_started)
            buffer = _status(second)["routes"]["from-ros"]["buffer"]
            figures["replayed"] = buffer["replayed"]
            assert not _connection_healthy(second)
            await asyncio.to_thread(broker.start)
            back = time.monotonic()
            await wait_for(lambda: not arrived.lost(expected), 120, "every spilled message")
            figures["restart_to_first"] = arrived.first_after(back)
            figures["second_exit_code"] = second.stop()
        finally:
            await connection.close()
            first.stop()
            if second is not None:
                second.stop()
            peer.close()

    if not broker.running:
        broker.start()
    asyncio.run(scenario(broker))
    print(f"\n{arrived.figures(expected)}; replayed={figures.get('replayed')} "
          f"restart->first delivered: {figures.get('restart_to_first')}")
    assert figures["exit_code"] == 0 and figures["second_exit_code"] == 0
    assert figures["spill_files"], "nothing was spilled"
    assert figures["replayed"] == N_SPILL
    assert not arrived.lost(expected)


MAVLINK_ROUTES = """
connections:
  uav: {{mavlink: "udpin:127.0.0.1:{port}"}}
routes:
  - name: uav-to-ros
    source:
      mavlink: {{connection: uav, message: GLOBAL_POSITION_INT}}
    mapping: "{{seq: time_boot_ms}}"
    schema: raw_json
    sink:
      ros2: {{topic: /{tag}/down}}
"""


async def _declare_collector_queue(broker: LocalBroker, names: dict[str, str]) -> None:
    """The collector's durable queue, bound, declared while the broker is up. Bound only once the
    broker is back, it could come after the engine's first publishes, which the broker drops
    (no queue bound, and not mandatory): CI saw the 200 held messages "lost" that way."""
    connection = await robust(broker.url)
    await declare_bound_queue(await connection.channel(), f"collect-{names['tag']}", names["outbox"], "up.#")
    await connection.close()


@pytest.mark.soak
def test_engine_starts_without_the_broker_and_routes_that_do_not_need_it_run_at_once(tmp_path: Path) -> None:
    """MAVLink -> ROS 2 works while the broker is down; AMQP -> ROS 2 starts when the broker
    comes up; ROS 2 -> AMQP holds what it gets meanwhile and delivers it then.
    ``--require-connections`` keeps the old fail-fast start."""
    from pymavlink import mavutil

    names = {**_names(), "port": str(free_udp_port())}
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "outage.yaml").write_text(ROUTES.format(extra="", **names))
    (routes / "uav.yaml").write_text(MAVLINK_ROUTES.format(**names))
    down, up = Tally("to ros2"), Tally("ros2->amqp")
    figures: dict[str, Any] = {}
    broker = LocalBroker()
    broker.start()  # once, so that what the engine holds has a queue to go to when the broker is back
    asyncio.run(_declare_collector_queue(broker, names))
    broker.halt()  # its port is closed from here on

    strict = subprocess.run(
        ["timeout", "-s", "KILL", "120", sys.executable, "-m", "engine", "--routes", str(routes),
         "--schemas", str(REPO / "schemas"), "--require-connections"],
        cwd=REPO, env={**os.environ, "RABBITROS_AMQP_URL": broker.url}, capture_output=True, text=True, timeout=130,
    )
    assert strict.returncode == 1, strict.stderr[-2000:]

    async def scenario() -> None:
        peer = RosPeer(int(names["domain"]), f"peer_{names['tag']}", f"/{names['tag']}/up", f"/{names['tag']}/down", down)
        engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": broker.url})
        vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{names['port']}", source_system=1, dialect="common")
        connection = None
        try:
            status = await asyncio.to_thread(engine.wait_started)
            started = time.monotonic()
            assert status["connections"]["default-amqp"]["healthy"] is False
            assert status["routes"]["to-ros"]["state"] == "waiting"
            assert status["routes"]["uav-to-ros"]["state"] == "running"
            assert status["routes"]["from-ros"]["state"] == "running", "a buffered route runs without its sink"
            sent = 0

            def send_position() -> None:
                nonlocal sent
                sent += 1
                vehicle.mav.global_position_int_send(sent, 0, 0, 0, 0, 0, 0, 0, 0)

            await probe_until(lambda: down.copies, send_position, 30, "MAVLink -> ROS 2 while the broker is down", every=0.05)
            figures["mavlink_to_ros_first_s"] = min(down.arrivals) - started
            for seq in range(100):  # while the broker is down: into from-ros's buffer
                vehicle.mav.global_position_int_send(10_000 + seq, 0, 0, 0, 0, 0, 0, 0, 0)
            await wait_for(lambda: peer.subscribers(f"/{names['tag']}/up") > 0, 30, "the engine's ROS subscription")
            await wait_for(lambda: _matched_publishers(_status(engine), "from-ros"), 30, "the engine's reader to match our writer")
            for seq in range(200):
                peer.publish(seq)
                up.sent += 1
            await wait_for(lambda: (_status(engine)["routes"]["from-ros"]["buffer"] or {}).get("held", 0) >= 200, 30,
                           "200 messages held for the broker")
            assert _status(engine)["routes"]["to-ros"]["state"] == "waiting"
            await wait_for(lambda: all(s in down.copies for s in range(10_000, 10_100)), 30, "MAVLink while the broker is down")

            await asyncio.to_thread(broker.start)
            back = time.monotonic()
            connection = await robust(broker.url)
            await Collector.bind(await connection.channel(), names["outbox"], "up.#", queue=f"collect-{names['tag']}", ack=True, tally=up, prefetch=500)
            await wait_for(lambda: _status(engine)["routes"]["to-ros"]["state"] == "running", 60, "to-ros to start")
            figures["broker_to_routes_started_s"] = time.monotonic() - back
            assert _connection_healthy(engine)
            amqp_seqs = range(20_000, 20_200)
            await publish_reliably(connection, names["inbox"], "r.x", amqp_seqs, 500.0, Tally("published"))
            await wait_for(lambda: all(s in down.copies for s in amqp_seqs), 60, "AMQP -> ROS 2 after the broker came up")
            await wait_for(lambda: not up.lost(range(200)), 60, "the held ROS 2 -> AMQP messages")
            figures["restart_to_first_held_delivered_s"] = up.first_after(back)
            figures["exit_code"] = engine.stop()
        finally:
            if connection is not None:
                await connection.close()
            engine.stop()
            vehicle.close()
            peer.close()

    try:
        asyncio.run(scenario())
    finally:
        broker.stop()
    print(f"\nstart without broker: {figures}; {up.figures(range(200))}")
    assert figures["exit_code"] == 0
    assert figures["mavlink_to_ros_first_s"] < 15


def test_held_messages_survive_a_reload_that_replaces_the_route(tmp_path: Path, broker: LocalBroker,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The broker is down; a ROS 2 -> AMQP route holds 300 messages in memory; a reload changes
    the route's source (a new runner) and the held messages move with the route; once the broker
    is up all arrive."""
    from engine.running.runtime import Engine

    names = _names()
    routes = tmp_path / "routes"
    routes.mkdir()
    text = ROUTES.format(extra="", **names)
    (routes / "outage.yaml").write_text(text)
    arrived, ignored = Tally("ros2->amqp across a reload"), Tally("unused")
    monkeypatch.setenv("RABBITROS_AMQP_URL", broker.url)

    async def scenario() -> None:
        engine = Engine(routes, REPO / "schemas")
        peer = RosPeer(int(names["domain"]), f"peer_{names['tag']}", f"/{names['tag']}/up", f"/{names['tag']}/down", ignored)
        connection = None
        try:
            await engine.start()
            runner = engine.runners["from-ros"]
            assert runner.state == "running" and engine.runners["to-ros"].state == "waiting"
            await wait_for(lambda: peer.subscribers(f"/{names['tag']}/up") > 0, 30, "the engine's ROS subscription")
            await wait_for(lambda: _matched_publishers(engine.status(), "from-ros"), 30, "the engine's reader to match our writer")
            for seq in range(300):
                peer.publish(seq)
                arrived.sent += 1
            await wait_for(lambda: runner.buffer is not None and len(runner.buffer) >= 300, 30, "300 held")
            (routes / "outage.yaml").write_text(text.replace(f"topic: /{names['tag']}/up}}", f"topic: /{names['tag']}/up, qos: {{depth: 500}}}}"))
            assert await engine.reload()
            replaced = engine.runners["from-ros"]
            assert replaced is not runner and replaced.buffer is runner.buffer and replaced.buffer is not None and len(replaced.buffer) == 300
            await asyncio.to_thread(broker.start)
            connection = await robust(broker.url)
            await Collector.bind(await connection.channel(), names["outbox"], "up.#", queue=f"collect-{names['tag']}", ack=True, tally=arrived, prefetch=500)
            await wait_for(lambda: not arrived.lost(range(300)), 60, "the held messages")
        finally:
            if connection is not None:
                await connection.close()
            await engine.stop(2.0)
            peer.close()

    if not broker.running:
        broker.start()
    asyncio.run(_declare_collector_queue(broker, names))
    broker.kill()
    asyncio.run(scenario())
    print(f"\n{arrived.figures(range(300))}")
    assert not arrived.lost(range(300))
