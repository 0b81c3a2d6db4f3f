"""Routes through the ros2 endpoint inside the engine: typed conversion both ways, failures
counted while valid messages keep flowing, and check errors that name the route."""

from __future__ import annotations

import asyncio
import io
import json
import os
import re
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest

import rclpy  # noqa: F401,E402  (a missing rclpy fails the run, never skips it)

from engine.common.schemas import canonical_bytes  # noqa: E402
from engine.endpoints.ros2.source import Ros2Source  # noqa: E402
from engine.running.runtime import Engine  # noqa: E402
from tests.support.amqp_helpers import Collector, header_text, message_count, publish  # noqa: E402
from tests.operator.test_cli import cli  # noqa: E402
from tests.support.repo import REPO  # noqa: E402
from tests.support.engine_process import EngineProcess  # noqa: E402
from tests.support.workers import ros_domain
from tests.support.waiting import wait_for, wait_for_sync

TYPED = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: position-to-ros
    source:
      amqp: {{exchange: {inbox}, binding_key: position, queue: {inbox}-q}}
    schema: position
    sink:
      ros2: {{topic: /{tag}/fix, type: sensor_msgs/msg/NavSatFix}}
      mapping: "{{header: {{frame_id: agent_id}}, latitude: lat, longitude: lon, altitude: alt_msl}}"
  - name: position-from-ros
    source:
      ros2: {{topic: /{tag}/fix, type: sensor_msgs/NavSatFix}}
    mapping: "{{agent_id: header.frame_id, lat: latitude, lon: longitude, alt_msl: altitude}}"
    schema: position
    sink:
      amqp: {{exchange: {outbox}, routing_key: "canonical.position.{{agent_id}}"}}
"""


@pytest.fixture
def typed_routes(tmp_path: Path, amqp_url: str, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, dict[str, str]]:
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "t" + uuid.uuid4().hex[:8]
    names = {"tag": tag, "inbox": f"in-{tag}", "outbox": f"out-{tag}", "domain": str(ros_domain(9))}
    (tmp_path / "typed.yaml").write_text(TYPED.format(**names))
    return tmp_path, names


async def matched_both_ways(engine: Engine, names: dict[str, str]) -> None:
    """The engine's NavSatFix publisher (route position-to-ros) and its subscriber (route
    position-from-ros) have found each other, each on its own side of DDS discovery: the
    publisher sees a subscription and the subscription a publisher. A message published before
    the subscriber's side matched is dropped by it (a fixed 1 s sleep hoped it had)."""
    sink = engine.runners["position-to-ros"].pipeline.sink
    source = engine.runners["position-from-ros"].source
    assert isinstance(source, Ros2Source), "position-from-ros reads a ROS 2 topic"
    topic = f"/{names['tag']}/fix"
    await wait_for(lambda: sink.ready and source._matched(topic) > 0, 30, f"the engine's publisher and subscriber on {topic} to match",
                   detail=lambda: f"publisher matched: {sink.ready}, subscriber matched: {source._matched(topic)}")


def test_canonical_position_through_navsatfix_and_back_is_byte_identical(typed_routes, amqp_url):
    directory, names = typed_routes
    positions = [
        {"agent_id": f"uav{i % 2}", "alt_msl": 600.0 + i / 3, "lat": -22.0 + i * 1.1e-7, "lon": -47.9 - 1 / (i + 3)}
        for i in range(50)
    ]
    originals = [canonical_bytes(p) for p in positions]

    async def scenario() -> list[bytes]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "canonical.position.#")
            await matched_both_ways(engine, names)
            await publish(channel, names["inbox"], "position", originals)
            received = await output.wait_for(len(originals), timeout=30)
        finally:
            await connection.close()
            await engine.stop()
        return [m.body for m in received]

    assert sorted(asyncio.run(scenario())) == sorted(originals)


def test_unmappable_ros_message_is_counted_and_the_next_one_flows(typed_routes, amqp_url):
    """A NavSatFix with a NaN latitude becomes null, which the position schema rejects."""
    directory, names = typed_routes
    good = canonical_bytes({"agent_id": "uav1", "alt_msl": 1.5, "lat": 1.25, "lon": 2.5})
    bad_fix_source = json.dumps({"agent_id": "uav1", "alt_msl": 1.5, "lat": 1.25, "lon": 2.5}).encode()

    async def scenario() -> tuple[list[bytes], list[aio_pika.abc.AbstractIncomingMessage], dict]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "canonical.position.#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "position-from-ros")
            await matched_both_ways(engine, names)
            sink = engine.runners["position-to-ros"].pipeline.sink
            from engine.endpoints.base import Outbound

            nan_fix = {"header": {"frame_id": "uav1"}, "latitude": float("nan"), "longitude": 2.5, "altitude": 1.5}
            await sink.send(Outbound(bad_fix_source, {}, nan_fix, "bad", {"route": "t", "generation": 0}))
            await publish(channel, names["inbox"], "position", [good])
            received = await output.wait_for(1, timeout=20)
            dead_letters = await dead.wait_for(1, timeout=10)
            # the dead letter is on the queue once the broker confirmed it; the route counts it
            # as failed when it has the confirmation back, a moment later under load
            await wait_for(lambda: engine.status()["routes"]["position-from-ros"]["failed"] >= 1, 10,
                           "position-from-ros counting its dead letter as failed")
            return [m.body for m in received], dead_letters, engine.status()
        finally:
            await connection.close()
            await engine.stop()

    received, dead_letters, status = asyncio.run(scenario())
    assert received == [good]
    assert status["routes"]["position-from-ros"]["failed"] == 1
    assert len(dead_letters) == 1
    assert dead_letters[0].headers["x-rabbitros-stage"] == "schema"
    assert "$.lat" in header_text(dead_letters[0], "x-rabbitros-error")


def test_a_null_from_the_sink_mapping_is_dead_lettered_naming_the_field_and_test_says_the_same(typed_routes, amqp_url):
    """A position without ``alt_msl`` (the schema allows it): the sink mapping's ``altitude:
    alt_msl`` gives null, which must not reach the robot as NaN or 0. It is dead-lettered at
    the ``sink mapping`` stage naming ``altitude``; the next message flows; and
    ``rabbitros-engine test`` reports the very same error for the same input."""
    directory, names = typed_routes
    no_altitude = {"agent_id": "uav1", "lat": 1.25, "lon": 2.5}
    good = canonical_bytes({"agent_id": "uav1", "alt_msl": 3.0, "lat": 1.25, "lon": 2.5})

    async def scenario() -> tuple[list[bytes], list[aio_pika.abc.AbstractIncomingMessage]]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "canonical.position.#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "position-to-ros")
            await publish(channel, names["inbox"], "position", [canonical_bytes(no_altitude), good])
            received = await output.wait_for(1, timeout=30)
            dead_letters = await dead.wait_for(1, timeout=10)
            await asyncio.sleep(0.5)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
            return [m.body for m in received], dead_letters
        finally:
            await connection.close()
            await engine.stop()

    received, dead_letters = asyncio.run(scenario())
    assert received == [good]
    assert len(dead_letters) == 1 and dead_letters[0].body == canonical_bytes(no_altitude)
    headers = dead_letters[0].headers
    error = f"ros2 topic '/{names['tag']}/fix': field altitude: null (the sink mapping gave no value"
    assert headers["x-rabbitros-stage"] == "sink mapping" and header_text(dead_letters[0], "x-rabbitros-error").startswith(error), headers

    (directory / "typed.test.yaml").write_text(f"""tests:
  - name: no altitude
    route: position-to-ros
    input: {json.dumps(no_altitude)}
    expect_sink: {{header: {{frame_id: uav1}}, latitude: 1.25, longitude: 2.5}}
  - name: no altitude is refused
    route: position-to-ros
    input: {json.dumps(no_altitude)}
    expect_error: sink mapping
""")
    result = cli("test", "--routes", str(directory), "--schemas", str(REPO / "schemas"))
    assert result.returncode == 1, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert lines[-1] == "1 passed, 1 failed", result.stdout
    assert f"no altitude: expected it to pass, got a sink mapping error: {header_text(dead_letters[0], 'x-rabbitros-error')}" in result.stdout


def test_check_names_the_route_for_uninstalled_type_and_bad_field(tmp_path: Path):
    (tmp_path / "ros.yaml").write_text("""
routes:
  - name: no-such-type
    source: {amqp: {queue: q1}}
    schema: raw_json
    sink: {ros2: {topic: /x, type: farm_msgs/msg/Weed}}
  - name: bad-field
    source: {amqp: {queue: q2}}
    schema: position
    sink:
      ros2: {topic: /fix, type: sensor_msgs/msg/NavSatFix}
      mapping: "{latitude: lat, longtitude: lon}"
""")
    result = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert any("'no-such-type'" in line and "farm_msgs/msg/Weed" in line and "ros.yaml:6:" in line for line in lines), lines
    assert any("'bad-field'" in line and "longtitude" in line for line in lines), lines


# ---------------------------------------------------------------- a sink waits for its reader

PREFILLED = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: backlog-to-ros
    source: {{amqp: {{queue: {queue}}}}}
    schema: raw_json
    sink: {{ros2: {{topic: /{tag}/backlog}}}}
"""
BACKLOG = 2000


def engine_cpu_seconds(engine: "EngineProcess") -> float:
    """User + system CPU of the engine's Python process (the child of ``timeout``)."""
    pid = engine.process.pid
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    fields = Path(f"/proc/{children[0]}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.parametrize("subscriber_delay", [None, 5.0], ids=["subscriber-first", "subscriber-5s-late"])
def test_a_prefilled_queue_reaches_a_subscriber_that_starts_before_or_after_the_engine(
        subscriber_delay, amqp_url: str, tmp_path: Path):
    """The engine starts on an AMQP queue already holding 2,000 messages for a ROS 2 topic
    (reliable, volatile). It must not publish them before DDS has matched the subscriber: a
    writer without a matched reader drops them, after the queue has had them acknowledged.
    Subscriber first (the issue's measurement: all 10,000 lost) or 5 s after the engine
    (meanwhile the route holds, says why in its status, spends no CPU): every message arrives,
    in order, and the queue is empty afterwards."""
    from rich.console import Console

    from engine.ops.opsview import status_table
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    tag = "b" + uuid.uuid4().hex[:8]
    queue = f"backlog-{tag}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "backlog.yaml").write_text(PREFILLED.format(domain=DOMAIN, tag=tag, queue=queue))
    bodies = [json.dumps({"seq": i, "note": "ção", "pad": "x" * (i % 50)}, ensure_ascii=False) for i in range(BACKLOG)]
    figures: dict[str, float] = {}

    async def fill() -> None:
        connection = await aio_pika.connect(amqp_url)
        async with connection:
            channel = await connection.channel(publisher_confirms=True)
            await channel.declare_queue(queue, durable=True)
            for body in bodies:
                await channel.default_exchange.publish(aio_pika.Message(body.encode()), queue)

    async def ready_count() -> int:
        connection = await aio_pika.connect(amqp_url)
        async with connection:
            declared = await (await connection.channel()).declare_queue(queue, passive=True)
            return message_count(declared)

    asyncio.run(fill())
    peer: Peer | None = None
    received: list[Any] = []  # the subscriber's messages, once it exists
    if subscriber_delay is None:
        peer = Peer()
        received = peer.subscribe(String, f"/{tag}/backlog")
        peer.start()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url})
    try:
        engine.wait_started()
        if subscriber_delay is not None:
            cpu, began = engine_cpu_seconds(engine), time.monotonic()
            time.sleep(subscriber_delay)  # quiet window: no subscriber this long, the engine holds (the behaviour under test)
            figures["cpu_while_waiting"] = (engine_cpu_seconds(engine) - cpu) / (time.monotonic() - began)
            route = engine.current_status()["routes"]["backlog-to-ros"]
            assert route["delivered"] == 0 and route["failed"] == 0, route
            assert route["sink_not_ready"].startswith(f"no subscriber has matched /{tag}/backlog"), route
            table = Console(width=250, record=True, file=io.StringIO())
            table.print(status_table(engine.current_status()))
            assert re.search(r"backlog-to-ros +│ holding .*│ no subscriber has matched", table.export_text()), table.export_text()
            assert asyncio.run(ready_count()) >= BACKLOG - 256  # at most a prefetch window taken, none acked
            assert figures["cpu_while_waiting"] < 0.10, figures
            peer = Peer()
            received = peer.subscribe(String, f"/{tag}/backlog")
            peer.start()
        subscribed_at = time.monotonic()

        def all_arrived() -> bool:
            if received and "first_message_s" not in figures:
                figures["first_message_s"] = time.monotonic() - subscribed_at
            return len(received) >= BACKLOG

        wait_for_sync(all_arrived, 60, f"the backlog's {BACKLOG} messages", lambda: f"{len(received)} arrived; {engine.log()}")
        figures["all_messages_s"] = time.monotonic() - subscribed_at
        time.sleep(0.5)  # quiet window: nothing more than the backlog may arrive
        assert len(received) == BACKLOG, f"{len(received)} of {BACKLOG} arrived; {engine.log()}"
        assert [m.data for m in received] == bodies
        wait_for_sync(lambda: (engine.status() or {}).get("routes", {}).get("backlog-to-ros", {}).get("delivered") == BACKLOG, 10,
                      f"the engine to count {BACKLOG} delivered", engine.status)
        route = engine.current_status()["routes"]["backlog-to-ros"]
        assert route["sink_not_ready"] is None and route["failed"] == 0 and route["retries"] == 0, route
        assert asyncio.run(ready_count()) == 0
    finally:
        assert engine.stop() == 0, engine.log()
        if peer is not None:
            peer.close()
    print(f"\n{subscriber_delay=}: {figures}")


WAITING = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: waits-for-reader
    source: {{amqp: {{queue: {queue}}}}}
    mapping: "merge(@, {{generation: `{generation}`}})"
    schema: raw_json
    sink: {{ros2: {{topic: /{tag}/waiting}}}}
"""


def test_a_reload_while_the_sink_waits_for_a_reader_completes_and_loses_nothing(
        amqp_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A route holding its messages for a subscriber must not hold a reload that swaps its
    pipeline: the held messages go back to the queue and are delivered, once the subscriber
    matches, by the new generation. Stopping the route while it waits is prompt too."""
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "w" + uuid.uuid4().hex[:8]
    names: dict[str, Any] = {"domain": DOMAIN, "tag": tag, "queue": f"waiting-{tag}"}
    (tmp_path / "waiting.yaml").write_text(WAITING.format(generation=1, **names))
    bodies = [json.dumps({"seq": i}).encode() for i in range(200)]

    async def scenario() -> tuple[list[Any], dict[str, float]]:
        engine = Engine(tmp_path, REPO / "schemas")
        figures: dict[str, float] = {}
        peer = None
        await engine.start()
        try:
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)
                for body in bodies:
                    await channel.default_exchange.publish(aio_pika.Message(body), names["queue"])
            runner = engine.runners["waits-for-reader"]
            await wait_for(lambda: runner.observer.received > 0, 10, "the route to take a batch (held in settle, waiting for a reader)")
            await asyncio.sleep(0.5)  # quiet window: the held batch stays undelivered (the behaviour under test)
            route = engine.status()["routes"]["waits-for-reader"]
            assert route["delivered"] == 0 and route["sink_not_ready"], route
            (tmp_path / "waiting.yaml").write_text(WAITING.format(generation=2, **names))
            began = time.monotonic()
            assert await asyncio.wait_for(engine.reload(), 10)
            figures["reload_s"] = time.monotonic() - began
            assert engine.runners["waits-for-reader"].pipeline.generation == 2
            peer = Peer()
            received = peer.subscribe(String, f"/{tag}/waiting")
            peer.start()
            await wait_for(lambda: len(received) >= len(bodies), 30, f"the {len(bodies)} held messages at the reader",
                           lambda: len(received))
            await asyncio.sleep(0.3)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
            return list(received), figures
        finally:
            began = time.monotonic()
            await engine.stop()
            if peer is not None:
                peer.close()
            print(f"\nfigures: {figures}, stop {time.monotonic() - began:.2f} s")

    received, figures = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert figures["reload_s"] < 3.0, figures
    got = [json.loads(m.data) for m in received]
    assert sorted(m["seq"] for m in got) == list(range(200)), f"{len(got)} of 200"
    assert {m["generation"] for m in got} == {2}


def test_an_engine_stops_at_once_while_a_route_waits_for_a_reader(amqp_url: str, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch):
    """Nothing can drain into a sink without a reader: the engine stops at once (measured:
    10.0 s, the drain timeout, before), and the held messages are back in the queue."""
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "s" + uuid.uuid4().hex[:8]
    names: dict[str, Any] = {"domain": DOMAIN, "tag": tag, "queue": f"stopping-{tag}"}
    (tmp_path / "waiting.yaml").write_text(WAITING.format(generation=1, **names))

    async def scenario() -> tuple[float, int]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        stopped = False
        try:
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)
                for i in range(50):
                    await channel.default_exchange.publish(aio_pika.Message(b'{"seq": %d}' % i), names["queue"])
                runner = engine.runners["waits-for-reader"]
                await wait_for(lambda: runner.observer.received > 0, 10, "the route to take a batch")
                began = time.monotonic()
                await engine.stop(drain_timeout=10.0)
                took = time.monotonic() - began
                stopped = True
                requeued = await connection.channel()

                async def back_in_queue() -> int:
                    declared = await requeued.declare_queue(names["queue"], passive=True)
                    return message_count(declared)

                left: list[int] = []

                async def all_back() -> bool:
                    left[:] = [await back_in_queue()]
                    return left == [50]

                await wait_for(all_back, 10, "the 50 held messages back in the queue", lambda: left)
                return took, left[0]
        finally:
            if not stopped:
                await engine.stop()

    took, left = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert took < 2.0 and left == 50, (took, left)


def test_a_subscriber_that_leaves_makes_the_route_hold_again(amqp_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A matched subscriber that goes away (its node closes: DDS says so at once) makes the
    route hold again; what is queued meanwhile waits on AMQP and reaches the next subscriber."""
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "l" + uuid.uuid4().hex[:8]
    names: dict[str, Any] = {"domain": DOMAIN, "tag": tag, "queue": f"leaving-{tag}"}
    (tmp_path / "waiting.yaml").write_text(WAITING.format(generation=1, **names))

    async def scenario() -> tuple[list[int], list[int], float]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        first = second = None
        try:
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)

                async def send(seqs: range) -> None:
                    for i in seqs:
                        await channel.default_exchange.publish(aio_pika.Message(b'{"seq": %d}' % i), names["queue"])

                first = Peer()
                got_first = first.subscribe(String, f"/{tag}/waiting")
                first.start()
                await send(range(100))
                await wait_for(lambda: len(got_first) == 100, 20, "the first subscriber's 100")
                first.close()
                first = None
                sink = engine.runners["waits-for-reader"].pipeline.sink
                began = time.monotonic()
                await wait_for(lambda: not sink.ready, 20, "the route to notice the subscriber left")
                noticed = time.monotonic() - began
                await send(range(100, 200))
                await asyncio.sleep(1.0)  # quiet window: held while no subscriber (the behaviour under test)
                assert engine.status()["routes"]["waits-for-reader"]["delivered"] == 100
                second = Peer()
                got_second = second.subscribe(String, f"/{tag}/waiting")
                second.start()
                await wait_for(lambda: len(got_second) == 100, 20, "the second subscriber's 100")
                await asyncio.sleep(0.3)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
                return ([json.loads(m.data)["seq"] for m in got_first], [json.loads(m.data)["seq"] for m in got_second],
                        noticed)
        finally:
            await engine.stop()
            for peer in (first, second):
                if peer is not None:
                    peer.close()

    first, second, noticed = asyncio.run(asyncio.wait_for(scenario(), 90))
    print(f"\nthe sink saw the subscriber leave after {noticed:.2f} s")
    assert first == list(range(100)) and second == list(range(100, 200))


TEMPLATED = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: per-robot
    max_attempts: 1
    source: {{amqp: {{queue: {queue}}}}}
    schema: raw_json
    sink: {{ros2: {{topic: "/{{agent_id}}/{tag}"}}}}
"""


def test_a_templated_topic_waits_for_its_robot_without_spending_attempts(amqp_url: str, tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch):
    """The first message for /uav1/... creates the publisher, finds no subscriber and is
    refused; the route then waits for that robot. With max_attempts 1, a refusal counted as an
    attempt would dead-letter it: nothing is, and every message reaches the robot that
    subscribes 2 s later."""
    from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "t" + uuid.uuid4().hex[:8]
    queue = f"per-robot-{tag}"
    (tmp_path / "robots.yaml").write_text(TEMPLATED.format(domain=DOMAIN, tag=tag, queue=queue))
    bodies = [json.dumps({"agent_id": "uav1", "seq": i}) for i in range(20)]

    async def scenario() -> tuple[list[str], dict[str, Any]]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        peer = None
        try:
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)
                for body in bodies:
                    await channel.default_exchange.publish(aio_pika.Message(body.encode()), queue)
            await wait_for(lambda: engine.status()["routes"]["per-robot"]["sink_not_ready"], 10, "the route to wait for its robot",
                           lambda: engine.status()["routes"]["per-robot"])
            assert f"no subscriber has matched /uav1/{tag}" in engine.status()["routes"]["per-robot"]["sink_not_ready"]
            await asyncio.sleep(2.0)  # quiet window: held while no subscriber (the behaviour under test)
            peer = Peer()
            received = peer.subscribe(String, f"/uav1/{tag}")
            peer.start()
            await wait_for(lambda: len(received) >= len(bodies), 30, f"the {len(bodies)} messages at the robot", lambda: len(received))
            await asyncio.sleep(0.3)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
            return [m.data for m in received], engine.status()["routes"]["per-robot"]
        finally:
            await engine.stop()
            if peer is not None:
                peer.close()

    received, route = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert route["failed"] == 0 and route["delivered"] == len(bodies), route
    assert received == bodies
