"""Recording and replay (issue 33): ``--record DIR`` read back with the ``mcap`` library, and
``rabbitros-engine replay``.

Real parts: the engine as a child process, a private mosquitto (the source), the session's
RabbitMQ (the sink, a queue bound to its exchange), the ``mcap`` reader (not our writer's view
of the file), ``jsonschema`` for the channel schemas, ``replay`` as the operator runs it.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import aio_pika
import jsonschema
import pytest
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from engine.common.processes import listening_port
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.ops.cli_parser import build_parser
from engine.ops.replay_sinks import parse_speed
from tests.endpoints.mqtt.test_mqtt import publish
from tests.support.amqp_helpers import Collector
from tests.support.engine_process import EngineProcess
from tests.support.repo import REPO
from tests.support.waiting import wait_for

ROUTES = """
connections:
  field: {{mqtt: "{mqtt}"}}
  bus: {{amqp: "{amqp}"}}
routes:
  - name: pos
    source: {{mqtt: {{connection: field, topic: "{tag}/+/position", qos: 1}}}}
    mapping: "{{type: 'position', agent_id: agent, stamp: stamp, lat: {lat}, lon: lon, alt_msl: alt, id: to_string(seq)}}"
    schema: position
    sink: {{amqp: {{connection: bus, exchange: {tag}-out, routing_key: "pos.{{agent_id}}"}}}}
  - name: quiet
    record: false
    source: {{mqtt: {{connection: field, topic: "{tag}/+/quiet", qos: 1}}}}
    schema: raw_json
    sink: {{amqp: {{connection: bus, exchange: {tag}-out, routing_key: "quiet"}}}}
"""
AGENTS = ("a", "b")
N = 200


def routes_dir(tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str, tag: str, lat: str = "lat") -> Path:
    routes = tmp_path / "routes"
    routes.mkdir(exist_ok=True)
    (routes / "rec.yaml").write_text(ROUTES.format(mqtt=mosquitto.url, amqp=amqp_url, tag=tag, lat=lat))
    return routes


def position(seq: int) -> dict[str, Any]:
    agent = AGENTS[seq % len(AGENTS)]
    return {"seq": seq, "agent": agent, "lat": 48.0 + seq / 1e4, "lon": 11.0, "alt": 500.0 + seq,
            "stamp": {"sec": 1_700_000_000 + seq, "nanosec": 0}}


def replay(recording: Path, routes: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "engine", "replay", str(recording), "--routes", str(routes),
                           "--schemas", str(REPO / "schemas"), *extra],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


def read_tolerant(path: Path) -> tuple[list[tuple[Channel, Message]], str | None]:
    """Every message of a file in file order, with ``mcap``'s StreamReader record by record: a
    file whose writer was killed has no summary (``make_reader``'s index) and may end in a cut
    record, which ends the reading (the error is returned)."""
    channels: dict[int, Channel] = {}
    messages: list[tuple[Channel, Message]] = []
    with path.open("rb") as stream:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    messages.append((channels[record.channel_id], record))
        except Exception as error:  # the cut tail: EndOfFile (mcap.exceptions) when the last record is short
            return messages, f"{type(error).__name__}: {error}"
    return messages, None


def test_recording_counts_schemas_and_replay(tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    tag = "r" + uuid.uuid4().hex[:8]
    routes = routes_dir(tmp_path, mosquitto, amqp_url, tag)
    record = tmp_path / "recording"
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--record", str(record), "--admin", str(port))
    metrics: list[str] = []

    async def traffic() -> int:
        connection = await aio_pika.connect_robust(amqp_url)
        async with connection:
            collector = await Collector.bind(await connection.channel(), f"{tag}-out")
            messages = [(f"{tag}/{AGENTS[seq % 2]}/position", position(seq)) for seq in range(N)]
            messages += [(f"{tag}/a/quiet", {"seq": seq}) for seq in range(20)]
            await publish(mosquitto, messages)
            await collector.wait_for(N + 20)
            await wait_for(lambda: (engine.status() or {}).get("routes", {}).get("pos", {}).get("delivered") == N, 30,
                           "the pos route's delivered counter", lambda: engine.status())
            metrics.append(await asyncio.to_thread(lambda: urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10)
                                                   .read().decode()))
            return len(collector.messages)

    arrived, _ = engine.run(traffic)
    assert arrived == N + 20
    status = engine.status() or {}
    counters = status["routes"]["pos"]
    assert counters["received"] == counters["delivered"] == N, counters
    assert status["recording"]["dropped"] == 0, status["recording"]
    samples = [line for line in metrics[0].splitlines() if line.startswith("rabbitros_record")]
    assert any(line.startswith("rabbitros_recorded_messages_total ") for line in samples), samples
    assert not [line for line in samples if line.startswith("rabbitros_recording_dropped_total{")], samples  # none dropped

    files = sorted(record.glob("*.mcap"))
    assert len(files) == 1, files
    with files[0].open("rb") as stream:  # stopped cleanly: the summary is there, make_reader uses its index
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert {c.topic for c in summary.channels.values()} == {"/routes/pos/in", "/routes/pos/canonical"}, "quiet has record: false"
        counts: Counter[str] = Counter()
        inputs: dict[int, dict[str, Any]] = {}
        validators: dict[int, Any] = {}
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] += 1
            assert schema is not None and schema.encoding == "jsonschema" and channel.message_encoding == "json"
            if schema.id not in validators:
                document = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(document)
                validators[schema.id] = jsonschema.Draft202012Validator(document)
            data = json.loads(message.data)
            validators[schema.id].validate(data)  # every message against its channel's schema
            if channel.topic == "/routes/pos/in":
                inputs[message.sequence] = data
    assert counts == {"/routes/pos/in": counters["delivered"], "/routes/pos/canonical": counters["delivered"]}, counts
    first = inputs[min(inputs)]
    assert first["meta"]["topic"].startswith(f"{tag}/") and json.loads(first["text"])["agent"] in AGENTS, first
    assert first["received_at"] > time.time() - 600

    same = replay(record, routes)
    assert same.returncode == 0, same.stdout + same.stderr
    assert f"{N} messages compared: {N} same, 0 differ" in same.stdout, same.stdout

    (tmp_path / "edited").mkdir()
    edited = routes_dir(tmp_path / "edited", mosquitto, amqp_url, tag, lat="(agent == 'b' && `1.5`) || lat")
    changed = replay(files[0], edited)
    assert changed.returncode == 1, changed.stdout + changed.stderr
    named = {int(line.split("#")[1].split()[0]) for line in changed.stdout.splitlines() if line.startswith("DIFF  pos #")}
    of_b = {sequence for sequence, data in inputs.items() if json.loads(data["text"])["agent"] == "b"}
    assert named == of_b and len(of_b) == N // 2, (sorted(named)[:10], sorted(of_b)[:10])
    assert '"lat": 1.5' in changed.stdout and f"{N} messages compared: {N // 2} same, {N // 2} differ" in changed.stdout

    made = subprocess.run([sys.executable, "-m", "engine", "test", "--from-recording", str(record), "--route", "pos", "--count", "10",
                           "--routes", str(routes), "--schemas", str(REPO / "schemas")],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr
    for directory in (routes, edited):
        (directory / "recorded.test.yaml").write_text(made.stdout)
    passing = subprocess.run([sys.executable, "-m", "engine", "test", "--routes", str(routes), "--schemas", str(REPO / "schemas")],
                             cwd=REPO, capture_output=True, text=True, timeout=120)
    assert passing.returncode == 0 and "10 passed, 0 failed" in passing.stdout, passing.stdout + passing.stderr
    failing = subprocess.run([sys.executable, "-m", "engine", "test", "--routes", str(edited), "--schemas", str(REPO / "schemas")],
                             cwd=REPO, capture_output=True, text=True, timeout=120)
    assert failing.returncode == 1 and "5 passed, 5 failed" in failing.stdout, failing.stdout + failing.stderr


def test_a_recording_engine_killed_with_9_leaves_all_but_the_last_second_readable(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    tag = "k" + uuid.uuid4().hex[:8]
    routes = routes_dir(tmp_path, mosquitto, amqp_url, tag)
    record = tmp_path / "recording"
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--record", str(record))
    arrivals: dict[int, float] = {}

    class Arrivals(Collector):
        def received(self, at: float, message: Any) -> None:
            arrivals[int(json.loads(message.body)["id"])] = at

    async def traffic() -> float:
        connection = await aio_pika.connect_robust(amqp_url)
        async with connection:
            await Arrivals.bind(await connection.channel(), f"{tag}-out")
            stream = asyncio.create_task(publish(mosquitto, ((f"{tag}/a/position", position(seq)) for seq in range(100_000)),
                                                 window=4, pause=0.01))
            await wait_for(lambda: arrivals and time.monotonic() - min(arrivals.values()) > 3, 60, "3 s of traffic")
            killed_at = time.monotonic()
            os.killpg(engine.process.pid, signal.SIGKILL)
            stream.cancel()
            await asyncio.gather(stream, return_exceptions=True)
            return killed_at

    try:
        engine.wait_started()
        killed_at = asyncio.run(traffic())
        engine.process.wait(30)
    finally:
        engine.stop()
    files = sorted(record.glob("*.mcap"))
    assert len(files) == 1, files
    messages, tail = read_tolerant(files[0])
    recorded = {int(json.loads(m.data)["id"]) for c, m in messages if c.topic == "/routes/pos/canonical"}
    inputs = {json.loads(json.loads(m.data)["text"])["seq"] for c, m in messages if c.topic == "/routes/pos/in"}
    older = {seq for seq, at in arrivals.items() if at < killed_at - 1.0}
    assert len(older) > 100, len(older)
    assert older <= recorded, sorted(older - recorded)[:10]
    assert older <= inputs, sorted(older - inputs)[:10]
    replayed = replay(files[0], routes)  # replay reads a killed file the same way, up to its cut end
    assert replayed.returncode == 0 and " 0 differ" in replayed.stdout, replayed.stdout + replayed.stderr
    assert tail is None or "read up to the last whole chunk" in replayed.stderr, replayed.stderr
    print(f"kill -9: {len(arrivals)} delivered, {len(older)} older than 1 s all readable, {len(recorded)} canonical in the "
          f"file, tail: {tail}")


def test_replay_to_sinks_sends_every_recorded_input_once_in_order_at_the_speed_asked(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    """``replay --to-sinks``: a recording of ~4 s of positions sent again into the route's real
    sink (a RabbitMQ exchange, a queue bound to it): all of them, once each, in the order
    received; at ``--speed 10`` the arrivals span about a tenth of the recorded span (from the
    recording's receive times and the queue's arrival times), at ``max`` less than that; and
    through the routes as they are now: after an edit that gives the route two sinks (``sinks:``),
    each sink gets every message, once, in order."""
    tag = "s" + uuid.uuid4().hex[:8]
    routes = routes_dir(tmp_path, mosquitto, amqp_url, tag)
    record = tmp_path / "recording"
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--record", str(record))
    count = 100

    async def traffic() -> None:
        connection = await aio_pika.connect_robust(amqp_url)
        async with connection:
            collector = await Collector.bind(await connection.channel(), f"{tag}-out")
            await publish(mosquitto, ((f"{tag}/{AGENTS[seq % 2]}/position", position(seq)) for seq in range(count)),
                          window=4, pause=0.15)  # the field's pace: 25 steps over ~4 s
            await collector.wait_for(count)

    engine.run(traffic)
    [file] = sorted(record.glob("*.mcap"))
    received = sorted(m.log_time for c, m in read_tolerant(file)[0] if c.topic == "/routes/pos/in")
    assert len(received) == count
    recorded_span = (received[-1] - received[0]) / 1e9
    assert recorded_span > 3.0, recorded_span

    async def replayed(speed: str, routes: Path = routes) -> tuple[list[tuple[str, str]], float, str]:
        connection = await aio_pika.connect_robust(amqp_url)
        async with connection:
            arrivals: list[tuple[float, str, str]] = []
            channel = await connection.channel()
            exchange = await channel.declare_exchange(f"{tag}-out", aio_pika.ExchangeType.TOPIC, durable=True)
            queue = await channel.declare_queue(f"{tag}-{speed}-{routes.name}", exclusive=True)
            await queue.bind(exchange, "#")

            async def arrived(message: aio_pika.abc.AbstractIncomingMessage) -> None:
                arrivals.append((time.monotonic(), json.loads(message.body)["id"], message.routing_key or ""))

            await queue.consume(arrived, no_ack=True)
            command = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "engine", "replay", str(record), "--routes", str(routes), "--schemas", str(REPO / "schemas"),
                "--to-sinks", "--speed", speed, cwd=REPO, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
            output = (await asyncio.wait_for(command.communicate(), 120))[0].decode()
            assert command.returncode == 0, output
            # every message was confirmed (in the queue) before the command exited: wait until the
            # queue is empty and all arrived; a duplicate (there must be none) would be counted
            expected = count * (2 if routes.name == "fan-out" else 1)
            await wait_for(lambda: len(arrivals) >= expected, 30, "the replayed messages", lambda: len(arrivals))
            waiting = await channel.declare_queue(queue.name, passive=True)
            assert waiting.declaration_result.message_count == 0
            return [(identity, key) for _, identity, key in arrivals], arrivals[-1][0] - arrivals[0][0], output

    arrived, span, output = asyncio.run(replayed("10"))
    ids = [identity for identity, _ in arrived]
    assert ids == [str(seq) for seq in range(count)], ids  # complete, once each, in order
    assert f"{count} sent, 0 filtered, 0 not sent, at 10x" in output, output
    print(f"--speed 10: recorded {recorded_span:.2f} s, arrivals over {span:.3f} s")
    assert 0.7 * recorded_span / 10 <= span <= 2.0 * recorded_span / 10 + 0.3, (span, recorded_span)

    arrived, fastest, output = asyncio.run(replayed("max"))
    ids = [identity for identity, _ in arrived]
    assert ids == [str(seq) for seq in range(count)], ids
    assert "as fast as the sinks take them" in output, output
    print(f"--speed max: arrivals over {fastest:.3f} s")
    assert fastest < span, (fastest, span)

    # the routes as they are now: the route sends each message to two sinks (sinks:)
    fan_out = tmp_path / "fan-out"
    fan_out.mkdir()
    one_sink = f'    sink: {{amqp: {{connection: bus, exchange: {tag}-out, routing_key: "pos.{{agent_id}}"}}}}\n'
    two_sinks = (f'    sinks:\n'
                 f'      - {{name: main, amqp: {{connection: bus, exchange: {tag}-out, routing_key: "pos.{{agent_id}}"}}}}\n'
                 f'      - {{name: copy, amqp: {{connection: bus, exchange: {tag}-out, routing_key: "copy.{{agent_id}}"}}}}\n')
    assert one_sink in (routes / "rec.yaml").read_text()
    (fan_out / "rec.yaml").write_text((routes / "rec.yaml").read_text().replace(one_sink, two_sinks, 1))
    arrived, _, output = asyncio.run(replayed("max", fan_out))
    for prefix in ("pos.", "copy."):
        assert [identity for identity, key in arrived if key.startswith(prefix)] == [str(seq) for seq in range(count)], arrived
    assert f"{count} sent, 0 filtered, 0 not sent" in output, output


@pytest.mark.fast
def test_replay_speed_is_a_factor_above_0_or_max(capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    for speed, problem in (("0", "--speed must be above 0 or max, not '0'"), ("fast", "could not convert string to float: 'fast'")):
        with pytest.raises(SystemExit) as refused:
            parser.parse_args(["replay", "rec", "--to-sinks", "--speed", speed])
        assert refused.value.code == 2 and problem in capsys.readouterr().err
    assert parser.parse_args(["replay", "rec", "--to-sinks", "--speed", "max"]).speed is None
    assert parser.parse_args(["replay", "rec", "--to-sinks"]).speed == 1.0
    assert parse_speed("10") == 10.0 and parse_speed("MAX") is None
