"""One template grammar (issue 30): ``check`` and the run read every ``{name}`` form alike.

``topic: /robot_{id:03d}/cmd`` passed ``check`` (engine/common/placeholders.py knew format
specs) and at run time the ROS 2 sink looked up a field named ``id:03d`` (its own regex) and
refused every message. Now a spec is honoured wherever a template renders (sink topics of every
protocol, routing keys, ``for_each`` values written into text) and refused by ``check`` wherever
a template matches (a source's captures: ROS 2 discovery, MQTT), with the file and line.

Real parts: a private mosquitto, rclpy peers on the test's ROS 2 domain, the engine in process
and the ``check`` command as operators run it.
"""

from __future__ import annotations

import asyncio
import re
import json
import uuid
from pathlib import Path

import aiomqtt
import pytest

import rclpy  # noqa: F401  (a missing rclpy fails the run, never skips it)

from engine.common.schemas import SchemaRegistry
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.language.routes import RoutesInvalid, load_routes
from engine.running.runtime import Engine
from tests.support.repo import REPO
from tests.support.waiting import wait_for
from tests.operator.test_cli import cli
from tests.endpoints.mqtt.test_mqtt import Subscriber, publish, routes_dir
from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String

NUMBERED = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
  field: {{mqtt: "{mqtt}"}}
routes:
  - name: to-ros
    source:
      mqtt: {{topic: "in/ros_{tag}"}}
    schema: raw_json
    sink:
      ros2: {{topic: "/robot_{{id:03d}}/cmd_{tag}", type: std_msgs/msg/String}}
  - name: to-mqtt
    source:
      mqtt: {{topic: "in/mqtt_{tag}"}}
    schema: raw_json
    sink:
      mqtt: {{topic: "robot/{{id:03d}}/cmd_{tag}"}}
"""


def test_a_format_spec_in_a_sink_topic_passes_check_and_renders_at_run_time(tmp_path: Path, mosquitto: LocalMosquitto) -> None:
    """``/robot_{id:03d}/cmd`` (ROS 2) and ``robot/{id:03d}/cmd`` (MQTT): ``check`` accepts both
    and the running engine publishes ``{"id": 7}`` on ``/robot_007/cmd`` and ``robot/007/cmd``,
    ``{"id": 12}`` on the ``012`` topics; a message whose id is a float (``/robot_7.5``, no ROS
    name) is refused at its sink, counted, and the next one still goes."""
    tag = "f" + uuid.uuid4().hex[:8]
    routes = routes_dir(tmp_path, NUMBERED.format(domain=DOMAIN, tag=tag, mqtt=mosquitto.url))
    checked = cli("check", "--routes", str(routes))
    assert checked.returncode == 0, checked.stdout + checked.stderr
    peer = Peer()
    on_ros = {number: peer.subscribe(String, f"/robot_{number}/cmd_{tag}") for number in ("007", "012")}
    peer.start()

    async def scenario() -> tuple[list[aiomqtt.Message], dict[str, object]]:
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        try:
            async with Subscriber(mosquitto, f"robot/+/cmd_{tag}") as subscriber:
                await publish(mosquitto, [(f"in/mqtt_{tag}", {"id": 7}), (f"in/mqtt_{tag}", {"id": 12})])
                await publish(mosquitto, [(f"in/ros_{tag}", {"id": 7.5}), (f"in/ros_{tag}", {"id": 7}),
                                          (f"in/ros_{tag}", {"id": 12})])
                await wait_for(lambda: all(on_ros.values()), 30, "a String on /robot_007 and /robot_012")
                return list(await subscriber.wait_for(2)), engine.status()["routes"]["to-ros"]
        finally:
            await engine.stop()

    try:
        mqtt_messages, to_ros = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        peer.close()
    assert sorted(str(m.topic) for m in mqtt_messages) == [f"robot/007/cmd_{tag}", f"robot/012/cmd_{tag}"]
    assert [json.loads(m.data) for m in on_ros["007"]] == [{"id": 7}]
    assert [json.loads(m.data) for m in on_ros["012"]] == [{"id": 12}]
    assert (to_ros["failed"], to_ros["delivered"]) == (1, 2), to_ros


def _problems(directory: Path) -> list[str]:
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(directory, SchemaRegistry(REPO / "schemas"))
    return [str(p).removeprefix(f"{directory}/") for p in invalid.value.problems]


def test_check_refuses_a_format_spec_in_a_capture_with_file_and_line(tmp_path: Path) -> None:
    """A ROS 2 source pattern ``/{id:03d}/fix`` and an MQTT source ``farm/{id:03d}/fix``: what
    would each match (``007`` only? ``1234``?) and give as ``meta('id')`` (text or number)? No
    single answer, so ``check`` refuses both, naming the file, the line and the way out. A
    MAVLink target ``"{vehicle:03d}"`` is refused too (a target is the id the field holds, not
    text), in words rather than the schema's regular expression."""
    (tmp_path / "r.yaml").write_text(
        "connections:\n"
        "  link: {mavlink: \"udpin:127.0.0.1:14550\"}\n"
        "routes:\n"
        "  - name: ros\n"
        "    source: {ros2: {topic: \"/{id:03d}/fix\", type: std_msgs/msg/String}}\n"
        "    schema: raw_json\n"
        "    sink: {amqp: {exchange: e, routing_key: k}}\n"
        "  - name: mqtt\n"
        "    source: {mqtt: {topic: \"farm/{id:03d}/fix\"}}\n"
        "    schema: raw_json\n"
        "    sink: {amqp: {exchange: e, routing_key: k}}\n"
        "  - name: mav\n"
        "    source: {amqp: {queue: q}}\n"
        "    schema: raw_json\n"
        "    sink: {mavlink: {connection: link, message: COMMAND_LONG, target_system: \"{vehicle:03d}\"}}\n")
    problems = _problems(tmp_path)
    for line, route in ((5, "ros"), (9, "mqtt")):
        assert any(p.startswith(f"r.yaml:{line}: route {route!r}") and "{id:03d} has a format spec, which a source "
                   "cannot match" in p for p in problems), (route, problems)
    assert any(p.startswith("r.yaml:15: route 'mav'") and "a format spec makes text" in p and 'write "{vehicle}"' in p
               for p in problems), problems
    assert len(problems) == 3, problems


FOR_EACH = """
routes:
  - name: cmd-{{id}}
    for_each: [{{id: {first}}}, {{id: 12}}]
    source: {{amqp: {{queue: "q{{id:02d}}"}}}}
    schema: raw_json
    sink: {{ros2: {{topic: "/robot_{{id:03d}}/cmd", type: std_msgs/msg/String}}}}
"""


def test_for_each_honours_a_format_spec_and_check_names_a_value_it_cannot_take(tmp_path: Path) -> None:
    """A ``for_each`` variable is read by the same grammar: ``{id:03d}`` with id 7 writes
    ``/robot_007/cmd`` at load (no longer left for the sink to read a field ``id``); an item
    whose value the spec cannot format (``seven`` with ``03d``) is a problem at the route's
    line, the other items still expanded."""
    (tmp_path / "r.yaml").write_text(FOR_EACH.format(first=7))
    config = load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    by_name = config.routes
    assert by_name["cmd-7"].sink.options.topic == "/robot_007/cmd"
    assert by_name["cmd-12"].sink.options.topic == "/robot_012/cmd"
    assert by_name["cmd-7"].source.options.queue == "q07"
    (tmp_path / "r.yaml").write_text(FOR_EACH.format(first="seven"))
    problems = _problems(tmp_path)
    assert len(problems) == 1 and problems[0].startswith("r.yaml:4: ") and "'seven'" in problems[0] \
        and "source.amqp.queue: template 'q{id:02d}'" in problems[0] and "Unknown format code 'd'" in problems[0], problems


@pytest.mark.parametrize("pattern, levels", [
    ("farm/{station}/weather", ["farm", "{station}", "weather"]),
    ("/{agent}/fix", ["", "{agent}", "fix"]),
    ("{a}/+/{b}/#", ["{a}", "+", "{b}", "#"]),
    ("/{node}/{agent}/cmd", ["", "{node}", "{agent}", "cmd"]),  # {node}: rcl's, kept as text
    ("farm/{{x}}/y", ["farm", "{x}", "y"]),  # an escaped brace is literal text
])
def test_capture_levels_read_each_level_as_text_or_one_capture(pattern: str, levels: list[str]) -> None:
    from engine.common.placeholders import Placeholder, capture_levels
    read = capture_levels(pattern, keep={"node"})
    assert ["{" + level.name + "}" if isinstance(level, Placeholder) else level for level in read] == levels


@pytest.mark.parametrize("pattern, refusal", [
    ("farm/s{n}/w", "must be a whole level"), ("farm/{a}{b}/w", "must be a whole level"),
    ("farm/{n:03d}/w", "has a format spec"), ("farm/{a.b}/w", "names one meta() key"),
    ("farm/{a!r}/w", "is not a field path"), ("farm/{a/w", "never closed"),
])
def test_capture_levels_refuse_what_a_capture_cannot_honour(pattern: str, refusal: str) -> None:
    from engine.common.placeholders import TemplateError, capture_levels
    with pytest.raises(TemplateError, match=re.escape(refusal)):
        capture_levels(pattern)


def test_one_tokenizer_strict_for_templates_lenient_for_for_each_text() -> None:
    """``for_each`` variables may sit in any text (JSON included): the same tokenizer skips what
    is no placeholder there, where a template refuses it."""
    from engine.common.placeholders import TemplateError, parse_template, scan_placeholders
    text = '{"a": 1} {x} {{y}} {z:03d} }'
    assert [(found.name, found.spec) for found in scan_placeholders(text)] == [("x", ""), ("z", "03d")]
    with pytest.raises(TemplateError):
        parse_template(text)
