"""Schemas of one's own (issue 32): a user's schema directory with its own ``$id``s (or none),
layered over the bundled one with ``--schemas`` given twice. ``$ref`` names a file whatever the
``$id``; a later directory's file replaces the earlier's of the same name, and only that one;
``check`` says which file each schema the routes use came from; an edit in either directory is
seen by the watcher."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from engine.common.schemas import SchemaError, SchemaRegistry
from engine.language.routes import load_routes
from engine.running.watch import watch_routes
from tests.support.repo import REPO
from tests.support.waiting import wait_for
from tests.support.schemas import known_schema

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

BUNDLED = REPO / "schemas"
DRAFT = "https://json-schema.org/draft/2020-12/schema"


def schema(properties: dict[str, Any], **more: Any) -> dict[str, Any]:
    return {"$schema": DRAFT, "type": "object", "properties": properties, **more}


def write(directory: Path, name: str, document: dict[str, Any]) -> Path:
    path = directory / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document))
    return path


@pytest.fixture
def mine(tmp_path: Path) -> Path:
    """A user's directory: schemas with their own ``$id``s, one without, one in a family, and
    ``position.v1.json`` replacing the bundled one."""
    directory = tmp_path / "mine"
    header = {"$ref": "envelope.v1.json#/$defs/header"}
    write(directory, "robot_pose.v1.json", schema(
        {"x": {"type": "number"}, "y": {"type": "number"}},
        **{"$id": "https://acme.example/schemas/robot_pose.v1.json", "allOf": [header], "required": ["agent_id", "x"],
           "additionalProperties": True}))
    write(directory, "no_id.v1.json", schema({"where": {"$ref": "envelope.v1.json#/$defs/point"}}, allOf=[header]))
    write(directory, "by_bundled_id.v1.json", schema(
        {"at": {"$ref": "https://rabbitros.dev/schemas/envelope.v1.json#/$defs/stamp"}},
        **{"$id": "urn:acme:by-bundled-id"}))
    write(directory, "acme/dock.v1.json", schema(
        {"stamp": {"$ref": "../envelope.v1.json#/$defs/stamp"}, "pose": {"$ref": "robot_pose.v1.json"}},
        **{"$id": "https://acme.example/elsewhere/dock.v1.json"}))
    write(directory, "position.v1.json", schema({"lat": {"type": "number"}, "label": {"type": "string"}},
                                               allOf=[header], required=["label"]))
    return directory


def test_own_ids_resolve_by_file_name_over_the_bundled_directory(mine: Path):
    registry = SchemaRegistry([BUNDLED, mine])
    assert registry.problems == []
    known_schema(registry, "robot_pose").validate({"agent_id": "r1", "x": 1.5})
    with pytest.raises(SchemaError, match=r"schema robot_pose.v1: \$.agent_id: .* is shorter than 1 character"):
        known_schema(registry, "robot_pose").validate({"agent_id": "", "x": 1.5})  # the bundled envelope's header, through $ref
    with pytest.raises(SchemaError, match=r"\$.where.lat"):
        known_schema(registry, "no_id").validate({"where": {"lat": 91, "lon": 0}})
    with pytest.raises(SchemaError, match=r"\$.at"):
        known_schema(registry, "by_bundled_id").validate({"at": {"sec": 1, "nanosec": 1, "extra": 1}})
    with pytest.raises(SchemaError, match=r"\$.pose"):
        known_schema(registry, "acme/dock").validate({"stamp": {"sec": 1, "nanosec": 0}, "pose": {"agent_id": "r1"}})
    # the user's position.v1.json replaced the bundled one, and only that file
    assert known_schema(registry, "position").path == mine / "position.v1.json"
    known_schema(registry, "position").validate({"label": "dock", "lat": 100})
    with pytest.raises(SchemaError, match="label"):
        known_schema(registry, "position").validate({"lat": 1})
    assert known_schema(registry, "battery").path == BUNDLED / "battery.v1.json"
    assert [(f.relative, f.path, f.replaces) for f in registry.files_used(["position", "robot_pose"])] == [
        ("envelope.v1.json", BUNDLED / "envelope.v1.json", ()),
        ("position.v1.json", mine / "position.v1.json", (BUNDLED / "position.v1.json",)),
        ("robot_pose.v1.json", mine / "robot_pose.v1.json", ())]


def test_one_directory_of_own_ids_was_the_trap_and_resolves_now(tmp_path: Path):
    """The issue's case: a copy of the envelope and a schema whose ``$id`` is the user's own."""
    directory = tmp_path / "schemas"
    write(directory, "envelope.v1.json", {**json.loads((BUNDLED / "envelope.v1.json").read_text()), "$id": "https://acme.example/envelope"})
    write(directory, "pose.v1.json", schema({"x": {"type": "number"}}, **{"$id": "https://acme.example/s/pose.v1.json",
                                                                          "allOf": [{"$ref": "envelope.v1.json#/$defs/header"}]}))
    registry = SchemaRegistry(directory)
    assert registry.problems == []
    with pytest.raises(SchemaError, match="agent_id"):
        known_schema(registry, "pose").validate({"agent_id": 5, "x": 1})


def test_a_copy_keeping_a_bundled_id_does_not_capture_the_bundled_references(mine: Path):
    """A user's ``my_envelope.v1.json`` copied from the bundled envelope keeps its ``$id``: the
    bundled schemas still reach ``envelope.v1.json`` by file name, not the copy by ``$id``."""
    bundled_envelope = json.loads((BUNDLED / "envelope.v1.json").read_text())
    bundled_envelope["$defs"]["header"]["properties"]["agent_id"] = {"type": "integer"}
    write(mine, "my_envelope.v1.json", bundled_envelope)
    registry = SchemaRegistry([BUNDLED, mine])
    assert registry.problems == []
    known_schema(registry, "battery").validate({"agent_id": "uav1", "voltage": 12.1})
    with pytest.raises(SchemaError, match="agent_id"):
        known_schema(registry, "battery").validate({"agent_id": 7, "voltage": 12.1})


def test_a_later_envelope_replaces_it_for_every_schema_and_changes_their_digests(mine: Path):
    before = SchemaRegistry([BUNDLED, mine])
    envelope = json.loads((BUNDLED / "envelope.v1.json").read_text())
    envelope["$defs"]["header"]["required"] = ["id"]
    write(mine, "envelope.v1.json", envelope)
    after = SchemaRegistry([BUNDLED, mine])
    assert after.problems == []
    with pytest.raises(SchemaError, match='"id" is a required property'):
        known_schema(after, "battery").validate({"agent_id": "uav1", "voltage": 12.1})  # a bundled schema, through the user's envelope
    assert known_schema(after, "battery").digest != known_schema(before, "battery").digest
    assert known_schema(after, "raw_json").digest == known_schema(before, "raw_json").digest


def test_a_reference_to_no_file_names_the_directories(mine: Path):
    write(mine, "lost.v1.json", schema({"x": {"$ref": "nowhere.v1.json#/$defs/x"}}, **{"$id": "https://acme.example/lost"}))
    write(mine, "leaning.v1.json", schema({"y": {"$ref": "lost.v1.json"}}))
    registry = SchemaRegistry([BUNDLED, mine])
    assert sorted((path.name, message) for path, message in registry.problems) == [
        ("leaning.v1.json", "refers to lost.v1.json, which does not load"),
        ("lost.v1.json", f"$ref 'nowhere.v1.json#/$defs/x' does not resolve to a schema file of {BUNDLED}, {mine}")]
    assert registry.get("lost") is None and registry.get("robot_pose") is not None


def test_routes_use_own_schemas_and_check_says_which_file_each_came_from(mine: Path, tmp_path: Path):
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text("""routes:
  - name: pose
    source: {amqp: {queue: q}}
    schema: robot_pose
    mapping: "{agent_id: robot, x: px, y: py}"
    sink: {amqp: {exchange: e, routing_key: k}}
  - name: where
    source: {amqp: {queue: q2}}
    schema: position
    mapping: "{agent_id: robot, label: name, lat: lat}"
    sink: {amqp: {exchange: e, routing_key: k}}
""")
    config = load_routes(routes, SchemaRegistry([BUNDLED, mine]), env={})
    assert config.warnings == ()  # agent_id is declared, in the bundled envelope the user's $ref reaches
    result = subprocess.run([sys.executable, "-m", "engine", "check", "--routes", str(routes),
                             "--schemas", str(BUNDLED), "--schemas", str(mine)],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[1:] == [
        f"  schema envelope.v1.json: {BUNDLED}/envelope.v1.json",
        f"  schema position.v1.json: {mine}/position.v1.json (over {BUNDLED}/position.v1.json)",
        f"  schema robot_pose.v1.json: {mine}/robot_pose.v1.json"]
    alone = subprocess.run([sys.executable, "-m", "engine", "check", "--routes", str(routes), "--schemas", str(BUNDLED)],
                           cwd=REPO, capture_output=True, text=True, timeout=120)
    assert alone.returncode == 1 and "unknown schema 'robot_pose'" in alone.stderr, alone.stderr


def test_an_edit_in_either_schema_directory_is_seen(mine: Path, tmp_path: Path):
    routes, bundled = tmp_path / "routes", tmp_path / "bundled"
    routes.mkdir()
    write(bundled, "envelope.v1.json", json.loads((BUNDLED / "envelope.v1.json").read_text()))

    async def scenario() -> None:
        calls: list[float] = []
        stop = asyncio.Event()
        task = asyncio.create_task(watch_routes(routes, lambda: calls.append(time.monotonic()), stop, [bundled, mine]))
        try:
            await asyncio.sleep(0)  # the watch task's first step sets the watch up (engine/running/watch.py), before our next
            for changed in (bundled / "envelope.v1.json", mine / "robot_pose.v1.json", mine / "acme" / "dock.v1.json"):
                count = len(calls)
                changed.write_text(changed.read_text() + "\n")
                await wait_for(lambda: len(calls) > count, 10, f"an edit of {changed} seen")
        finally:
            stop.set()
            await asyncio.wait_for(task, 10)

    asyncio.run(scenario())
