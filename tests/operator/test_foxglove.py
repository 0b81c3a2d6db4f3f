"""``run --foxglove``: the live view against a real engine and RabbitMQ, read by an independent
client: plain ``websockets`` speaking the Foxglove WebSocket protocol (JSON ``advertise`` and
``subscribe``; binary message data: opcode 1, subscription id u32 LE, timestamp u64 LE,
payload). The SDK's server speaks it under the name ``foxglove.sdk.v1`` (the protocol of
``foxglove.websocket.v1``, renamed; the older name is refused at the handshake)."""

from __future__ import annotations

import asyncio
import json
import socket
import ssl
import struct
import uuid
from pathlib import Path
from typing import Iterator

import aio_pika
import jsonschema
import pytest
import websockets
from websockets.typing import Subprotocol
from foxglove.messages import LocationFix, LocationFixes

from engine.common.processes import listening_port
from engine.ops.foxglove import LOCATION_FIXES_SCHEMA, EngineFeed, Fleet, FoxgloveView, RouteChannel, agent_colour
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, publish
from tests.support.engine_process import EngineProcess
from tests.support.foxglove_client import SUBPROTOCOL, FoxgloveClient, connect
from tests.support.tls_helpers import make_pki
from tests.support.waiting import wait_for

ROUTES = """
routes:
  - name: positions
    source: {amqp: {exchange: fox-test, binding_key: "pos.#", queue: fox-positions}}
    mapping: "{agent_id: agent, type: 'position', lat: lat, lon: lon, alt_msl: alt, heading: heading}"
    schema: position
    sink: {amqp: {exchange: fox-test, routing_key: "out.positions.{agent_id}"}}
  - name: telemetry
    source: {amqp: {exchange: fox-test, binding_key: "tel.#", queue: fox-telemetry}}
    mapping: "{agent_id: agent, seq: seq}"
    schema: raw_json
    sink: {amqp: {exchange: fox-test, routing_key: "out.telemetry"}}
"""


@pytest.fixture
def engine(amqp_url: str, tmp_path: Path) -> Iterator[tuple[EngineProcess, int]]:
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "fox.yaml").write_text(ROUTES)
    port = listening_port()
    process = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                            "--foxglove", str(port))
    try:
        process.wait_started()
        yield process, port
    finally:
        assert process.stop() == 0, process.log()


async def _feed(url: str, stop: asyncio.Event) -> int:
    """Positions of two agents and telemetry, every 50 ms, until ``stop``; returns how many."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    collector = await Collector.bind(channel, "fox-test", "out.#")  # the sinks publish mandatory: someone reads
    sent = 0
    try:
        while not stop.is_set():
            for agent, lat in (("uav1", 52.1), ("robot7", 52.2)):
                body = {"agent": agent, "lat": lat + sent * 1e-6, "lon": 5.1, "alt": 12.5, "heading": 90}
                await publish(channel, "fox-test", f"pos.{agent}", [json.dumps(body).encode()])
            await publish(channel, "fox-test", "tel.x", [json.dumps({"agent": "uav1", "seq": sent}).encode()])
            sent += 1
            await asyncio.sleep(0.05)  # pacing: a position of each agent every 50 ms
    finally:
        del collector
        await connection.close()
    return sent


def test_every_route_is_a_channel_with_its_schema_and_messages_flow_after_subscribing(engine, amqp_url: str) -> None:
    process, port = engine

    async def scenario() -> None:
        client = await connect(port)
        stop = asyncio.Event()
        feeder = asyncio.create_task(_feed(amqp_url, stop))
        try:
            topics = ["/routes/positions/canonical", "/routes/telemetry/canonical", "/fleet", "/routes/status"]
            await wait_for(lambda: all(t in client.channels for t in topics), 15, "every channel advertised",
                           lambda: sorted(client.channels))
            assert "clientPublish" not in client.server_info["capabilities"], client.server_info
            positions = client.channels["/routes/positions/canonical"]
            assert positions["encoding"] == "json" and positions["schemaEncoding"] == "jsonschema"
            assert positions["schemaName"] == "position.v1"
            schema = json.loads(positions["schema"])
            jsonschema.Draft202012Validator.check_schema(schema)
            assert client.channels["/fleet"]["schemaName"] == "foxglove.LocationFixes"
            assert json.loads(client.channels["/fleet"]["schema"]) == LOCATION_FIXES_SCHEMA
            await wait_for(lambda: (process.status() or {}).get("routes", {}).get("positions", {}).get("delivered", 0) > 5,
                           15, "positions delivered before any subscription")
            assert not client.received, "message data before subscribing"
            ids = await client.subscribe(topics)
            await wait_for(lambda: all(len(client.received.get(i, [])) >= 2 for i in ids.values()), 15,
                           "messages on every channel", lambda: {t: len(client.received.get(i, [])) for t, i in ids.items()})
            validator = jsonschema.Draft202012Validator(schema)
            for message in client.messages(ids["/routes/positions/canonical"]):
                validator.validate(message)
            assert {m["agent_id"] for m in client.messages(ids["/routes/positions/canonical"])} <= {"uav1", "robot7"}
            assert all("seq" in m for m in client.messages(ids["/routes/telemetry/canonical"]))
            status = client.messages(ids["/routes/status"])[-1]
            assert set(status["routes"]) == {"positions", "telemetry"}
            assert status["routes"]["positions"]["state"] == "running" and status["routes"]["positions"]["delivered"] > 0
            fleet_validator = jsonschema.Draft202012Validator(LOCATION_FIXES_SCHEMA)
            await wait_for(lambda: any(len(m["fixes"]) == 2 for m in client.messages(ids["/fleet"])), 15,
                           "both agents on the fleet channel", lambda: client.messages(ids["/fleet"])[-1:])
            for fleet in client.messages(ids["/fleet"]):
                fleet_validator.validate(fleet)
                LocationFixes(fixes=[LocationFix(latitude=f["latitude"], longitude=f["longitude"]) for f in fleet["fixes"]])
            last = [m for m in client.messages(ids["/fleet"]) if len(m["fixes"]) == 2][-1]
            by_agent = {fix["frame_id"]: fix for fix in last["fixes"]}
            assert by_agent["uav1"]["color"] == agent_colour("uav1") != by_agent["robot7"]["color"]
            assert by_agent["uav1"]["altitude"] == 12.5 and abs(by_agent["uav1"]["heading"] - 1.5708) < 1e-3
        finally:
            stop.set()
            await feeder
            await client.close()

    asyncio.run(scenario())


def test_a_client_cannot_publish_into_a_route(engine, amqp_url: str) -> None:
    process, port = engine

    async def scenario() -> None:
        client = await connect(port)
        try:
            await wait_for(lambda: "/routes/telemetry/canonical" in client.channels, 15, "the route advertised")
            before = (process.status() or {})["routes"]["telemetry"]["received"]
            for topic in ("/routes/telemetry/canonical", "tel.x"):
                await client.ws.send(json.dumps({"op": "advertise", "channels": [
                    {"id": 9, "topic": topic, "encoding": "json", "schemaName": "raw_json"}]}))
                await client.ws.send(b"\x01" + struct.pack("<I", 9) + json.dumps({"agent": "intruder", "seq": 1}).encode())
            await wait_for(lambda: len(client.statuses) >= 4, 10, "the server refusing each advertise and message",
                           lambda: client.statuses)
            assert any("clientPublish" in s["message"] for s in client.statuses), client.statuses
            marker = uuid.uuid4().hex  # a message the engine does carry: after it, nothing of the client's can come
            connection = await aio_pika.connect(amqp_url)
            channel = await connection.channel()
            collector = await Collector.bind(channel, "fox-test", "out.telemetry")
            await publish(channel, "fox-test", "tel.x", [json.dumps({"agent": marker, "seq": 0}).encode()])
            await wait_for(lambda: any(marker in m.body.decode() for m in collector.messages), 15, "the marker carried")
            assert not any(b"intruder" in m.body for m in collector.messages)
            assert (process.status() or {})["routes"]["telemetry"]["received"] in (before, before + 1)
            await connection.close()
        finally:
            await client.close()

    asyncio.run(scenario())


def test_the_older_subprotocol_name_is_refused_at_the_handshake(engine) -> None:
    _, port = engine

    async def scenario() -> None:
        with pytest.raises(websockets.InvalidStatus):
            await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol("foxglove.websocket.v1")])

    asyncio.run(scenario())


def test_with_tls_only_wss_is_served_and_verified(amqp_url: str, tmp_path: Path) -> None:
    pki = make_pki(tmp_path / "pki", server_names=("localhost", "127.0.0.1"))
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "fox.yaml").write_text(ROUTES)
    port = listening_port()
    process = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                            "--foxglove", f"127.0.0.1:{port}", "--foxglove-tls-cert", str(pki.server_cert),
                            "--foxglove-tls-key", str(pki.server_key))

    async def scenario() -> None:
        trusted = ssl.create_default_context(cafile=str(pki.ca))
        ws = await websockets.connect(f"wss://localhost:{port}", subprotocols=[SUBPROTOCOL], ssl=trusted)
        client = FoxgloveClient(ws)
        try:
            await wait_for(lambda: "/routes/positions/canonical" in client.channels, 15, "the routes advertised over wss")
        finally:
            await client.close()
        with pytest.raises((websockets.InvalidMessage, websockets.InvalidHandshake, OSError)):
            await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=10)
        with pytest.raises(ssl.SSLCertVerificationError):
            await websockets.connect(f"wss://localhost:{port}", subprotocols=[SUBPROTOCOL],
                                     ssl=ssl.create_default_context(cafile=str(pki.other_ca)))

    process.run(scenario)


def test_nothing_watches_a_route_while_no_client_subscribes_and_channels_follow_a_reload(
        amqp_url: str, tmp_path: Path, schemas_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "fox.yaml").write_text(ROUTES)

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        view = FoxgloveView(EngineFeed(engine), "127.0.0.1", 0)
        await view.start()
        positions, telemetry = engine.observers.get("positions"), engine.observers.get("telemetry")
        client = await connect(view.port)
        try:
            await wait_for(lambda: "/routes/telemetry/canonical" in client.channels, 15, "the routes advertised")
            assert positions.watchers == () and telemetry.watchers == (), "watching with no subscriber"
            await client.subscribe(["/routes/positions/canonical", "/fleet"])
            await wait_for(lambda: len(positions.watchers) == 2, 10, "the route's channel and the fleet attached",
                           lambda: positions.watchers)
            assert set(map(type, positions.watchers)) == {RouteChannel, Fleet} and telemetry.watchers == ()
            await client.close()
            await wait_for(lambda: positions.watchers == (), 10, "everything detached once the client left",
                           lambda: positions.watchers)
            client = await connect(view.port)
            await wait_for(lambda: "/routes/telemetry/canonical" in client.channels, 15, "the routes advertised again")
            (routes / "extra.yaml").write_text(ROUTES.replace("positions", "extra-positions").replace("telemetry", "extra-tel")
                                               .replace("pos.#", "xpos.#").replace("tel.#", "xtel.#")
                                               .replace("fox-extra-positions", "fox-xpos").replace("fox-extra-tel", "fox-xtel"))
            assert await engine.reload(), engine.reloads.last_error
            await wait_for(lambda: "/routes/extra-tel/canonical" in client.channels, 15, "a new route advertised")
            gone = client.channels["/routes/extra-tel/canonical"]["id"]
            (routes / "extra.yaml").unlink()
            assert await engine.reload(), engine.reloads.last_error
            await wait_for(lambda: gone in client.unadvertised, 15, "a removed route withdrawn", lambda: client.unadvertised)
        finally:
            await client.close()
            await view.stop()
            await engine.stop(1.0)

    asyncio.run(scenario())


def test_a_port_in_use_is_a_clear_exit_1(tmp_path: Path) -> None:
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "fox.yaml").write_text(ROUTES)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        process = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {}, "--foxglove", str(taken.getsockname()[1]))
        assert process.process.wait(60) == 1
        process.stop()
        assert "foxglove view cannot listen" in process.log() and "Address already in use" in process.log(), process.log()
