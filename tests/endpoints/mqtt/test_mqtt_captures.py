"""MQTT topic captures (issue 31): a ``{name}`` level of an MQTT source topic subscribes with
``+`` and gives each message that level as ``meta('name')`` and to the sink's templates, as a
ROS 2 source's discovery does; ``check`` refuses the braces a capture cannot honour.

Real parts: a private mosquitto (tests/conftest.py ``mosquitto``), RabbitMQ, the engine in
process. On main before this change the route passed ``check`` but subscribed to the literal
filter ``farm/{station}/weather`` (no message ever arrived) and ``meta('station')`` was refused.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import aio_pika
import pytest

from engine.common.schemas import SchemaRegistry
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.language.routes import RoutesInvalid, load_routes
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.operator.test_cli import cli
from tests.endpoints.mqtt.test_mqtt import publish, routes_dir

STATIONS = ("north", "south", "east")
PER_STATION = 40

CAPTURED = """
connections:
  field: {{mqtt: "{mqtt}"}}
  gcs: {{amqp: "{amqp}"}}
routes:
  - name: weather-in
    source:
      mqtt: {{topic: "farm/{{station}}/weather_{tag}"}}
    mapping: "{{seq: seq, temp_c: temp_c, station: meta('station'), topic: meta('topic')}}"
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "weather.{{station}}"}}
"""


def test_three_stations_each_message_with_its_station(tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    """``farm/{station}/weather`` over three stations: every message reaches RabbitMQ once, under
    the routing key ``weather.<station>`` (the sink's template reads the capture) and with its
    station in the body (``meta('station')``); the bodies carry no station of their own, so
    only the topic can have given it. Topics one level longer or shorter do not match."""
    tag = uuid.uuid4().hex[:8]
    outbox = f"cap-{tag}"
    routes = routes_dir(tmp_path, CAPTURED.format(mqtt=mosquitto.url, amqp=amqp_url, tag=tag, outbox=outbox))

    async def scenario() -> tuple[list[Any], dict[str, Any]]:
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            out = await Collector.bind(await connection.channel(), outbox, "#")
            stray = [(f"farm/north/x/weather_{tag}", {"seq": -1, "temp_c": 0}), (f"farm/weather_{tag}", {"seq": -2, "temp_c": 0})]
            sent = [(f"farm/{STATIONS[seq % 3]}/weather_{tag}", {"seq": seq, "temp_c": 20 + seq % 7})
                    for seq in range(3 * PER_STATION)]
            await publish(mosquitto, [*stray, *sent])
            received = await out.wait_for(len(sent), 30)
            return list(received), engine.status()["routes"]["weather-in"]
        finally:
            await connection.close()
            await engine.stop()

    received, status = asyncio.run(asyncio.wait_for(scenario(), 120))
    bodies = [(m.routing_key, json.loads(m.body)) for m in received]
    assert sorted(body["seq"] for _, body in bodies) == list(range(3 * PER_STATION))  # once each, no stray
    for key, body in bodies:
        assert body["station"] == STATIONS[body["seq"] % 3], body
        assert key == f"weather.{body['station']}", (key, body)
        assert body["topic"] == f"farm/{body['station']}/weather_{tag}"
    assert Counter(key for key, _ in bodies) == {f"weather.{s}": PER_STATION for s in STATIONS}
    assert status["source"]["subscription"] == f"farm/+/weather_{tag}"


def _problems(tmp_path: Path, topics: list[str]) -> list[str]:
    routes = [f"  - name: r{number}\n"
              f"    source: {{mqtt: {{topic: {json.dumps(topic)}}}}}\n"
              f"    schema: raw_json\n"
              f"    sink: {{amqp: {{exchange: e, routing_key: k}}}}\n" for number, topic in enumerate(topics)]
    (tmp_path / "r.yaml").write_text("routes:\n" + "".join(routes))
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    return [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]


def test_check_refuses_the_braces_a_capture_cannot_honour_with_file_and_line(tmp_path: Path) -> None:
    """A capture is one whole level named once, without a format spec or a dotted path, not
    taking a name the source's metadata gives; each refusal names the file, line and route."""
    problems = _problems(tmp_path, [
        "farm/s{n}/weather", "farm/{n:03d}/weather", "farm/{a.b}/weather", "farm/{a}/x/{a}", "farm/{topic}/weather",
        "farm/{bad/weather", "farm/{x}/#/y",
    ])
    expected = [
        (3, "r0", "{n} must be a whole level"),
        (7, "r1", "{n:03d} has a format spec, which a source cannot match"),
        (11, "r2", "a capture names one meta() key"),
        (15, "r3", "{a} is captured twice"),
        (19, "r4", "capture {topic} would hide the message's own meta('topic')"),
        (23, "r5", "is never closed"),
        (27, "r6", "is not an MQTT topic filter"),
    ]
    for line, route, text in expected:
        assert any(p.startswith(f"r.yaml:{line}: route {route!r}") and text in p for p in problems), (route, problems)
    assert len(problems) == len(expected), problems


def test_check_takes_captures_beside_wildcards_and_meta_reads_them(tmp_path: Path) -> None:
    """``+`` and a trailing ``#`` beside captures are fine (the captured levels come first);
    ``meta('station')`` is known to ``check`` while ``meta('statoin')`` is refused with a hint."""
    (tmp_path / "r.yaml").write_text(
        "routes:\n"
        "  - name: ok\n"
        "    source: {mqtt: {topic: \"farm/{station}/+/{sensor}/#\"}}\n"
        "    mapping: \"{s: meta('station'), n: meta('sensor')}\"\n"
        "    schema: raw_json\n"
        "    sink: {amqp: {exchange: e, routing_key: \"w.{station}.{sensor}\"}}\n"
        "  - name: typo\n"
        "    source: {mqtt: {topic: \"farm/{station}/weather\"}}\n"
        "    mapping: \"{s: meta('statoin')}\"\n"
        "    schema: raw_json\n"
        "    sink: {amqp: {exchange: e, routing_key: k}}\n")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert len(problems) == 1 and "route 'typo'" in problems[0] and "meta('statoin')" in problems[0] \
        and "station" in problems[0], problems


def test_route_test_gives_the_capture_as_meta_and_to_the_sink_template(tmp_path: Path) -> None:
    """``rabbitros-engine test`` takes a capture as ``meta: {station: ...}``, and the mapping and
    the sink's routing key read it as the run does."""
    (tmp_path / "r.yaml").write_text("""
routes:
  - name: weather-in
    source: {mqtt: {topic: "farm/{station}/weather"}}
    mapping: "{temp_c: temp_c, station: meta('station')}"
    schema: raw_json
    sink: {amqp: {exchange: fleet, routing_key: "weather.{station}"}}
""")
    (tmp_path / "r.test.yaml").write_text("""
tests:
  - route: weather-in
    input: {temp_c: 21}
    meta: {station: north, topic: farm/north/weather}
    expect: {temp_c: 21, station: north}
    expect_routing_key: weather.north
""")
    result = cli("test", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode == 0, result.stdout + result.stderr
