"""Every edit takes effect and none takes the engine down, against a real RabbitMQ node and
real MAVLink over UDP: a schema edit without touching a route file, rejected loads (a
recursive YAML alias, a broken ``$ref``), a udpin connection changed while telemetry flows
(break-before-make, gap reported), a new signing key written over the key file, and
``sink.mapping`` shaping an AMQP body."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest

from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, publish, started_with_client
from tests.support.engine_process import EngineProcess
from tests.support.udp_vehicle import Vehicle, free_udp_port, telemetry_routes
from tests.support.waiting import probe_until, wait_for

PROBE_SCHEMA = {"$schema": "https://json-schema.org/draft/2020-12/schema", "type": "object", "required": ["a"]}
PROBE_ROUTE = """
routes:
  - name: probe
    source: {{amqp: {{exchange: {inbox}, binding_key: "p.#", queue: {queue}}}}}
    schema: probe
    sink: {{amqp: {{exchange: {outbox}, routing_key: ok}}}}
"""


def names() -> dict[str, str]:
    tag = uuid.uuid4().hex[:8]
    return {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}


def workspace(tmp_path: Path, schemas_dir: Path, route: str) -> tuple[Path, Path]:
    routes, schemas = tmp_path / "routes", tmp_path / "schemas"
    routes.mkdir()
    shutil.copytree(schemas_dir, schemas)
    (schemas / "probe.v1.json").write_text(json.dumps(PROBE_SCHEMA))
    (routes / "probe.yaml").write_text(route)
    return routes, schemas


def write_atomically(path: Path, text: str) -> None:
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


def test_schema_edit_takes_effect_within_a_second(amqp_url: str, tmp_path: Path, schemas_dir: Path):
    n = names()
    routes, schemas = workspace(tmp_path, schemas_dir, PROBE_ROUTE.format(**n))
    route_mtime = (routes / "probe.yaml").stat().st_mtime_ns
    engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--schemas", str(schemas))

    async def scenario() -> float:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"])
            await publish(channel, n["inbox"], "p.x", [b'{"a": 1}'])
            assert len(await out.wait_for(1)) == 1, "the route does not run"
            await publish(channel, n["inbox"], "p.x", [b'{"b": 0}'])
            await asyncio.sleep(0.3)  # quiet window: the invalid message must not be delivered (the behaviour under test)
            assert len(out.messages) == 1, "a message invalid under the old schema was delivered"
            write_atomically(schemas / "probe.v1.json", json.dumps({**PROBE_SCHEMA, "required": ["b"]}))
            edited = time.monotonic()
            exchange = await channel.get_exchange(n["inbox"])
            sequence = 0

            async def send_b() -> None:
                nonlocal sequence
                sequence += 1
                await exchange.publish(aio_pika.Message(json.dumps({"b": sequence}).encode()), "p.x")

            await probe_until(lambda: len(out.messages) >= 2, send_b, 10, "the schema edit applied (a {b} message delivered)",
                              every=0.01, detail=engine.log)
            live = time.monotonic() - edited
            # the new generation carries messages before its reload returns and the status file
            # is written: wait for the file (read at the end) to say so
            await wait_for(lambda: (engine.status() or {}).get("generation") == 2, 10, "the status file's generation 2",
                           lambda: (engine.status() or {}).get("generation"))
            return live
        finally:
            await connection.close()

    live_s, status = engine.run(scenario)
    print(f"schema edit to live: {live_s * 1e3:.0f} ms")
    assert (routes / "probe.yaml").stat().st_mtime_ns == route_mtime
    assert status["generation"] == 2 and status["reloads"]["succeeded"] == 1
    assert live_s < 1.0, f"schema edit took {live_s:.2f} s to go live"


BILLION_LAUGHS = "routes: []\n" + "".join(
    f"x{level}: &l{level} [" + ",".join([f"*l{level - 1}" if level else '"lol"'] * 10) + "]\n" for level in range(9))
"""Nine lines, each a list of ten aliases of the one before: 10^9 nodes (5.3 GB before the bounds)."""


def peak_rss_kib(pid: int) -> int:
    """The process's peak resident set (VmHWM), in KiB."""
    line = next(line for line in Path(f"/proc/{pid}/status").read_text().splitlines() if line.startswith("VmHWM:"))
    return int(line.split()[1])


def test_recursive_alias_alias_bomb_and_broken_ref_are_rejected_and_the_engine_keeps_running(
    amqp_url: str, tmp_path: Path, schemas_dir: Path
):
    n = names()
    routes, schemas = workspace(tmp_path, schemas_dir, PROBE_ROUTE.format(**n))
    engine = EngineProcess(routes, tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url}, "--schemas", str(schemas))

    def status() -> dict[str, Any]:
        return engine.status() or {}

    def rejected() -> int:
        return status().get("reloads", {}).get("rejected", 0)

    async def delivered_through_probe(channel: Any, out: Collector, count: int) -> None:
        await publish(channel, n["inbox"], "p.x", [b'{"a": 1}'])
        assert len(await out.wait_for(count)) == count, f"the running route stopped: {engine.log()}"

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"])
            await delivered_through_probe(channel, out, 1)

            (routes / "loop.yaml").write_text("routes: []\nx: &loop [1, *loop]\n")
            await wait_for(lambda: rejected() == 1, 10, f"recursive alias not rejected: {engine.log()}")
            assert any("loop.yaml:2: invalid YAML" in p for p in status()["reloads"]["last_error"]), status()
            (routes / "loop.yaml").unlink()
            await delivered_through_probe(channel, out, 2)

            peak_before = peak_rss_kib(status()["pid"])
            write_atomically(routes / "bomb.yaml", BILLION_LAUGHS)
            written = time.monotonic()
            await wait_for(lambda: rejected() == 2, 10, f"billion laughs not rejected: {engine.log()}")
            refused_s = time.monotonic() - written
            grown_kib = peak_rss_kib(status()["pid"]) - peak_before
            print(f"billion laughs: refused {refused_s * 1e3:.0f} ms after the write, engine peak RSS +{grown_kib} KiB")
            assert any("bomb.yaml:6: alias *l3 copies 11,111 nodes" in p for p in status()["reloads"]["last_error"]), status()
            assert grown_kib < 8 * 1024 and refused_s < 2.0  # the watcher's debounce and a status write included
            (routes / "bomb.yaml").unlink()
            await delivered_through_probe(channel, out, 3)

            position = schemas / "position.v1.json"
            good = position.read_text()
            write_atomically(position, good.replace("envelope.v1.json#", "nowhere.v1.json#"))
            await wait_for(lambda: rejected() == 3, 10, f"broken $ref not rejected: {engine.log()}")
            assert any("position.v1.json:0: $ref 'nowhere.v1.json#/$defs/header' does not resolve" in p
                       for p in status()["reloads"]["last_error"]), status()
            await delivered_through_probe(channel, out, 4)

            write_atomically(position, good)
            (routes / "more.yaml").write_text(PROBE_ROUTE.replace("probe\n", "probe2\n", 1).format(**names()))
            await wait_for(lambda: set(status().get("routes", {})) == {"probe", "probe2"}, 10,
                             f"the reloader no longer applies edits: {engine.log()}")
            await delivered_through_probe(channel, out, 5)
        finally:
            await connection.close()

    try:
        engine.wait_started()
        asyncio.run(scenario())
        assert engine.process.poll() is None
        final = status()
    finally:
        assert engine.stop() == 0
    assert final["reloads"]["rejected"] == 3 and final["generation"] == 2
    assert final["routes"]["probe"]["generation"] == 1, "rejected loads touched the running route"


OTHER_ROUTE = """
  - name: other
    source: {{amqp: {{connection: gcs, exchange: {inbox}, binding_key: "o.#", queue: {queue}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: other}}}}
"""


def radio_routes(n: dict[str, str], port: int, host: str = "127.0.0.1", heartbeat: float = 1) -> str:
    """Telemetry from a udpin connection to AMQP, and a route ``other`` on the AMQP connection only."""
    return telemetry_routes("${TEST_AMQP_URL}", n["outbox"], port, host, heartbeat) + OTHER_ROUTE.format(**n)


def test_udpin_settings_change_while_telemetry_flows_is_break_before_make(
    amqp_url: str, tmp_path: Path, schemas_dir: Path, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    n, port, rate = names(), free_udp_port(), 200.0
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "radio.yaml").write_text(radio_routes(n, port))

    async def scenario() -> tuple[list[int], dict[str, Any], int]:
        engine = Engine(routes, schemas_dir)
        vehicle = Vehicle(port, rate)
        async with started_with_client(engine, amqp_url) as connection:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"], "telemetry")
            vehicle.start()
            try:
                await out.wait_for(50)
                assert len(out.messages) >= 50, "no telemetry before the change"
                other = engine.runners["other"]
                (routes / "radio.yaml").write_text(radio_routes(n, port, heartbeat=2))
                assert await engine.reload(), engine.reloads.last_error
                sent_at_reload = vehicle.sent
                assert engine.runners["other"] is other, "a route on another connection was touched"
                radio = next(c for (name, _), c in engine.connections.items() if name == "radio")
                assert isinstance(radio, MavlinkConnection), "the radio connection is the MAVLink one"
                assert radio.config.heartbeat == 2.0
                await out.wait_for(len(out.messages) + 50)
                seqs = [json.loads(m.body)["seq"] for m in out.messages]
                assert max(seqs) > sent_at_reload, "no telemetry after the change"
                return seqs, engine.reloads.last_handovers[0], sent_at_reload
            finally:
                vehicle.stop.set()

    seqs, handover, sent_at_reload = asyncio.run(scenario())
    missed = sorted(set(range(max(seqs))) - set(seqs))
    print(f"udpin handover: gap {handover['gap_ms']} ms, {len(missed)} datagrams at {rate:.0f} Hz not received")
    assert handover["resource"] == f"udp:{port}" and handover["routes"] == ["telemetry"]
    assert 0 < handover["gap_ms"] < 2000
    assert all(seq <= sent_at_reload for seq in missed), "telemetry lost after the new link was up"


def test_udpin_handover_that_cannot_open_restores_the_old_link(
    amqp_url: str, tmp_path: Path, schemas_dir: Path, monkeypatch: pytest.MonkeyPatch
):
    """The new settings pass every check but cannot bind (an address this host does not
    have): the old link is reopened, telemetry flows again, the reload is rejected."""
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    n, port = names(), free_udp_port()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "radio.yaml").write_text(radio_routes(n, port))

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        vehicle = Vehicle(port, 100.0)
        async with started_with_client(engine, amqp_url) as connection:
            out = await Collector.bind(await connection.channel(), n["outbox"], "telemetry")
            vehicle.start()
            try:
                assert len(await out.wait_for(20)) >= 20, "no telemetry before the change"
                (routes / "radio.yaml").write_text(radio_routes(n, port, host="192.0.2.1"))
                assert not await engine.reload(), "binding an address this host lacks cannot succeed"
                assert "cannot open udpin:192.0.2.1" in engine.reloads.last_error[0], engine.reloads.last_error
                assert engine.generation == 1 and set(engine.runners) == {"telemetry", "other"}
                sent = vehicle.sent
                await out.wait_for(len(out.messages) + 20)
                assert max(json.loads(m.body)["seq"] for m in out.messages) > sent, "the old link was not restored"
            finally:
                vehicle.stop.set()

    asyncio.run(scenario())


def test_sink_mapping_shapes_the_amqp_body(amqp_url: str, tmp_path: Path, schemas_dir: Path,
                                          monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    n = names()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "legacy.yaml").write_text(f"""
routes:
  - name: legacy
    source: {{amqp: {{connection: gcs, exchange: {n['inbox']}, binding_key: "l.#", queue: {n['queue']}}}}}
    mapping: "{{agent_id: agent, lat: lat, lon: lon}}"
    schema: position
    sink:
      amqp: {{connection: gcs, exchange: {n['outbox']}, routing_key: "legacy.{{agent_id}}"}}
      mapping: "{{robot: agent_id, where: [lat, lon]}}"
connections:
  gcs: {{amqp: "${{TEST_AMQP_URL}}"}}
""")

    async def scenario() -> list[Any]:
        async with started_with_client(Engine(routes, schemas_dir), amqp_url) as connection:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"])
            await publish(channel, n["inbox"], "l.x", [b'{"agent": "uav1", "lat": -22.5, "lon": -47.25}'])
            return await out.wait_for(1)

    (message,) = asyncio.run(scenario())
    assert message.routing_key == "legacy.uav1", "the routing key still comes from the canonical message"
    assert message.body == b'{"robot":"uav1","where":[-22.5,-47.25]}'


def test_a_new_signing_key_written_over_the_key_file_takes_effect(amqp_url: str, tmp_path: Path):
    """The key file lives outside the routes directory; writing the vehicle's new key there is
    a reload (the connection reopens with it) without touching a route file."""
    n, port = names(), free_udp_port()
    old_key, new_key = bytes(range(32)), bytes(range(1, 33))
    keys, routes = tmp_path / "keys", tmp_path / "routes"
    keys.mkdir()
    routes.mkdir()
    key_file = keys / "uav1.key"
    key_file.write_bytes(old_key)
    (routes / "radio.yaml").write_text(telemetry_routes("${TEST_AMQP_URL}", n["outbox"], port, heartbeat=0, key_file=str(key_file)))
    engine = EngineProcess(routes, tmp_path / "status.json", {"TEST_AMQP_URL": amqp_url})

    def rejected_signatures() -> int:
        radio = ((engine.status() or {}).get("connections") or {}).get("radio") or {}
        return int((radio.get("rejected") or {}).get("bad_signature", 0))

    async def scenario() -> float:
        connection = await aio_pika.connect(amqp_url)
        vehicle = Vehicle(port, 50.0, key=new_key)  # the vehicle already signs with the new key
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, n["outbox"], "telemetry")
            vehicle.start()
            await wait_for(lambda: rejected_signatures() >= 20, 20, f"frames signed with another key not rejected: {engine.log()}")
            assert out.messages == [], "frames signed with a key the engine does not have were delivered"
            write_atomically(key_file, new_key.hex())
            written = time.monotonic()
            await out.wait_for(10, timeout=20)
            assert len(out.messages) >= 10, f"the new key was never applied: {engine.log()}"
            return time.monotonic() - written
        finally:
            vehicle.stop.set()
            await connection.close()

    live_s, status = engine.run(scenario)
    print(f"new signing key to first delivery: {live_s * 1e3:.0f} ms")
    assert status["generation"] == 2 and status["reloads"]["succeeded"] == 1


def test_the_same_broken_files_found_again_are_one_rejection(amqp_url: str, tmp_path: Path, schemas_dir: Path,
                                                             monkeypatch: pytest.MonkeyPatch):
    """An editor's save is often seen as two changes; a rejection is counted once per broken
    state of the files, and reverting to what runs clears the error."""
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    routes, schemas = workspace(tmp_path, schemas_dir, PROBE_ROUTE.format(**names()))
    good = (routes / "probe.yaml").read_text()

    async def scenario() -> None:
        engine = Engine(routes, schemas)
        await engine.start()
        try:
            (routes / "probe.yaml").write_text(good.replace("schema: probe", "schema: [probe"))
            assert not await engine.reload() and not await engine.reload()
            assert engine.reloads.rejected == 1 and "probe.yaml:" in engine.reloads.last_error[0]
            (routes / "probe.yaml").write_text(good)
            assert await engine.reload()
            assert engine.reloads.last_error == [] and engine.generation == 1, "reverting is not a change"
            (routes / "probe.yaml").write_text(good.replace("schema: probe", "schema: [probe"))
            assert not await engine.reload()
            assert engine.reloads.rejected == 2
        finally:
            await engine.stop()

    asyncio.run(scenario())
