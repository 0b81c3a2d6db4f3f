"""Templates read fields only (issue 21): ``format()``, AMQP routing keys and ROS 2 topics
accept literal text and ``{field.path}``, never Python attribute access or indexing."""

from __future__ import annotations

from pathlib import Path

import pytest

from engine.common.placeholders import MappingError, compile_template
from engine.common.schemas import SchemaRegistry
from engine.language.mapping import compile_mapping
from engine.language.routes import RoutesInvalid, load_routes
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

HOSTILE = [
    "{agent.__class__.__mro__}", "{agent.__class__}", "{__class__}", "{a[0]}", "{a!r}", "{0}", "{}",
    "{agent:{agent.__class__}}", "{agent.__init__.__globals__}", "x}", "{x", "{a b}",
]


@pytest.mark.parametrize("template", HOSTILE)
def test_a_template_taken_from_a_message_is_a_mapping_error(template: str):
    """The issue's reproduction: ``format(tmpl, @)`` with ``tmpl`` from the message returned
    ``(<class 'str'>, <class 'object'>)`` through str.format."""
    render = compile_mapping("format(tmpl, @)")
    with pytest.raises(MappingError, match="format: template") as refused:
        render({"tmpl": template, "agent": "uav1", "a": [1], "x": 1})
    assert "<class" not in str(refused.value)


def test_field_paths_escapes_and_plain_specs_still_render():
    render = compile_mapping("format(tmpl, @)")
    data = {"agent": "uav1", "pose": {"frame": "map"}, "lat": -22.00051234, "n": 7}
    assert render({**data, "tmpl": "{agent} in {pose.frame}"}) == "uav1 in map"
    assert render({**data, "tmpl": "{{agent}} {lat:.4f} {n:03d}"}) == "{agent} -22.0005 007"
    assert compile_template("canonical.{type}.{agent.id}")({"type": "w", "agent": {"id": "u"}}) == "canonical.w.u"
    with pytest.raises(MappingError, match="applies to numbers and strings"):
        compile_template("{pose:>9}")(data)


@pytest.mark.parametrize("template", ["c.{agent.__class__}", "c.{ids[0]}", "c.{agent!r}", "c.{agent"])
def test_routing_key_template_is_refused(template: str):
    with pytest.raises(MappingError):
        compile_template(template)


def test_check_refuses_literal_templates_with_file_and_line(tmp_path: Path):
    (tmp_path / "r.yaml").write_text(
        "routes:\n"
        "  - name: fmt\n"
        "    source: {amqp: {queue: q}}\n"
        "    schema: raw_json\n"
        "    mapping: \"{s: format('{agent.__class__.__mro__}', @)}\"\n"
        "    sink: {amqp: {exchange: e, routing_key: x}}\n"
        "  - name: key\n"
        "    source: {amqp: {queue: q2}}\n"
        "    schema: raw_json\n"
        "    sink: {amqp: {exchange: e, routing_key: \"canonical.{ids[0]}\"}}\n"
        "  - name: topic\n"
        "    source: {amqp: {queue: q3}}\n"
        "    schema: raw_json\n"
        "    sink: {ros2: {topic: \"/{agent.__class__}/x\", type: std_msgs/msg/String}}\n"
        "  - name: mqtt\n"
        "    source: {amqp: {queue: q4}}\n"
        "    schema: raw_json\n"
        "    sink: {mqtt: {topic: \"farm/{agent!r}/cmd\"}}\n"
    )
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert any(p.startswith("r.yaml:5: route 'fmt'") and "{agent.__class__.__mro__} is not a field path" in p
               for p in problems), problems
    assert any(p.startswith("r.yaml:10: route 'key'") and "{ids[0]} is not a field path" in p for p in problems), problems
    assert any(p.startswith("r.yaml:14: route 'topic'") and "{agent.__class__} is not a field path" in p
               for p in problems), problems
    assert any(p.startswith("r.yaml:18: route 'mqtt'") and "{agent!r} is not a field path" in p for p in problems), problems
