"""The farm demo recorded (issue 33): ``examples/farm_demo.py --record DIR``, read back with the
``mcap`` library, checked against the engine's own counters, and replayed.

Every part is real, as in tests/examples/test_farm_example.py: the simulated UAV on MAVLink 2
through the emulated SiK radio, the ROS 2 ground robot, the engine with a private RabbitMQ node
and the AMQP-only supervisor. What is checked:

- per route, the file's ``/routes/NAME/canonical`` channel holds as many messages as the route's
  ``delivered`` counter in the engine's final status (the sink took them: what the issue calls
  ``sent``), and ``/routes/NAME/in`` as many as ``received``; nothing was dropped;
- every message validates against its channel's schema (``jsonschema``, the schema records of
  the file: the route's canonical JSON Schema, or the input envelope's);
- ``rabbitros-engine replay`` of the recording against the same routes finds 0 differences
  (the keys that come from the clock, ``stamp``, and from ``uuid()``, ``id``, left out: they
  differ on every conversion); after a mapping edit in a copy of the routes, it names exactly the
  messages of the edited route and exits 1.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader

from tests.support.repo import REPO
from tests.support.workers import ros_domain

DURATION = 20
ROUTES = REPO / "examples" / "farm_uav_gcs.yaml"


def replay(recording: Path, routes: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "engine", "replay", str(recording), "--routes", str(routes),
                           "--schemas", str(REPO / "schemas")],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.mark.soak
@pytest.mark.timeout(400)  # the demo's own bound is 320 s
def test_the_farm_recorded_counts_schemas_and_replay(tmp_path: Path) -> None:
    work, record = tmp_path / "farm", tmp_path / "recording"
    demo = subprocess.run(
        ["timeout", "-s", "KILL", "300", sys.executable, "examples/farm_demo.py", "--duration", str(DURATION),
         "--work", str(work), "--plain", "--record", str(record),
         "--ros-domain", str(ros_domain(17))],
        cwd=REPO, capture_output=True, text=True, timeout=320)
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    final = json.loads((work / "status.json").read_text())
    status = final["routes"]
    assert final["recording"]["dropped"] == 0 and final["recording"]["write_errors"] == 0, final["recording"]

    files = sorted(record.glob("*.mcap"))
    assert len(files) == 1, files
    counts: Counter[str] = Counter()
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    inputs: dict[str, set[int]] = {}
    with files[0].open("rb") as stream:  # the engine stopped cleanly: the summary is there
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] += 1
            assert schema is not None and schema.encoding == "jsonschema" and channel.message_encoding == "json", channel
            if schema.id not in validators:
                document = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(document)
                validators[schema.id] = jsonschema.Draft202012Validator(document)
            validators[schema.id].validate(json.loads(message.data))  # every message against its channel's schema
            topic = re.fullmatch(r"/routes/(.+)/(in|canonical)", channel.topic)
            assert topic is not None, f"a channel that is neither a route's input nor its canonical: {channel.topic}"
            route, kind = topic.groups()
            if kind == "in":
                inputs.setdefault(route, set()).add(message.sequence)

    expected = {f"/routes/{name}/canonical": route["delivered"] for name, route in status.items()}
    expected |= {f"/routes/{name}/in": route["received"] for name, route in status.items()}
    assert dict(counts) == expected, (dict(counts), expected)
    assert len(status) == 13 and all(route["delivered"] for route in status.values()), status
    sent = sum(route["delivered"] for route in status.values())

    same = replay(record, ROUTES)
    assert same.returncode == 0, same.stdout[-3000:] + same.stderr[-3000:]
    assert f"{sent} messages compared: {sent} same, 0 differ" in same.stdout, same.stdout[-3000:]
    # what the mappings take from the clock (stamp(), stamp_boot_ms()) or uuid() is named, not compared
    assert "not compared in route 'uav1-battery': stamp (" in same.stderr, same.stderr[-3000:]
    assert re.search(r"not compared in route 'uav1-mission-acks': (id, stamp|stamp, id) \(", same.stderr), same.stderr[-3000:]

    # A mapping edit in a copy of the routes: the battery's voltage from mV by 100 instead of 1000.
    edited = tmp_path / "edited"
    edited.mkdir()
    original = ROUTES.read_text()
    assert original.count("div(voltage_battery, `1000`)") == 1
    (edited / "farm_uav_gcs.yaml").write_text(original.replace("div(voltage_battery, `1000`)", "div(voltage_battery, `100`)"))
    changed = replay(record, edited)
    assert changed.returncode == 1, changed.stdout[-3000:] + changed.stderr[-3000:]
    named: dict[str, set[int]] = {}
    for route, number in re.findall(r"^DIFF  (\S+) #(\d+) ", changed.stdout, re.MULTILINE):
        named.setdefault(route, set()).add(int(number))
    battery = status["uav1-battery"]["delivered"]
    assert list(named) == ["uav1-battery"] and len(named["uav1-battery"]) == battery, changed.stdout[-3000:]
    assert named["uav1-battery"] <= inputs["uav1-battery"], (named, inputs["uav1-battery"])
    assert '"voltage": ' in changed.stdout and f"{sent} messages compared: {sent - battery} same, {battery} differ" in changed.stdout
    print(f"farm recorded: {sum(counts.values())} messages in {files[0].stat().st_size} bytes, "
          f"{len(validators)} schemas, {sent} canonical replayed: 0 differ; edited: {battery} named")
