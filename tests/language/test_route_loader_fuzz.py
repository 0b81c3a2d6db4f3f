"""Hostile route files, measured (issue 21): the loader behind ``check`` and ``run`` answers
every malformed file, YAML, JMESPath mapping or template with ``file:line: message``
problems, never a traceback or a hang.

Inputs are a valid route file damaged by hypothesis (characters inserted, deleted or
replaced anywhere) and valid files whose mapping, routing key, topic, ``format()`` template,
``${...}`` reference and option values are arbitrary text. Each input runs in-process with a
per-input time limit (HANG_S). The counts print with ``-s``."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from engine.common.schemas import SchemaRegistry
from engine.language.routes import RoutesInvalid, load_routes
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

VALID = """connections:
  gcs: {amqp: {url: "amqp://farmer:${RABBITROS_FUZZ_PW:-pw}@localhost:5672/", heartbeat: 30}}
routes:
  - name: weeds
    source: {amqp: {connection: gcs, exchange: farm, binding_key: "uav.#", queue: weeds}}
    schema: raw_json
    mapping: "{agent_id: agent, n: to_int(count), s: format('{agent} at {hdg}', @)}"
    sink: {amqp: {connection: gcs, exchange: out, routing_key: "canonical.weeds.{agent_id}"}}
"""
TEMPLATE = """routes:
  - name: r
    source: {{amqp: {{queue: q}}}}
    schema: raw_json
    mapping: {mapping}
    sink: {{amqp: {{exchange: e, routing_key: {key}}}}}
  - name: t
    source: {{amqp: {{queue: q2}}}}
    schema: raw_json
    sink: {{ros2: {{topic: {topic}, type: std_msgs/msg/String}}}}
"""
PROBLEM = re.compile(r"^r\.yaml:\d+: \S")
HANG_S = 10.0
"""One file taking longer is a hang (a shared 2-core CI machine loads one in ~30 ms; hypothesis'
own deadline, 2 s at first, failed on a loaded machine's first input)."""
SCHEMAS = SchemaRegistry(REPO / "schemas")
COUNTS = {"inputs": 0, "valid": 0, "invalid": 0, "slowest_s": 0.0}
ALPHABET = st.sampled_from(list("{}[]()'\"`:@,.|&!?*$#-_ \n\tabxyz019") + ["__class__", "${", "${file:", "format(", "\\u0000", "\t- "])


def _load(tmp_path: Path, text: str) -> None:
    directory = tmp_path / f"d{COUNTS['inputs']}"
    directory.mkdir()
    (directory / "r.yaml").write_text(text)
    began = time.monotonic()
    COUNTS["inputs"] += 1
    try:
        load_routes(directory, SCHEMAS, env={})
        COUNTS["valid"] += 1
    except RoutesInvalid as invalid:
        COUNTS["invalid"] += 1
        assert invalid.problems, text
        for problem in invalid.problems:
            assert PROBLEM.match(str(problem).removeprefix(f"{directory}/")), (str(problem), text)
    finally:
        COUNTS["slowest_s"] = max(COUNTS["slowest_s"], time.monotonic() - began)
    assert time.monotonic() - began < HANG_S, f"{time.monotonic() - began:.1f}s for one file: {text!r}"


@st.composite
def damaged(draw: st.DrawFn) -> str:
    text = VALID
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(text)))
        kind = draw(st.sampled_from(["insert", "delete", "replace"]))
        piece = "".join(draw(st.lists(ALPHABET, min_size=1, max_size=4)))
        if kind == "insert":
            text = text[:at] + piece + text[at:]
        elif kind == "delete":
            text = text[:at] + text[at + draw(st.integers(1, 12)):]
        else:
            text = text[:at] + piece + text[at + len(piece):]
    return text


def _quoted(value: str) -> str:
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'


FUZZ = settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@FUZZ
@given(damaged())
def test_a_damaged_route_file_gets_file_line_problems(tmp_path: Path, text: str) -> None:
    _load(tmp_path, text)


@FUZZ
@given(st.lists(ALPHABET, max_size=12).map("".join), st.lists(ALPHABET, max_size=12).map("".join),
       st.lists(ALPHABET, max_size=8).map("".join))
def test_arbitrary_mappings_and_templates_get_file_line_problems(tmp_path: Path, mapping: str, key: str, topic: str) -> None:
    _load(tmp_path, TEMPLATE.format(mapping=_quoted(mapping), key=_quoted(key), topic=_quoted("/" + topic)))


def test_print_counts() -> None:
    print(f"\nroute loader fuzz: {COUNTS['inputs']} inputs, {COUNTS['valid']} valid, {COUNTS['invalid']} invalid "
          f"(each with file:line problems), 0 tracebacks, slowest {COUNTS['slowest_s'] * 1000:.0f} ms")
